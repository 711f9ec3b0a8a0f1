"""ORB vocabulary (training, files, scores) and the keyframe database."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ggfslam.backend.place_recognition import (
    BowVector,
    KeyframeDatabase,
    Vocabulary,
    bow_score,
    hamming_knn2,
    hamming_matrix,
)
from ggfslam.data.synthetic import SyntheticSequence
from ggfslam.errors import DatasetError

STRIDE = 10  # frames between the "keyframes" of the test sequences (~10 cm)


def orb_descriptors(rgb: np.ndarray) -> np.ndarray:
    """ORB descriptors [N, 32] uint8 of a float RGB image [H, W, 3]."""
    grey = cv2.cvtColor(np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    _, desc = cv2.ORB_create(nfeatures=1000).detectAndCompute(grey, None)
    return desc


@pytest.fixture(scope="module")
def orbit_desc() -> list[np.ndarray]:
    """Descriptors of every 10th frame of a 300-frame orbit (no revisits) at 320x240."""
    seq = SyntheticSequence(300, 320, 240, "orbit", seed=1)
    return [orb_descriptors(seq[i].rgb) for i in range(0, len(seq), STRIDE)]


@pytest.fixture(scope="module")
def small_vocab(orbit_desc) -> Vocabulary:
    return Vocabulary.train(orbit_desc[:12], branching=6, depth=3, seed=0)


def test_hamming_matrix_counts_differing_bits():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    expected = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=-1).sum(-1)
    assert np.array_equal(hamming_matrix(a, b), expected)
    assert np.all(np.diag(hamming_matrix(a, a)) == 0)
    idx, best, second = hamming_knn2(a, b)
    D = np.sort(expected, axis=1)
    assert np.array_equal(best, D[:, 0]) and np.array_equal(second, D[:, 1])
    assert np.array_equal(expected[np.arange(5), idx], best)
    idx, best, second = hamming_knn2(a, b[:1])  # one candidate: no second best
    assert np.all(idx == 0) and np.all(second == 1 << 30)


def test_training_is_deterministic_for_a_seed(orbit_desc, small_vocab):
    again = Vocabulary.train(orbit_desc[:12], branching=6, depth=3, seed=0)
    assert np.array_equal(again.centres, small_vocab.centres)
    assert np.array_equal(again.parent, small_vocab.parent)
    assert np.array_equal(again.idf, small_vocab.idf)
    other = Vocabulary.train(orbit_desc[:12], branching=6, depth=3, seed=1)
    assert not (other.centres.shape == small_vocab.centres.shape and np.array_equal(other.centres,
                                                                                  small_vocab.centres))
    assert 100 < small_vocab.n_words <= 6 ** 3
    w = small_vocab.words(orbit_desc[0])
    assert w.shape == (len(orbit_desc[0]),) and w.min() >= 0 and w.max() < small_vocab.n_words
    # idf: log(N / n_i) over the 12 training images, so never negative and at most log(12)
    assert np.all(small_vocab.idf >= 0) and small_vocab.idf.max() <= np.log(12) + 1e-9


def test_training_input_forms(orbit_desc):
    flat = np.concatenate(orbit_desc[:3])
    ids = np.repeat(np.arange(3), [len(d) for d in orbit_desc[:3]])
    a = Vocabulary.train(orbit_desc[:3], branching=4, depth=2, seed=3)
    b = Vocabulary.train(flat, branching=4, depth=2, seed=3, image_ids=ids)
    assert np.array_equal(a.centres, b.centres) and np.allclose(a.idf, b.idf)
    c = Vocabulary.train(flat, branching=4, depth=2, seed=3)  # without images every word weighs the same
    assert np.all(c.idf == 1.0)
    with pytest.raises(ValueError, match="uint8"):
        Vocabulary.train(flat.astype(np.int32))
    with pytest.raises(ValueError, match="image_ids"):
        Vocabulary.train(flat, image_ids=ids[:-1])


def test_save_load_round_trip(tmp_path, orbit_desc, small_vocab):
    path = small_vocab.save(tmp_path / "sub" / "vocab.bin")  # any suffix: numpy must not append .npz
    assert path.is_file() and path.name == "vocab.bin"
    loaded = Vocabulary.load(path)
    assert np.array_equal(loaded.words(orbit_desc[5]), small_vocab.words(orbit_desc[5]))
    a, b = loaded.transform(orbit_desc[5]), small_vocab.transform(orbit_desc[5])
    assert np.array_equal(a.words, b.words)
    np.testing.assert_allclose(a.weights, b.weights, rtol=1e-6)  # idf is stored as float32


def test_load_errors_name_the_file(tmp_path, small_vocab):
    missing = tmp_path / "nope.npz"
    with pytest.raises(DatasetError, match="nope.npz: vocabulary file not found"):
        Vocabulary.load(missing)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(DatasetError, match="junk.npz: cannot read vocabulary npz"):
        Vocabulary.load(junk)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(DatasetError, match="other.npz: not a ggfslam vocabulary: missing"):
        Vocabulary.load(other)
    good = small_vocab.save(tmp_path / "good.npz")
    with np.load(good) as z:
        data = {k: z[k] for k in z.files}
    data["centres"] = data["centres"][:-1]
    broken = tmp_path / "broken.npz"
    np.savez(broken, **data)
    with pytest.raises(DatasetError, match="broken.npz: malformed vocabulary: centres"):
        Vocabulary.load(broken)


def test_default_vocabulary_is_packaged_and_small():
    path = Vocabulary.default_path()
    assert path.is_file() and path.stat().st_size < 1_000_000
    voc = Vocabulary.default()
    assert voc is Vocabulary.default()  # loaded once
    assert voc.n_words >= 5000 and voc.branching == 10 and voc.depth == 4


def test_scores_rank_same_and_nearby_views_above_far_ones(orbit_desc):
    voc = Vocabulary.default()
    bows = [voc.transform(d) for d in orbit_desc]
    n = len(bows)
    S = np.array([[bow_score(a, b) for b in bows] for a in bows])  # [n, n]
    assert np.all((S >= 0) & (S <= 1 + 1e-12))
    np.testing.assert_allclose(np.diag(S), 1.0)
    np.testing.assert_allclose(S, S.T, atol=1e-12)
    assert bow_score(bows[0], BowVector.empty()) == 0.0
    # the same view rendered with image noise (other ORB keypoints) is still nearly the best match
    noisy = SyntheticSequence(300, 320, 240, "orbit", seed=1, rgb_noise=0.02)
    for k in (3, 15, 26):
        v = voc.transform(orb_descriptors(noisy[k * STRIDE].rgb))
        s = np.array([bow_score(v, b) for b in bows])
        far = [j for j in range(n) if abs(j - k) >= 8]  # >= 80 cm along the orbit
        assert np.argmax(s) == k
        assert s[k] > 1.5 * s[far].max()
    # a neighbour (10 cm away) scores above every far view (>= 80 cm away)
    for k in range(n):
        far = [j for j in range(n) if abs(j - k) >= 8]
        near = [j for j in (k - 1, k + 1) if 0 <= j < n]
        assert max(S[k, j] for j in near) > S[k, far].max(), k


def test_keyframe_database(orbit_desc):
    voc = Vocabulary.default()
    db = KeyframeDatabase()
    bows = {k: voc.transform(d) for k, d in enumerate(orbit_desc)}
    for k, b in bows.items():
        db.add(k, b)
    assert len(db) == len(bows) and 5 in db
    res = db.query(bows[10], top_k=4)
    assert res[0] == (10, pytest.approx(1.0))
    assert all(abs(k - 10) <= 2 for k, _ in res[1:])  # then views within 20 cm
    # scores equal the brute-force L1 score, best first
    brute = sorted(((k, bow_score(bows[10], b)) for k, b in bows.items()), key=lambda ks: (-ks[1], ks[0]))
    assert [k for k, _ in db.query(bows[10], top_k=len(bows))] == [k for k, _ in brute]
    res = db.query(bows[10], top_k=3, exclude={9, 10, 11})
    assert all(k not in {9, 10, 11} for k, _ in res) and len(res) == 3
    assert db.query(bows[10], top_k=10, min_score=0.99) == [(10, pytest.approx(1.0))]
    db.remove(10)
    db.remove(10)  # absent: no error
    assert 10 not in db and all(k != 10 for k, _ in db.query(bows[10], top_k=50))
    db.add(11, bows[10])  # replacing a keyframe's vector updates the inverted index
    assert db.query(bows[10], top_k=1)[0] == (11, pytest.approx(1.0))
    assert db.query(BowVector.empty()) == []


def test_keyframe_database_query_equals_exact_scoring_of_every_keyframe(orbit_desc):
    """The query's postings sum only preselects: what it returns is, to the bit, every stored keyframe scored
    exactly (``bow_score``), filtered and cut as asked; it also survives a pickle (checkpoints), in either layout."""
    import pickle

    voc = Vocabulary.default()
    bows = {k: voc.transform(d) for k, d in enumerate(orbit_desc)}
    db = KeyframeDatabase()
    for k, b in bows.items():
        db.add(k, b)

    def brute(q, top_k, exclude=(), min_score=0.0):
        s = [(k, bow_score(q, b)) for k, b in bows.items() if k not in exclude]
        s = sorted(((k, v) for k, v in s if v >= min_score and v > 0.0), key=lambda ks: (-ks[1], ks[0]))
        return s[:top_k]

    for q in range(0, len(bows), 3):
        for top_k in (1, 2, 5, 10):
            assert db.query(bows[q], top_k=top_k) == brute(bows[q], top_k)
            assert db.query(bows[q], top_k=top_k, exclude={q, q + 1}) == brute(bows[q], top_k, {q, q + 1})
        # a threshold at a stored score keeps that keyframe (>=), one just above drops it
        second = brute(bows[q], 2)[1]
        assert db.query(bows[q], top_k=10, min_score=second[1]) == brute(bows[q], 10, min_score=second[1])
        assert second not in db.query(bows[q], top_k=10, min_score=np.nextafter(second[1], 1.0))
    restored = pickle.loads(pickle.dumps(db))
    assert restored.query(bows[7], top_k=5) == db.query(bows[7], top_k=5) and len(restored) == len(db)
    old = KeyframeDatabase.__new__(KeyframeDatabase)  # a checkpoint from before the compact index
    old.__setstate__({"_bows": dict(bows), "_inverted": {}})
    assert old.query(bows[7], top_k=5) == db.query(bows[7], top_k=5)
    for k in list(bows):  # removing every keyframe leaves no postings behind
        db.remove(k)
    assert len(db) == 0 and db._postings == {} and db.query(bows[3]) == []
