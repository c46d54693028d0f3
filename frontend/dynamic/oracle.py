"""A detector that returns known boxes: ground truth of generated scenes, or boxes from elsewhere.

Used to measure the dynamic methods' classification quality independently of a neural network
(the synthetic people are not COCO-like enough for YOLOX), and by users who already have boxes.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from frontend.dynamic.base import Detection, DetectorDefaults

PERSON = 0


class OracleDetector(DetectorDefaults):
    """Boxes per timestamp: {round(t, 6): [(x0, y0, x1, y1, class_id), ...]}."""

    def __init__(self, boxes_by_time: dict[float, Iterable[tuple]]):
        self._boxes = {round(float(t), 6): list(b) for t, b in boxes_by_time.items()}

    def detect(self, bgr: np.ndarray, timestamp: float = 0.0) -> list[Detection]:
        return [Detection(float(x0), float(y0), float(x1), float(y1), int(cls), 1.0)
                for x0, y0, x1, y1, cls in self._boxes.get(round(float(timestamp), 6), [])]


def synthetic_oracle(sequence, kinds: dict[str, int] | None = None, margin_px: int = 0,
                     skip_frames: Iterable[int] = ()) -> OracleDetector:
    """Ground-truth boxes of a SyntheticSequence's movers ('person' → COCO person, 'chair' → chair),
    widened by ``margin_px`` as a detector's boxes are (pixel-tight boxes are not what the methods
    were designed for); kinds not in ``kinds`` (e.g. flying boxes) are left out, and frames in
    ``skip_frames`` have no boxes (a detector's misses)."""
    kinds = kinds if kinds is not None else {"person": PERSON, "chair": 56}
    w, h, m = sequence.width, sequence.height, margin_px
    boxes = {}
    skip = set(skip_frames)
    for i, t in enumerate(sequence.timestamps):
        if i in skip:
            boxes[t] = []
            continue
        boxes[t] = [(max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h), kinds[k])
                    for x0, y0, x1, y1, k in sequence.mover_boxes(i) if k in kinds]
    return OracleDetector(boxes)


def precision_recall(flagged: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Precision and recall of boolean dynamic flags against ground truth (nan when undefined)."""
    tp = float(np.sum(flagged & truth))
    precision = tp / flagged.sum() if flagged.sum() else float("nan")
    recall = tp / truth.sum() if truth.sum() else float("nan")
    return precision, recall
