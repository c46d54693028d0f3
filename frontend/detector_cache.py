"""The per-sequence detection cache: the boxes of every frame, keyed by timestamp, in a compressed ``.npz``
whose name and content carry the model file's sha256 and the settings that change the boxes, so repeated
runs on a sequence skip the network and another model never reads old boxes (``frontend.detector``
builds it around the ONNX detector)."""
from __future__ import annotations

import hashlib
import re
import warnings
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from frontend.dynamic.base import Detection, Detector
from frontend.model_lookup import DetectorError, resolve_model_path
from frontend.onnx_input_shape import SIZE_FREE_MODELS
from slam.core.atomic_io import write_npz_atomic
from slam.core.dynamic_config import DetectorConfig


def _ts_key(timestamp: float) -> str:
    return "%.6f" % float(timestamp)


_DIGESTS: dict[tuple[str, int, int], str] = {}   # (resolved path, mtime_ns, size) -> sha256 hex


def model_digest(model_path) -> str:
    """sha256 (hex) of a model file's content. The model's kind and settings do not identify its boxes
    (a re-exported or retrained file keeps its name), its bytes do. Cached by path, mtime and size, so
    a run hashes its model once and a replaced file is hashed again."""
    path = Path(model_path).expanduser().resolve()
    if not path.is_file():
        raise DetectorError(f"detector model file not found: {path} (needed to key the detection cache)")
    key = (str(path), path.stat().st_mtime_ns, path.stat().st_size)
    if key not in _DIGESTS:
        digest = hashlib.sha256()
        with open(path, "rb") as handle:
            for chunk in iter(lambda: handle.read(1 << 20), b""):
                digest.update(chunk)
        _DIGESTS[key] = digest.hexdigest()
    return _DIGESTS[key]


def cache_path_for(cache_dir, sequence_name: str, cfg: DetectorConfig,
                   class_filter: Optional[Iterable[int]] = None, model_path=None) -> Path:
    """``<cache_dir>/<sequence>__<model>_m<sha256[:16]>_s<score>_n<nms>[_c<classes hash>].npz``: the model
    file's content (``model_path``, default ``resolve_model_path(cfg)``) and the settings that change the
    boxes are part of the name, so a different model or setting never shares a cache."""
    seq = re.sub(r"[^A-Za-z0-9_.-]+", "_", sequence_name.strip()).strip("._") or "sequence"
    digest = model_digest(resolve_model_path(cfg) if model_path is None else model_path)
    name = f"{seq}__{cfg.model}_m{digest[:16]}_s{cfg.score_threshold:.3f}_n{cfg.nms_iou:.3f}"
    if cfg.fit_input and cfg.model in SIZE_FREE_MODELS:
        name += "_fit"       # the boxes of the fitted input differ a little near the bottom edge
    if class_filter is not None:
        ids = ",".join(str(c) for c in sorted(set(int(c) for c in class_filter)))
        name += "_c" + hashlib.sha1(ids.encode()).hexdigest()[:8]
    return Path(cache_dir).expanduser() / f"{name}.npz"


class CachedDetector:
    """Detections per frame, keyed by the timestamp ('%.6f'), backed by a compressed ``.npz``.

    Loads the file on construction when present (a corrupt file is reported with a warning and
    ignored: the boxes are recomputed and the file rewritten on ``save``). ``save()`` writes
    atomically (temporary file in the same folder, then ``os.replace``) and only when something new
    was computed. Frames must have distinct timestamps. With ``model_sha256`` (``model_digest(path)``)
    the file records it, and a file recorded with another model is treated like a corrupt one.
    """

    def __init__(self, inner: Detector, cache_file, model_sha256: Optional[str] = None):
        self.inner = inner
        self.cache_file = Path(cache_file)
        self.model_sha256 = model_sha256
        self._entries: dict[str, np.ndarray] = {}   # key -> (N,6) x0 y0 x1 y1 score class
        self._dirty = False
        self.hits = 0
        self.misses = 0
        self._load()

    def _load(self) -> None:
        if not self.cache_file.exists():
            return
        try:
            with np.load(self.cache_file, allow_pickle=False) as data:
                keys = data["keys"]
                counts = data["counts"].astype(np.int64)
                rows = data["rows"].astype(np.float64)
                stored = str(data["model_sha256"]) if "model_sha256" in data.files else None
            if self.model_sha256 is not None and stored is not None and stored != self.model_sha256:
                raise ValueError(f"made with another model file (sha256 {stored[:16]}..., this model's is "
                                 f"{self.model_sha256[:16]}...)")
            if keys.ndim != 1 or counts.shape != keys.shape or rows.ndim != 2 or rows.shape[1] != 6 \
                    or int(counts.sum()) != rows.shape[0] or np.any(counts < 0):
                raise ValueError("inconsistent arrays")
            ends = np.cumsum(counts)
            entries = {}
            for key, end, n in zip(keys.tolist(), ends.tolist(), counts.tolist()):
                entries[str(key)] = rows[end - n:end]
            self._entries = entries
        except Exception as exc:  # any unreadable file: recompute rather than crash
            warnings.warn(f"detection cache {self.cache_file} is unreadable ({type(exc).__name__}: {exc}); "
                          f"ignoring it, detections will be recomputed and the file rewritten", RuntimeWarning,
                          stacklevel=3)
            self._entries = {}
            self._dirty = True

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, timestamp: float) -> bool:
        return _ts_key(timestamp) in self._entries

    def detect(self, bgr: np.ndarray, timestamp: float = 0.0) -> list[Detection]:
        key = _ts_key(timestamp)
        rows = self._entries.get(key)
        if rows is None:
            self.misses += 1
            dets = list(self.inner.detect(bgr, timestamp))
            rows = np.array([[d.x0, d.y0, d.x1, d.y1, d.score, d.class_id] for d in dets],
                            dtype=np.float64).reshape(-1, 6)
            self._entries[key] = rows
            self._dirty = True
            return dets
        self.hits += 1
        return [Detection(float(r[0]), float(r[1]), float(r[2]), float(r[3]), int(r[5]), float(r[4])) for r in rows]

    def save(self) -> None:
        if not self._dirty:
            return
        keys = sorted(self._entries)
        counts = np.array([len(self._entries[k]) for k in keys], dtype=np.int64)
        rows = (np.concatenate([self._entries[k] for k in keys], axis=0) if keys else np.zeros((0, 6)))
        digest = {} if self.model_sha256 is None else {"model_sha256": np.array(self.model_sha256)}
        write_npz_atomic(self.cache_file, keys=np.array(keys, dtype=np.str_), counts=counts,
                         rows=rows.astype(np.float64), **digest)
        self._dirty = False

    def close(self) -> None:
        self.save()
        self.inner.close()

    def __repr__(self) -> str:
        return f"CachedDetector({self.inner!r}, cache_file={str(self.cache_file)!r}, entries={len(self)})"
