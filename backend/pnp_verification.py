"""Geometric verification shared by loop detection and relocalization: descriptors → PnP-RANSAC → depth check.

Given some image features (static ones only: the caller selects them) and a set of landmarks, find
the camera pose that explains them:

1. ``cv2.BFMatcher`` Hamming kNN, Lowe ratio, a maximum descriptor distance, one feature per landmark
   (the closest descriptor wins);
2. ``cv2.solvePnPRansac`` (EPnP; its samples come from a generator fixed inside the call, so the result
   does not depend on what else drew from OpenCV's, nor on ``seed``) on world landmark positions vs.
   undistorted pixels (``K``, no distortion), then
   ``SOLVEPNP_ITERATIVE`` refinement on the inliers;
3. inliers must lie in front of the camera, reproject within the threshold and, where the feature
   has a measured depth, agree with it to ``depth_tolerance`` (relative): an RGB-D camera measures
   that depth, and a repeated texture at another distance is a classic false match.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from slam.core.frame import MapPoints


@dataclass
class PnpParams:
    min_inliers: int = 30
    ratio: float = 0.75
    max_descriptor_distance: int = 64
    reprojection_error: float = 3.0
    ransac_iterations: int = 300
    depth_tolerance: Optional[float] = 0.1   # None: no depth check
    seed: int = 0


@dataclass
class PnpSolution:
    T_cw: np.ndarray            # world → camera
    feature_idx: np.ndarray     # (M,) indices into the features given, inliers only
    landmark_ids: np.ndarray    # (M,) landmark id matched to each


_MATCHER = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)


def pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def match_descriptors(query: np.ndarray, train: np.ndarray, ratio: float, max_distance: int) -> np.ndarray:
    """(M, 2) int64 (query index, train index) pairs passing the ratio test, one query per train row."""
    if len(query) == 0 or len(train) == 0:
        return np.zeros((0, 2), np.int64)
    knn = _MATCHER.knnMatch(np.ascontiguousarray(query), np.ascontiguousarray(train), k=2)
    rows = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance if len(m) > 1 else np.inf)
                     for m in knn if len(m)], np.float64).reshape(-1, 4)
    rows = rows[(rows[:, 2] < ratio * rows[:, 3]) & (rows[:, 2] <= max_distance)]
    rows = rows[np.argsort(rows[:, 2], kind="stable")]
    _, first = np.unique(rows[:, 1].astype(np.int64), return_index=True)
    return rows[np.sort(first), :2].astype(np.int64)


def solve_pnp(descriptors: np.ndarray, uv: np.ndarray, depths: np.ndarray, points: MapPoints, K: np.ndarray,
              params: PnpParams) -> Optional[PnpSolution]:
    """Pose of the camera that saw ``descriptors`` at ``uv`` (depths: 0 = none), or None."""
    if len(descriptors) < params.min_inliers or len(points) < params.min_inliers:
        return None
    pairs = match_descriptors(descriptors, points.descriptors, params.ratio, params.max_descriptor_distance)
    if len(pairs) < params.min_inliers:
        return None
    obj = np.ascontiguousarray(points.xyz[pairs[:, 1]], np.float64)
    img = np.ascontiguousarray(uv[pairs[:, 0]], np.float64)
    cv2.setRNGSeed(params.seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=params.ransac_iterations,
                                             reprojectionError=params.reprojection_error, confidence=0.999,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < params.min_inliers:
        return None
    inl = inl.ravel()
    ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], K, None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    T_cw = pose_from_rvec(rvec, tvec)
    inlier = _consistent(T_cw, obj, img, np.asarray(depths, np.float64)[pairs[:, 0]], K, params)
    if int(inlier.sum()) < params.min_inliers:
        return None
    return PnpSolution(T_cw, pairs[inlier, 0], points.ids[pairs[inlier, 1]])


def _consistent(T_cw: np.ndarray, obj: np.ndarray, img: np.ndarray, measured: np.ndarray, K: np.ndarray,
                params: PnpParams) -> np.ndarray:
    pc = obj @ T_cw[:3, :3].T + T_cw[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = pc[:, :2] / pc[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    inlier = (pc[:, 2] > 0) & (np.linalg.norm(proj - img, axis=1) < params.reprojection_error)
    if params.depth_tolerance is not None:
        has = measured > 0
        inlier &= ~has | (np.abs(pc[:, 2] - measured) <= params.depth_tolerance * np.where(has, measured, 1.0))
    return inlier
