"""Per-module wall-clock timing, kept per frame so the summary can report medians; a block's thread CPU."""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np


@contextmanager
def thread_cpu_ms(record: list[float]):
    """Append the calling thread's CPU milliseconds spent in the block to ``record`` (also when it raises):
    a back end's cost per update, whatever other threads of the process do meanwhile."""
    start = time.thread_time()
    try:
        yield
    finally:
        record.append((time.thread_time() - start) * 1e3)


class ModuleTimer:
    def __init__(self):
        self._frames: list[dict[str, float]] = []
        self._current: dict[str, float] = defaultdict(float)

    @contextmanager
    def measure(self, module: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self._current[module] += (time.perf_counter() - start) * 1e3

    def end_frame(self) -> dict[str, float]:
        """Close the current frame; 'total' is the sum of its top-level modules ('a.b' is a part of 'a')."""
        frame = dict(self._current)
        frame["total"] = sum(v for k, v in frame.items() if "." not in k)
        self._frames.append(frame)
        self._current = defaultdict(float)
        return frame

    def per_frame(self, module: str) -> np.ndarray:
        """Milliseconds spent in ``module`` in each frame (0 where it did not run)."""
        return np.array([f.get(module, 0.0) for f in self._frames])

    def modules(self) -> list[str]:
        names = sorted({k for f in self._frames for k in f if k != "total"})
        return names + ["total"]

    def summary(self) -> dict[str, dict[str, float]]:
        """Median, mean and max milliseconds per frame for every module."""
        out = {}
        for name in self.modules():
            ms = self.per_frame(name)
            if len(ms):
                out[name] = {"median_ms": float(np.median(ms)), "mean_ms": float(np.mean(ms)),
                             "max_ms": float(np.max(ms))}
        return out
