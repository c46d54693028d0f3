"""Binary k-majority clustering in Hamming space, the building block of the BoW vocabulary.

Descriptors are uint8 (N, 32) ORB strings. Distances are XOR + popcount (``slam.core.descriptors``), chunked so the
(rows, k, 32) temporaries stay ~10 MB; centres are per-bit majorities (k-medians in Hamming space),
seeded k-means++ style. All nodes of one tree level are clustered together in one vectorised pass.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from slam.core.descriptors import hamming

DESCRIPTOR_BYTES = 32
_CHUNK = 1 << 15  # rows per chunk of the (rows, k, 32) XOR tensors, bounds memory at ~10 MB per k=10


def row_distances(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(n, 32) descriptors against their own (n, c, 32) candidate centres -> (n, c) distances, chunked."""
    out = np.empty(centres.shape[:2], np.int32)
    for s in range(0, len(x), _CHUNK):
        out[s:s + _CHUNK] = hamming(x[s:s + _CHUNK, None, :], centres[s:s + _CHUNK])
    return out


def _pick_in_groups(weights, starts, sizes, need, rng) -> np.ndarray:
    """For each group with ``need``: index (into the group-sorted arrays) drawn with prob ~ weights,
    uniformly when a group's weights are all zero. Returns -1 where not needed."""
    u = rng.random(len(sizes))
    cs = np.cumsum(weights)
    before = np.where(starts > 0, cs[np.maximum(starts - 1, 0)], 0.0)
    ends = starts + sizes
    total = cs[np.maximum(ends - 1, 0)] - before
    pick = np.searchsorted(cs, before + u * total, side="right")
    uniform = starts + np.minimum((u * sizes).astype(np.int64), np.maximum(sizes - 1, 0))
    pick = np.where(total > 0, pick, uniform)
    pick = np.clip(pick, starts, np.maximum(ends - 1, starts))
    return np.where(need, pick, -1)


def cluster_level(x: np.ndarray, group: np.ndarray, n_groups: int, k: int, iterations: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """k-majority clustering of every group at once. ``x`` (n, 32) sorted by ``group`` (n,).

    Returns (labels (n,) in [0, k), centres (G, k, 32)); group g uses min(k, size_g) centre slots.
    """
    n = len(x)
    sizes = np.bincount(group, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    kg = np.minimum(sizes, k)
    slot_ok = np.arange(k)[None, :] < kg[:, None]  # (G, k)

    # k-means++ seeding (weights = squared distance to the nearest chosen centre), all groups at once.
    centres = np.zeros((n_groups, k, DESCRIPTOR_BYTES), np.uint8)
    mind = np.full(n, np.iinfo(np.int32).max, np.int64)
    for j in range(k):
        need = kg > j
        if not need.any():
            break
        w = np.where(mind == np.iinfo(np.int32).max, 1.0, mind.astype(np.float64) ** 2)
        pick = _pick_in_groups(w, starts, sizes, need, rng)
        centres[need, j] = x[pick[need]]
        row_need = need[group]
        d = hamming(x[row_need], centres[group[row_need], j])
        mind[row_need] = np.minimum(mind[row_need], d)

    bits = np.unpackbits(x, axis=1).astype(np.int32)  # (n, 256)
    big = np.int32(1 << 20)

    def assign(c: np.ndarray) -> np.ndarray:
        d = row_distances(x, c[group])
        d[~slot_ok[group]] = big
        return np.argmin(d, axis=1)

    labels = assign(centres)
    cols = np.arange(n)
    for _ in range(iterations):
        cid = group * k + labels
        member = sp.csr_matrix((np.ones(n, np.int32), (cid, cols)), shape=(n_groups * k, n))
        counts = np.asarray(member @ bits)  # (G*k, 256) number of set bits per cluster
        csize = np.bincount(cid, minlength=n_groups * k)
        new = np.packbits((2 * counts > csize[:, None]).astype(np.uint8), axis=1).reshape(centres.shape)
        keep = (csize == 0).reshape(n_groups, k)  # empty clusters keep their old centre
        new[keep] = centres[keep]
        centres = new
        relabel = assign(centres)
        if np.array_equal(relabel, labels):
            break
        labels = relabel
    return labels, centres
