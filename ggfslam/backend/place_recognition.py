"""Place recognition with a bag of binary words (DBoW2-style) for ORB descriptors.

A vocabulary tree is built by hierarchical k-majority clustering (k-medians in Hamming space: the centre
of a cluster is the bitwise majority of its descriptors) with k-means++ seeding, ``branching`` children
per node and ``depth`` levels; its leaves are the words. Words carry an idf weight ``log(N / n_i)`` (N
training images, n_i of them contain word i); an image becomes a sparse, L1-normalised tf-idf vector,
and two vectors are compared with DBoW2's L1 score ``1 - |a - b|_1 / 2`` in [0, 1]. A keyframe database
keeps an inverted index (word -> keyframes, with their weights) so a query only scores keyframes sharing a word
with it.
"""
from __future__ import annotations

import functools
import threading
from array import array
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numba
import numpy as np

from ggfslam.atomic import atomic_path
from ggfslam.errors import DatasetError

__all__ = ["DESCRIPTOR_BYTES", "BowVector", "Vocabulary", "KeyframeDatabase", "bow_score", "hamming_matrix",
           "hamming_knn2"]

DESCRIPTOR_BYTES = 32  # ORB: 256-bit descriptors
_FORMAT = "ggfslam-orb-vocabulary/1"
_DEFAULT_RESOURCE = "vocabulary/orb_vocab.npz"  # inside the ggfslam.backend package


# --------------------------------------------------------------------------------------------------
# Hamming distances
# --------------------------------------------------------------------------------------------------
def _as_words64(desc: np.ndarray) -> np.ndarray:
    """View descriptors [N, 32] uint8 as [N, 4] uint64 so one XOR + popcount covers 64 bits."""
    desc = np.ascontiguousarray(desc, dtype=np.uint8)
    return desc.view(np.uint64)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances [N, M] (int) between binary descriptors a [N, 32] and b [M, 32] uint8."""
    a64 = _as_words64(a)  # [N, 4]
    b64 = _as_words64(b)  # [M, 4]
    return np.bitwise_count(a64[:, None, :] ^ b64[None, :, :]).sum(axis=-1, dtype=np.int32)  # [N, M]


@numba.njit(cache=True, inline="always")
def _popcount64(x):
    # SWAR bit count; LLVM turns it into the popcnt instruction where the CPU has one
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@numba.njit(cache=True)
def _knn2_kernel(a, b, idx, best, second):
    for i in range(a.shape[0]):
        a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
        d1 = 1 << 30
        d2 = 1 << 30
        k = -1
        for j in range(b.shape[0]):
            d = _popcount64(a0 ^ b[j, 0]) + _popcount64(a1 ^ b[j, 1]) + _popcount64(a2 ^ b[j, 2]) + \
                _popcount64(a3 ^ b[j, 3])
            if d < d1:
                d2 = d1
                d1 = d
                k = j
            elif d < d2:
                d2 = d
        idx[i] = k
        best[i] = d1
        second[i] = d2


def hamming_knn2(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each descriptor of a [N, 32]: index of the nearest in b [M, 32], its distance and the second best.

    Returns (idx [N] int64, -1 if b is empty; best [N]; second [N]); missing distances are 2**30. Ties
    keep the lower index in b.
    """
    a64 = _as_words64(_check_descriptors(a, "a"))
    b64 = _as_words64(_check_descriptors(b, "b"))
    idx = np.full(len(a64), -1, np.int64)
    best = np.full(len(a64), 1 << 30, np.int64)
    second = np.full(len(a64), 1 << 30, np.int64)
    if len(a64) and len(b64):
        _knn2_kernel(a64, b64, idx, best, second)
    return idx, best, second


def _check_descriptors(desc: np.ndarray, what: str = "descriptors") -> np.ndarray:
    """Descriptors as a C-contiguous [N, 32] uint8 array, or ValueError."""
    desc = np.asarray(desc)
    if desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_BYTES or desc.dtype != np.uint8:
        raise ValueError(f"{what} must be uint8 of shape [N, {DESCRIPTOR_BYTES}], got {desc.dtype} {desc.shape}")
    return np.ascontiguousarray(desc)


