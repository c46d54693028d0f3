"""The back end: a GTSAM iSAM2 keyframe graph with landmarks, the map and its local mapping, place
recognition, loop closing, relocalization, map files and graph export. It never imports ``frontend``;
other pipelines can drive ``FactorGraphBackend`` alone (README, "Using the back end")."""
from __future__ import annotations

from slam.core.lazy_exports import lazy_exports

# name -> module, imported on first use (slam/core/lazy_exports.py)
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

__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
