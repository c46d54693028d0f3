"""Bag-of-binary-words place recognition over ORB descriptors (DBoW2-style), vectorised with numpy.

Three pieces:

``Vocabulary``
    A tree of binary "visual words" built by hierarchical k-majority clustering (k-medians in Hamming
    space: k-means++ seeding, assignment by Hamming distance, centre update by per-bit majority vote),
    ``k`` branches and at most ``levels`` levels, as in DBoW2. All groups (tree nodes) of one level are
    clustered *together* in one vectorised pass, so training has Python loops only over levels,
    k-means++ picks and iterations, never over descriptors or nodes. ``transform`` descends the tree
    level by level for all descriptors at once (Hamming distance = XOR + popcount, `slam.core.descriptors`).
    Leaves are the words; each word has an idf weight ``log(n_docs / n_docs_containing_word)`` from the
    training set (a "document" is one image when ``train`` gets a list of per-image arrays, else one
    descriptor).

``BowVector`` / ``score``
    A sparse tf-idf vector (sorted word ids + weights, L1-normalised; zero-weight words dropped) and
    DBoW2's L1 score ``1 - 0.5 * |a - b|_1`` in [0, 1]. For L1-normalised non-negative vectors this
    equals ``sum_common min(a_i, b_i)``, which is what the inverted-file query computes.

``KeyframeIndex``
    An inverted file (postings sorted by word: word, keyframe id, weight as flat arrays), so a query
    touches only keyframes that share a word with it.

File format (``Vocabulary.save`` / ``load``): a compressed ``.npz`` (no pickled objects) holding

    format            0-d str    "dynslam-bow-vocabulary"
    version           0-d int64  1 (``VOCABULARY_VERSION``)
    k, levels         0-d int64  branching factor and depth used in training
    n_training_docs   0-d int64  number of training documents (idf denominator)
    node_descriptors  (M, 32) uint8  node centres, node 0 is the root (its row is unused zeros)
    node_parents      (M,) int32     parent of each node, -1 for the root; parents precede children
    idf               (W,) float64   idf weight per word; word ids number the leaves in node order

Children are ordered by node id under their parent; leaves (nodes without children) get word ids
0..W-1 in node order. ``save`` writes a temporary file beside the target, fsyncs it and
``os.replace``-s it over the target. ``load`` raises ``VocabularyError`` naming the path for a
missing, truncated, corrupt, inconsistent or wrong-version file.
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence, Union

import numpy as np

from backend.binary_clustering import DESCRIPTOR_BYTES, cluster_level, hamming
from backend.vocabulary_kernels import descend
from slam.core.atomic_io import write_npz_atomic
from slam.core.descriptors import descriptor_words
from slam.core.errors import DynslamError

__all__ = ["VOCABULARY_VERSION", "VocabularyError", "Vocabulary", "BowVector", "score", "hamming",
           "KeyframeIndex"]

VOCABULARY_VERSION = 1
_FORMAT = "dynslam-bow-vocabulary"


class VocabularyError(DynslamError, ValueError):
    """A vocabulary file cannot be used (missing, truncated, corrupt, inconsistent, wrong version)."""


def _check_descriptors(descriptors) -> np.ndarray:
    if descriptors is None:
        return np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    d = np.asarray(descriptors)
    if d.size == 0:
        return np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"descriptors must be uint8 of shape (N, {DESCRIPTOR_BYTES}), "
                         f"got {d.dtype} {d.shape}")
    return np.ascontiguousarray(d)


@dataclass(frozen=True)
class BowVector:
    """Sparse tf-idf bag of words: strictly increasing ``words`` (int32) and positive ``weights``
    (float64) summing to 1 (both empty when no descriptor maps to a weighted word)."""

    words: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.words)


def score(a: BowVector, b: BowVector) -> float:
    """DBoW2 L1 score ``1 - 0.5 * |a - b|_1`` over the union of words; 0 if either vector is empty."""
    if len(a) == 0 or len(b) == 0:
        return 0.0
    union = np.union1d(a.words, b.words)
    va = np.zeros(len(union))
    vb = np.zeros(len(union))
    va[np.searchsorted(union, a.words)] = a.weights
    vb[np.searchsorted(union, b.words)] = b.weights
    return float(np.clip(1.0 - 0.5 * np.abs(va - vb).sum(), 0.0, 1.0))


class Vocabulary:
    """A trained word tree. Build with ``Vocabulary.train(...)`` or ``Vocabulary.load(path)``."""

    def __init__(self, node_descriptors: np.ndarray, node_parents: np.ndarray, idf: np.ndarray,
                 k: int, levels: int, n_training_docs: int) -> None:
        self.node_descriptors = np.ascontiguousarray(node_descriptors, np.uint8)
        self._node_words = descriptor_words(self.node_descriptors)      # (M, 4) uint64: the descent's bit counts
        self.node_parents = np.asarray(node_parents, np.int32)
        self.k = int(k)
        self.levels = int(levels)
        self.n_training_docs = int(n_training_docs)
        m = len(self.node_parents)
        self._children = np.full((m, max(self.k, 1)), -1, np.int32)
        child = np.arange(1, m, dtype=np.int32)
        par = self.node_parents[1:]
        order = np.argsort(par, kind="stable")
        par_s, child_s = par[order], child[order]
        first = np.searchsorted(par_s, par_s, side="left")
        slot = np.arange(len(par_s)) - first
        self._children[par_s, slot] = child_s
        is_leaf = self._children[:, 0] < 0
        if m == 1:
            is_leaf[0] = True
        self._node_word = np.full(m, -1, np.int32)
        self._node_word[is_leaf] = np.arange(int(is_leaf.sum()), dtype=np.int32)
        self.idf = np.asarray(idf, np.float64)

    # ------------------------------------------------------------------ properties
    @property
    def n_words(self) -> int:
        return int((self._node_word >= 0).sum())

    @property
    def n_nodes(self) -> int:
        return len(self.node_parents)

    # ------------------------------------------------------------------ training
    @classmethod
    def train(cls, descriptors: Union[np.ndarray, Sequence[np.ndarray]], k: int = 10, levels: int = 3,
              seed: int = 0, iterations: int = 10) -> "Vocabulary":
        """Train on uint8 (N, 32) descriptors, or a list of per-image arrays (then idf counts images).

        Deterministic for a given input and ``seed``. Nodes holding a single descriptor stop splitting.
        """
        if k < 2 or levels < 1 or iterations < 0:
            raise ValueError("need k >= 2, levels >= 1, iterations >= 0")
        if isinstance(descriptors, np.ndarray):
            x = _check_descriptors(descriptors)
            docs = None
        else:
            parts = [_check_descriptors(d) for d in descriptors]
            x = np.concatenate(parts) if parts else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
            docs = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
        if len(x) == 0:
            raise ValueError("cannot train a vocabulary on zero descriptors")
        rng = np.random.default_rng(seed)
        node_desc = [np.zeros((1, DESCRIPTOR_BYTES), np.uint8)]
        node_par = [np.array([-1], np.int32)]
        n_nodes = 1
        assign = np.zeros(len(x), np.int64)  # current node of each training descriptor
        active = np.array([0])  # nodes to split at this level
        for _ in range(levels):
            if len(active) == 0:
                break
            is_active = np.zeros(n_nodes, bool)
            is_active[active] = True
            sel = np.flatnonzero(is_active[assign])
            node_of = assign[sel]
            order = np.argsort(node_of, kind="stable")
            sel, node_of = sel[order], node_of[order]
            groups, group = np.unique(node_of, return_inverse=True)
            labels, centres = cluster_level(x[sel], group, len(groups), k, iterations, rng)
            cid = group * k + labels
            csize = np.bincount(cid, minlength=len(groups) * k)
            made = np.flatnonzero(csize)  # (group, slot) pairs that got descriptors, group-major
            new_id = np.full(len(groups) * k, -1, np.int64)
            new_id[made] = n_nodes + np.arange(len(made))
            node_desc.append(centres.reshape(-1, DESCRIPTOR_BYTES)[made])
            node_par.append(groups[made // k].astype(np.int32))
            n_nodes += len(made)
            assign[sel] = new_id[cid]
            active = new_id[made[csize[made] >= 2]]
        vocab = cls(np.concatenate(node_desc), np.concatenate(node_par),
                    np.zeros(0), k, levels, 1)
        words = vocab.transform(x)
        if docs is None:
            n_docs = len(x)
            df = np.bincount(words, minlength=vocab.n_words)
        else:
            n_docs = int(docs[-1]) + 1 if len(docs) else 0
            pairs = np.unique(docs.astype(np.int64) * vocab.n_words + words)
            df = np.bincount(pairs % vocab.n_words, minlength=vocab.n_words)
        vocab.idf = np.log(n_docs / np.maximum(df, 1))
        vocab.n_training_docs = n_docs
        return vocab

    # ------------------------------------------------------------------ lookup
    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id (int32, shape (N,)) of each descriptor: greedy descent, nearest child per level (the first of
        equal ones), compiled (``backend.vocabulary_kernels.descend``)."""
        x = _check_descriptors(descriptors)
        return descend(descriptor_words(x), self._node_words, self._children, int(self.levels), self._node_word)

    def bow(self, descriptors: np.ndarray) -> BowVector:
        """tf-idf ``BowVector`` of one image's descriptors (tf = count / N, L1-normalised)."""
        words = self.transform(descriptors)
        if len(words) == 0:
            return BowVector(np.zeros(0, np.int32), np.zeros(0))
        uw, counts = np.unique(words, return_counts=True)
        w = counts / len(words) * self.idf[uw]
        keep = w > 0
        uw, w = uw[keep], w[keep]
        total = w.sum()
        if total <= 0:
            return BowVector(np.zeros(0, np.int32), np.zeros(0))
        return BowVector(uw.astype(np.int32), w / total)

    # ------------------------------------------------------------------ persistence
    def save(self, path: Union[str, os.PathLike]) -> Path:
        """Write the documented ``.npz`` format atomically (temp file + fsync + os.replace)."""
        return write_npz_atomic(path, format=np.array(_FORMAT), version=np.array(VOCABULARY_VERSION, np.int64),
                                **self.to_arrays())

    @classmethod
    def load(cls, path: Union[str, os.PathLike]) -> "Vocabulary":
        """Read a file written by ``save``; any problem raises ``VocabularyError`` naming ``path``."""
        keys = ("format", "version", "k", "levels", "n_training_docs", "node_descriptors",
                "node_parents", "idf")
        try:
            with np.load(path, allow_pickle=False) as z:
                if "version" not in z.files or "format" not in z.files:
                    raise VocabularyError(f"{path}: not a dynslam vocabulary file (no format/version)")
                if str(z["format"]) != _FORMAT:
                    raise VocabularyError(f"{path}: format {str(z['format'])!r}, expected {_FORMAT!r}")
                version = int(z["version"])
                if version != VOCABULARY_VERSION:
                    raise VocabularyError(f"{path}: vocabulary version {version}, "
                                          f"this code reads version {VOCABULARY_VERSION}")
                missing = [key for key in keys if key not in z.files]
                if missing:
                    raise VocabularyError(f"{path}: missing arrays {missing}")
                a = {key: z[key] for key in keys}
        except VocabularyError:
            raise
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile) as e:
            raise VocabularyError(f"{path}: cannot read vocabulary ({type(e).__name__}: {e})") from e
        return cls.from_arrays(a, str(path))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The members of the file format (also embedded, prefixed, in map files)."""
        return {"k": np.array(self.k, np.int64), "levels": np.array(self.levels, np.int64),
                "n_training_docs": np.array(self.n_training_docs, np.int64),
                "node_descriptors": self.node_descriptors, "node_parents": self.node_parents, "idf": self.idf}

    @classmethod
    def from_arrays(cls, a: dict, source: str) -> "Vocabulary":
        """A vocabulary from ``to_arrays`` members, checked; problems raise ``VocabularyError``."""
        desc, par, idf = a["node_descriptors"], a["node_parents"], a["idf"]
        k, levels, n_docs = int(a["k"]), int(a["levels"]), int(a["n_training_docs"])
        m = len(par)
        problems = []
        if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape != (m, DESCRIPTOR_BYTES):
            problems.append("node_descriptors must be uint8 (M, 32) matching node_parents")
        if par.ndim != 1 or m < 1 or not np.issubdtype(par.dtype, np.integer):
            problems.append("node_parents must be a non-empty integer vector")
        elif par[0] != -1 or np.any(par[1:] < 0) or np.any(par[1:] >= np.arange(1, m)):
            problems.append("node_parents must have root -1 and each parent before its child")
        elif m > 1 and np.bincount(par[1:], minlength=m).max() > k:
            problems.append("a node has more than k children")
        if k < 2 or levels < 1 or n_docs < 1:
            problems.append("k, levels, n_training_docs out of range")
        if idf.dtype != np.float64 or idf.ndim != 1 or not np.all(np.isfinite(idf)) or np.any(idf < 0):
            problems.append("idf must be a finite non-negative float64 vector")
        if problems:
            raise VocabularyError(f"{source}: inconsistent vocabulary: {'; '.join(problems)}")
        vocab = cls(desc, par.astype(np.int32), idf, k, levels, n_docs)
        if len(idf) != vocab.n_words:
            raise VocabularyError(f"{source}: idf has {len(idf)} entries for {vocab.n_words} words")
        return vocab


DEFAULT_VOCABULARY = Path(__file__).resolve().parent / "data" / "orb_vocabulary.npz"
"""Shipped with the package: 10 branches x 4 levels (9924 words) trained on every 4th colour image of
the sequences in ../shared/data (TUM fr1 rpy/xyz/desk, Bonn crowd): ``dynslam vocabulary
../shared/data/*/rgb -o backend/data/orb_vocabulary.npz --step 4 --branches 10 --levels 4``."""


def load_vocabulary(path: Union[str, os.PathLike, None] = None) -> "Vocabulary":
    """The vocabulary at ``path``, or the shipped default when ``path`` is None."""
    return Vocabulary.load(DEFAULT_VOCABULARY if path is None else path)


class KeyframeIndex:
    """Inverted-file keyframe database over a ``Vocabulary``.

    Postings are three flat arrays sorted by word (stable, so insertion order within a word);
    ``add`` merges with ``np.insert`` (O(postings)), ``remove`` filters, ``query`` gathers only the
    postings of the query's words and accumulates ``min(q_w, kf_w)`` per keyframe, which equals the
    L1 score ``1 - 0.5 |q - kf|_1`` for L1-normalised vectors.
    """

    def __init__(self, vocabulary: Vocabulary) -> None:
        self.vocabulary = vocabulary
        self._bows: dict[int, BowVector] = {}
        self._words = np.zeros(0, np.int32)
        self._kfs = np.zeros(0, np.int64)
        self._weights = np.zeros(0, np.float64)

    def __len__(self) -> int:
        return len(self._bows)

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._bows

    def bow(self, kf_id: int) -> BowVector:
        return self._bows[int(kf_id)]

    def add(self, kf_id: int, descriptors: np.ndarray) -> BowVector:
        """Index keyframe ``kf_id`` (raises ValueError if already present); returns its BowVector."""
        kf_id = int(kf_id)
        if kf_id in self._bows:
            raise ValueError(f"keyframe {kf_id} is already indexed")
        v = self.vocabulary.bow(descriptors)
        self.add_bow(kf_id, v)
        return v

    def add_bow(self, kf_id: int, v: BowVector) -> None:
        """Index a keyframe by a BoW vector computed earlier (e.g. read from a map file)."""
        kf_id = int(kf_id)
        if kf_id in self._bows:
            raise ValueError(f"keyframe {kf_id} is already indexed")
        self._bows[kf_id] = v
        if len(v):
            pos = np.searchsorted(self._words, v.words, side="right")
            self._words = np.insert(self._words, pos, v.words)
            self._kfs = np.insert(self._kfs, pos, kf_id)
            self._weights = np.insert(self._weights, pos, v.weights)

    def remove(self, kf_id: int) -> None:
        """Drop keyframe ``kf_id`` (KeyError if absent)."""
        kf_id = int(kf_id)
        del self._bows[kf_id]
        keep = self._kfs != kf_id
        self._words, self._kfs, self._weights = self._words[keep], self._kfs[keep], self._weights[keep]

    def query(self, descriptors: np.ndarray, exclude: Iterable[int] = frozenset(),
              top_k: int = 10) -> list[tuple[int, float]]:
        """Best ``top_k`` (kf_id, score) pairs, score descending (ties: lower kf_id first), among
        keyframes that share at least one word with the query and are not in ``exclude``."""
        return self.query_bow(self.vocabulary.bow(descriptors), exclude, top_k)

    def query_bow(self, q: BowVector, exclude: Iterable[int] = frozenset(),
                  top_k: int = 10) -> list[tuple[int, float]]:
        """``query`` by a BoW vector computed earlier (a keyframe's, which is also indexed and scored)."""
        if len(q) == 0 or len(self._words) == 0 or top_k <= 0:
            return []
        lo = np.searchsorted(self._words, q.words, side="left")
        hi = np.searchsorted(self._words, q.words, side="right")
        n = hi - lo
        total = int(n.sum())
        if total == 0:
            return []
        # Expand the [lo, hi) ranges into one index array without a Python loop.
        owner = np.repeat(np.arange(len(n)), n)
        idx = lo[owner] + np.arange(total) - np.repeat(np.cumsum(n) - n, n)
        kfs = self._kfs[idx]
        contrib = np.minimum(self._weights[idx], q.weights[owner])
        ex = np.fromiter((int(e) for e in exclude), np.int64)
        if len(ex):
            keep = ~np.isin(kfs, ex)
            kfs, contrib = kfs[keep], contrib[keep]
            if len(kfs) == 0:
                return []
        ids, inv = np.unique(kfs, return_inverse=True)
        scores = np.bincount(inv, weights=contrib, minlength=len(ids))
        order = np.lexsort((ids, -scores))[:top_k]
        return [(int(ids[i]), float(min(scores[i], 1.0))) for i in order]
