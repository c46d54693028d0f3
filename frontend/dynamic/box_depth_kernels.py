"""Compiled kernels of the box_depth method (numba): the frame-to-frame descriptor match of Algorithm 3, Eq. 8's
per-pixel test, the flood fill's prepared crop, and the person layer's histogram and band counts (each the same
result as the numpy code it replaced, which ``tests/test_box_depth_equivalence.py`` and
``tests/test_compiled_masks.py`` keep as the reference).

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
def _side_gaps(size, near, far):
    """Distance of each pixel centre (index + 0.5) along one axis of ``size`` pixels to the nearer of a box's two
    sides, of those that count (``near``: the low side, ``far``: the high one; none: infinite)."""
    gaps = np.empty(size, np.float64)
    for i in range(size):
        centre = np.float64(i) + 0.5
        gap = np.inf
        if near:
            gap = centre
        if far:
            gap = min(gap, np.float64(size) - centre)
        gaps[i] = gap
    return gaps


@numba.njit(**_JIT)
def eq8_keep(region, depth, bound, omega, sides, has_layer, layer, half):
    """``box_depth_segmentation.eq8_filter`` after its mean: ``region`` less the pixels with ``bound - d_i +
    omega G_i < 0`` (``bound`` = alpha * d_ave in the depth's precision, the sum in float64, as numpy computes
    them); with ``has_layer`` a pixel within ``half`` of ``layer`` also stays when the sum holds with G measured
    to the ``sides`` that count (left, top, right, bottom)."""
    h, w = depth.shape
    out = np.zeros((h, w), np.bool_)
    all_sides = sides[0] and sides[1] and sides[2] and sides[3]
    gy_all, gx_all = _side_gaps(h, True, True), _side_gaps(w, True, True)
    gy_sides, gx_sides = _side_gaps(h, sides[1], sides[3]), _side_gaps(w, sides[0], sides[2])
    for r in range(h):
        gy = gy_all[r]
        for c in range(w):
            if not region[r, c]:
                continue
            deficit = np.float64(bound - depth[r, c])
            keep = deficit + omega * min(gy, gx_all[c]) >= 0.0
            if not keep and has_layer and not all_sides and abs(depth[r, c] - layer) <= half:
                keep = deficit + omega * min(gy_sides[r], gx_sides[c]) >= 0.0
            out[r, c] = keep
    return out


@numba.njit(**_JIT)
def fill_inputs(depth):
    """What ``cv2.floodFill`` takes for a depth crop, in one pass: the depth as contiguous float32 with 0 where it
    is invalid (not finite or <= 0 after the cast; floodFill must not see NaN), and its (h+2, w+2) uint8 mask with
    1 on the invalid pixels (never entered) and 0 elsewhere, the border included."""
    h, w = depth.shape
    image = np.empty((h, w), np.float32)
    mask = np.zeros((h + 2, w + 2), np.uint8)
    inf = np.float32(np.inf)
    for r in range(h):
        for c in range(w):
            d = np.float32(depth[r, c])
            valid = d > 0 and d < inf            # NaN fails both; a select, not a branch
            image[r, c] = d if valid else np.float32(0)
            mask[r + 1, c + 1] = np.uint8(0 if valid else 1)
    return image, mask


@numba.njit(**_JIT)
def histogram_counts(values, edges, step):
    """``np.histogram(values, edges)[0]`` for increasing ``edges`` about ``step`` apart: bin k holds edges[k] <= v <
    edges[k+1], the last bin its right edge too, values outside (and NaN) in none. The bin is guessed from
    ``step`` and settled by comparing with the edges themselves, the comparisons numpy's sorted search makes,
    so the counts are the same whatever the guess."""
    n_bins = edges.shape[0] - 1
    counts = np.zeros(max(n_bins, 0), np.int64)
    if n_bins < 1:
        return counts
    first, last = edges[0], edges[n_bins]
    for i in range(values.shape[0]):
        v = values[i]
        if not (v >= first and v <= last):
            continue
        k = min(max(int((v - first) / step), 0), n_bins - 1)
        while k > 0 and v < edges[k]:
            k -= 1
        while k < n_bins - 1 and v >= edges[k + 1]:
            k += 1
        counts[k] += 1
    return counts


@numba.njit(**_JIT)
def band_counts(values, centres, half):
    """For each centre, how many ``values`` lie within ``half`` of it (|v - c| <= half, in float64)."""
    counts = np.zeros(centres.shape[0], np.int64)
    for k in range(centres.shape[0]):
        centre, count = centres[k], 0
        for i in range(values.shape[0]):
            count += abs(values[i] - centre) <= half
        counts[k] = count
    return counts


@numba.njit(**_JIT)
def positive_samples(depth, y0, y1, x0, x1, step):
    """``depth[y0:y1:step, x0:x1:step]`` as float64, its values > 0 only, in row-major order (numpy's cast and
    boolean index of the strided crop in one pass)."""
    count = 0
    for r in range(y0, y1, step):
        for c in range(x0, x1, step):
            if np.float64(depth[r, c]) > 0:
                count += 1
    out = np.empty(count, np.float64)
    k = 0
    for r in range(y0, y1, step):
        for c in range(x0, x1, step):
            v = np.float64(depth[r, c])
            if v > 0:
                out[k] = v
                k += 1
    return out


@numba.njit(**_JIT)
def _pixel_index(x, size):
    """``np.clip(np.rint(x).astype(int), 0, size - 1)`` for one coordinate: numpy's cast of a NaN, an infinity or a
    value beyond int64 gives int64's minimum (x86), which the clip takes to 0."""
    r = np.rint(x)
    i = np.int64(-9223372036854775807 - 1)
    if r >= -9.223372036854775808e18 and r < 9.223372036854775808e18:
        i = np.int64(r)
    return min(max(i, 0), size - 1)


