"""tools/cpu_usage.py: the benchmark's CPU time by thread and process, read from /proc while a run goes."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import load_tool

cpu_usage = load_tool("cpu_usage")
pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")


def _burn(seconds: float, then_idle: float = 0.0) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        sum(range(1000))
    time.sleep(then_idle)      # a pool thread idles until the run closes: its last poll sees all its CPU


def test_threads_and_child_processes_are_counted_by_name():
    with cpu_usage.CpuSampler() as cpu:
        worker = threading.Thread(target=_burn, args=(0.25, 0.35), name="dynslam-detector_0")
        worker.start()
        child = subprocess.Popen([sys.executable, "-c", "import time\nend = time.process_time() + 0.25\n"
                                  "while time.process_time() < end: pass\ntime.sleep(0.35)"])
        worker.join()
        _burn(0.15)
        time.sleep(0.4)                # the child has burnt its CPU and still lives: sampled
        child.wait()
    seconds = cpu.seconds
    assert 0.2 <= seconds["dynslam-detector"] <= 0.4      # the pool suffix _0 is dropped
    assert seconds["tracking"] >= 0.1                    # the main thread
    assert any("python" in name and 0.2 <= v <= 0.45 for name, v in seconds.items()), seconds   # the child


def test_cpu_line_gives_per_frame_figures_and_the_per_core_bound():
    line = cpu_usage.cpu_line({"tracking": 2.0, "mapping worker": 1.0, "idle thread": 0.0001}, 100, 2.0, cores=2)
    assert line == ("CPU ms per frame: tracking 20.0, mapping worker 10.0; all 30.0 = 15.0 per core on 2 cores "
                    "(whole run 20.0)")


def test_only_the_cpu_used_inside_the_block_counts():
    _burn(0.3)                                           # before: imports, an earlier run
    with cpu_usage.CpuSampler() as cpu:
        _burn(0.1)
    assert 0.05 <= cpu.seconds["tracking"] <= 0.25


def test_the_mapping_worker_is_counted_by_its_own_name_not_the_fork_servers():
    """Every worker is forked from the fork server and shares its command line; the worker names itself
    (slam/core/worker_process.py), so the benchmark's CPU line tells the back end from the server."""
    from slam.core.config import BackendConfig
    from slam.runtime.graph_process import GraphProcess, GraphSpec
    from conftest import RING_CALIBRATION

    graph = GraphProcess(GraphSpec(BackendConfig(), RING_CALIBRATION))
    try:
        pid = graph._process.pid
        deadline = time.monotonic() + 30       # the worker names itself first thing; the server may be starting
        while Path(f"/proc/{pid}/comm").read_text().strip() != "dynslam-mapping" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert Path(f"/proc/{pid}/comm").read_text().strip() == "dynslam-mapping"
        assert cpu_usage._process_name(pid) == "mapping worker"
        server = Path(f"/proc/{pid}/stat").read_text().split(") ")[1].split()[1]   # its parent: the server
        assert cpu_usage._process_name(int(server)) == "fork server"
    finally:
        graph.close()


def test_the_mapping_worker_runs_openblas_on_one_thread_and_this_process_keeps_its_setting(monkeypatch):
    """The worker solves while the tracking threads hold both cores; OpenBLAS's second thread would spin for a
    core (docs/design.md, "Runtime"). The server the worker forks from starts with one BLAS thread; this
    process's environment is left as it was, and a user's own setting is kept (``_one_blas_thread``)."""
    from slam.core.config import BackendConfig
    from slam.core.worker_process import _one_blas_thread
    from slam.runtime.graph_process import GraphProcess, GraphSpec
    from conftest import RING_CALIBRATION

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    graph = GraphProcess(GraphSpec(BackendConfig(), RING_CALIBRATION))
    try:
        environ = Path(f"/proc/{graph._process.pid}/environ").read_bytes().split(b"\0")
        assert b"OPENBLAS_NUM_THREADS=1" in environ
        assert "OPENBLAS_NUM_THREADS" not in os.environ
    finally:
        graph.close()
    with _one_blas_thread():
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    assert "OPENBLAS_NUM_THREADS" not in os.environ
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    with _one_blas_thread():
        assert os.environ["OPENBLAS_NUM_THREADS"] == "4"
    assert os.environ["OPENBLAS_NUM_THREADS"] == "4"
