"""Dynamic-feature rejection: each method gives every keypoint a dynamic probability.

The core system honours ``FeatureFrame.dynamic_prob`` in tracking and in the back end; the methods
plug in through a ``DynamicFilter``. ``build_dynamic_filter`` picks them from the config; with none
enabled it returns the null filter (every feature static), so the pipeline has no "if dynamic"
branches. Ablations are configs: any subset of methods, any fusion mode.
"""
from __future__ import annotations

import importlib
from typing import Optional, Protocol

import numpy as np

from slam.camera import PinholeCamera
from slam.frame import FeatureFrame
from slam.timing import ModuleTimer

# method name -> (module, class, config attribute, takes class groups)
_METHODS = {
    "cpr": ("frontend.dynamic.cpr", "CprMethod", "cpr", False),
    "box_depth": ("frontend.dynamic.box_depth", "BoxDepthMethod", "box_depth", True),
    "flow_epipolar": ("frontend.dynamic.flow_epipolar", "FlowEpipolarMethod", "flow_epipolar", True),
    "depth_sdf": ("frontend.dynamic.depth_sdf", "DepthSdfMethod", "depth_sdf", True),
}


class DynamicFilter(Protocol):
    name: str

    def process(self, frame: FeatureFrame, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray,
                predicted_T_cw: Optional[np.ndarray], last_T_cw: Optional[np.ndarray]) -> np.ndarray:
        """Dynamic probability in [0, 1] for each of the frame's features."""
        ...

    def end_frame(self, T_cw: Optional[np.ndarray], is_keyframe: bool) -> None:
        """The tracked pose of the frame just processed (None if lost) and its keyframe status."""
        ...


class StaticWorld:
    """The null filter: every feature is static."""

    name = "none"

    def process(self, frame, rgb, gray, depth, predicted_T_cw, last_T_cw) -> np.ndarray:
        return np.zeros(len(frame))

    def end_frame(self, T_cw, is_keyframe) -> None:
        return None


def build_method(name: str, config):
    module_name, class_name, cfg_attr, takes_classes = _METHODS[name]
    cls = getattr(importlib.import_module(module_name), class_name)
    method_cfg = getattr(config.dynamic, cfg_attr)
    return cls(method_cfg, config.dynamic.classes) if takes_classes else cls(method_cfg)


def build_dynamic_filter(config, camera: PinholeCamera, timer: Optional[ModuleTimer] = None,
                         sequence_name: str = "", detector=None) -> DynamicFilter:
    """The filter for ``config.dynamic``: the null filter, or the enabled methods and their fusion."""
    if not config.dynamic.methods and config.dynamic.box_prior <= 0:
        return StaticWorld()
    from frontend.dynamic.rejector import DynamicRejector

    methods = [build_method(name, config) for name in config.dynamic.methods]
    if detector is None and (any(m.needs_detector for m in methods) or config.dynamic.box_prior > 0):
        from frontend.detector import build_detector

        detector = build_detector(config.dynamic.detector, config.dynamic.classes, sequence_name)
    return DynamicRejector(config.dynamic, camera, methods, detector, timer)
