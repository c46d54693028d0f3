"""Compiled kernel of the match by projection (numba): from the projected map points to one map point per keypoint.

``match_by_projection`` does in one pass what ``matching.search_by_projection`` did with two k-d trees, their
pair list (~25,000 pairs a call, most beyond the point's own radius: the list's radius is that of the coarsest
level) and a pass over the pairs: the candidates come from a grid of the keypoints, then the radius and
pyramid-level tests, the Hamming distances, the best and second-best candidate of each map point, the ratio test
and the best map point of each keypoint. Ties resolve as they did: of equally similar candidates a point takes the
one the k-d tree listed first, i.e. the one earlier in its leaf order (``matching.search_by_projection`` passes
that order as ``tie_rank``), of equal winners a keypoint keeps the lower map point. GIL released, cached on disk, no
``fastmath`` (see ``frontend/dynamic/cpr_cloud_kernels.py``).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}


@numba.njit(**_JIT)
def _popcount64(x):
    """Set bits of a uint64 (the SWAR count; exact). This module's own copy of box_depth_kernels' count: a cached
    kernel may call compiled functions of its own file only (tests/test_compiled_kernels.py)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


_CELL_PX = 16.0
"""Side of the grid cells the eligible keypoints are bucketed in (ORB-SLAM's GetFeaturesInArea grid is ~10 px):
a local-map search (4 px x the level's scale) reads 2 x 2 to 3 x 3 cells, a motion-model search (15-30 px) up to
~15 x 15 on the coarsest level."""


@numba.njit(**_JIT)
def _keypoint_grid(kp_uv, width, height, cell):
    """Eligible keypoints bucketed by grid cell (a counting sort, each cell's keypoints in ascending order):
    (columns, rows, start of every cell's run in ``order`` (cells + 1), ``order``). A keypoint outside the image
    (undistorted coordinates may be) goes to the nearest border cell, where a search that reaches past the
    border looks."""
    cols = max(1, int(np.ceil(width / cell)))
    rows = max(1, int(np.ceil(height / cell)))
    n = kp_uv.shape[0]
    cell_of = np.empty(n, np.int64)
    counts = np.zeros(cols * rows + 1, np.int64)
    for t in range(n):
        cx = min(max(int(np.floor(kp_uv[t, 0] / cell)), 0), cols - 1)
        cy = min(max(int(np.floor(kp_uv[t, 1] / cell)), 0), rows - 1)
        cell_of[t] = cy * cols + cx
        counts[cell_of[t] + 1] += 1
    for c in range(cols * rows):
        counts[c + 1] += counts[c]
    fill = counts[:-1].copy()
    order = np.empty(n, np.int64)
    for t in range(n):
        order[fill[cell_of[t]]] = t
        fill[cell_of[t]] += 1
    return cols, rows, counts, order


@numba.njit(**_JIT)
def _best_two(p, u, v, reach, grid, kp_uv, kp_idx, tie_rank, point_octaves, frame_octaves, check_levels, max_level_gap,
              point_words, frame_words):
    """Map point ``p``'s best and second candidate among the keypoints within ``reach`` px of (u, v), ranked by
    (Hamming distance, ``tie_rank``): (best, its distance, second, its distance), -1 where there is none. The grid's
    reading order decides nothing."""
    cols, rows, starts, order = grid
    cell = _CELL_PX
    c0 = min(max(int(np.floor((u - reach) / cell)), 0), cols - 1)
    c1 = min(max(int(np.floor((u + reach) / cell)), 0), cols - 1)
    r0 = min(max(int(np.floor((v - reach) / cell)), 0), rows - 1)
    r1 = min(max(int(np.floor((v + reach) / cell)), 0), rows - 1)
    best, best_h, best_r = -1, 0, 0
    second, second_h, second_r = -1, 0, 0
    for cy in range(r0, r1 + 1):
        for cx in range(c0, c1 + 1):
            c = cy * cols + cx
            for s in range(starts[c], starts[c + 1]):
                t = order[s]
                dx, dy = kp_uv[t, 0] - u, kp_uv[t, 1] - v
                if not np.sqrt(dx * dx + dy * dy) <= reach:
                    continue
                k = kp_idx[t]
                if check_levels and abs(frame_octaves[k] - point_octaves[p]) > max_level_gap:
                    continue
                h = 0
                for j in range(point_words.shape[1]):
                    h += _popcount64(point_words[p, j] ^ frame_words[k, j])
                r = tie_rank[t]
                if best < 0 or h < best_h or (h == best_h and r < best_r):
                    second, second_h, second_r = best, best_h, best_r
                    best, best_h, best_r = k, h, r
                elif second < 0 or h < second_h or (h == second_h and r < second_r):
                    second, second_h, second_r = k, h, r
    return best, best_h, second, second_h


@numba.njit(**_JIT)
def match_by_projection(vis_idx, uv, kp_idx, kp_uv, tie_rank, radius, point_scale, point_octaves, frame_octaves,
                        check_levels, max_level_gap, point_words, frame_words, max_distance, ratio, width, height):
    """The map points ``vis_idx`` (projected to ``uv``, one row each) against the eligible keypoints ``kp_idx``
    (at ``kp_uv``): (keypoint of each of the ``len(point_scale)`` map points or -1, its Hamming distance or -1).

    A keypoint is a candidate of a point when it lies within ``radius`` times the point's scale (Euclidean, the
    distance a k-d tree reports) and (``check_levels``) its pyramid level is within ``max_level_gap`` of the
    point's; a point takes its least distant candidate (of equal distances the one of lower ``tie_rank``) if at most
    ``max_distance`` and, when its runner-up lies on the same level, at most ``ratio`` times the runner-up's
    distance; a keypoint keeps the least distant of the points that took it (of equal distances the lower map
    point). Candidates come from a grid of the keypoints (``_keypoint_grid``), so no pair list is built."""
    m = point_scale.shape[0]
    best = np.full(m, -1, np.int64)              # per map point: its best and second keypoint, their distances
    second = np.full(m, -1, np.int64)
    best_h = np.zeros(m, np.int64)
    second_h = np.zeros(m, np.int64)
    grid = _keypoint_grid(kp_uv, width, height, _CELL_PX)
    for i in range(vis_idx.shape[0]):
        p = vis_idx[i]
        best[p], best_h[p], second[p], second_h[p] = _best_two(
            p, uv[i, 0], uv[i, 1], radius * point_scale[p], grid, kp_uv, kp_idx, tie_rank, point_octaves,
            frame_octaves, check_levels, max_level_gap, point_words, frame_words)
    winner = np.full(frame_octaves.shape[0], -1, np.int64)   # per keypoint: the map point that keeps it
    for p in range(m):
        k = best[p]
        if k < 0 or best_h[p] > max_distance:
            continue
        if second[p] >= 0 and frame_octaves[second[p]] == frame_octaves[k] and not best_h[p] <= ratio * second_h[p]:
            continue
        if winner[k] < 0 or best_h[p] < best_h[winner[k]]:
            winner[k] = p
    keypoint_of_point = np.full(m, -1, np.int64)
    distance = np.full(m, -1, np.int64)
    for k in range(winner.shape[0]):
        p = winner[k]
        if p >= 0:
            keypoint_of_point[p] = k
            distance[p] = best_h[p]
    return keypoint_of_point, distance
