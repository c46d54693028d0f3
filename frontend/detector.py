"""COCO object detectors (YOLOX-Nano, NanoDet-m) in ONNX, plus a per-sequence detection cache.

The models and their exact pre/post-processing are described in ``../shared/models/README.md``:

* ``yolox_nano`` (416x416): BGR raw 0..255, letterbox at the top-left padded with 114; output
  ``[1, 3549, 85]`` = (x, y, log w, log h, obj, 80 class scores) for strides 8/16/32, decoded as
  ``xy = (p + grid) * stride``, ``wh = exp(p) * stride``, ``score = obj * cls``. With ``fit_input`` (an
  option, off by default) the same network runs on the letterboxed image's own size rounded up to 32 (416 x 320 for
  640 x 480, output ``[1, 2730, 85]``): the 96 rows of padding below a 4:3 image cost a quarter of the
  work and found nothing (``frontend/onnx_input_shape.py``).
* ``nanodet`` (320x320): BGR normalised with mean/std, letterbox centred padded with 0; per stride a
  class-score map ``[1, HW, 80]`` and a distance distribution ``[1, HW, 32]`` (left, top, right,
  bottom x 8 bins: softmax, expectation, times stride) measured from the cell centres
  ``(i + 0.5) * stride``.

Both models have sigmoids applied inside and no NMS: every (anchor, class) pair whose score reaches
``score_threshold`` becomes a candidate (multi-label, as the upstream ONNX demos do), followed by
per-class NMS and clipping to the image. Decoding is vectorised; the grids are built once.

``CachedDetector`` stores the boxes per frame timestamp in a compressed ``.npz`` so repeated runs on
the same sequence skip the network, keyed by the model file's sha256 (in its name and inside it) so
another model never reads old boxes (``frontend.detector_cache``, re-exported here); ``build_detector`` wires
config, model path and cache together.
The box geometry (letterbox, box mapping, IoU, NMS) is in ``frontend.detector_boxes``, re-exported here.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Iterable, Optional

import cv2
import numpy as np

from frontend.detector_boxes import boxes_from_input, letterbox_params, nms_per_class
from frontend.detector_boxes import box_iou, boxes_to_input, nms_numpy  # noqa: F401  (re-exported)
from frontend.detector_cache import CachedDetector, cache_path_for, model_digest  # noqa: F401  (re-exported)
from frontend.dynamic.base import Detection
from frontend.model_lookup import (ENV_MODEL, MODEL_FILES, DetectorError,  # noqa: F401  (re-exported)
                                   ModelNotFoundError, default_model_dir, resolve_model_path)
from frontend.model_lookup import howto as _howto
from frontend.onnx_input_shape import SIZE_FREE_MODELS, with_input_size
from slam.core.dynamic_config import ClassGroups, DetectorConfig

_INPUT_SIZE = {"yolox_nano": 416, "nanodet": 320}
_STRIDES = (8, 16, 32)
_NANODET_MEAN = np.array([103.53, 116.28, 123.675], dtype=np.float32)
_NANODET_STD = np.array([57.375, 57.12, 58.395], dtype=np.float32)
_NANODET_BINS = 8
_YOLOX_PAD = 114.0


class _InputGeometry:
    """One network input size: its ONNX Runtime session, its anchors and its reused input buffer."""

    def __init__(self, session, height: int, width: int, priors: np.ndarray):
        self.session, self.height, self.width, self.priors = session, height, width, priors
        self.blob = np.empty((1, 3, height, width), dtype=np.float32)


# --------------------------------------------------------------------------------------------
# ONNX detector


class OnnxDetector:
    """YOLOX-Nano or NanoDet-m on onnxruntime's CPU provider.

    ``detect(bgr)`` returns the boxes in raw image pixels, clipped to the image, sorted by score,
    restricted to ``class_filter`` (COCO ids) when given.
    """

    def __init__(self, model_path, kind: str = "yolox_nano", score_threshold: float = 0.3,
                 nms_iou: float = 0.45, threads: int = 1, class_filter: Optional[Iterable[int]] = None,
                 fit_input: bool = False):
        if kind not in MODEL_FILES:
            raise DetectorError(f"unknown detector model '{kind}' (expected one of {', '.join(MODEL_FILES)})")
        self.kind = kind
        self.model_path = Path(model_path)
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        self.threads = max(1, int(threads))
        self.size = _INPUT_SIZE[kind]
        self.class_filter = None if class_filter is None else np.array(sorted(set(int(c) for c in class_filter)),
                                                                         dtype=np.int64)
        self._session = self._load()
        inputs = self._session.get_inputs()
        self._input_name = inputs[0].name
        shape = list(inputs[0].shape)
        if len(shape) != 4 or shape[2:] != [self.size, self.size]:
            raise DetectorError(f"detector model {self.model_path} has input shape {shape}, expected "
                                f"[1, 3, {self.size}, {self.size}] for '{kind}': is it the right file for "
                                f"dynamic.detector.model? {_howto(kind)}")
        self._output_names = self._pick_outputs()
        self.fit_input = bool(fit_input) and self.kind in SIZE_FREE_MODELS
        self._square = _InputGeometry(self._session, self.size, self.size, self._make_priors(self.size, self.size))
        self._geometries: dict[tuple[int, int], _InputGeometry] = {}   # image (h, w) -> the network input
        self._inv_std = (1.0 / _NANODET_STD).astype(np.float32)
        self._mean_over_std = (_NANODET_MEAN / _NANODET_STD).astype(np.float32)

    # -- loading ----------------------------------------------------------------------------------------

    def _load(self, model_bytes: Optional[bytes] = None):
        path = self.model_path
        if not path.is_file():
            raise DetectorError(f"detector model file not found: {path}; {_howto(self.kind)}")
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - dependency of the package
            raise DetectorError(f"onnxruntime is not installed, cannot load detector model {path}") from exc
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            return ort.InferenceSession(str(path) if model_bytes is None else model_bytes, sess_options=opts,
                                        providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad protobufs
            raise DetectorError(f"cannot load detector model {path} (corrupt or not an ONNX model: "
                                f"{type(exc).__name__}: {str(exc).strip()[:200]}); {_howto(self.kind)}") from exc

    def _pick_outputs(self) -> list[str]:
        names = [o.name for o in self._session.get_outputs()]
        if self.kind == "yolox_nano":
            if len(names) != 1:
                raise DetectorError(f"detector model {self.model_path} has outputs {names}, expected one "
                                    f"YOLOX output; {_howto(self.kind)}")
            return names
        ordered = []
        for s in _STRIDES:
            for prefix in ("cls_pred_stride_", "dis_pred_stride_"):
                if f"{prefix}{s}" not in names:
                    raise DetectorError(f"detector model {self.model_path} lacks output '{prefix}{s}' "
                                        f"(outputs: {names}), expected NanoDet-m; {_howto(self.kind)}")
                ordered.append(f"{prefix}{s}")
        return ordered

    def _make_priors(self, height: int, width: int):
        """Per-anchor (x, y, stride) for all strides of a height x width input, row-major per stride."""
        grids = []
        for s in _STRIDES:
            rows, cols = height // s, width // s
            ys, xs = np.meshgrid(np.arange(rows, dtype=np.float32), np.arange(cols, dtype=np.float32), indexing="ij")
            grid = np.stack([xs.ravel(), ys.ravel(), np.full(rows * cols, s, dtype=np.float32)], axis=1)
            if self.kind == "nanodet":
                grid[:, :2] = (grid[:, :2] + 0.5) * s   # cell centres in input pixels
            grids.append(grid)
        return np.concatenate(grids, axis=0)

    def close(self) -> None:
        """Nothing to persist; present so every detector can be closed alike."""

    def save(self) -> None:
        """Nothing to persist; present so every detector can be saved alike."""

    # -- inference ----------------------------------------------------------------------------------------

    def input_geometry(self, height: int, width: int) -> "_InputGeometry":
        """The network input for height x width images: the model's square, or with ``fit_input`` (YOLOX) the
        letterboxed image's own size rounded up to the largest stride (416 x 320 for 640 x 480), made at
        the first image of that size and kept. A model whose graph does not run at that size (a re-export
        with fixed reshapes) keeps the square, with a warning."""
        key = (int(height), int(width))
        if key in self._geometries:
            return self._geometries[key]
        geometry = self._square
        if self.fit_input:
            _, nw, nh, _, _ = letterbox_params(height, width, self.size, False)
            stride = max(_STRIDES)
            in_h, in_w = -(-nh // stride) * stride, -(-nw // stride) * stride
            if (in_h, in_w) != (self.size, self.size):
                geometry = self._fitted_geometry(in_h, in_w) or self._square
        self._geometries[key] = geometry
        return geometry

    def _fitted_geometry(self, height: int, width: int) -> Optional["_InputGeometry"]:
        priors = self._make_priors(height, width)
        try:
            session = self._load(with_input_size(self.model_path.read_bytes(), height, width))
            probe = np.full((1, 3, height, width), _YOLOX_PAD, np.float32)
            anchors = session.run(self._output_names, {self._input_name: probe})[0].shape[1]
        except Exception as exc:   # ONNX Runtime's own exception types (Fail, InvalidArgument ...) included
            warnings.warn(f"detector model {self.model_path} does not run on a {width} x {height} input "
                          f"({type(exc).__name__}: {str(exc).strip()[:160]}); using its {self.size} x {self.size} "
                          f"input (dynamic.detector.fit_input)", RuntimeWarning, stacklevel=3)
            return None
        if anchors != len(priors):
            warnings.warn(f"detector model {self.model_path} gives {anchors} anchors on a {width} x {height} "
                          f"input, expected {len(priors)}; using its {self.size} x {self.size} input",
                          RuntimeWarning, stacklevel=3)
            return None
        return _InputGeometry(session, height, width, priors)

    def preprocess(self, bgr: np.ndarray) -> tuple[np.ndarray, float, int, int]:
        """Network input (1,3,H,W) float32 (an internal buffer, overwritten by the next call; H x W from
        ``input_geometry``) and the letterbox (r, left, top): input pixel = image pixel * r + (left, top)."""
        if bgr.ndim == 2:
            bgr = cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
        elif bgr.shape[2] == 4:
            bgr = cv2.cvtColor(bgr, cv2.COLOR_BGRA2BGR)
        h, w = bgr.shape[:2]
        # A fitted input (YOLOX only: SIZE_FREE_MODELS) holds the image where the square does, at its top left.
        r, nw, nh, left, top = letterbox_params(h, w, self.size, self.kind == "nanodet")
        resized = cv2.resize(bgr, (nw, nh), interpolation=cv2.INTER_LINEAR)
        blob = self.input_geometry(h, w).blob
        blob.fill(_YOLOX_PAD if self.kind == "yolox_nano" else 0.0)   # NanoDet: 0 after normalisation
        for c in range(3):   # write each channel straight into the planar input
            plane = blob[0, c, top:top + nh, left:left + nw]
            if self.kind == "yolox_nano":
                plane[...] = resized[:, :, c]
            else:
                np.multiply(resized[:, :, c], self._inv_std[c], out=plane, casting="unsafe")
                plane -= self._mean_over_std[c]
        return blob, r, left, top

    @staticmethod
    def _nanodet_boxes(dis: np.ndarray, pri: np.ndarray) -> np.ndarray:
        d = dis.reshape(-1, 4, _NANODET_BINS)
        d = np.exp(d - d.max(axis=2, keepdims=True))
        d /= d.sum(axis=2, keepdims=True)
        dist = (d @ np.arange(_NANODET_BINS, dtype=np.float32)) * pri[:, 2:3]   # (A,4) l, t, r, b
        return np.concatenate([pri[:, :2] - dist[:, :2], pri[:, :2] + dist[:, 2:]], axis=1)

    def detect(self, bgr: np.ndarray, timestamp: float = 0.0) -> list[Detection]:
        boxes, scores, classes = self.detect_arrays(bgr)
        return [Detection(float(b[0]), float(b[1]), float(b[2]), float(b[3]), int(c), float(s))
                for b, s, c in zip(boxes, scores, classes)]

    def detect_arrays(self, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like ``detect`` but as arrays: boxes (N,4) float64 x0 y0 x1 y1, scores (N,), class ids (N,)."""
        h, w = bgr.shape[:2]
        blob, r, left, top = self.preprocess(bgr)
        geometry = self.input_geometry(h, w)          # the one preprocess filled: a dict lookup
        outputs = geometry.session.run(self._output_names, {self._input_name: blob})
        if self.kind == "yolox_nano":
            # Threshold on the objectness first: the score is obj*cls <= obj, so this is exact and
            # spares the decoding of almost every anchor.
            p = outputs[0].reshape(-1, outputs[0].shape[-1])
            sel = np.flatnonzero(p[:, 4] >= self.score_threshold)
            pri = geometry.priors[sel]
            p = p[sel]
            stride = pri[:, 2:3]
            xy = (p[:, :2] + pri[:, :2]) * stride
            wh = np.exp(np.minimum(p[:, 2:4], 20.0)) * stride
            anchor_boxes = np.concatenate([xy - 0.5 * wh, xy + 0.5 * wh], axis=1)
            anchor_scores = p[:, 4:5] * p[:, 5:]
        else:
            cls = np.concatenate([o.reshape(-1, o.shape[-1]) for o in outputs[0::2]], axis=0)
            sel = np.flatnonzero(cls.max(axis=1) >= self.score_threshold)
            dis = np.concatenate([o.reshape(-1, o.shape[-1]) for o in outputs[1::2]], axis=0)[sel]
            anchor_boxes = self._nanodet_boxes(dis, geometry.priors[sel])
            anchor_scores = cls[sel]
        if self.class_filter is not None:
            cols = self.class_filter[self.class_filter < anchor_scores.shape[1]]
            anchor_scores = anchor_scores[:, cols]
        else:
            cols = None
        a_idx, c_idx = np.nonzero(anchor_scores >= self.score_threshold)   # multi-label candidates
        if a_idx.size == 0:
            return np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64)
        scores = anchor_scores[a_idx, c_idx].astype(np.float64)
        classes = (cols[c_idx] if cols is not None else c_idx).astype(np.int64)
        boxes = boxes_from_input(anchor_boxes[a_idx], r, left, top)
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, float(w))
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, float(h))
        valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        boxes, scores, classes = boxes[valid], scores[valid], classes[valid]
        keep = nms_per_class(boxes, scores, classes, self.nms_iou)
        return boxes[keep], scores[keep], classes[keep]

    def __repr__(self) -> str:
        return (f"OnnxDetector(kind={self.kind!r}, path={str(self.model_path)!r}, "
                f"score_threshold={self.score_threshold}, nms_iou={self.nms_iou}, threads={self.threads}, "
                f"fit_input={self.fit_input})")


# --------------------------------------------------------------------------------------------
# Factory


def class_filter_of(classes: ClassGroups) -> list[int]:
    """Union of the dynamic, high- and low-probability passive class ids."""
    return sorted(set(int(c) for c in (*classes.dynamic, *classes.high_passive, *classes.low_passive)))


def build_detector(cfg: DetectorConfig, classes: ClassGroups, sequence_name: str = ""):
    """The ONNX detector for ``cfg`` keeping only the configured classes, wrapped in a
    ``CachedDetector`` when ``cfg.cache_dir`` is set. Both have ``save()`` and ``close()``."""
    class_filter = class_filter_of(classes)
    path = resolve_model_path(cfg)
    detector = OnnxDetector(path, kind=cfg.model, score_threshold=cfg.score_threshold,
                            nms_iou=cfg.nms_iou, threads=cfg.threads, class_filter=class_filter,
                            fit_input=cfg.fit_input)
    if cfg.cache_dir:
        return CachedDetector(detector, cache_path_for(cfg.cache_dir, sequence_name, cfg, class_filter, path),
                              model_digest(path))
    return detector
