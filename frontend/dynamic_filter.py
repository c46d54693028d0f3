"""Building the dynamic filter a config asks for: the enabled methods, the detector they need (unless
one is given, e.g. ground-truth boxes of a generated sequence) and their fusion, or the null filter.

Kept apart from ``frontend.dynamic`` because the detector module imports that package (its
``Detection`` type): the factory sits above both, so neither imports the other back.
"""
from __future__ import annotations

import importlib
from typing import Optional

from frontend.detector import build_detector
from frontend.dynamic import DynamicFilter, StaticWorld
from frontend.dynamic.rejector import DynamicRejector
from slam.core.camera import PinholeCamera
from slam.core.timing import ModuleTimer

# method name -> (module, class, config attribute, takes class groups)
_METHODS = {
    "cpr": ("frontend.dynamic.cpr", "CprMethod", "cpr", False),
    "box_depth": ("frontend.dynamic.box_depth", "BoxDepthMethod", "box_depth", True),
    "flow_epipolar": ("frontend.dynamic.flow_epipolar", "FlowEpipolarMethod", "flow_epipolar", True),
    "depth_sdf": ("frontend.dynamic.depth_sdf", "DepthSdfMethod", "depth_sdf", True),
}


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
    methods = [build_method(name, config) for name in config.dynamic.methods]
    if detector is None and (any(m.needs_detector for m in methods) or config.dynamic.box_prior > 0):
        detector = build_detector(config.dynamic.detector, config.dynamic.classes, sequence_name)
    return DynamicRejector(config.dynamic, camera, methods, detector, timer)
