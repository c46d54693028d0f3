"""CLI smoke tests of ``dynslam demo`` through ``slam.cli.main([...])`` in-process: its results folder,
counts and accuracy, and the default demo's two runs (with and without dynamic handling)."""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from _cli_helpers import data_lines
from slam.cli import main
from slam.core.config import load_config
from slam.run.evaluation import evaluate_files
from slam.run.trajectory import read_tum

pytestmark = pytest.mark.usefixtures("restore_warning_format")

RESULT_FILES = ("config.yaml", "trajectory.txt", "trajectory_online.txt", "keyframes.txt", "groundtruth.txt",
                "summary.json", "evaluation.json")


# --- demo ----------------------------------------------------------------------------------------------

DEMO40_ATE, DEMO40_ONLINE_ATE = 0.0034, 0.0036   # measured: dynslam demo --frames 40 (final, online)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[int, Path]:
    out_dir = tmp_path_factory.mktemp("demo") / "results"
    saved_format = warnings.formatwarning
    try:
        code = main(["demo", "--no-compare", "--movers", "none", "--frames", "40", "-o", str(out_dir), "-q"])
    finally:
        warnings.formatwarning = saved_format
    return code, out_dir


@pytest.mark.slow   # the 120-frame demo (~7 s) keeps the fast tier under its 2 minutes
def test_demo_exits_0_and_writes_the_results_folder(demo_run):
    code, out_dir = demo_run
    assert code == 0
    for name in RESULT_FILES:
        assert (out_dir / name).is_file(), name
    config = load_config(out_dir / "config.yaml")
    assert config.camera.name == "synthetic"


@pytest.mark.slow   # the 120-frame demo (~7 s) keeps the fast tier under its 2 minutes
def test_demo_summary_counts_and_accuracy(demo_run):
    _, out_dir = demo_run
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["frames"] == 40
    assert summary["tracked"] == 40
    assert summary["lost"] == 0 and summary["lost_frames"] == []
    assert summary["keyframes"] >= 2
    report = evaluate_files(out_dir / "groundtruth.txt", out_dir / "trajectory.txt")
    assert report.ate.n_matched == 40
    assert report.ate.rmse < DEMO40_ATE * 1.15   # the regression margin of every accuracy gate
    assert summary["ate_rmse_m"] == pytest.approx(report.ate.rmse, abs=1e-6)
    evaluation = json.loads((out_dir / "evaluation.json").read_text())
    assert evaluation["ate"]["rmse"] == pytest.approx(report.ate.rmse, abs=1e-6)
    gt_t, _ = read_tum(out_dir / "groundtruth.txt")
    np.testing.assert_allclose(gt_t, np.arange(40) / 30.0, atol=1e-6)
    # Every tracked frame's pose uncertainty is below the LOST limit (beyond it the frame is not tracked).
    sigma = summary["pose_sigma_mm"]
    assert 0 < sigma["median"] <= sigma["p95"] <= sigma["max"] <= 10.0   # tracking.max_pose_sigma_m
    assert 1 <= sigma["max_frame"] < 40    # frame 0 initialises the map: no pose estimate, no sigma


@pytest.mark.slow   # the 120-frame demo (~7 s) keeps the fast tier under its 2 minutes
def test_demo_trajectory_files_are_complete_and_sorted(demo_run):
    _, out_dir = demo_run
    rows = data_lines(out_dir / "trajectory.txt")
    stamps = np.array([float(r[0]) for r in rows])
    assert len(rows) == 40 and all(len(r) == 8 for r in rows)
    assert np.all(np.diff(stamps) > 0), "trajectory.txt must be sorted by timestamp"
    online = data_lines(out_dir / "trajectory_online.txt")
    assert len(online) == 40
    np.testing.assert_allclose([float(r[0]) for r in online], stamps)
    summary = json.loads((out_dir / "summary.json").read_text())
    keyframes = data_lines(out_dir / "keyframes.txt")
    assert len(keyframes) == summary["keyframes"]
    assert set(float(r[0]) for r in keyframes) <= set(stamps.tolist())
    # the online (causal) poses are good too, not only the optimised ones
    assert evaluate_files(out_dir / "groundtruth.txt", out_dir / "trajectory_online.txt").ate.rmse < DEMO40_ONLINE_ATE * 1.15


@pytest.mark.slow
def test_demo_runs_with_and_without_dynamic_handling_and_prints_both(tmp_path, capsys):
    """The default demo: people walking, the default config (dynamic handling on), then the same run
    with dynamic handling off; both ATEs on one line, the second run in without_dynamic/."""
    out = tmp_path / "demo"
    assert main(["demo", "--frames", "20", "-o", str(out), "-q"]) == 0
    printed = capsys.readouterr().out
    line = [ln for ln in printed.splitlines() if ln.startswith("ATE with dynamic handling")]
    assert len(line) == 1, printed
    on_mm, off_mm = (float(x) for x in re.findall(r"([0-9.]+) mm", line[0]))
    on = json.loads((out / "summary.json").read_text())
    off = json.loads((out / "without_dynamic" / "summary.json").read_text())
    assert on["dynamic_methods"] and not off["dynamic_methods"]
    assert on_mm == pytest.approx(on["ate_rmse_m"] * 1000, abs=0.05)
    assert off_mm == pytest.approx(off["ate_rmse_m"] * 1000, abs=0.05)
    assert on_mm < off_mm