@numba.njit(**_JIT)
def _sum8(a0, a1, a2, a3, a4, a5, a6, a7):
    """numpy's sum of a row of 8 float64 (its pairwise summation unrolled by 8)."""
    return ((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7))


@numba.njit(**_JIT)
def composite_values(img, uv, skip_zero):
    """``box_depth.composite``: (the value at each point's nearest pixel + the mean of its 8 neighbours, the border
    clamped) / 2 in float64; with ``skip_zero`` the neighbours <= 0 (or NaN) are left out of the mean (none left:
    the centre), and a centre that is not > 0 gives NaN."""
    h, w = img.shape
    out = np.empty(uv.shape[0])
    nb = np.empty(8)
    for t in range(uv.shape[0]):
        c = _pixel_index(uv[t, 0], w)
        r = _pixel_index(uv[t, 1], h)
        centre = np.float64(img[r, c])
        k = 0
        for dr in range(-1, 2):            # the ring in row-major order, as the numpy code lists it
            for dc in range(-1, 2):
                if dr == 0 and dc == 0:
                    continue
                nb[k] = np.float64(img[min(max(r + dr, 0), h - 1), min(max(c + dc, 0), w - 1)])
                k += 1
        if not skip_zero:
            out[t] = (centre + _sum8(nb[0], nb[1], nb[2], nb[3], nb[4], nb[5], nb[6], nb[7]) / 8.0) / 2.0
            continue
        count = 0
        for k in range(8):
            if nb[k] > 0:
                count += 1
                nb[k] = nb[k] * 1.0
            else:
                nb[k] = nb[k] * 0.0             # NaN stays NaN, as numpy's value * False
        mean = centre
        if count > 0:
            mean = _sum8(nb[0], nb[1], nb[2], nb[3], nb[4], nb[5], nb[6], nb[7]) / np.float64(count)
        out[t] = (centre + mean) / 2.0 if centre > 0 else np.nan
    return out
