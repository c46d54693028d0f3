"""Shared test set-up: where the real data lives, how its absence is handled, and factories.

Tiers (markers registered in pyproject.toml):
- ``real``: needs ``../shared`` (real sequences or the ONNX detectors) beside the checkout;
- ``slow``: takes more than a few seconds; ``pytest -m "not slow"`` is the everyday tier (< 2 min).

Missing real data: a user's clone without ``../shared`` skips those tests with a reason. In CI (the
environment variable ``CI`` is set, as ``.ci/run`` runs) a missing data set or model is a *failure*
naming what is missing, so a green CI always means the real-data gates ran.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data"
MODELS = SHARED / "models"

RPY = "rgbd_dataset_freiburg1_rpy_first400"
XYZ = "rgbd_dataset_freiburg1_xyz_first37"
DESK = "rgbd_dataset_freiburg1_desk_9frames"
BONN = "rgbd_bonn_crowd_first480"
MODEL_FILES = {"yolox": "yolox_nano_416.onnx", "nanodet": "nanodet_m_320.onnx"}


def in_ci() -> bool:
    return bool(os.environ.get("CI"))


def require_shared(path: Path, what: str) -> Path:
    """``path`` if it exists; otherwise skip (a user's clone) or fail (CI) saying what is missing."""
    if path.exists():
        return path
    message = f"{what} is missing: {path} does not exist (it comes with ../shared beside the checkout)"
    if in_ci():
        pytest.fail(f"CI needs the real data: {message}", pytrace=False)
    pytest.skip(message)


def real_sequence(name: str) -> Path:
    """The folder of a real sequence in ../shared/data (skip or CI failure when absent)."""
    return require_shared(DATA / name, f"real sequence {name}")


def model_file(kind: str) -> Path:
    """The development copy of a detector model in ../shared/models (skip or CI failure when absent)."""
    return require_shared(MODELS / MODEL_FILES[kind], f"detector model {kind}")


# ----------------------------------------------------------------------------------- factories
def synthetic_sequence(n_frames: int = 40, seed: int = 0, **kwargs):
    """A generated RGB-D room (``slam.datasets.SyntheticSequence``), e.g. ``movers="people"``."""
    from slam.datasets import SyntheticSequence

    return SyntheticSequence(n_frames=n_frames, seed=seed, **kwargs)


def synthetic_config(sequence, preset: Optional[str] = None, **overrides):
    """The default config with ``sequence``'s camera, then ``preset``, then dotted overrides."""
    from slam.dynamic_eval import synthetic_config as make

    return make(sequence, preset=preset, **overrides)


def run_dynslam(args: Sequence[str], timeout: float = 600, env: Optional[dict] = None,
                cwd: Optional[Path] = None) -> subprocess.CompletedProcess:
    """``dynslam ARGS`` in a fresh Python process (what a user runs), capturing its output."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "slam.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=full_env, cwd=cwd or REPO)


def read_summary(results: Path) -> dict:
    return json.loads((Path(results) / "summary.json").read_text())


def tum_pose_lines(path: Path) -> list[str]:
    """The pose lines of a TUM file (comments, e.g. ``# t LOST``, left out)."""
    return [line for line in Path(path).read_text().splitlines() if line and not line.startswith("#")]


def frame_errors(results: Path, groundtruth: Path) -> np.ndarray:
    """Per-frame translation error (m) of a run's trajectory after the ATE alignment."""
    from slam.evaluation import evaluate_files

    report = evaluate_files(groundtruth, Path(results) / "trajectory.txt", 0.02)
    return np.asarray(report.ate.errors)


def load_tool(name: str):
    """A script of ``tools/`` imported as a module (the tools are scripts, not a package)."""
    import importlib.util

    tools = REPO / "tools"
    spec = importlib.util.spec_from_file_location(f"{name}_tool", tools / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    sys.path.insert(0, str(tools))   # a tool may import its siblings (ablation.py imports sweep.py)
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(tools))
    return module


class AccuracyRuns:
    """The cases of ``tools/accuracy.py``, each run once per test session as ``dynslam`` processes
    (2 at a time: this machine's cores) and shared by every test that needs them (the gates, the
    Bonn map export, ...)."""

    def __init__(self, root: Path):
        self.tool = load_tool("accuracy")
        self.root = root
        self.results: dict = {}
        self.identical: dict[str, bool] = {}

    def get(self, *names: str, twins: bool = False) -> dict:
        """Results of the named cases, running those not run yet; ``twins``: also the second process
        of the determinism cases among them."""
        for name in names:
            case = self.tool.CASES[name]
            if case.sequence:
                real_sequence(case.sequence)
            if "dynamic_all" in case.args and case.sequence:
                model_file("yolox")   # the real detector, no cache
        todo = [n for n in names if n not in self.results]
        late_twins = [n for n in names if twins and n in self.results and n in self.tool.DETERMINISM_CASES
                      and n not in self.identical]
        if todo:
            results, identical = self.tool.run_cases(todo, self.root, jobs=2, determinism=twins)
            self.results.update(results)
            self.identical.update(identical)
        for name in late_twins:   # run first without its twin: the second process now
            again = self.tool.run_case(self.tool.CASES[name], self.root / f"{name}_again")
            self.identical[name] = self.tool.same_trajectory(self.root / name, again.results)
        return {n: self.results[n] for n in names}


@pytest.fixture(scope="session")
def accuracy_runs(tmp_path_factory) -> AccuracyRuns:
    return AccuracyRuns(tmp_path_factory.mktemp("accuracy"))


# ------------------------------------------------------------------------------- printed figures
_FIGURES: list[tuple[str, str]] = []


def report_figures(title: str, text: str) -> None:
    """Measured figures that the README quotes: printed at the end of every pytest run (no ``-s``
    needed), so each README number named after a test is reproduced by running that test."""
    _FIGURES.append((title, text))


def pytest_terminal_summary(terminalreporter) -> None:
    if not _FIGURES:
        return
    terminalreporter.section("measured figures (quoted in the README)")
    for title, text in _FIGURES:
        terminalreporter.write_line(f"{title}:")
        for line in text.splitlines():
            terminalreporter.write_line(f"    {line}")
