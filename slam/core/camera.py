"""Pinhole RGB-D camera with OpenCV distortion and ORB-SLAM's virtual stereo baseline."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.core.config import CameraConfig


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    depth_scale: float = 5000.0
    bf: float = 40.0
    depth_threshold: float = 40.0
    min_depth: float = 0.1
    max_depth: float = 8.0

    @classmethod
    def from_config(cls, cfg: CameraConfig) -> "PinholeCamera":
        return cls(cfg.fx, cfg.fy, cfg.cx, cfg.cy, cfg.width, cfg.height, tuple(cfg.distortion),
                   cfg.depth_scale, cfg.bf, cfg.depth_threshold, cfg.min_depth, cfg.max_depth)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def baseline(self) -> float:
        return self.bf / self.fx

    @property
    def close_depth(self) -> float:
        """Depth below which a point counts as close (well-measured), as ORB-SLAM's mThDepth."""
        return self.baseline * self.depth_threshold

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0.0 for d in self.distortion)

    def undistort_points(self, pts: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N,2) of the distorted image to those of the ideal pinhole image."""
        if not self.has_distortion or len(pts) == 0:
            return np.asarray(pts, dtype=float).copy()
        # OpenCV's default 5 iterations leave ~0.1 px near the corners under fr1's strong distortion.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        und = cv2.undistortPoints(np.asarray(pts, np.float64).reshape(-1, 1, 2), self.K,
                                  np.asarray(self.distortion), R=None, P=self.K, criteria=criteria)
        return und.reshape(-1, 2)

    def project(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal pixel coordinates (N,2) of camera-frame points and their depths (N,)."""
        z = points_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * points_c[:, 0] / z + self.cx
            v = self.fy * points_c[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points (N,3) from ideal pixel coordinates and depths."""
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        return np.stack([x, y, depth], axis=1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        return ((uv[:, 0] >= margin) & (uv[:, 0] < self.width - margin)
                & (uv[:, 1] >= margin) & (uv[:, 1] < self.height - margin))

    def right_u(self, u: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Virtual right-image u = u - bf / z; NaN where the depth is not usable."""
        valid = (depth > self.min_depth) & (depth < self.max_depth)
        out = np.full(len(u), np.nan)
        out[valid] = u[valid] - self.bf / depth[valid]
        return out
