"""Per-module wall-clock timing and the CPU time of the thread that ran each block, kept per frame so the
summary can report medians; a block's thread CPU."""
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
    """Wall milliseconds per module and frame, and beside them the CPU milliseconds of the thread that ran
    the block: on two busy cores a module's wall time also counts the time its thread waited for a core
    (fr1/rpy, 2026-12-01: flow_epipolar 42 ms of wall per frame for 19 ms of CPU), and only the CPU says
    what a module itself costs. Blocks may run on several threads (cpr's registration runs on its own)."""

    def __init__(self):
        self._frames: list[dict[str, float]] = []
        self._cpu_frames: list[dict[str, float]] = []
        self._current: dict[str, float] = defaultdict(float)
        self._cpu_current: dict[str, float] = defaultdict(float)

    @contextmanager
    def measure(self, module: str):
        start, cpu_start = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self._current[module] += (time.perf_counter() - start) * 1e3
            self._cpu_current[module] += (time.thread_time() - cpu_start) * 1e3

    def end_frame(self) -> dict[str, float]:
        """Close the current frame; 'total' is the sum of its top-level modules ('a.b' is a part of 'a')."""
        frame = dict(self._current)
        frame["total"] = sum(v for k, v in frame.items() if "." not in k)
        self._frames.append(frame)
        cpu = dict(self._cpu_current)
        cpu["total"] = sum(v for k, v in cpu.items() if "." not in k)
        self._cpu_frames.append(cpu)
        self._current = defaultdict(float)
        self._cpu_current = defaultdict(float)
        return frame

    def per_frame(self, module: str) -> np.ndarray:
        """Milliseconds spent in ``module`` in each frame (0 where it did not run)."""
        return np.array([f.get(module, 0.0) for f in self._frames])

    def cpu_per_frame(self, module: str) -> np.ndarray:
        """CPU milliseconds of the threads that ran ``module`` in each frame (0 where it did not run)."""
        return np.array([f.get(module, 0.0) for f in self._cpu_frames])

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
