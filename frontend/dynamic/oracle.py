"""A detector that returns known boxes: ground truth of generated scenes, or boxes from elsewhere.

Used to measure the dynamic methods' classification quality independently of a neural network
(the synthetic people are not COCO-like enough for YOLOX), and by users who already have boxes.
"""
from __future__ import annotations

import threading
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
                for x0, y0, x1, y1, cls in self._boxes_at(round(float(timestamp), 6))]

    def _boxes_at(self, key: float) -> list[tuple]:
        return self._boxes.get(key, [])


class SyntheticOracle(OracleDetector):
    """Ground-truth boxes of a generated sequence's movers, looked up when a frame is detected: the
    sequence notes every frame's mover extents as it renders it, so a run pays nothing for its boxes
    (reading them all before the run cast every frame once more, ~30 ms each). The detector runs on its
    own thread; the lock keeps a frame's boxes computed once."""

    def __init__(self, sequence, kinds: dict[str, int], margin_px: int, skip_frames: Iterable[int]):
        super().__init__({})
        self._sequence, self._kinds, self._margin = sequence, kinds, margin_px
        self._index = {round(float(t), 6): i for i, t in enumerate(sequence.timestamps)}
        self._skip = frozenset(int(i) for i in skip_frames)
        self._lock = threading.Lock()

    def _boxes_at(self, key: float) -> list[tuple]:
        index = self._index.get(key)
        if index is None or index in self._skip:
            return []
        with self._lock:
            if key not in self._boxes:
                seq, m, kinds = self._sequence, self._margin, self._kinds
                w, h = seq.width, seq.height
                self._boxes[key] = [(max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h), kinds[k])
                                    for x0, y0, x1, y1, k in seq.mover_boxes(index) if k in kinds]
            return self._boxes[key]


def synthetic_oracle(sequence, kinds: dict[str, int] | None = None, margin_px: int = 0,
                     skip_frames: Iterable[int] = ()) -> SyntheticOracle:
    """Ground-truth boxes of a SyntheticSequence's movers ('person' → COCO person, 'chair' → chair),
    widened by ``margin_px`` as a detector's boxes are (pixel-tight boxes are not what the methods
    were designed for); kinds not in ``kinds`` (e.g. flying boxes) are left out, and frames in
    ``skip_frames`` have no boxes (a detector's misses)."""
    return SyntheticOracle(sequence, {"person": PERSON, "chair": 56} if kinds is None else kinds, margin_px,
                           skip_frames)


def precision_recall(flagged: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Precision and recall of boolean dynamic flags against ground truth (nan when undefined)."""
    tp = float(np.sum(flagged & truth))
    precision = tp / flagged.sum() if flagged.sum() else float("nan")
    recall = tp / truth.sum() if truth.sum() else float("nan")
    return precision, recall
