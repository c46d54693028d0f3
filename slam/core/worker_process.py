"""Starting and stopping the run's worker process (the mapping back end's solver, slam/runtime/graph_process.py).

Work that holds the GIL for long (GTSAM's solves) runs in a process of its own, so the tracking thread is
not slowed by it (docs/design.md, "Runtime", has what else was measured there). A worker is forked from a
forkserver, not from the main process, whose detector and OpenCV threads a fork would copy mid-state; the
server has the worker target's module imported once, so a worker starts in milliseconds.

A worker ignores SIGINT (Ctrl-C is the main process's to handle: it still finishes the run and writes
complete files), stops when its pipe closes, and is a daemon, so no process outlives the run.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
from contextlib import contextmanager
from typing import Callable


@contextmanager
def _main_module_hidden():
    """multiprocessing re-imports the caller's main script in a forkserver/spawn child so the target can
    come from it; ours come from our modules, and a user's script without an ``if __name__ ==
    "__main__"`` guard would run again in the worker (and start a worker of its own). While the worker
    is started, the main module shows no file or spec, so nothing of it is imported there."""
    main = sys.modules.get("__main__")
    saved = {key: main.__dict__[key] for key in ("__file__", "__spec__") if main is not None and key in main.__dict__}
    try:
        for key in saved:
            if key == "__spec__":
                main.__spec__ = None
            else:
                del main.__dict__[key]
        yield
    finally:
        main.__dict__.update(saved)


@contextmanager
def _one_blas_thread():
    """OpenBLAS on one thread in the server the workers fork from (it reads the variable when the server
    imports numpy and SciPy; this process's own BLAS is loaded already and keeps its threads). A worker solves
    while the tracking threads keep both cores busy, and OpenBLAS's second thread waits for a core by
    spinning: a Cholesky of a 408 x 408 camera system (fr1/rpy-400's final adjustment) took 17 ms on two
    threads on a busy machine against 2 ms on one. Left as it is when the user set it."""
    if "OPENBLAS_NUM_THREADS" in os.environ:
        yield
        return
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        yield
    finally:
        del os.environ["OPENBLAS_NUM_THREADS"]


def start_worker(target: Callable, args: tuple, name: str):
    """Start ``target(*args, conn)`` in a daemon process named ``name`` (<= 15 characters: Linux's
    process name); returns (process, this side's connection). ``target`` must call ``worker_started(name)``
    first."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload([target.__module__])   # read when the server starts (the first worker)
    conn, child = ctx.Pipe()
    process = ctx.Process(target=target, args=(*args, child), name=name, daemon=True)
    # SIGINT stays blocked from before the (first) server starts until the worker ignores it: a Ctrl-C
    # during start-up must not kill the worker that the main process needs to finish the run. The
    # mask passes to the server (fork + exec) and from it to each worker; here it is restored at once
    # (a Ctrl-C in between is delivered then, not lost).
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        with _main_module_hidden(), _one_blas_thread():
            process.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
    child.close()
    return process, conn


def worker_started(name: str) -> None:
    """In a worker, first: Ctrl-C is for the main process (SIGINT was blocked since before the worker
    started); the process takes ``name`` as its Linux name, so ``top`` and tools/cpu_usage.py can tell
    the workers apart (all have the fork server's command line)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    try:
        with open("/proc/self/comm", "w") as comm:
            comm.write(name[:15])
    except OSError:     # no /proc (not Linux): the name is only a label
        pass


def stop_worker(process, conn, timeout_s: float = 10.0) -> None:
    """Ask the worker to stop (None on its pipe), wait for it, kill it if it does not stop in time."""
    try:
        conn.send(None)
    except (BrokenPipeError, OSError):
        pass
    conn.close()
    process.join(timeout=timeout_s)
    if process.is_alive():
        process.kill()
        process.join()
