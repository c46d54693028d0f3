"""dynslam: RGB-D SLAM that stays accurate when people and objects move through the scene.

    from slam import System, load_config
    system = System(load_config("tum_fr1"))
    out = system.process(bgr_uint8, depth_metres_float32, timestamp)   # out.T_wc: 4x4 camera-to-world or None

Layers (README, "Layout"): ``slam.core`` < ``frontend``, ``backend``, ``slam.datasets`` < ``slam.runtime``
< ``slam.run`` < ``slam.cli``."""
from __future__ import annotations

from slam.core.lazy_exports import lazy_exports

# name -> module, imported on first use (slam/core/lazy_exports.py)
_PUBLIC = {
    "System": "slam.runtime.system",
    "FrameOutput": "slam.runtime.system",
    "Pipeline": "slam.run.pipeline",
    "RunSummary": "slam.run.run_results",
    "SlamConfig": "slam.core.config",
    "load_config": "slam.core.config",
    "ConfigError": "slam.core.config",
    "DynslamError": "slam.core.errors",
    "open_dataset": "slam.datasets",
    "SyntheticSequence": "slam.datasets",
    "TumDataset": "slam.datasets",
    "RGBDDataset": "slam.datasets",
    "RGBDFrame": "slam.datasets",
    "DatasetDefaults": "slam.datasets",
    "evaluate_files": "slam.run.evaluation",
}
__all__ = sorted(_PUBLIC)

__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
