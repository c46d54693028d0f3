"""Descriptor matching: by projection into the current frame, and brute force with a ratio test.

By projection: one compiled pass (numba) over the projected points, candidates from a grid of keypoints,
Hamming distances by popcount of 64-bit words; it runs three times a frame on the tracking thread, where the
k-d tree, the sorts and the ~20 numpy calls of the vectorised version cost ~3 ms a frame. Brute force: OpenCV's
matcher, then "one map point per keypoint" by sorting.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from slam.core.camera import PinholeCamera
from slam.core.frame import FeatureFrame, MapPoints

@dataclass
class ProjectionMatches:
    keypoint_of_point: np.ndarray   # (M,) index into the frame's features, -1 = unmatched
    distance: np.ndarray            # (M,) Hamming distance of the match (or -1)
    visible: np.ndarray             # (M,) bool: projected inside the image in front of the camera


def first_per_group(groups: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Indices of the element with the smallest key in each group."""
    order = np.lexsort((keys, groups))
    if len(order) == 0:
        return order
    first = np.r_[True, groups[order][1:] != groups[order][:-1]]
    return order[first]


def search_by_projection(frame: FeatureFrame, points: MapPoints, T_cw: np.ndarray, camera: PinholeCamera,
                         radius: float, max_distance: int, ratio: float, eligible: np.ndarray,
                         max_level_gap: int = 1) -> ProjectionMatches:
    """Match map points to the frame's eligible keypoints near their projection under T_cw.

    The search radius grows with the keypoint's pyramid scale; the best candidate must beat the
    second best by ``ratio`` and stay under ``max_distance``; each keypoint keeps its best point.
    Among candidates at the same Hamming distance the lower keypoint index counts as nearer, and among
    points claiming one keypoint at the same distance the lower point index wins (``_match_projected``).
    """
    m = len(points)
    result = ProjectionMatches(np.full(m, -1), np.full(m, -1), np.zeros(m, bool))
    if m == 0 or not eligible.any():
        return result
    pc = points.xyz @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv, z = camera.project(pc)
    visible = (z > camera.min_depth) & camera.in_image(np.nan_to_num(uv, nan=-1.0))
    result.visible = visible
    vis_idx = np.flatnonzero(visible)
    kp_idx = np.flatnonzero(eligible)
    if len(vis_idx) == 0:
        return result
    has_octave = len(points.octaves) == m
    point_octave = points.octaves[vis_idx] if has_octave else np.zeros(len(vis_idx), np.int64)
    # ORB-SLAM: the radius scales with the level the point was seen at, and the keypoint must lie
    # on a neighbouring level of the pyramid.
    point_scale = frame.scale_factors[np.clip(point_octave, 0, len(frame.scale_factors) - 1)] if has_octave \
        else np.ones(len(vis_idx))
    kp_of_point, distance = _match_projected(
        np.ascontiguousarray(uv[vis_idx]), radius * np.asarray(point_scale, np.float64),
        np.asarray(point_octave, np.int64), _words(points.descriptors[vis_idx]),
        np.ascontiguousarray(frame.uv[kp_idx], dtype=np.float64), np.asarray(frame.octaves[kp_idx], np.int64),
        _words(frame.descriptors[kp_idx]), int(max_distance), float(ratio), int(max_level_gap), has_octave,
        float(camera.width), float(camera.height))
    matched = kp_of_point >= 0
    result.keypoint_of_point[vis_idx[matched]] = kp_idx[kp_of_point[matched]]
    result.distance[vis_idx[matched]] = distance[matched]
    return result


def _words(descriptors: np.ndarray) -> np.ndarray:
    """32-byte ORB descriptors as (N, 4) uint64 words (for the compiled popcount)."""
    return np.ascontiguousarray(descriptors, dtype=np.uint8).view(np.uint64).reshape(len(descriptors), -1)


