"""Box geometry for the object detectors: letterbox placement, image <-> network-input box mapping, IoU
and per-class non-maximum suppression. Boxes are (N, 4) x0 y0 x1 y1 in pixels.

Pure numpy/OpenCV helpers without model state, so they are tested on their own; ``frontend.detector``
uses and re-exports them.
"""
from __future__ import annotations

import cv2
import numpy as np


def letterbox_params(h: int, w: int, size: int, centred: bool) -> tuple[float, int, int, int, int]:
    """Scale ``r`` and the placement (new_w, new_h, left, top) of an h x w image in a size x size input."""
    r = min(size / h, size / w)
    nw, nh = int(round(w * r)), int(round(h * r))
    nw, nh = min(max(nw, 1), size), min(max(nh, 1), size)
    if centred:
        left, top = (size - nw) // 2, (size - nh) // 2
    else:
        left, top = 0, 0
    return r, nw, nh, left, top


def boxes_to_input(boxes: np.ndarray, r: float, left: float, top: float) -> np.ndarray:
    """Image pixel boxes (N,4 x0 y0 x1 y1) -> network input pixels."""
    out = np.asarray(boxes, dtype=np.float64) * r
    out[:, [0, 2]] += left
    out[:, [1, 3]] += top
    return out


def boxes_from_input(boxes: np.ndarray, r: float, left: float, top: float) -> np.ndarray:
    """Network input pixel boxes (N,4 x0 y0 x1 y1) -> image pixels (inverse of ``boxes_to_input``)."""
    out = np.array(boxes, dtype=np.float64, copy=True)
    out[:, [0, 2]] -= left
    out[:, [1, 3]] -= top
    return out / r


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix between boxes a (N,4) and b (M,4), x0 y0 x1 y1."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    ix0 = np.maximum(a[:, None, 0], b[None, :, 0])
    iy0 = np.maximum(a[:, None, 1], b[None, :, 1])
    ix1 = np.minimum(a[:, None, 2], b[None, :, 2])
    iy1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(ix1 - ix0, 0, None) * np.clip(iy1 - iy0, 0, None)
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def nms_numpy(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Per-class greedy NMS (boxes of different classes never suppress each other).

    Classes are separated by offsetting each class's boxes far apart (the batched-NMS trick), so one
    greedy pass serves all classes. Returns kept indices sorted by descending score.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if boxes.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    span = float(np.max(np.abs(boxes))) + 1.0
    shifted = boxes + (np.asarray(class_ids, dtype=np.float64) * 2.0 * span)[:, None]
    order = np.argsort(-scores, kind="stable")
    x0, y0, x1, y1 = shifted[:, 0], shifted[:, 1], shifted[:, 2], shifted[:, 3]
    area = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        w = np.clip(np.minimum(x1[i], x1[rest]) - np.maximum(x0[i], x0[rest]), 0, None)
        h = np.clip(np.minimum(y1[i], y1[rest]) - np.maximum(y0[i], y0[rest]), 0, None)
        inter = w * h
        union = area[i] + area[rest] - inter
        iou = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def nms_per_class(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Per-class NMS: OpenCV's ``NMSBoxesBatched`` when present, else ``nms_numpy``.
    Returns kept indices sorted by descending score."""
    n = len(scores)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    batched = getattr(cv2.dnn, "NMSBoxesBatched", None)
    if batched is not None:
        b = np.asarray(boxes, dtype=np.float64)
        xywh = np.stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], axis=1)
        try:
            idx = batched(xywh.tolist(), np.asarray(scores, dtype=np.float32).tolist(),
                          np.asarray(class_ids, dtype=np.int32).tolist(), -np.inf, float(iou_threshold))
            idx = np.asarray(idx, dtype=np.int64).reshape(-1)
            return idx[np.argsort(-np.asarray(scores)[idx], kind="stable")]
        except cv2.error:  # pragma: no cover - fall back on any OpenCV binding quirk
            pass
    return nms_numpy(boxes, scores, class_ids, iou_threshold)
