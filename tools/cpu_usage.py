"""CPU time of a run by thread and process, read from ``/proc`` (Linux), for ``tools/benchmark.py``.

Whole-run wall time on a 2-core machine is bounded below by the CPU the run needs divided by the cores:
where that bound is close to the wall time, the run is CPU-bound and only less work makes it faster.
``CpuSampler`` polls every thread of this process and of its descendants (the mapping worker lives under
multiprocessing's fork server) and keeps each one's last ``utime + stime``; threads end with the run
(the pools shut down in ``System.close``), so they are sampled while it goes. Names come from Python's
threads (``dynslam-detector_0`` ...), the main thread is ``tracking``, threads Python did not start
(OpenCV's and ONNX Runtime's own workers) are ``other threads``, the workers by the names they give themselves
(``mapping worker``: slam/core/worker_process.py), other processes by their command line. Only the CPU used inside
the ``with`` block counts (a thread's reading at the start is subtracted). Up to one poll interval (0.2 s) of
the CPU of a thread that ends inside the block may be missed.
"""
from __future__ import annotations

import os
import re
import threading
from collections import defaultdict
from pathlib import Path
from typing import Optional

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 0.01
_INTERVAL_S = 0.2


def _cpu_s(stat_path: Path) -> Optional[float]:
    try:
        text = stat_path.read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) * _TICK_S     # utime + stime (fields 14, 15 of stat)


def _children(pid: int) -> list[int]:
    kids = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return kids


_WORKERS = {"dynslam-mapping": "mapping worker"}   # slam/core/worker_process.py


def _process_name(pid: int) -> str:
    try:
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        comm = ""
    if comm in _WORKERS:
        return _WORKERS[comm]
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return f"process {pid}"
    if "forkserver" in cmd:
        return "fork server"
    return re.sub(r"\s+", " ", cmd)[:40] or f"process {pid}"


class CpuSampler:
    """``with CpuSampler() as cpu: run()``; then ``cpu.seconds`` = {name: CPU seconds} (same-named threads
    summed). Empty where ``/proc`` is missing."""

    def __init__(self):
        self._last: dict[tuple[int, int], tuple[str, float]] = {}
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._self_pid = os.getpid()
        self._start: dict[tuple[int, int], float] = {}

    def __enter__(self) -> "CpuSampler":
        if Path(f"/proc/{self._self_pid}/task").is_dir():
            # what this process's threads had used before (imports, an earlier run): not this run's
            self._poll()
            self._start = {key: cpu for key, (_, cpu) in self._last.items()}
            self._last.clear()
            self._thread = threading.Thread(target=self._loop, name="cpu-sampler", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._poll()

    @property
    def seconds(self) -> dict[str, float]:
        out: dict[str, float] = defaultdict(float)
        for key, (name, cpu) in self._last.items():
            out[name] += cpu - self._start.get(key, 0.0)
        return dict(out)

    def _loop(self) -> None:
        while not self._stop.wait(_INTERVAL_S):
            self._poll()

    def _poll(self) -> None:
        names = {t.native_id: t.name for t in threading.enumerate()}
        pid = self._self_pid
        for task in Path(f"/proc/{pid}/task").glob("*"):
            tid = int(task.name)
            if names.get(tid) == "cpu-sampler":
                continue
            cpu = _cpu_s(task / "stat")
            if cpu is not None:
                name = "tracking" if tid == pid else re.sub(r"_\d+$", "", names.get(tid, "other threads"))
                previous = self._last.get((pid, tid))
                # a thread id reused by a later pool thread: keep the larger reading (never lose CPU)
                self._last[(pid, tid)] = (name, max(cpu, previous[1]) if previous else cpu)
        stack = _children(pid)
        while stack:
            child = stack.pop()
            stack += _children(child)
            cpu = _cpu_s(Path(f"/proc/{child}/stat"))
            if cpu is not None:
                known = self._last.get((child, child))     # named while alive: an exited one has no cmdline
                self._last[(child, child)] = (known[0] if known else _process_name(child), cpu)


def cpu_line(seconds: dict[str, float], frames: int, wall_s: float, cores: Optional[int] = None) -> str:
    """'CPU ms per frame: tracking 51.0, mapping worker 39.0, ... ; all 150.2 = 75.1 per core on 2 cores
    (wall 80.0)': where the per-core figure is near the wall time, the run is CPU-bound."""
    cores = cores or os.cpu_count() or 1
    frames = max(frames, 1)
    parts = sorted(seconds.items(), key=lambda kv: -kv[1])
    total = sum(seconds.values())
    listed = ", ".join(f"{name} {1e3 * s / frames:.1f}" for name, s in parts if 1e3 * s / frames >= 0.5)
    return (f"CPU ms per frame: {listed}; all {1e3 * total / frames:.1f} = {1e3 * total / frames / cores:.1f} "
            f"per core on {cores} cores (whole run {1e3 * wall_s / frames:.1f})")