@numba.njit(nogil=True, cache=True)
def _popcount(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@numba.njit(nogil=True, cache=True)
def _match_projected(uv, search_px, octave, words, kp_uv, kp_octave, kp_words, max_distance, ratio, max_level_gap,
                     has_octave, width, height):
    """The matching of ``search_by_projection`` for projected points (``uv``, their search radius in pixels,
    octave, descriptor words) and keypoints: a keypoint is a candidate within the point's radius (and, with
    octaves, within ``max_level_gap`` levels); the best candidate (Hamming, then the lower keypoint index)
    must stay under ``max_distance`` and, where the runner-up lies on its level, within ``ratio`` of it; each
    keypoint keeps the point of lowest distance (then the lower point index). Candidates come from a grid of
    cells as large as the largest radius (the 3 x 3 cells around a point hold all of them).
    Returns (keypoint of each point or -1, its distance or -1)."""
    n, k = len(uv), len(kp_uv)
    out_kp = np.full(n, -1, np.int64)
    out_d = np.full(n, -1, np.int64)
    if n == 0 or k == 0:
        return out_kp, out_d
    cell = max(search_px.max(), 1.0)
    gw, gh = int(width // cell) + 1, int(height // cell) + 1
    kp_cell = np.empty(k, np.int64)
    count = np.zeros(gw * gh + 1, np.int64)
    for j in range(k):
        cx = min(max(int(kp_uv[j, 0] // cell), 0), gw - 1)
        cy = min(max(int(kp_uv[j, 1] // cell), 0), gh - 1)
        kp_cell[j] = cy * gw + cx
        count[kp_cell[j] + 1] += 1
    start = np.cumsum(count)                     # keypoints of cell c: items[start[c]:start[c + 1]], ascending
    items = np.empty(k, np.int64)
    fill = start[:-1].copy()
    for j in range(k):
        items[fill[kp_cell[j]]] = j
        fill[kp_cell[j]] += 1
    n_words = words.shape[1]
    best_kp = np.full(n, -1, np.int64)
    best_d = np.full(n, -1, np.int64)
    for i in range(n):
        r = search_px[i]
        pcx, pcy = int(uv[i, 0] // cell), int(uv[i, 1] // cell)
        b1, d1, b2, d2 = -1, 1 << 30, -1, 1 << 30     # best and runner-up (distance, then keypoint index)
        for cy in range(max(pcy - 1, 0), min(pcy + 2, gh)):
            for cx in range(max(pcx - 1, 0), min(pcx + 2, gw)):
                c = cy * gw + cx
                for a in range(start[c], start[c + 1]):
                    j = items[a]
                    dx, dy = kp_uv[j, 0] - uv[i, 0], kp_uv[j, 1] - uv[i, 1]
                    if not np.sqrt(dx * dx + dy * dy) <= r:
                        continue
                    if has_octave and abs(kp_octave[j] - octave[i]) > max_level_gap:
                        continue
                    d = 0
                    for w in range(n_words):
                        d += _popcount(words[i, w] ^ kp_words[j, w])
                    if d < d1 or (d == d1 and j < b1):
                        b2, d2 = b1, d1
                        b1, d1 = j, d
                    elif b2 < 0 or d < d2 or (d == d2 and j < b2):
                        b2, d2 = j, d
        if b1 < 0 or d1 > max_distance:
            continue
        if b2 >= 0 and kp_octave[b2] == kp_octave[b1] and not d1 <= ratio * d2:
            continue
        best_kp[i], best_d[i] = b1, d1
    claim_d = np.full(k, 1 << 30, np.int64)
    claim_point = np.full(k, -1, np.int64)
    for i in range(n):                           # one point per keypoint: the lowest distance, then index
        j = best_kp[i]
        if j >= 0 and best_d[i] < claim_d[j]:
            claim_d[j], claim_point[j] = best_d[i], i
    for j in range(k):
        i = claim_point[j]
        if i >= 0:
            out_kp[i], out_d[i] = j, claim_d[j]
    return out_kp, out_d


def match_brute_force(des_query: np.ndarray, des_train: np.ndarray, ratio: float,
                      max_distance: int) -> tuple[np.ndarray, np.ndarray]:
    """(query_idx, train_idx) of mutual-unique matches passing Lowe's ratio test."""
    if len(des_query) < 2 or len(des_train) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(des_query, des_train, k=2)
    rows = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) == 2])
    if len(rows) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    keep = (rows[:, 2] < ratio * rows[:, 3]) & (rows[:, 2] <= max_distance)
    rows = rows[keep]
    winners = first_per_group(rows[:, 1].astype(int), rows[:, 2])
    return rows[winners, 0].astype(int), rows[winners, 1].astype(int)
