"""What ``dynslam demo`` runs on: a generated room (random walkers or a scripted hard scene) and the
detector that stands in for YOLOX there."""
from __future__ import annotations

from frontend.dynamic.oracle import OracleDetector, synthetic_oracle
from slam.datasets import SyntheticSequence
from slam.datasets.synthetic_scenes import HARD_SCENES, HardScene
from slam.run.dynamic_eval import scene_detector

DEMO_ORACLE_MARGIN_PX = 8
"""The generated movers' true boxes, widened as a detector's boxes are (pixel-tight boxes are not what
the methods were designed for)."""


def demo_sequence(movers: str, frames: int, seed: int) -> SyntheticSequence:
    """``movers``: a mover set of ``SyntheticSequence`` ("none", "people", ...) or a hard scene's name."""
    if movers in HARD_SCENES:
        return HardScene(movers, n_frames=frames, seed=seed)
    return SyntheticSequence(n_frames=frames, seed=seed, movers=movers)


def demo_detector(sequence: SyntheticSequence) -> OracleDetector:
    """YOLOX does not detect the generated people: their true boxes stand in, without the frames a
    scripted hard scene's detector misses."""
    if isinstance(sequence, HardScene):
        return scene_detector(sequence, margin_px=DEMO_ORACLE_MARGIN_PX)
    return synthetic_oracle(sequence, margin_px=DEMO_ORACLE_MARGIN_PX)
