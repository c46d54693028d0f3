"""ORB features spread evenly over the image, with undistorted coordinates and depth per keypoint.

OpenCV's ORB keeps the globally strongest corners, which cluster on textured patches. ORB-SLAM
instead spreads features over a grid per pyramid level; we detect with a low FAST threshold and
then keep, level by level, the strongest corner of every cell first, then the second strongest,
and so on (a vectorised round-robin over cells).
"""
from __future__ import annotations

import cv2
import numpy as np

from slam.core.camera import PinholeCamera
from slam.core.config import OrbConfig
from slam.core.frame import FeatureFrame


def features_per_level(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """ORB-SLAM's geometric share of features per level (coarser levels get fewer); sums exactly
    to n_features (largest-remainder rounding)."""
    inv = 1.0 / scale_factor
    share = n_features * (1 - inv) / (1 - inv**n_levels) * inv ** np.arange(n_levels)
    counts = np.floor(share).astype(int)
    remainder = n_features - counts.sum()
    counts[np.argsort(-(share - counts), kind="stable")[:remainder]] += 1
    return counts


def distribute_on_grid(xy: np.ndarray, response: np.ndarray, octave: np.ndarray, scale_factors: np.ndarray,
                       quota: np.ndarray, cell_size: int) -> np.ndarray:
    """Indices of the keypoints to keep: per level, round-robin over grid cells by response."""
    # Cell of each keypoint in its own level's coordinates, so cells cover equal image content.
    level_xy = xy / scale_factors[octave][:, None]
    cell = (np.floor(level_xy[:, 1] / cell_size) * 4096 + np.floor(level_xy[:, 0] / cell_size)).astype(np.int64)
    group = octave.astype(np.int64) * (1 << 40) + cell
    order = np.lexsort((-response, group))
    sorted_group = group[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_group)) + 1]
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    # Rank within cell first, then response: the best of every cell precedes any second-best.
    pick = order[np.lexsort((-response[order], rank, octave[order]))]
    keep = []
    for level, n in enumerate(quota):
        on_level = pick[octave[pick] == level]
        keep.append(on_level[:n])
    return np.concatenate(keep) if keep else np.zeros(0, int)


class OrbExtractor:
    """Extracts a FeatureFrame from a grey image and its registered depth map."""

    def __init__(self, cfg: OrbConfig, camera: PinholeCamera):
        self.cfg = cfg
        self.camera = camera
        self.scale_factors = cfg.scale_factor ** np.arange(cfg.n_levels)
        self.quota = features_per_level(cfg.n_features, cfg.scale_factor, cfg.n_levels)
        self._orb = cv2.ORB_create(nfeatures=int(cfg.n_features * cfg.oversample), scaleFactor=cfg.scale_factor,
                                   nlevels=cfg.n_levels, edgeThreshold=cfg.edge_threshold,
                                   fastThreshold=cfg.fast_threshold, patchSize=31)

    def extract(self, gray: np.ndarray, depth: np.ndarray, index: int = 0, timestamp: float = 0.0,
                mask: np.ndarray | None = None) -> FeatureFrame:
        """Features of the image (only where ``mask`` is non-zero, if given)."""
        # Detect, keep the grid's share, then describe only those: the descriptors of the ~2/3 of the
        # corners the grid drops were computed for nothing (the same bits as detectAndCompute's rows of the
        # kept corners: tests/test_frontend_features.py; ~1.3 ms a frame).
        keypoints = self._orb.detect(gray, mask)
        if not keypoints:
            return self._empty(index, timestamp, gray)
        xy = cv2.KeyPoint_convert(keypoints).astype(float)      # the same float32 values as KeyPoint.pt
        response = np.fromiter((k.response for k in keypoints), float, len(keypoints))
        octave = np.fromiter((k.octave for k in keypoints), int, len(keypoints))
        keep = distribute_on_grid(xy, response, octave, self.scale_factors, self.quota, self.cfg.cell_size)
        xy, octave = xy[keep], octave[keep]
        kept, descriptors = self._orb.compute(gray, [keypoints[i] for i in keep])
        if descriptors is None or len(kept) != len(keep) or not np.array_equal(cv2.KeyPoint_convert(kept), xy):
            # OpenCV may drop or regroup provided corners while describing them (it has not on any frame
            # here: detect() keeps none too close to the border); then describe them all, as before.
            _, every = self._orb.compute(gray, keypoints)
            descriptors = every[keep]
        uv = self.camera.undistort_points(xy)
        depths = sample_depth(depth, xy)
        u_right = self.camera.right_u(uv[:, 0], depths)
        return FeatureFrame(index, timestamp, xy, uv, octave, descriptors, depths, u_right,
                            np.zeros(len(xy)), self.scale_factors, gray)

    def _empty(self, index: int, timestamp: float, gray: np.ndarray) -> FeatureFrame:
        return FeatureFrame(index, timestamp, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int),
                            np.zeros((0, 32), np.uint8), np.zeros(0), np.zeros(0), np.zeros(0),
                            self.scale_factors, gray)


def sample_depth(depth: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Depth (m) at each keypoint's nearest pixel of the registered depth map; 0 where invalid."""
    h, w = depth.shape
    cols = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    d = depth[rows, cols].astype(float)
    d[~np.isfinite(d)] = 0.0
    return d
