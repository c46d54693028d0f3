"""Per-module wall-clock and thread-CPU milliseconds, kept per frame so the summary can report medians."""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

import numpy as np

_WALL, _CPU = 0, 1      # the entries of a module's per-frame record


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
    """Wall milliseconds per module and frame, and beside them the CPU milliseconds of the thread that ran
    the block: on two busy cores a module's wall time also counts the time its thread waited for a core
    (fr1/rpy, 2026-12-01: flow_epipolar 42 ms of wall per frame for 19 ms of CPU), and only the CPU says
    what a module itself costs. Blocks may run on several threads (cpr's registration runs on its own)."""

    def __init__(self):
        self._frames: list[dict[str, list[float]]] = []      # per frame: module -> [wall ms, CPU ms]
        self._current: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])

    @contextmanager
    def measure(self, module: str):
        # Plain floats: ~50 blocks a frame on the tracking thread, where numpy's per-call cost would show.
        start, cpu_start = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            record = self._current[module]
            record[_WALL] += (time.perf_counter() - start) * 1e3
            record[_CPU] += (time.thread_time() - cpu_start) * 1e3

    def end_frame(self) -> dict[str, float]:
        """Close the current frame and return its wall milliseconds per module; 'total' is the sum of its
        top-level modules ('a.b' is a part of 'a')."""
        frame = dict(self._current)
        top = [v for k, v in frame.items() if "." not in k]
        frame["total"] = [sum(v[_WALL] for v in top), sum(v[_CPU] for v in top)]
        self._frames.append(frame)
        self._current = defaultdict(lambda: [0.0, 0.0])
        return {k: v[_WALL] for k, v in frame.items()}

    def per_frame(self, module: str) -> np.ndarray:
        """Wall milliseconds spent in ``module`` in each frame (0 where it did not run)."""
        return self._column(module, _WALL)

    def cpu_per_frame(self, module: str) -> np.ndarray:
        """CPU milliseconds of the threads that ran ``module`` in each frame (0 where it did not run)."""
        return self._column(module, _CPU)

    def _column(self, module: str, clock: int) -> np.ndarray:
        return np.array([f[module][clock] if module in f else 0.0 for f in self._frames])

    def modules(self) -> list[str]:
        names = sorted({k for f in self._frames for k in f if k != "total"})
        return names + ["total"]

    def summary(self) -> dict[str, dict[str, float]]:
        """Median, mean and max wall milliseconds per frame for every module, and its mean CPU ms per frame."""
        out = {}
        for name in self.modules():
            ms = self.per_frame(name)
            if len(ms):
                out[name] = {"median_ms": float(np.median(ms)), "mean_ms": float(np.mean(ms)),
                             "max_ms": float(np.max(ms)), "cpu_mean_ms": float(np.mean(self.cpu_per_frame(name)))}
        return out
