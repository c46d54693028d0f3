"""The front end: ORB extraction, matching, pose-only optimisation, the tracker, the keyframe policy, the
ONNX detector and the dynamic-feature methods (``frontend.dynamic``). It never imports ``backend``."""
from __future__ import annotations

from typing import Any

# name -> module: imported on first use (PEP 562), so importing one submodule stays light
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
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
