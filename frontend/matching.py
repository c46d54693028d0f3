"""Descriptor matching: by projection into the current frame, and brute force with a ratio test.

Both are vectorised: candidate pairs come from a k-d tree in one call, Hamming distances from a
popcount of the XORed descriptors (``slam.core.descriptors``), and "best per map point" / "one map point per
keypoint" are resolved by sorting rather than by Python loops.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slam.core.camera import PinholeCamera
from slam.core.descriptors import hamming
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
    point_scale = frame.scale_factors[np.clip(points.octaves, 0, len(frame.scale_factors) - 1)] if has_octave \
        else np.ones(m)
    pairs = cKDTree(uv[vis_idx]).sparse_distance_matrix(
        cKDTree(frame.uv[kp_idx]), radius * point_scale[vis_idx].max(), output_type="ndarray")
    if len(pairs) == 0:
        return result
    pi, ki, dist_px = vis_idx[pairs["i"]], kp_idx[pairs["j"]], pairs["v"]
    # ORB-SLAM: the radius scales with the level the point was seen at, and the keypoint must lie
    # on a neighbouring level of the pyramid.
    ok = dist_px <= radius * point_scale[pi]
    if has_octave:
        ok &= np.abs(frame.octaves[ki] - points.octaves[pi]) <= max_level_gap
    pi, ki = pi[ok], ki[ok]
    if len(pi) == 0:
        return result
    ham = hamming(points.descriptors[pi], frame.descriptors[ki])
    best, second = _best_two(pi, ham)
    accept = ham[best] <= max_distance
    # The ratio test only rejects when the runner-up lies on the same level (as in ORB-SLAM).
    ambiguous = second >= 0
    ambiguous[ambiguous] &= frame.octaves[ki[second[ambiguous]]] == frame.octaves[ki[best[ambiguous]]]
    accept[ambiguous] &= ham[best][ambiguous] <= ratio * ham[second[ambiguous]]
    best = best[accept]
    # One point per keypoint: the lowest distance wins.
    winners = best[first_per_group(ki[best], ham[best])]
    result.keypoint_of_point[pi[winners]] = ki[winners]
    result.distance[pi[winners]] = ham[winners]
    return result


def _best_two(groups: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group: index of the smallest key, and of the second smallest (-1 if none)."""
    order = np.lexsort((keys, groups))
    if len(order) == 0:
        return order, order.copy()
    g = groups[order]
    is_first = np.r_[True, g[1:] != g[:-1]]
    first_pos = np.flatnonzero(is_first)
    second_pos = first_pos + 1
    has_second = (second_pos < len(order))
    has_second[has_second] &= ~is_first[second_pos[has_second]]
    second = np.full(len(first_pos), -1)
    second[has_second] = order[second_pos[has_second]]
    return order[first_pos], second


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
