"""The compiled loops' one-time cost: a notice when numba compiles the project's kernels, and how long it took.

numba compiles a kernel the first time it is called with new argument types and keeps the machine code in its
cache (beside the package, or numba's user cache where that is not writable): the first run after an install
compiles the project's ~50 kernel specialisations, which took 80 s on a 2-core machine on 2026-12-02 (a 40-frame
Bonn run: 93 s with an empty cache, 13 s with the cache), once. Without a word a user takes that for the speed of
every run, and a benchmark would count it as per-frame cost, so ``watch_kernel_compilation`` says it when it
happens (the ``dynslam`` logger, INFO) and ``compile_seconds`` tells how long it took in this process.

A listener on numba's ``numba:compile`` event, which numba fires only on a cache miss; compilations nest (a
kernel compiles the functions it calls) and are serialised by numba's compiler lock, so the outermost one of
each chain is timed, and only chains that start at a kernel of this project count.
"""
from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger("dynslam")

_PROJECT_PACKAGES = ("frontend", "backend", "slam")


class _CompileClock:
    """Wall seconds spent compiling this project's kernels in this process (``numba:compile`` listener)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.kernels = 0
        self._depth = 0
        self._started = 0.0
        self._ours = False
        self._announced = False
        self._lock = threading.Lock()

    def on_start(self, event) -> None:
        with self._lock:
            self._depth += 1
            if self._depth > 1:
                return
            self._started = time.perf_counter()
            dispatcher = event.data.get("dispatcher")
            module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
            self._ours = module.split(".")[0] in _PROJECT_PACKAGES
            announce = self._ours and not self._announced
            self._announced |= announce
        if announce:
            log.info("numba is compiling the kernels for this machine (once after an install: a minute or two); "
                     "later runs load them from its cache")

    def on_end(self, event) -> None:
        with self._lock:
            self._depth = max(self._depth - 1, 0)
            if self._depth == 0 and self._ours:
                self.seconds += time.perf_counter() - self._started
                self.kernels += 1


_clock: _CompileClock | None = None


def watch_kernel_compilation() -> None:
    """Start timing (and announcing) the compilation of this project's kernels in this process; idempotent."""
    global _clock
    if _clock is not None:
        return
    from numba.core import event

    clock = _CompileClock()

    class _Listener(event.Listener):
        def on_start(self, ev) -> None:
            clock.on_start(ev)

        def on_end(self, ev) -> None:
            clock.on_end(ev)

    event.register("numba:compile", _Listener())
    _clock = clock


def compile_seconds() -> tuple[float, int]:
    """(wall seconds, kernels) compiled in this process since ``watch_kernel_compilation``; (0, 0) before."""
    return (0.0, 0) if _clock is None else (_clock.seconds, _clock.kernels)
