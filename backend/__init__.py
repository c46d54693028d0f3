"""The back end: a GTSAM iSAM2 keyframe graph with landmarks, the map and its local mapping, place
recognition, loop closing, relocalization, map files and graph export. It never imports ``frontend``;
other pipelines can drive ``FactorGraphBackend`` alone (README, "Using the back end")."""
from __future__ import annotations

from typing import Any

# name -> module: imported on first use (PEP 562), so importing one submodule stays light
_PUBLIC = {
    "FactorGraphBackend": "backend.graph",
    "BackendParams": "backend.graph",
    "StereoCalibration": "backend.graph",
    "BackendError": "backend.graph",
    "LocalMapper": "backend.local_mapping",
    "SlamMap": "backend.map_store",
    "LoopCloser": "backend.loop_closing",
    "LoopEdge": "backend.loop_closing",
    "Vocabulary": "backend.place_recognition",
    "KeyframeIndex": "backend.place_recognition",
    "load_vocabulary": "backend.place_recognition",
    "save_map": "backend.map_io",
    "load_map": "backend.map_io",
    "MapFormatError": "backend.map_io",
    "export_g2o": "backend.graph_export",
    "export_json": "backend.graph_export",
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
