"""The project's numba kernels: what their on-disk cache can and cannot see.

numba keys a cached function on its own source file only. A cached kernel that calls a compiled function of
another module carries that function's machine code, and an edit to that module alone runs the old code from
the cache (seen here: the pose optimiser's SE(3) functions, edited in a module of their own, ran stale until
pose_optimizer.py changed). So a cached kernel may call compiled functions of its own module only, and use no
project module at all: this test reads every kernel's global names."""
from __future__ import annotations

import importlib
import types
from pathlib import Path

from numba.core.registry import CPUDispatcher

ROOT = Path(__file__).resolve().parents[1]
ALLOWED_MODULES = {"numpy", "math", "numba"}


def _kernel_modules() -> list[str]:
    names = []
    for top in ("frontend", "backend", "slam"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if "numba.njit" in path.read_text(encoding="utf-8"):
                names.append(".".join(path.relative_to(ROOT).with_suffix("").parts))
    return names


def _is_cached(dispatcher: CPUDispatcher) -> bool:
    return type(dispatcher._cache).__name__ != "NullCache"     # numba keeps no public flag for it


def _cross_module_uses(name: str) -> tuple[int, list[str]]:
    """(how many cached kernels module ``name`` defines, what of other modules they use)."""
    module = importlib.import_module(name)
    checked, problems = 0, []
    for attr, obj in vars(module).items():
        if not isinstance(obj, CPUDispatcher) or obj.py_func.__module__ != name or not _is_cached(obj):
            continue
        checked += 1
        for ref in obj.py_func.__code__.co_names:
            target = obj.py_func.__globals__.get(ref)
            if isinstance(target, CPUDispatcher) and target.py_func.__module__ != name:
                problems.append(f"{name}.{attr} calls {target.py_func.__module__}.{ref}")
            elif isinstance(target, types.ModuleType) and target.__name__.split(".")[0] not in ALLOWED_MODULES:
                problems.append(f"{name}.{attr} uses the module {target.__name__}")
    return checked, problems


def test_cached_kernels_call_only_their_own_modules_compiled_functions():
    modules = _kernel_modules()
    assert {"frontend.pose_optimizer", "frontend.dynamic.cpr_icp_kernels"} <= set(modules)
    results = [_cross_module_uses(name) for name in modules]
    assert sum(checked for checked, _ in results) >= 20
    assert not [p for _, problems in results for p in problems]


def test_the_guard_sees_a_call_into_another_module(tmp_path, monkeypatch):
    """The check on a deliberately wrong pair of modules (a function imported by name, a module by attribute)."""
    (tmp_path / "kern_a.py").write_text("import numba\n@numba.njit(cache=True)\ndef helper(x):\n    return x + 1\n")
    (tmp_path / "kern_b.py").write_text("import numba\nimport kern_a\nfrom kern_a import helper\n"
                                        "@numba.njit(cache=True)\ndef kernel(x):\n    return helper(x) * 2\n"
                                        "@numba.njit(cache=True)\ndef other(x):\n    return kern_a.helper(x)\n"
                                        "@numba.njit\ndef uncached(x):\n    return helper(x)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    checked, problems = _cross_module_uses("kern_b")
    assert checked == 2
    assert {"kern_b.kernel calls kern_a.helper", "kern_b.other uses the module kern_a"} <= set(problems)
    assert not [p for p in problems if p.startswith("kern_b.uncached")]
