"""slam/core/kernel_compile.py: numba compiling this project's kernels is announced once and timed (the first run
after an install spends a minute or two there), other numba code is not counted, and a run records it."""
from __future__ import annotations

import logging

import numba
import numpy as np

from slam.core.kernel_compile import compile_seconds, watch_kernel_compilation


def _kernel(module: str):
    """A fresh (uncached) numba kernel that looks as if it were defined in ``module``, calling a helper of its own."""
    def helper(x):
        return x * 2.0
    helper.__module__ = module
    jitted_helper = numba.njit(helper)

    def kernel(x):
        total = 0.0
        for v in x:
            total += jitted_helper(v)
        return total
    kernel.__module__ = module
    return numba.njit(kernel)


def test_project_kernels_are_timed_once_per_chain_and_announced_once(caplog):
    watch_kernel_compilation()
    watch_kernel_compilation()                          # idempotent: one listener
    seconds0, kernels0 = compile_seconds()
    with caplog.at_level(logging.INFO, logger="dynslam"):
        assert _kernel("frontend.fake_kernels")(np.arange(3.0)) == 6.0
        assert _kernel("backend.fake_kernels")(np.arange(3.0)) == 6.0
        assert _kernel("frontend.fake_kernels")(np.arange(3.0)) == 6.0
    seconds1, kernels1 = compile_seconds()
    assert kernels1 - kernels0 == 3                     # the helper compiled inside its kernel is not a chain of its own
    assert seconds1 > seconds0
    said = [r for r in caplog.records if "numba is compiling the kernels" in r.getMessage()]
    assert len(said) <= 1                               # at most once a process (an earlier test may have said it)


def test_other_numba_code_is_not_counted():
    watch_kernel_compilation()
    before = compile_seconds()
    assert _kernel("someone_elses_package")(np.arange(4.0)) == 12.0
    assert compile_seconds() == before


def test_the_clock_announces_the_first_project_chain_only_and_times_outermost_chains(caplog):
    from types import SimpleNamespace

    from slam.core.kernel_compile import _CompileClock

    def event(module):
        return SimpleNamespace(data={"dispatcher": SimpleNamespace(py_func=SimpleNamespace(__module__=module))})
    clock = _CompileClock()
    with caplog.at_level(logging.INFO, logger="dynslam"):
        clock.on_start(event("numpy_helpers"))            # someone else's chain, with one of ours inside it
        clock.on_start(event("frontend.x"))
        clock.on_end(None)
        clock.on_end(None)
        assert clock.kernels == 0 and not caplog.records
        for _ in range(2):                                  # two chains of ours, each with a nested compile
            clock.on_start(event("frontend.dynamic.cpr_icp_kernels"))
            clock.on_start(event("numba.np.arraymath"))
            clock.on_end(None)
            clock.on_end(None)
    assert clock.kernels == 2 and clock.seconds > 0
    assert [r.getMessage().startswith("numba is compiling the kernels") for r in caplog.records] == [True]
