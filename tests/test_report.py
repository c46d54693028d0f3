"""The run report (slam.run.report): images exist, have their sizes and content, the page shows the
summary's numbers, the plotted series are the evaluated ones, and a report never breaks a run."""
from __future__ import annotations

import json
import logging
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from slam.cli import main
from slam.run.evaluation import evaluate_files
from slam.run.report import DynamicStripRecorder, NullStripRecorder, make_strip_recorder, render_index, write_report
from slam.run.report_plots import FIGURE_SIZE_PX
from slam.core.config import SlamConfig

FRAMES = 40
PLOTS = ("trajectory_top.png", "ate_over_time.png", "rpe.png", "timing.png")


@pytest.fixture(autouse=True)
def _restore_warning_format(monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)


@pytest.fixture(scope="module")
def dynamic_run(tmp_path_factory) -> Path:
    """One short demo with a detector-free dynamic method and the extra trajectory formats on."""
    out = tmp_path_factory.mktemp("report") / "results"
    saved = warnings.formatwarning
    try:
        code = main(["demo", "--no-compare", "--movers", "none", "--frames", str(FRAMES), "-o", str(out), "-q", "--set", "dynamic.methods=[cpr]",
                     "--set", "dynamic.fusion=single", "--set", "output.trajectory_formats=[tum,kitti,euroc]"])
    finally:
        warnings.formatwarning = saved
    assert code == 0
    return out


def read_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, f"{path} does not open as an image"
    return image


