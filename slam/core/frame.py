"""Struct-of-arrays records shared by the front end, the back end and the orchestration.

Only plain numpy arrays live here so that ``frontend`` and ``backend`` can exchange data without
importing each other.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FeatureFrame:
    """ORB features of one RGB-D frame.

    Every per-feature array has length N. ``uv`` are undistorted (ideal pinhole) coordinates, the
    ones all geometry uses; ``uv_raw`` index the distorted images (depth lookup, diagnostics).
    ``u_right`` is the virtual stereo coordinate (NaN without usable depth). ``dynamic_prob`` is the
    fused dynamic probability in [0, 1]; zeros until a dynamic front end fills it.
    """

    index: int
    timestamp: float
    uv_raw: np.ndarray          # (N,2) float
    uv: np.ndarray              # (N,2) float
    octaves: np.ndarray         # (N,) int
    descriptors: np.ndarray     # (N,32) uint8
    depths: np.ndarray          # (N,) float, 0 = none
    u_right: np.ndarray         # (N,) float, NaN = none
    dynamic_prob: np.ndarray    # (N,) float
    scale_factors: np.ndarray   # (L,) scale of each pyramid level
    gray: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, keep: np.ndarray) -> "FeatureFrame":
        return FeatureFrame(self.index, self.timestamp, self.uv_raw[keep], self.uv[keep], self.octaves[keep],
                            self.descriptors[keep], self.depths[keep], self.u_right[keep], self.dynamic_prob[keep],
                            self.scale_factors, self.gray)

    def append(self, other: "FeatureFrame") -> "FeatureFrame":
        """This frame's features followed by ``other``'s (same image, same pyramid)."""
        cat = np.concatenate
        return FeatureFrame(self.index, self.timestamp, cat([self.uv_raw, other.uv_raw]), cat([self.uv, other.uv]),
                            cat([self.octaves, other.octaves]), cat([self.descriptors, other.descriptors]),
                            cat([self.depths, other.depths]), cat([self.u_right, other.u_right]),
                            cat([self.dynamic_prob, other.dynamic_prob]), self.scale_factors, self.gray)

    @property
    def has_depth(self) -> np.ndarray:
        return np.isfinite(self.u_right)

    @property
    def level_scale(self) -> np.ndarray:
        return self.scale_factors[self.octaves]

    @property
    def inv_sigma2(self) -> np.ndarray:
        """Information of a keypoint's pixel coordinates: 1 / scale^2 of its pyramid level."""
        return 1.0 / self.level_scale**2


@dataclass
class MapPoints:
    """Landmarks offered to the tracker: ids (-1 for temporary points that are no landmark)."""

    ids: np.ndarray             # (M,) int64
    xyz: np.ndarray             # (M,3) world coordinates
    descriptors: np.ndarray     # (M,32) uint8
    octaves: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # (M,) level seen at

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> "MapPoints":
        return MapPoints(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 32), np.uint8),
                         np.zeros(0, int))

    def subset(self, mask: np.ndarray) -> "MapPoints":
        return MapPoints(self.ids[mask], self.xyz[mask], self.descriptors[mask], self.octaves[mask])

    @staticmethod
    def concat(parts: list["MapPoints"]) -> "MapPoints":
        parts = [p for p in parts if len(p)]
        if not parts:
            return MapPoints.empty()
        return MapPoints(np.concatenate([p.ids for p in parts]), np.concatenate([p.xyz for p in parts]),
                         np.concatenate([p.descriptors for p in parts]),
                         np.concatenate([p.octaves for p in parts]))
