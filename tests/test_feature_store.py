"""Keyframe features on disk behind a bounded cache: the same arrays back, checkpoints without them, and runs
whose results do not depend on the cache size."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from ggfslam import slam
from ggfslam.backend.feature_store import FeatureStore
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import config_from_dict
from ggfslam.data.synthetic import write_synthetic_sequence
from ggfslam.errors import RunDirError
from ggfslam.frontend.features import Features
from ggfslam.safe_load import load_tracker_pickle


def _features(n: int, seed: int) -> Features:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 4.0, n)  # [N]
    depth[::7] = 0.0
    pts = rng.normal(size=(n, 3))  # [N, 3]
    pts[depth == 0] = np.nan
    return Features(rng.uniform(0, 640, (n, 2)), rng.integers(0, 8, n), rng.integers(0, 256, (n, 32), dtype=np.uint8),
                    depth, pts)


def _assert_same(a: Features, b: Features) -> None:
    for name in ("uv", "octave", "descriptors", "depth", "points_cam"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)  # NaN where NaN


def test_an_attached_store_keeps_cache_size_keyframes_in_memory_and_reads_the_rest_back_exactly(tmp_path):
    store = FeatureStore()
    store.attach(tmp_path, cache_size=2)
    feats = {k: _features(50 + k, k) for k in range(5)}
    for k, f in feats.items():
        store.put(k, f)
    assert len(store._cache) == 2 and len(store) == 5 and sorted(p.name for p in tmp_path.iterdir()) == [
        f"kf_{k:06d}.npy" for k in range(5)]
    for k in (4, 3, 0, 1, 2):
        _assert_same(store.get(k), feats[k])
    assert store.reads == 3  # keyframes 0-2 had left the cache; 3 and 4 were its last two
    store.get(2)
    assert store.reads == 3 and len(store._cache) == 2
    store.get(4)  # left when 1 and 2 were read
    assert store.reads == 4
    with pytest.raises(KeyError, match="keyframe 9"):
        store.get(9)


def test_a_store_in_memory_attached_later_writes_what_it_holds(tmp_path):
    store = FeatureStore()
    f = _features(30, 1)
    store.put(3, f)
    assert not list(tmp_path.iterdir())
    store.attach(tmp_path / "feats", cache_size=1)
    assert (tmp_path / "feats" / "kf_000003.npy").is_file()
    store.put(4, _features(20, 2))
    _assert_same(store.get(3), f)


def test_a_checkpointed_map_pickles_no_features_and_finds_them_again_in_a_moved_folder(tmp_path):
    smap = SlamMap()
    smap.feature_store.attach(tmp_path / "run" / "keyframe_features", cache_size=2)
    feats = {k: _features(40, k) for k in range(4)}
    for k, f in feats.items():
        smap.add_keyframe(KeyFrame(k, 10 * k, float(k), np.eye(4), f, np.full(40, -1, np.int64)))
    blob = pickle.dumps(smap)
    in_memory = SlamMap()
    for k, f in feats.items():
        in_memory.add_keyframe(KeyFrame(k, 10 * k, float(k), np.eye(4), f, np.full(40, -1, np.int64)))
    feature_bytes = sum(getattr(f, n).nbytes for f in feats.values() for n in ("uv", "octave", "descriptors", "depth",
                                                                             "points_cam"))
    assert len(pickle.dumps(in_memory)) - len(blob) >= feature_bytes  # the features stay out of the pickle
    assert all(f.descriptors.tobytes() not in blob for f in feats.values())
    (tmp_path / "run").rename(tmp_path / "moved")
    back = load_tracker_pickle(blob)  # the checkpoint reader's allow-list knows the store
    back.feature_store.attach(tmp_path / "moved" / "keyframe_features")
    for k, f in feats.items():
        _assert_same(back.keyframes[k].features, f)


def test_attaching_a_checkpoints_store_names_a_missing_file_and_drops_files_made_after_it(tmp_path):
    store = FeatureStore()
    store.attach(tmp_path, cache_size=1)
    for k in range(3):
        store.put(k, _features(10, k))
    back = pickle.loads(pickle.dumps(store))
    store.put(3, _features(10, 3))  # after the checkpoint: made again when the run resumes
    back.attach(tmp_path)
    assert not (tmp_path / "kf_000003.npy").exists() and len(back) == 3
    (tmp_path / "kf_000001.npy").unlink()
    with pytest.raises(RunDirError, match="kf_000001.npy"):
        pickle.loads(pickle.dumps(back)).attach(tmp_path)


def test_a_damaged_features_file_is_an_error_naming_it(tmp_path):
    store = FeatureStore()
    store.attach(tmp_path, cache_size=1)
    store.put(0, _features(10, 0))
    store.put(1, _features(10, 1))
    (tmp_path / "kf_000000.npy").write_bytes(b"not an .npy file")
    with pytest.raises(RunDirError, match="kf_000000.npy"):
        store.get(0)


def test_a_keyframe_from_a_checkpoint_before_the_store_keeps_its_features():
    kf = KeyFrame(0, 0, 0.0, np.eye(4), _features(12, 0), np.full(12, -1, np.int64))
    smap = SlamMap()
    smap.keyframes[0] = kf  # as a checkpoint of an earlier version held it: features in the keyframe
    state = smap.__getstate__()
    del state["feature_store"]
    old_kf = KeyFrame.__new__(KeyFrame)
    old_kf.__setstate__({"id": 0, "frame_index": 0, "timestamp": 0.0, "T_wc": np.eye(4),
                         "features": kf._features, "landmark_ids": kf.landmark_ids, "meta": {}})
    state["keyframes"] = {0: old_kf}
    back = SlamMap.__new__(SlamMap)
    back.__setstate__(state)
    assert 0 in back.feature_store and old_kf._features is None
    _assert_same(back.keyframes[0].features, kf._features)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A rendered stretch of the room in TUM layout."""
    return write_synthetic_sequence(tmp_path_factory.mktemp("seq") / "room", n_frames=45, width=320, height=240)


def _tracking_config(path, cache: int):
    return config_from_dict({"name": "features", "dataset": {"kind": "tum", "path": str(path)},
                             "tracking": {"keyframe_max_frames": 3},
                             "backend": {"feature_cache": cache, "keyframe_culling": True},
                             "mapping": {"enabled": False}}, "t")


def test_a_run_keeping_one_keyframes_features_in_memory_tracks_exactly_as_one_keeping_them_all(sequence, tmp_path):
    runs = {}
    for cache in (4096, 1):
        runs[cache] = slam.run(_tracking_config(sequence, cache), tmp_path / f"cache{cache}", progress=False)
    assert runs[4096]["backend"]["feature_reads"] == 0
    assert runs[1]["backend"]["feature_reads"] > 50  # bundle adjustment, fusion and culling read older keyframes
    one, all_ = (np.loadtxt(tmp_path / f"cache{c}" / "trajectory.txt") for c in (1, 4096))
    np.testing.assert_array_equal(one, all_)
    assert runs[1]["backend"]["keyframes"] == runs[4096]["backend"]["keyframes"] >= 12
    files = list((tmp_path / "cache1" / "keyframe_features").glob("kf_*.npy"))
    assert len(files) == runs[1]["backend"]["keyframes"]