# --------------------------------------------------------------------------------------------------
# bag-of-words vectors
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BowVector:
    """Sparse bag-of-words vector: sorted unique word ids [W] int32 and their weights [W] float64 (L1 = 1)."""

    words: np.ndarray  # [W] int32, strictly increasing
    weights: np.ndarray  # [W] float64, >= 0, summing to 1 (or empty)

    def __len__(self) -> int:
        return int(len(self.words))

    @staticmethod
    def empty() -> "BowVector":
        """The vector of an image without features."""
        return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float64))


def _l1_common(wa: np.ndarray, va: np.ndarray, wb: np.ndarray, vb: np.ndarray) -> float:
    """DBoW2 L1 score of two L1-normalised sparse vectors; only shared words contribute."""
    _, ia, ib = np.intersect1d(wa, wb, assume_unique=True, return_indices=True)
    if len(ia) == 0:
        return 0.0
    a, b = va[ia], vb[ib]
    # |a|_1 = |b|_1 = 1, so 1 - |a - b|_1 / 2 = sum over shared words of (|a| + |b| - |a - b|) / 2
    return float(np.clip(0.5 * np.sum(a + b - np.abs(a - b)), 0.0, 1.0))


def bow_score(a: BowVector, b: BowVector) -> float:
    """DBoW2 L1 similarity of two BoW vectors, in [0, 1] (1 for identical vectors)."""
    return _l1_common(a.words, a.weights, b.words, b.weights)


# --------------------------------------------------------------------------------------------------
# vocabulary tree
# --------------------------------------------------------------------------------------------------
def _majority(bits: np.ndarray) -> np.ndarray:
    """Bitwise majority [32] uint8 of unpacked descriptors bits [n, 256] (ties give 0, like DBoW2)."""
    return np.packbits(bits.sum(axis=0, dtype=np.int64) * 2 > len(bits))


