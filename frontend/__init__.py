"""The front end: ORB extraction, matching, pose-only optimisation, the tracker, the keyframe policy, the
ONNX detector and the dynamic-feature methods (``frontend.dynamic``). It never imports ``backend``."""
from __future__ import annotations

from slam.core.lazy_exports import lazy_exports

# name -> module, imported on first use (slam/core/lazy_exports.py)
_PUBLIC = {
    "OrbExtractor": "frontend.orb_extractor",
    "Tracker": "frontend.tracker",
    "TrackingState": "frontend.tracker",
    "TrackingResult": "frontend.tracker",
    "OnnxDetector": "frontend.detector",
    "DetectorError": "frontend.detector",
    "build_detector": "frontend.detector",
    "build_dynamic_filter": "frontend.dynamic_filter",
    "DynamicFilter": "frontend.dynamic",
    "StaticWorld": "frontend.dynamic",
    "Detection": "frontend.dynamic.base",
    "Detector": "frontend.dynamic.base",
    "DetectorDefaults": "frontend.dynamic.base",
}
__all__ = sorted(_PUBLIC)

__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
