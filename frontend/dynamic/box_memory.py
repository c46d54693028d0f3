"""Dynamic-class boxes held through the frames where the detector misses them.

A detector misses a person it saw a moment ago when they blur past the camera, fill the view, or turn
their head away (Bonn crowd: YOLOX-Nano finds no person on three consecutive frames where a blurred
person covers 70 % of the image). Every method that reads boxes (box_depth's segmentation, flow_epipolar's
regions, the box prior) would then treat the person as background exactly when they matter most. As a
multi-object tracker does, a box that finds no successor in the next frame's detections is kept for a
few frames, moved on by the velocity of its corners over its last two detections (so an approaching
person's box keeps growing); a detection that overlaps it again takes over. Detections of other classes
pass through untouched.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontend.dynamic.base import Detection

MIN_MATCH_IOU = 0.3
"""A new detection continues a held box when they overlap this much (a walking person's box moves a
fraction of its width per frame at 30 Hz; two different people rarely overlap this much)."""


@dataclass
class _HeldBox:
    seen: np.ndarray        # (4,) x0, y0, x1, y1 where the detector last saw it
    velocity: np.ndarray    # (4,) corner motion per frame
    class_id: int
    score: float
    missed: int = 0         # frames since then

    def predicted(self) -> np.ndarray:
        """Where it is expected in the coming frame."""
        return self.seen + (self.missed + 1) * self.velocity


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in ``a`` (N,4) with every box in ``b`` (M,4): (N,M)."""
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


class BoxMemory:
    """Holds missed boxes of ``classes`` for up to ``hold_frames`` frames (0 = off: detections pass
    through). Deterministic: a function of the sequence of detections alone."""

    def __init__(self, hold_frames: int, classes: set[int], width: int, height: int):
        self.hold_frames = hold_frames
        self.classes = classes
        self.width, self.height = width, height
        self._held: list[_HeldBox] = []
        self.carried: list[Detection] = []     # the held boxes the last ``update`` added

    def update(self, detections: list[Detection]) -> list[Detection]:
        """This frame's detections plus the held boxes no detection continued."""
        if self.hold_frames <= 0:
            self.carried = []
            return detections
        tracked = [d for d in detections if d.class_id in self.classes]
        new = np.array([[d.x0, d.y0, d.x1, d.y1] for d in tracked], float).reshape(-1, 4)
        continued = self._match(new, [d.class_id for d in tracked])
        next_held, carried = [], []
        for i, detection in enumerate(tracked):
            before = continued.get(i)
            velocity = np.zeros(4) if before is None else (new[i] - before.seen) / (before.missed + 1)
            next_held.append(_HeldBox(new[i], velocity, detection.class_id, detection.score))
        taken = {id(box) for box in continued.values()}
        for box in self._held:
            if id(box) in taken or box.missed >= self.hold_frames:
                continue
            clipped = np.clip(box.predicted(), 0, [self.width, self.height, self.width, self.height])
            if clipped[2] - clipped[0] < 1 or clipped[3] - clipped[1] < 1:
                continue   # moved out of the image
            next_held.append(_HeldBox(box.seen, box.velocity, box.class_id, box.score, box.missed + 1))
            carried.append(Detection(*map(float, clipped), box.class_id, box.score))
        self._held = next_held
        self.carried = carried
        return list(detections) + carried

    def _match(self, new: np.ndarray, classes: list[int]) -> dict[int, _HeldBox]:
        """Greedy best-IoU pairs (same class, IoU >= MIN_MATCH_IOU): new detection index -> held box."""
        if not self._held or not len(new):
            return {}
        old = np.array([box.predicted() for box in self._held])
        iou = box_iou(new, old)
        iou[np.array(classes)[:, None] != np.array([b.class_id for b in self._held])[None, :]] = 0.0
        pairs: dict[int, _HeldBox] = {}
        for flat in np.argsort(-iou, axis=None):
            i, j = np.unravel_index(flat, iou.shape)
            if iou[i, j] < MIN_MATCH_IOU:
                break
            if i in pairs or any(self._held[j] is box for box in pairs.values()):
                continue
            pairs[int(i)] = self._held[j]
        return pairs