def _kmeanspp(desc: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds: indices [<=k] into desc [n, 32] (each next seed drawn with probability ~ d^2)."""
    n = len(desc)
    seeds = [int(rng.integers(n))]
    d2 = hamming_matrix(desc, desc[seeds[0]:seeds[0] + 1])[:, 0].astype(np.float64) ** 2  # [n]
    while len(seeds) < k:
        total = d2.sum()
        if total <= 0:  # every descriptor equals some seed already: fewer distinct clusters than k
            break
        nxt = int(np.searchsorted(np.cumsum(d2), rng.random() * total, side="right"))
        nxt = min(nxt, n - 1)
        seeds.append(nxt)
        d2 = np.minimum(d2, hamming_matrix(desc, desc[nxt:nxt + 1])[:, 0].astype(np.float64) ** 2)
    return np.asarray(seeds)


def _kmajority(desc: np.ndarray, k: int, rng: np.random.Generator, max_iter: int) -> list[np.ndarray]:
    """Cluster desc [n, 32] into <= k groups; returns (centre [32] uint8, member indices) pairs in a fixed order."""
    centres = desc[_kmeanspp(desc, k, rng)]  # [k', 32]
    bits = np.unpackbits(desc, axis=1)  # [n, 256]
    labels = None
    for _ in range(max_iter):
        new = np.argmin(hamming_matrix(desc, centres), axis=1)  # [n]
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        keep = np.unique(labels)  # empty clusters disappear
        centres = np.stack([_majority(bits[labels == c]) for c in keep])
    labels = np.argmin(hamming_matrix(desc, centres), axis=1)
    return [(centres[c], np.nonzero(labels == c)[0]) for c in range(len(centres)) if np.any(labels == c)]


class Vocabulary:
    """Vocabulary tree of ORB words: ``train``, ``words``, ``transform``, ``save`` / ``load``, ``default``.

    Nodes are numbered breadth-first; node 0 is the root (no centre). ``centres`` [n_nodes, 32] uint8,
    ``parent`` [n_nodes] int32 (-1 for the root), ``word_of_node`` [n_nodes] int32 (-1 for inner nodes),
    ``idf`` [n_words] float64.
    """

    def __init__(self, centres: np.ndarray, parent: np.ndarray, word_of_node: np.ndarray, idf: np.ndarray,
                 branching: int, depth: int):
        self.centres = np.ascontiguousarray(centres, dtype=np.uint8)  # [n_nodes, 32]
        self.parent = np.asarray(parent, dtype=np.int32)  # [n_nodes]
        self.word_of_node = np.asarray(word_of_node, dtype=np.int32)  # [n_nodes]
        self.idf = np.asarray(idf, dtype=np.float64)  # [n_words]
        self.branching = int(branching)
        self.depth = int(depth)
        n = len(self.parent)
        # children table [n_nodes, B] (-1 = none) for a vectorised descent; B = the largest child count
        child_ids = np.nonzero(self.parent >= 0)[0]
        counts = np.bincount(self.parent[child_ids], minlength=n)
        width = max(int(counts.max(initial=0)), 1)
        self._children = np.full((n, width), -1, dtype=np.int32)
        order = child_ids[np.argsort(self.parent[child_ids], kind="stable")]
        slot = np.arange(len(order)) - np.repeat(np.cumsum(counts) - counts, counts)[: len(order)]
        self._children[self.parent[order], slot] = order
        self._centres64 = _as_words64(self.centres)  # [n_nodes, 4]

    # ---- properties ----
    @property
    def n_words(self) -> int:
        """Number of words (leaves)."""
        return int(len(self.idf))

    @property
    def n_nodes(self) -> int:
        """Number of tree nodes including the root."""
        return int(len(self.parent))

    def __repr__(self) -> str:
        return f"Vocabulary(branching={self.branching}, depth={self.depth}, words={self.n_words}, nodes={self.n_nodes})"

    # ---- training ----
    @classmethod
    def train(cls, descriptors: np.ndarray | Sequence[np.ndarray], branching: int = 10, depth: int = 3,
              seed: int = 0, image_ids: np.ndarray | None = None, max_iter: int = 15) -> "Vocabulary":
        """Build a vocabulary from ORB descriptors: a list of per-image [Ni, 32] arrays, or [M, 32] (+ image_ids [M]).

        Image membership only sets the idf weights; without it every word gets idf 1. Deterministic for a seed.
        """
        if branching < 2 or depth < 1:
            raise ValueError(f"need branching >= 2 and depth >= 1, got branching={branching} depth={depth}")
        if isinstance(descriptors, np.ndarray):
            desc = _check_descriptors(descriptors)
            if image_ids is not None:
                image_ids = np.asarray(image_ids).reshape(-1)
                if len(image_ids) != len(desc):
                    raise ValueError(f"image_ids has {len(image_ids)} entries for {len(desc)} descriptors")
        else:
            parts = [_check_descriptors(d, f"descriptors[{i}]") for i, d in enumerate(descriptors)]
            desc = np.concatenate(parts) if parts else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
            image_ids = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
        if len(desc) == 0:
            raise ValueError("cannot train a vocabulary without descriptors")
        rng = np.random.default_rng(seed)
        centres = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]  # root
        parent = [-1]
        members = [np.arange(len(desc))]
        level = [0]
        frontier = [0]  # nodes to split, breadth first
        while frontier:
            nxt = []
            for node in frontier:
                idx = members[node]
                sub = desc[idx]
                if len(sub) <= branching:
                    # as DBoW2: with no more descriptors than children, each distinct one becomes a child
                    uniq, inverse = np.unique(sub, axis=0, return_inverse=True)
                    groups = [(uniq[c], np.nonzero(inverse.reshape(-1) == c)[0]) for c in range(len(uniq))]
                else:
                    groups = _kmajority(sub, branching, rng, max_iter)
                if len(groups) < 2 and level[node] > 0:
                    continue  # one descriptor value: the node stays a leaf
                for centre, local in groups:
                    centres.append(centre)
                    parent.append(node)
                    members.append(idx[local])
                    level.append(level[node] + 1)
                    if level[-1] < depth and len(local) > 1:
                        nxt.append(len(parent) - 1)
            frontier = nxt
        parent_arr = np.asarray(parent, dtype=np.int32)
        is_leaf = np.ones(len(parent_arr), bool)
        is_leaf[parent_arr[parent_arr >= 0]] = False
        is_leaf[0] = False
        word_of_node = np.full(len(parent_arr), -1, np.int32)
        word_of_node[is_leaf] = np.arange(int(is_leaf.sum()), dtype=np.int32)
        idf = np.ones(int(is_leaf.sum()))
        if image_ids is not None:
            n_images = len(np.unique(image_ids))
            word_images = np.zeros(len(idf), np.int64)  # training images containing each word
            for node in np.nonzero(is_leaf)[0]:
                word_images[word_of_node[node]] = len(np.unique(image_ids[members[node]]))
            idf = np.log(n_images / np.maximum(word_images, 1))
        return cls(np.stack(centres), parent_arr, word_of_node, idf, branching, depth)

    # ---- use ----
    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id [N] int32 of each descriptor [N, 32] uint8 (greedy descent of the tree)."""
        desc = _check_descriptors(descriptors)
        node = np.zeros(len(desc), dtype=np.int32)
        if len(desc) == 0:
            return node
        d64 = _as_words64(desc)  # [N, 4]
        for _ in range(self.depth):
            kids = self._children[node]  # [N, B]
            valid = kids >= 0
            if not valid.any():
                break
            dist = np.bitwise_count(d64[:, None, :] ^ self._centres64[np.maximum(kids, 0)]).sum(-1, dtype=np.int32)
            dist[~valid] = np.iinfo(np.int32).max
            best = kids[np.arange(len(desc)), np.argmin(dist, axis=1)]  # [N]
            node = np.where(valid.any(axis=1), best, node)  # leaves above the full depth stay put
        return self.word_of_node[node]

    def transform(self, descriptors: np.ndarray) -> BowVector:
        """L1-normalised tf-idf BoW vector of one image's descriptors [N, 32] uint8."""
        w = self.words(descriptors)
        if len(w) == 0:
            return BowVector.empty()
        ids, counts = np.unique(w, return_counts=True)
        weights = counts / len(w) * self.idf[ids]  # tf * idf
        keep = weights > 0  # words seen in every training image carry no information
        ids, weights = ids[keep], weights[keep]
        total = weights.sum()
        if total <= 0:
            return BowVector.empty()
        return BowVector(ids.astype(np.int32), weights / total)

    def score(self, a: np.ndarray, b: np.ndarray) -> float:
        """L1 score between the BoW vectors of two descriptor sets."""
        return bow_score(self.transform(a), self.transform(b))

    # ---- files ----
    def save(self, path: str | Path) -> Path:
        """Write the vocabulary to a compressed npz file; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        # a file object keeps numpy from appending ".npz" to other suffixes
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, format=np.array(_FORMAT), centres=self.centres, parent=self.parent,
                                word_of_node=self.word_of_node, idf=self.idf.astype(np.float32),
                                branching=np.int32(self.branching), depth=np.int32(self.depth))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Vocabulary":
        """Read a vocabulary written by ``save``; DatasetError naming the file if it is missing or malformed."""
        path = Path(path)
        if not path.is_file():
            raise DatasetError(path, "vocabulary file not found")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except Exception as e:  # zip, pickle and format errors all mean "not a vocabulary npz"
            raise DatasetError(path, f"cannot read vocabulary npz ({type(e).__name__}: {e})") from None
        missing = [k for k in ("format", "centres", "parent", "word_of_node", "idf", "branching", "depth")
                   if k not in data]
        if missing:
            raise DatasetError(path, f"not a ggfslam vocabulary: missing {', '.join(missing)}")
        if str(data["format"]) != _FORMAT:
            raise DatasetError(path, f"unsupported vocabulary format {str(data['format'])!r}, expected {_FORMAT!r}")
        centres, parent, won, idf = data["centres"], data["parent"], data["word_of_node"], data["idf"]
        n = len(parent)
        problems = []
        if centres.dtype != np.uint8 or centres.shape != (n, DESCRIPTOR_BYTES):
            problems.append(f"centres must be uint8 [{n}, {DESCRIPTOR_BYTES}], got {centres.dtype} {centres.shape}")
        if won.shape != (n,) or parent.shape != (n,) or n == 0:
            problems.append("parent and word_of_node must be equal-length 1-D arrays")
        elif parent[0] != -1 or np.any(parent[1:] < 0) or np.any(parent[1:] >= np.arange(1, n)):
            problems.append("parent must list an earlier node for every node but the root")
        elif not np.array_equal(np.sort(won[won >= 0]), np.arange(len(idf))):
            problems.append(f"word_of_node must number the {len(idf)} words 0..{len(idf) - 1}")
        if not np.all(np.isfinite(idf)):
            problems.append("idf has non-finite values")
        if problems:
            raise DatasetError(path, "malformed vocabulary: " + "; ".join(problems))
        return cls(centres, parent, won, idf, int(data["branching"]), int(data["depth"]))

    @staticmethod
    def default_path() -> Path:
        """Path of the packaged default vocabulary."""
        return Path(str(resources.files("ggfslam.backend").joinpath(_DEFAULT_RESOURCE)))

    @classmethod
    def default(cls) -> "Vocabulary":
        """The packaged ORB vocabulary (loaded once and shared)."""
        return _load_default()


@functools.lru_cache(maxsize=1)
def _load_default() -> Vocabulary:
    return Vocabulary.load(Vocabulary.default_path())


# --------------------------------------------------------------------------------------------------
# keyframe database
# --------------------------------------------------------------------------------------------------
class KeyframeDatabase:
    """Inverted index of keyframe BoW vectors: add / remove keyframes and query the most similar ones.

    Each word's postings are two compact arrays (keyframe ids int32, their weights float32: 8 bytes an entry;
    Python sets of ids took ~84 KB a keyframe, about a fifth of what tracking keeps per keyframe). A query sums
    DBoW2's score over the postings of its words at once (for L1-normalised vectors ``1 - |a - b|_1 / 2`` is the sum
    of ``min(a_w, b_w)`` over shared words), keeps the keyframes that can reach ``min_score`` and the top ``top_k``
    (with a margin far above the float32 weights' rounding) and scores those exactly with ``bow_score``: the result
    is that of scoring every keyframe exactly, at the cost of a few of them. Thread-safe (tracking relocalises
    from it while the backend adds keyframes)."""

    MARGIN = 1e-5  # >> twice the summed float32 rounding of the postings' weights (~1e-7)

    def __init__(self):
        self._bows: dict[int, BowVector] = {}
        self._postings: dict[int, tuple[array, array]] = {}  # word -> (keyframe ids 'i', their weights 'f')
        self._lock = threading.RLock()

    def __getstate__(self) -> dict:  # checkpoints keep the vectors; the index and the lock are rebuilt
        return {"_bows": self._bows}

    def __setstate__(self, state: dict) -> None:
        self.__init__()  # also reads checkpoints from before the compact index (their ``_inverted`` sets)
        for kf_id, bow in state["_bows"].items():
            self.add(kf_id, bow)

    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._bows

    def ids(self) -> list[int]:
        """Ids of the stored keyframes, in insertion order."""
        return list(self._bows)

    def bow(self, kf_id: int) -> BowVector:
        """The stored BoW vector of a keyframe (KeyError if absent)."""
        return self._bows[int(kf_id)]

    def add(self, kf_id: int, bow: BowVector) -> None:
        """Store (or replace) a keyframe's BoW vector."""
        kf_id = int(kf_id)
        if not 0 <= kf_id < 2**31:
            raise ValueError(f"keyframe id {kf_id}: expected 0 <= id < 2^31")
        with self._lock:
            self.remove(kf_id)  # re-adding an id replaces its vector
            self._bows[kf_id] = bow
            for w, v in zip(bow.words.tolist(), bow.weights.tolist()):
                p = self._postings.get(w)
                if p is None:
                    p = self._postings[w] = (array("i"), array("f"))
                ids, weights = p
                ids.append(kf_id)
                weights.append(v)

    def remove(self, kf_id: int) -> None:
        """Forget a keyframe (no error if it is absent)."""
        with self._lock:
            bow = self._bows.pop(int(kf_id), None)
            if bow is None:
                return
            for w in bow.words.tolist():
                ids, weights = self._postings[w]
                i = ids.index(int(kf_id))
                del ids[i], weights[i]
                if not ids:
                    del self._postings[w]

    def score(self, bow: BowVector, kf_ids: Iterable[int]) -> dict[int, float]:
        """L1 scores of ``bow`` against the given stored keyframes (absent ids are skipped)."""
        with self._lock:
            stored = [(int(k), self._bows.get(int(k))) for k in kf_ids]
        return {k: bow_score(bow, b) for k, b in stored if b is not None}

    def _shared_scores(self, bow: BowVector) -> tuple[np.ndarray, np.ndarray]:
        """Keyframes sharing a word with ``bow`` (ids [C] ascending) and their scores [C] from the float32
        postings (within ``MARGIN / 2`` of ``bow_score``)."""
        ids, weights, q, n = [], [], [], []
        with self._lock:
            for w, v in zip(bow.words.tolist(), bow.weights.tolist()):
                p = self._postings.get(w)
                if p is not None:  # views, concatenated (copied) before the lock is released: the arrays may grow
                    ids.append(np.frombuffer(p[0], np.int32))
                    weights.append(np.frombuffer(p[1], np.float32))
                    q.append(v)
                    n.append(len(p[0]))
            if not ids:
                return np.zeros(0, np.int64), np.zeros(0)
            ids_all = np.concatenate(ids)  # [E]
            w_all = np.concatenate(weights).astype(np.float64)  # [E]
            del ids, weights
        total = np.bincount(ids_all, weights=np.minimum(w_all, np.repeat(q, n)))  # [max id + 1]
        present = np.flatnonzero(np.bincount(ids_all, minlength=len(total)))  # [C]
        return present, total[present]

    def query(self, bow: BowVector, top_k: int = 10, exclude: set[int] | None = None,
              min_score: float = 0.0) -> list[tuple[int, float]]:
        """The ``top_k`` stored keyframes most similar to ``bow`` as (kf_id, score), best first.

        Keyframes in ``exclude`` and those scoring below ``min_score`` are left out; ties go to the lower id.
        """
        top_k = max(int(top_k), 0)
        ids, approx = self._shared_scores(bow)  # only keyframes sharing a word can score above 0
        ok = approx >= min_score - self.MARGIN
        if exclude:
            ok &= ~np.isin(ids, np.fromiter((int(e) for e in exclude), np.int64))
        ids, approx = ids[ok], approx[ok]
        if 0 < top_k < len(ids):  # every one of the exact top_k is within 2 x MARGIN / 2 of the approximate k-th
            kth = np.partition(approx, len(approx) - top_k)[len(approx) - top_k]
            ids = ids[approx >= kth - self.MARGIN]
        scored = [(k, s) for k, s in self.score(bow, ids).items() if s >= min_score and s > 0.0]
        scored.sort(key=lambda ks: (-ks[1], ks[0]))
        return scored[:top_k]
