"""graph.json: structure of a real (tiny) run's export, errors equal to GTSAM's, networkx loading, speed."""
from __future__ import annotations

import json
import time

import gtsam
import numpy as np
import pytest

from ggfslam.backend.export import FORMAT_VERSION, MIN_COVISIBILITY, graph_to_dict, load_graph_networkx
from ggfslam.backend.graph import L, P, X, calibrations, observation_factor, whitened_chi2
from ggfslam.backend.slam_map import KeyFrame, SlamMap
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.types import Camera
from ggfslam.frontend.features import Features
from ggfslam.rundir import GRAPH_FILE
from tests.conftest import run_synthetic


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A 20-frame synthetic run (keyframe every 4 frames at most, noisy depth so errors are not all zero)."""
    return run_synthetic(tmp_path_factory, "export", {
        "dataset": {"kind": "synthetic", "synthetic": {"n_frames": 20, "width": 320, "height": 240,
                                                      "depth_noise": True}},
        "tracking": {"keyframe_max_frames": 4}, "mapping": {"enabled": False}})


@pytest.fixture(scope="module")
def graph(run_dir) -> dict:
    return json.loads((run_dir / GRAPH_FILE).read_text())


def _values(graph: dict, kf_ids, lm_ids) -> gtsam.Values:
    """GTSAM values of the named keyframes and landmarks as the export saw them."""
    kfs = {k["id"]: k for k in graph["keyframes"]}
    lms = {l["id"]: l for l in graph["landmarks"]}
    v = gtsam.Values()
    for k in set(kf_ids):
        v.insert(X(k), gtsam.Pose3(np.array(kfs[k]["T_wc"])))
    for l in set(lm_ids):
        v.insert(L(l), gtsam.Point3(*lms[l]["position"]))
    return v


def test_structure_and_keys(graph):
    meta = graph["meta"]
    assert meta["version"] == FORMAT_VERSION
    assert meta["counts"]["keyframes"] == len(graph["keyframes"]) >= 3
    assert meta["counts"]["landmarks"] == len(graph["landmarks"]) > 100
    assert meta["counts"]["factors"] == len(graph["factors"])
    assert meta["camera"]["width"] == 320 and meta["virtual_baseline"] > 0
    kf_keys = {k["key"] for k in graph["keyframes"]}
    lm_keys = {l["key"] for l in graph["landmarks"]}
    plane_keys = {p["key"] for p in graph["planes"]}
    n_obs = dict.fromkeys(lm_keys, 0)
    n_plane_obs = dict.fromkeys(plane_keys, 0)
    for f in graph["factors"]:
        assert f["type"] in ("rgbd_stereo", "projection", "odometry_link", "plane")
        assert np.isfinite(f["error"]) and f["error"] >= 0
        a, b = f["keys"]
        if f["type"] == "plane":
            assert a == f"x{f['kf']}" in kf_keys and b == f"p{f['plane']}" in plane_keys
            assert f["gtsam_keys"] == [X(f["kf"]), P(f["plane"])]
            n_plane_obs[b] += 1
        elif f["type"] == "odometry_link":
            assert a in kf_keys and b in kf_keys
            assert f["gtsam_keys"] == [X(int(a[1:])), X(int(b[1:]))]
        else:
            assert a == f"x{f['kf']}" in kf_keys and b == f"l{f['lm']}" in lm_keys
            assert f["gtsam_keys"] == [X(f["kf"]), L(f["lm"])]
            assert (f["type"] == "rgbd_stereo") == (f["depth"] > 0)
            n_obs[b] += 1
    for l in graph["landmarks"]:  # every observation of a living landmark is a factor
        assert l["observations"] == n_obs[l["key"]] >= 1
    assert graph["planes"], "the synthetic room's floor and walls are plane landmarks"
    assert meta["counts"]["planes"] == len(graph["planes"])
    for p in graph["planes"]:
        assert p["observations"] == n_plane_obs[p["key"]] >= 1
        assert abs(np.linalg.norm(p["coefficients"][:3]) - 1.0) < 1e-9
    for kf in graph["keyframes"]:
        assert np.allclose(np.array(kf["T_wc"])[3], [0, 0, 0, 1])
    for e in graph["covisibility"]:
        assert e["kf_a"] < e["kf_b"] and e["shared"] >= MIN_COVISIBILITY
    assert graph["covisibility"], "consecutive keyframes share many landmarks"


def test_errors_match_gtsam(graph):
    meta = graph["meta"]
    cam = Camera(**{k: meta["camera"][k] for k in ("fx", "fy", "cx", "cy", "width", "height")})
    mono, stereo = calibrations(cam, meta["virtual_baseline"])
    obs = [f for f in graph["factors"] if f["type"] in ("rgbd_stereo", "projection")]
    rng = np.random.default_rng(0)
    sample = [obs[i] for i in rng.choice(len(obs), size=min(300, len(obs)), replace=False)]
    sample += [f for f in obs if f["type"] == "projection"][:50]  # make sure both kinds are compared
    values = _values(graph, [f["kf"] for f in sample], [f["lm"] for f in sample])
    for f in sample:
        factor = observation_factor(f["kf"], f["lm"], np.array(f["uv"]), f["depth"], f["sigma"], mono, stereo,
                                    meta["huber_stereo"], meta["huber_mono"])
        assert f["error"] == pytest.approx(factor.error(values), rel=1e-6, abs=1e-9)
        assert f["chi2"] == pytest.approx(whitened_chi2(factor, values, f["sigma"]), rel=1e-6, abs=1e-9)


def test_networkx(run_dir, graph):
    g = load_graph_networkx(run_dir / GRAPH_FILE)
    assert g.number_of_nodes() == len(graph["keyframes"]) + len(graph["landmarks"]) + len(graph["planes"])
    assert g.number_of_edges() == len(graph["factors"])  # one factor per (keyframe, landmark or plane) pair
    p0 = graph["planes"][0]
    assert g.nodes[p0["key"]]["kind"] == "plane"
    k0 = graph["keyframes"][0]
    assert g.nodes[k0["key"]]["kind"] == "keyframe" and g.nodes[k0["key"]]["frame_index"] == k0["frame_index"]
    f = graph["factors"][0]
    assert g.edges[f["keys"]]["error"] == f["error"]
    assert g.graph["meta"]["version"] == FORMAT_VERSION


def _random_map(n_kf: int = 50, n_lm: int = 5000, per_kf: int = 400, seed: int = 0):
    """A map of n_kf keyframes on a line looking along +z, each observing per_kf landmarks (noisy pixels)."""
    rng = np.random.default_rng(seed)
    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480, 5000.0, ())
    smap = SlamMap(capacity=16)
    pts = rng.uniform([-2, -1.5, 2], [2, 1.5, 6], size=(n_lm, 3))
    pts[:20, 2] = -1.0  # a few behind every camera: GTSAM's cheirality branch
    lm_of = np.full(n_lm, -1, np.int64)  # landmark id of each point
    for k in range(n_kf):
        T = np.eye(4)
        T[0, 3] = 0.02 * k
        seen = rng.choice(n_lm, size=per_kf, replace=False)
        if k == 0:
            seen[:20] = np.arange(20)
        q = pts[seen] - T[:3, 3]  # camera frame (identity rotation)
        z = np.where(q[:, 2] > 0, q[:, 2], 1.0)
        uv = np.stack([cam.fx * q[:, 0] / z + cam.cx, cam.fy * q[:, 1] / z + cam.cy], 1) + rng.normal(0, 2, (per_kf, 2))
        depth = np.where(rng.random(per_kf) < 0.8, np.abs(q[:, 2]) + rng.normal(0, 0.02, per_kf), 0.0)
        octave = rng.integers(0, 8, per_kf)
        feats = Features(uv, octave, np.zeros((per_kf, 32), np.uint8), depth, np.full((per_kf, 3), np.nan))
        kf = KeyFrame(k, 3 * k, 0.1 * k, T, feats, np.full(per_kf, -1, np.int64))
        if k % 10 == 5:  # a dense-odometry keyframe, slightly inconsistent with its reference
            T_link = np.eye(4)
            T_link[0, 3] = 0.025
            kf.meta["odometry_link"] = (k - 1, T_link)
        smap.add_keyframe(kf)
        new = lm_of[seen] < 0  # first sighting creates the landmark, later ones observe it
        lm_of[seen[new]] = smap.add_landmarks(pts[seen[new]], np.zeros((new.sum(), 32), np.uint8), kf,
                                              np.nonzero(new)[0])
        for kp in np.nonzero(~new)[0]:
            smap.add_observation(int(lm_of[seen[kp]]), kf, int(kp))
    return smap, cam


def test_vectorised_errors_and_speed():
    smap, cam = _random_map()
    tcfg, bcfg = TrackingConfig(), BackendConfig()
    t0 = time.perf_counter()
    data = graph_to_dict(smap, cam, tcfg, bcfg)
    seconds = time.perf_counter() - t0
    assert data["meta"]["counts"]["observations"] == 20000
    assert seconds < 5.0, f"export of 50 keyframes / 20k observations took {seconds:.1f} s"
    json.dumps(data)  # serialisable as is
    mono, stereo = calibrations(cam, tcfg.virtual_baseline)
    values = gtsam.Values()
    for k, kf in smap.keyframes.items():
        values.insert(X(k), gtsam.Pose3(kf.T_wc))
    obs = [f for f in data["factors"] if f["type"] != "odometry_link"]
    behind = [f for f in obs if f["lm"] < 20]
    assert behind, "the sample must cover points behind the camera"
    rng = np.random.default_rng(1)
    sample = [obs[i] for i in rng.choice(len(obs), 500, replace=False)] + behind
    for f in sample:
        if not values.exists(L(f["lm"])):
            values.insert(L(f["lm"]), gtsam.Point3(*smap.positions[f["lm"]]))
        factor = observation_factor(f["kf"], f["lm"], np.array(f["uv"]), f["depth"], f["sigma"], mono, stereo,
                                    bcfg.huber_stereo, bcfg.huber_mono)
        assert f["error"] == pytest.approx(factor.error(values), rel=1e-9, abs=1e-12)
    links = [f for f in data["factors"] if f["type"] == "odometry_link"]
    assert len(links) == 5
    for f in links:
        assert f["keys"] == [f"x{f['other_kf']}", f"x{f['kf']}"]
        assert 0 < f["error"] < 1.0  # 5 mm off with a 3 cm sigma: 0.5 (0.005 / 0.03)^2
        assert f["error"] == pytest.approx(0.5 * (0.005 / tcfg.dense_link_sigmas[1]) ** 2, rel=1e-6)
