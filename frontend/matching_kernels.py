"""Compiled kernel of the match by projection (numba): from the k-d tree's candidate pairs to one map point per
keypoint.

``choose_projection_matches`` does in one pass over the pairs what ``matching.search_by_projection`` did with
~15 whole-array steps on 25,000 pairs a call (fr1/rpy: ~2.4 calls a frame, 4.2 ms of the tracking thread's
CPU per frame besides the tree): the radius and pyramid-level tests, the Hamming distances, the best and
second-best candidate of each map point, the ratio test and the best map point of each keypoint. Ties resolve
as the stable sorts did: of equal distances the pair the tree lists first, of equal winners the lower map
point. GIL released, cached on disk, no ``fastmath`` (see ``frontend/dynamic/cpr_cloud_kernels.py``).
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


@numba.njit(**_JIT)
def choose_projection_matches(pi, ki, dist_px, radius, point_scale, point_octaves, frame_octaves, check_levels,
                              max_level_gap, point_words, frame_words, max_distance, ratio):
    """For candidate pairs (map point ``pi[t]``, keypoint ``ki[t]``, ``dist_px[t]`` pixels apart) in the tree's
    order: (keypoint of each map point or -1, its Hamming distance or -1), over ``len(point_scale)`` map points.

    A pair counts when it lies within ``radius`` times the point's scale and (``check_levels``) the keypoint's
    pyramid level is within ``max_level_gap`` of the point's; a point takes its least distant keypoint if at
    most ``max_distance`` and, when its runner-up lies on the same level, at most ``ratio`` times the
    runner-up's distance; a keypoint keeps the least distant of the points that took it."""
    m = point_scale.shape[0]
    best = np.full(m, -1, np.int64)              # per map point: its best and second keypoint, their distances
    second = np.full(m, -1, np.int64)
    best_h = np.zeros(m, np.int64)
    second_h = np.zeros(m, np.int64)
    for t in range(pi.shape[0]):
        p, k = pi[t], ki[t]
        if not dist_px[t] <= radius * point_scale[p]:
            continue
        if check_levels and abs(frame_octaves[k] - point_octaves[p]) > max_level_gap:
            continue
        h = 0
        for j in range(point_words.shape[1]):
            h += _popcount64(point_words[p, j] ^ frame_words[k, j])
        if best[p] < 0 or h < best_h[p]:         # (distance, tree order): a later equal pair ranks after
            second[p], second_h[p] = best[p], best_h[p]
            best[p], best_h[p] = k, h
        elif second[p] < 0 or h < second_h[p]:
            second[p], second_h[p] = k, h
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
