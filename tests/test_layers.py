"""The package's layers, checked on the source: imports only go down, never sideways between the
front and the back end, and no two modules import each other (also not lazily inside a function).

    L0  slam.core                       config, camera, geometry, frame types, errors, timing, atomic writes
    L1  frontend, backend, slam.datasets  each imports slam.core only (and itself)
    L2  slam.runtime                    the System facade: wires frontend and backend
    L3  slam.run                        pipeline, outputs, reports, evaluation, export
    L4  slam.cli                        argument parsing, exit codes
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from conftest import REPO

PACKAGES = ("slam", "frontend", "backend")
LAYERS = [("slam.core", 0), ("frontend", 1), ("backend", 1), ("slam.datasets", 1), ("slam.runtime", 2),
          ("slam.run", 3), ("slam.cli", 4)]
SIBLINGS_APART = {"frontend", "backend", "slam.datasets"}   # the L1 packages never import each other


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def resolve(name: str) -> str | None:
    """The project module an imported name lives in (longest existing prefix), or None if external."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ".".join(parts[:n])
        if candidate in MODULES:
            return candidate
    return None


def imports_of(module: str) -> set[str]:
    """Every project module ``module`` imports, at the top or inside a function, TYPE_CHECKING too."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        for name in names:
            target = resolve(name)
            if target is not None and target != module:
                found.add(target)
    return found


def layer_of(module: str) -> tuple[str, int] | None:
    matches = [(p, level) for p, level in LAYERS if module == p or module.startswith(p + ".")]
    return max(matches, key=lambda m: len(m[0])) if matches else None


GRAPH = {m: imports_of(m) for m in MODULES}


def test_every_module_has_a_layer():
    assert not [m for m in MODULES if layer_of(m) is None and m not in PACKAGES], "modules outside every layer"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if layer_of(m)))
def test_imports_only_go_down(module):
    package, level = layer_of(module)
    wrong = []
    for target in sorted(GRAPH[module]):
        target_layer = layer_of(target)
        if target_layer is None:
            continue   # a package's empty __init__ (slam)
        target_package, target_level = target_layer
        if target_level > level:
            wrong.append(f"{target} (L{target_level}) is above {module} (L{level})")
        elif target_level == level and target_package != package and \
                {package, target_package} <= SIBLINGS_APART | {p for p, lv in LAYERS if lv == level}:
            wrong.append(f"{target} is a sibling layer of {module} (L{level}): they must not import each other")
    assert not wrong, "\n".join(wrong)


def test_frontend_and_backend_never_import_each_other():
    crossing = [(m, t) for m, targets in GRAPH.items() for t in targets
                if {m.split(".")[0], t.split(".")[0]} == {"frontend", "backend"}]
    assert not crossing, crossing


def test_no_import_cycles():
    """Tarjan's strongly connected components over the import graph: every component is one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:   # recursion depth is bounded by the number of modules (~100)
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in GRAPH:
        if module not in index:
            visit(module)
    assert not cycles, cycles


def test_the_checker_sees_lazy_and_relative_imports():
    """The rules above are only as good as the import reader: it must find an import inside a function
    (slam.runtime.system's lazy map_io import) and a relative one (slam.datasets' own modules)."""
    assert "backend.map_io" in GRAPH["slam.runtime.system"]
    assert "slam.datasets.tum" in GRAPH["slam.datasets.synthetic_export"]


def test_packages_export_their_public_names():
    """``from backend import FactorGraphBackend`` (the README's example) and the like resolve, for
    every name each package lists, without importing what is not asked for."""
    import importlib

    for package in PACKAGES:
        module = importlib.import_module(package)
        assert module.__all__, package
        for name in module.__all__:
            assert getattr(module, name) is not None, f"{package}.{name}"
        assert (REPO / package / "py.typed").is_file(), f"{package} lacks py.typed"


def test_pyproject_lists_every_package_and_ships_the_presets():
    """pyproject.toml names its packages one by one (configs/ is mapped to slam.presets); a new
    subpackage missing from that list would be missing from the wheel."""
    import tomllib

    setuptools_cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    in_tree = {module_name(p.parent / "__init__.py") for pkg in PACKAGES for p in (REPO / pkg).rglob("__init__.py")}
    assert set(setuptools_cfg["packages"]) == in_tree | {"slam.presets", "backend.data"}   # + the data folders
    assert setuptools_cfg["package-dir"] == {"slam.presets": "configs"}
    assert setuptools_cfg["package-data"]["slam.presets"] == ["*.yaml"]


def test_importing_a_package_imports_nothing_it_exports_until_asked():
    """slam/core/lazy_exports.py: ``import slam, frontend, backend`` loads none of the modules behind
    their public names (nor gtsam or OpenCV); the first read of a name imports its module and keeps the
    value; a name the package does not export is an AttributeError naming it."""
    import subprocess
    import sys

    code = (
        "import sys, slam, frontend, backend\n"
        "loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('slam', 'frontend', 'backend', 'gtsam', 'cv2'))\n"
        "print(loaded)\n"
        "system = slam.System\n"
        "print('slam.runtime.system' in sys.modules, vars(slam)['System'] is system, 'System' in dir(slam))\n"
        "try:\n"
        "    slam.Sistem\n"
        "except AttributeError as exc:\n"
        "    print(exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO).stdout
    loaded, cached, missing = out.splitlines()
    assert loaded == "['backend', 'frontend', 'slam', 'slam.core', 'slam.core.lazy_exports']"
    assert cached == "True True True"
    assert missing == "module 'slam' has no attribute 'Sistem'"
