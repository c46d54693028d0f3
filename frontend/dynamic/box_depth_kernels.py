"""Compiled kernels of the box_depth method (numba): the frame-to-frame descriptor match of Algorithm 3.

``mutual_best`` takes the candidate pairs in the order the k-d tree lists them and keeps, like a stable sort
on (index, distance), the first pair of least Hamming distance per keypoint of either frame: the same matches
in the same order as the numpy formulation it replaced (a packed-key argsort per side, ~5 ms of 7 for
1,000 x 1,000 keypoints on Bonn), so RANSAC's homography sees the same rows. GIL released, cached on disk,
no ``fastmath`` (see ``cpr_cloud_kernels``).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}


@numba.njit(**_JIT)
def _popcount64(x):
    """Set bits of a uint64 (the SWAR count; exact)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@numba.njit(**_JIT)
def mutual_best(words_a, words_b, ia, ib, max_distance):
    """Pairs (M,2) among the candidates ``ia[k], ib[k]`` whose Hamming distance (descriptors as rows of uint64
    words, ``words_a`` / ``words_b``) is at most ``max_distance`` and least for both of their keypoints, the
    earliest candidate winning a tie; in candidate order."""
    n = ia.shape[0]
    ham = np.empty(n, np.int64)
    for k in range(n):
        s = 0
        for j in range(words_a.shape[1]):
            s += _popcount64(words_a[ia[k], j] ^ words_b[ib[k], j])
        ham[k] = s
    best_a = np.full(words_a.shape[0], -1, np.int64)
    best_b = np.full(words_b.shape[0], -1, np.int64)
    for k in range(n):
        if ham[k] > max_distance:
            continue
        a, b = ia[k], ib[k]
        if best_a[a] < 0 or ham[k] < ham[best_a[a]]:
            best_a[a] = k
        if best_b[b] < 0 or ham[k] < ham[best_b[b]]:
            best_b[b] = k
    count = 0
    for k in range(n):
        if best_a[ia[k]] == k and best_b[ib[k]] == k:
            count += 1
    out = np.empty((count, 2), np.int64)
    m = 0
    for k in range(n):
        if best_a[ia[k]] == k and best_b[ib[k]] == k:
            out[m, 0] = ia[k]
            out[m, 1] = ib[k]
            m += 1
    return out


@numba.njit(**_JIT)
def _side_gap(pos, size, near, far):
    """Distance of a pixel centre (``pos`` + 0.5) to the nearer of a box's two sides along one axis, of those
    that count (``near``: the low side, ``far``: the high one; none: infinite)."""
    centre = pos + 0.5
    gap = np.inf
    if near:
        gap = centre
    if far:
        gap = min(gap, size - centre)
    return gap


@numba.njit(**_JIT)
def eq8_keep(region, depth, bound, omega, sides, has_layer, layer, half):
    """``box_depth_segmentation.eq8_filter`` after its mean: ``region`` less the pixels with ``bound - d_i +
    omega G_i < 0`` (``bound`` = alpha * d_ave in the depth's precision, the sum in float64, as numpy computes
    them); with ``has_layer`` a pixel within ``half`` of ``layer`` also stays when the sum holds with G measured
    to the ``sides`` that count (left, top, right, bottom)."""
    h, w = depth.shape
    out = np.zeros((h, w), np.bool_)
    all_sides = sides[0] and sides[1] and sides[2] and sides[3]
    for r in range(h):
        gy_all = _side_gap(np.float64(r), np.float64(h), True, True)
        gy = _side_gap(np.float64(r), np.float64(h), sides[1], sides[3])
        for c in range(w):
            if not region[r, c]:
                continue
            deficit = np.float64(bound - depth[r, c])
            g = min(gy_all, _side_gap(np.float64(c), np.float64(w), True, True))
            keep = deficit + omega * g >= 0.0
            if not keep and has_layer and not all_sides and abs(depth[r, c] - layer) <= half:
                g = min(gy, _side_gap(np.float64(c), np.float64(w), sides[0], sides[2]))
                keep = deficit + omega * g >= 0.0
            out[r, c] = keep
    return out