def read_csv(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


# --- images ----------------------------------------------------------------------------------------

@pytest.mark.slow
def test_plots_exist_have_their_size_and_are_not_blank(dynamic_run):
    for name in PLOTS:
        image = read_png(dynamic_run / "report" / name)
        assert image.shape == (FIGURE_SIZE_PX[1], FIGURE_SIZE_PX[0], 3), name
        assert image.std() > 10.0, f"{name} looks blank"
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20, f"{name} has almost no colours"


@pytest.mark.slow
def test_dynamic_strip_has_six_thumbnails_side_by_side(dynamic_run):
    strip = read_png(dynamic_run / "report" / "dynamic_strip.png")
    assert strip.shape == (240, 6 * 320 + 5 * 4, 3)     # 640x480 frames at 320 px wide, 4 px gaps
    for k in range(6):
        thumb = strip[:, k * 324:k * 324 + 320]
        assert thumb.std() > 10.0, f"thumbnail {k} looks blank"
    # static features are drawn in green on every thumbnail (the demo room does not move)
    green = (strip[..., 1] > 180) & (strip[..., 0] < 90) & (strip[..., 2] < 90)
    assert all(green[:, k * 324:k * 324 + 320].sum() > 50 for k in range(6))


# --- the plotted numbers are the evaluated ones -------------------------------------------------------

@pytest.mark.slow
def test_ate_series_is_the_summary_ate(dynamic_run):
    summary = json.loads((dynamic_run / "summary.json").read_text())
    series = read_csv(dynamic_run / "report" / "ate_over_time.csv")
    assert len(series) == summary["tracked"] == FRAMES
    rmse = float(np.sqrt(np.mean(series[:, 2] ** 2)))
    assert rmse == pytest.approx(summary["ate_rmse_m"], rel=1e-9, abs=1e-12)
    report = evaluate_files(dynamic_run / "groundtruth.txt", dynamic_run / "trajectory.txt")
    np.testing.assert_allclose(series[:, 2], report.ate.errors, atol=1e-7)


@pytest.mark.slow
def test_rpe_series_is_the_evaluated_rpe(dynamic_run):
    evaluation = json.loads((dynamic_run / "evaluation.json").read_text())
    series = read_csv(dynamic_run / "report" / "rpe.csv")
    assert len(series) == evaluation["rpe_frame"]["n_pairs"]
    assert np.sqrt(np.mean(series[:, 2] ** 2)) == pytest.approx(evaluation["rpe_frame"]["translation"]["rmse"],
                                                                rel=1e-9)
    assert np.sqrt(np.mean(series[:, 3] ** 2)) == pytest.approx(evaluation["rpe_frame"]["rotation"]["rmse"],
                                                                rel=1e-9)


# --- index.html ------------------------------------------------------------------------------------

@pytest.mark.slow
def test_index_links_every_image_and_shows_the_summary(dynamic_run):
    page = (dynamic_run / "report" / "index.html").read_text()
    summary = json.loads((dynamic_run / "summary.json").read_text())
    evaluation = json.loads((dynamic_run / "evaluation.json").read_text())
    sources = re.findall(r"<img src='([^']+)'", page)
    assert set(sources) == set(PLOTS) | {"dynamic_strip.png"}
    for link in sources + re.findall(r"<a href='([^']+)'", page):
        assert (dynamic_run / "report" / link).is_file(), link
    assert f"{summary['ate_rmse_m']:.4f}" in page
    assert f"{evaluation['rpe_frame']['translation']['rmse']:.4f}" in page
    assert f"<td>frames</td><td>{FRAMES}</td>" in page and f"<td>keyframes</td><td>{summary['keyframes']}</td>" in page
    assert f"{summary['timing_ms']['total']['median_ms']:.1f}" in page
    assert "<td>cpr</td>" in page and "Dynamic features" in page


def test_index_escapes_values():
    page = render_index({"dataset": "<script>alert(1)</script>", "frames": 3, "timing_ms": {}}, None, [])
    assert "<script>" not in page and "&lt;script&gt;" in page
    assert "No ground truth" in page and "evaluation.json" not in page


# --- the extra trajectory formats of the same run ------------------------------------------------------

@pytest.mark.slow
def test_configured_formats_are_written_by_the_run(dynamic_run):
    for name in ("trajectory.kitti.txt", "trajectory.kitti.times.txt", "trajectory.euroc.csv",
                 "trajectory_online.kitti.txt", "trajectory_online.euroc.csv", "keyframes.kitti.txt",
                 "keyframes.euroc.csv"):
        assert (dynamic_run / name).is_file(), name
    assert len((dynamic_run / "trajectory.kitti.txt").read_text().splitlines()) == FRAMES


# --- never breaks a run ------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_failing_plot_is_a_warning_and_left_out(dynamic_run, tmp_path, monkeypatch, caplog):
    import slam.run.report_plots

    def broken(*_args, **_kw):
        raise RuntimeError("no plotting today")

    monkeypatch.setattr(slam.run.report_plots, "plot_rpe", broken)
    summary = json.loads((dynamic_run / "summary.json").read_text())
    evaluation = evaluate_files(dynamic_run / "groundtruth.txt", dynamic_run / "trajectory.txt")
    with caplog.at_level(logging.WARNING, logger="dynslam"):
        index = write_report(tmp_path, summary, evaluation, [])
    assert "rpe.png not written" in caplog.text and "no plotting today" in caplog.text
    page = index.read_text()
    assert "rpe.png" not in page and "trajectory_top.png" in page
    assert not (tmp_path / "report" / "dynamic_strip.png").exists()


def test_a_failing_report_keeps_the_run_and_report_false_skips_it(tmp_path, monkeypatch, caplog):
    import slam.run.report

    def broken(*_args, **_kw):
        raise OSError("disk full")

    monkeypatch.setattr(slam.run.report, "write_report", broken)
    with caplog.at_level(logging.WARNING, logger="dynslam"):
        assert main(["demo", "--no-compare", "--movers", "none", "--frames", "5", "-o", str(tmp_path / "a"), "-q"]) == 0
    assert (tmp_path / "a" / "summary.json").is_file()
    assert "report not written" in caplog.text and "disk full" in caplog.text
    monkeypatch.undo()
    assert main(["demo", "--no-compare", "--movers", "none", "--frames", "5", "-o", str(tmp_path / "b"), "-q", "--set", "output.report=false"]) == 0
    assert (tmp_path / "b" / "summary.json").is_file() and not (tmp_path / "b" / "report").exists()


# --- choosing the strip's frames ---------------------------------------------------------------------

def fake_frame(n: int = 10) -> SimpleNamespace:
    rng = np.random.default_rng(0)
    return SimpleNamespace(uv_raw=rng.uniform(0, 60, (n, 2)), dynamic_prob=rng.uniform(0, 1, n))


def kept_positions(recorder: DynamicStripRecorder, frames: int) -> list[int]:
    image = np.full((60, 80, 3), 128, np.uint8)
    for position in range(frames):
        recorder.observe(position, image, fake_frame(), lambda: np.zeros((60, 80)))
    return [p for p, _ in recorder._kept]


def test_strip_frames_known_length_are_evenly_spaced_first_to_last():
    assert kept_positions(DynamicStripRecorder(0.5, expected_frames=101, width=40), 101) == [0, 20, 40, 60, 80, 100]


def test_strip_asks_for_the_mask_only_on_the_frames_it_keeps():
    """Fusing a frame's pixel mask costs ~10 ms: a 1000-frame run must not pay it 1000 times for 6 thumbnails."""
    asked = []
    recorder = DynamicStripRecorder(0.5, expected_frames=1000, width=40)
    image = np.full((60, 80, 3), 128, np.uint8)
    for position in range(1000):
        recorder.observe(position, image, fake_frame(), lambda p=position: asked.append(p) or np.zeros((60, 80)))
    assert asked == [p for p, _ in recorder._kept] and len(asked) == 6


@pytest.mark.parametrize("frames", [3, 6, 7, 50, 1000])
def test_strip_frames_unknown_length_stay_bounded_and_even(frames):
    recorder = DynamicStripRecorder(0.5, expected_frames=None, width=40)
    positions = kept_positions(recorder, frames)
    assert 0 < len(positions) <= 6 and positions[0] == 0
    assert len(set(np.diff(positions).tolist())) <= 1        # one spacing throughout
    assert len(positions) >= min(frames, 3)                 # never fewer than half the capacity
    assert all(t.shape == (30, 40, 3) for t in recorder.thumbnails)


def test_strip_recorder_only_for_dynamic_runs_with_reports():
    config = SlamConfig()
    config.dynamic.methods = []          # dynamic handling off (configs/static.yaml)
    assert isinstance(make_strip_recorder(config, 10), NullStripRecorder)
    config.dynamic.methods = ["cpr"]
    assert isinstance(make_strip_recorder(config, 10), DynamicStripRecorder)
    config.output.report = False
    assert isinstance(make_strip_recorder(config, 10), NullStripRecorder)


def test_the_strip_thumbnails_leave_matplotlib_unimported():
    """matplotlib takes 1-2 s to import: the thumbnails are made inside the tracking loop, with OpenCV
    alone, and the import waits for the figures at the end of the run (started on a thread while the
    final adjustment runs: Pipeline._preload_report_imports)."""
    import subprocess
    import sys

    script = ("import sys, numpy as np\n"
              "from types import SimpleNamespace\n"
              "from slam.run.report import DynamicStripRecorder\n"
              "recorder = DynamicStripRecorder(0.5, expected_frames=2, width=40)\n"
              "frame = SimpleNamespace(uv_raw=np.array([[10.0, 10.0]]), dynamic_prob=np.array([0.9]))\n"
              "recorder.observe(0, np.zeros((60, 80, 3), np.uint8), frame, lambda: np.zeros((60, 80)))\n"
              "assert len(recorder.thumbnails) == 1\n"
              "print('matplotlib' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False", result.stderr
