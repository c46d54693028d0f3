"""Dynamic-feature rejection: each method gives every keypoint a dynamic probability.

The core system already honours ``FeatureFrame.dynamic_prob`` in tracking and the back end; the
methods themselves plug in through ``DynamicFilter``. ``build_dynamic_filter`` picks them from the
config; with none enabled it returns the null filter (all features static), so the pipeline has no
"if dynamic" branches.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from slam.frame import FeatureFrame


class DynamicFilter(Protocol):
    name: str

    def __call__(self, frame: FeatureFrame, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Dynamic probability in [0, 1] for each of the frame's features."""
        ...


class StaticWorld:
    """The null filter: every feature is static."""

    name = "none"

    def __call__(self, frame: FeatureFrame, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        return np.zeros(len(frame))


def build_dynamic_filter(config) -> DynamicFilter:
    return StaticWorld()
