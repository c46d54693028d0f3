"""CLI smoke tests: ``slam.cli.main([...])`` in-process (fast) and one real ``dynslam --help`` subprocess."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from slam.cli import main
from slam.core.config import SlamConfig, load_config
from slam.datasets import SyntheticSequence, write_tum_layout
from slam.run.evaluation import evaluate_files
from slam.run.trajectory import read_tum, write_tum

RESULT_FILES = ("config.yaml", "trajectory.txt", "trajectory_online.txt", "keyframes.txt", "groundtruth.txt",
                "summary.json", "evaluation.json")
SYNTH_FX = 550.0  # differs from both the config default (525) and the freiburg1 preset (517.3)


@pytest.fixture(autouse=True)
def _restore_warning_format(monkeypatch):
    """main() installs its own warnings.formatwarning; keep it from leaking into other tests."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def data_lines(path: Path) -> list[list[str]]:
    return [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


# --- help / config -----------------------------------------------------------------------------------

def test_dynslam_help_in_a_subprocess():
    exe = shutil.which("dynslam") or str(Path(sys.executable).with_name("dynslam"))
    if not Path(exe).exists():
        pytest.skip("the dynslam console script is not installed (pip install -e .)")
    proc = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for command in ("run", "demo", "eval", "config"):
        assert command in proc.stdout


def test_help_imports_no_heavy_modules():
    """``dynslam --help`` must stay instant: the heavy libraries load inside the commands only."""
    code = ("import sys\nfrom slam.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('gtsam', 'cv2', 'numpy', 'scipy', 'open3d', 'onnxruntime') if m in sys.modules]\n"
            "assert not heavy, heavy")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_config_prints_yaml_that_loads_back(capsys, tmp_path):
    code, out, _ = run_cli(capsys, "config")
    assert code == 0
    path = tmp_path / "printed.yaml"
    path.write_text(out)
    assert load_config(path).to_dict() == SlamConfig().to_dict()


def test_config_with_preset_shows_its_intrinsics(capsys):
    code, out, _ = run_cli(capsys, "config", "-c", "tum_fr1")
    assert code == 0
    data = yaml.safe_load(out)
    assert data["camera"]["fx"] == pytest.approx(517.306408)
    assert data["camera"]["name"] == "tum_fr1"
    assert "517.306408" in out


def test_config_set_override_is_applied(capsys):
    code, out, _ = run_cli(capsys, "config", "--set", "tracking.match_ratio=0.7", "--set", "orb.n_features=1500")
    assert code == 0
    data = yaml.safe_load(out)
    assert data["tracking"]["match_ratio"] == 0.7 and data["orb"]["n_features"] == 1500


def test_config_unknown_preset_exits_2(capsys):
    code, out, err = run_cli(capsys, "config", "-c", "no_such_preset")
    assert code == 2
    assert "no_such_preset" in err and "tum_fr1" in err


# --- eval --------------------------------------------------------------------------------------------

@pytest.fixture
def trajectories(tmp_path) -> tuple[Path, Path]:
    """Ground truth and an estimate (noisy, in another world frame) as TUM files."""
    rng = np.random.default_rng(0)
    t = 100.0 + np.arange(90) / 30.0
    gt = np.tile(np.eye(4), (len(t), 1, 1))
    gt[:, :3, :3] = Rotation.from_rotvec(np.c_[0.2 * np.sin(t), 0.3 * np.cos(0.5 * t), 0.1 * t]).as_matrix()
    gt[:, :3, 3] = np.c_[np.cos(t), np.sin(t), 0.1 * t]
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    offset[:3, 3] = [1.0, -2.0, 0.5]
    est = offset @ gt
    est[:, :3, 3] += rng.normal(scale=0.01, size=(len(t), 3))
    gt_path, est_path = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum(gt_path, t, gt)
    write_tum(est_path, t + 0.003, est)
    return gt_path, est_path


def test_eval_prints_the_ate_table(capsys, trajectories):
    gt, est = trajectories
    code, out, _ = run_cli(capsys, "eval", gt, est)
    assert code == 0
    assert "ATE [m]" in out and "RPE/frame" in out
    rmse = evaluate_files(gt, est).ate.rmse
    ate_row = next(line for line in out.splitlines() if line.startswith("ATE [m]"))
    assert ate_row.split()[2:4] == ["90", f"{rmse:.4f}"]


def test_eval_json_matches_slam_evaluation(capsys, trajectories):
    gt, est = trajectories
    code, out, _ = run_cli(capsys, "eval", gt, est, "--json")
    assert code == 0
    report = json.loads(out)
    expected = evaluate_files(gt, est)
    assert report["ate"]["rmse"] == pytest.approx(expected.ate.rmse, rel=1e-12)
    assert report["ate"]["n_matched"] == 90
    assert 0.005 < report["ate"]["rmse"] < 0.03  # the 1 cm noise, the world offset aligned away
    assert report["rpe_frame"]["n_pairs"] == 89


def test_eval_max_dt_option_is_used(capsys, trajectories):
    gt, est = trajectories  # estimate stamps are 3 ms late
    code, _, err = run_cli(capsys, "eval", gt, est, "--max-dt", "0.001")
    assert code == 2
    assert "no timestamps associated" in err


@pytest.mark.parametrize("which", ["groundtruth", "estimate"])
def test_eval_missing_file_exits_2_naming_it(capsys, trajectories, tmp_path, which):
    gt, est = trajectories
    missing = tmp_path / f"missing_{which}.txt"
    args = (missing, est) if which == "groundtruth" else (gt, missing)
    code, out, err = run_cli(capsys, "eval", *args)
    assert code == 2
    assert str(missing) in err
    assert "Traceback" not in err and out == ""


def test_eval_malformed_file_exits_2_naming_file_and_line(capsys, trajectories, tmp_path):
    gt, _ = trajectories
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n")
    code, _, err = run_cli(capsys, "eval", gt, bad)
    assert code == 2
    assert f"{bad}, line 3" in err


# --- run: argument and config errors -------------------------------------------------------------------

def test_run_missing_folder_exits_2(capsys, tmp_path):
    missing = tmp_path / "no_such_sequence"
    code, out, err = run_cli(capsys, "run", missing, "-o", tmp_path / "out")
    assert code == 2
    assert str(missing) in err and "does not exist" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_run_folder_without_lists_exits_2(capsys, tmp_path):
    code, _, err = run_cli(capsys, "run", tmp_path, "-o", tmp_path / "out")
    assert code == 2
    assert "rgb.txt" in err


def test_run_bad_override_exits_2_naming_the_key(capsys, tmp_path, synthetic_folder):
    code, _, err = run_cli(capsys, "run", synthetic_folder, "-o", tmp_path / "out", "--set", "tracking.match_ratio=2")
    assert code == 2
    assert "tracking.match_ratio" in err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_run_unknown_override_key_exits_2(capsys, tmp_path, synthetic_folder):
    code, _, err = run_cli(capsys, "run", synthetic_folder, "-o", tmp_path / "out", "--set", "tracking.no_such_key=1")
    assert code == 2
    assert "tracking.no_such_key" in err


def test_set_without_equals_exits_2(capsys):
    code, _, err = run_cli(capsys, "config", "--set", "tracking.match_ratio")
    assert code == 2
    assert "key=value" in err


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
    assert 0 < sigma["median"] <= sigma["p95"] <= sigma["max"] <= 25.0   # tracking.max_pose_sigma_m
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


# --- run on a synthetic sequence written to disk -----------------------------------------------------

@pytest.fixture(scope="module")
def synthetic_folder(tmp_path_factory) -> Path:
    """SyntheticSequence(n_frames=30) in TUM layout with its camera.yaml. The folder name mentions
    freiburg1 on purpose: the camera.yaml must win over the preset guessed from the name."""
    seq = SyntheticSequence(n_frames=30, fx=SYNTH_FX, fy=SYNTH_FX, cx=321.0, cy=238.0)
    return write_tum_layout(seq, tmp_path_factory.mktemp("seq") / "rgbd_dataset_freiburg1_synthetic")


@pytest.fixture(scope="module")
def synthetic_run(synthetic_folder, tmp_path_factory) -> tuple[int, Path]:
    out_dir = tmp_path_factory.mktemp("run") / "results"
    saved_format = warnings.formatwarning
    try:
        code = main(["run", str(synthetic_folder), "-o", str(out_dir), "-q", "-c", "static"])
    finally:
        warnings.formatwarning = saved_format
    return code, out_dir


def test_run_on_synthetic_folder_uses_camera_yaml(synthetic_run):
    code, out_dir = synthetic_run
    assert code == 0
    resolved = yaml.safe_load((out_dir / "config.yaml").read_text())
    camera = resolved["camera"]
    assert camera["fx"] == SYNTH_FX and camera["fy"] == SYNTH_FX
    assert camera["cx"] == 321.0 and camera["cy"] == 238.0
    assert camera["width"] == 640 and camera["height"] == 480
    assert camera["distortion"] == [0.0] * 5, "no freiburg1 distortion: camera.yaml takes precedence"


def test_run_on_synthetic_folder_tracks_every_frame(synthetic_run, synthetic_folder):
    _, out_dir = synthetic_run
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["frames"] == summary["tracked"] == 30
    assert summary["dataset"] == synthetic_folder.name
    report = evaluate_files(synthetic_folder / "groundtruth.txt", out_dir / "trajectory.txt")
    assert report.ate.n_matched == 30
    assert report.ate.rmse < 0.0042 * 1.15   # measured 4.2 mm; the regression margin of every accuracy gate
    assert not (out_dir / "groundtruth.txt").exists(), "real folders keep their ground truth where it is"


def test_run_max_frames(capsys, synthetic_folder, tmp_path):
    code, out, _ = run_cli(capsys, "run", synthetic_folder, "-o", tmp_path / "out", "-q", "-c", "static", "--max-frames", "12")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["frames"] == 12 and summary["tracked"] == 12
    assert len(data_lines(tmp_path / "out" / "trajectory.txt")) == 12
    assert "12 frames" in out


def test_run_realtime_replays_at_the_recorded_rate_and_reports_dropped_frames(capsys, synthetic_folder, tmp_path):
    """--realtime: the 30 frames (1 s at 30 fps) are offered at their recorded times, so the run lasts at
    least the recording; whatever this machine drops is counted, and the frames processed are all written."""
    code, out, _ = run_cli(capsys, "run", synthetic_folder, "-o", tmp_path / "out", "-q", "-c", "static",
                           "--realtime", "--set", "output.report=false")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["realtime"] is True and isinstance(summary["dropped_frames"], int)
    assert summary["frames"] + summary["dropped_frames"] == 30
    assert summary["wall_time_s"] >= 29 / 30 * 0.95   # the last frame is due 29 intervals after the first
    assert yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())["runtime"]["realtime"] is True
    assert len(data_lines(tmp_path / "out" / "trajectory.txt")) == summary["frames"]
    assert ("dropped" in out) if summary["dropped_frames"] else ("realtime: no frame dropped" in out)


def test_run_help_explains_realtime(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--realtime" in text and "dropped_frames" in text and "not deterministic" in text


def test_recordings_run_in_dataset_mode_by_default(synthetic_run):
    _, out_dir = synthetic_run
    assert yaml.safe_load((out_dir / "config.yaml").read_text())["runtime"]["realtime"] is False
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["realtime"] is False and summary["dropped_frames"] is None


def test_dynamic_run_writes_per_frame_flag_counts(tmp_path):
    """A run with a detector-free dynamic method writes dynamic.csv with one row per frame."""
    from slam.cli import main

    out = tmp_path / "dyn"
    assert main(["demo", "--no-compare", "--movers", "none", "--frames", "12", "-o", str(out), "-q", "--set", "dynamic.methods=[cpr]",
                 "--set", "dynamic.fusion=single"]) == 0
    lines = (out / "dynamic.csv").read_text().strip().splitlines()
    # The demo's detector (the scene's boxes) serves the person-box prior: people standing still are counted.
    assert lines[0] == "timestamp,cpr,fused,standing_people"
    assert len(lines) == 13 and all(line.endswith(",0") for line in lines[1:])   # no people in this room
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dynamic_methods"] == ["cpr"] and "cpr" in summary["dynamic_flagged"]
    assert "dynamic.cpr" in summary["timing_ms"]


def test_missing_detector_model_is_a_clear_error(tmp_path, capsys):
    from slam.cli import main

    folder = write_tum_layout(SyntheticSequence(n_frames=3), tmp_path / "seq")
    missing = tmp_path / "nowhere" / "yolox.onnx"
    code = main(["run", str(folder), "-o", str(tmp_path / "out"), "-q", "-c", "dynamic_box_depth",
                 "--set", f"dynamic.detector.path={missing}"])
    assert code == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "error" in err


def test_detector_free_method_needs_no_model(tmp_path, monkeypatch):
    from slam.cli import main

    monkeypatch.setenv("DYNSLAM_DETECTOR_MODEL", str(tmp_path / "absent.onnx"))
    assert main(["demo", "--no-compare", "--movers", "none", "--frames", "4", "-o", str(tmp_path / "out"), "-q", "-c", "dynamic_cpr"]) == 0


def test_blackout_option_marks_blank_frames_lost(tmp_path):
    from slam.cli import main
    from slam.datasets import SyntheticSequence, write_tum_layout

    folder = write_tum_layout(SyntheticSequence(n_frames=20), tmp_path / "seq")
    out = tmp_path / "out"
    assert main(["run", str(folder), "-o", str(out), "-q", "-c", "static", "--blackout", "8:4"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["lost_frames"] == [8, 9, 10, 11] and summary["tracked"] == 16
    lines = (out / "trajectory.txt").read_text().splitlines()
    assert sum(line.startswith("# ") and line.endswith(" LOST") for line in lines[1:]) == 4


def test_blackout_option_rejects_bad_specs(tmp_path, capsys):
    from slam.cli import main
    from slam.datasets import SyntheticSequence, write_tum_layout

    folder = write_tum_layout(SyntheticSequence(n_frames=3), tmp_path / "seq")
    assert main(["run", str(folder), "-o", str(tmp_path / "o"), "-q", "--blackout", "eight"]) == 2
    assert "--blackout expects START:COUNT" in capsys.readouterr().err


def test_vocabulary_command_builds_a_loadable_vocabulary(tmp_path):
    import cv2

    from backend.place_recognition import Vocabulary
    from slam.cli import main
    from slam.datasets import SyntheticSequence

    images = tmp_path / "images"
    images.mkdir()
    for frame in SyntheticSequence(n_frames=6):
        cv2.imwrite(str(images / f"{frame.index:03d}.png"), frame.rgb)
    out = tmp_path / "voc.npz"
    assert main(["vocabulary", str(images), "-o", str(out), "--step", "1", "--levels", "2"]) == 0
    vocabulary = Vocabulary.load(out)
    assert 10 < vocabulary.n_words <= 100


def test_vocabulary_command_without_images_is_a_clear_error(tmp_path, capsys):
    from slam.cli import main

    assert main(["vocabulary", str(tmp_path), "-o", str(tmp_path / "v.npz")]) == 2
    assert "no PNG/JPEG images" in capsys.readouterr().err


def test_run_writes_the_keyframe_graph(tmp_path):
    import gtsam

    from slam.cli import main

    out = tmp_path / "out"
    assert main(["demo", "--no-compare", "--movers", "none", "--frames", "15", "-o", str(out), "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    graph, values = gtsam.readG2o(str(out / "graph.g2o"), True)
    assert values.size() == summary["keyframes"] and graph.size() >= summary["keyframes"] - 1
    data = json.loads((out / "graph.json").read_text())
    assert len(data["keyframes"]) == summary["keyframes"]


# --- conventions -----------------------------------------------------------------------------------

def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.startswith("dynslam ")


@pytest.mark.parametrize("argv", [["-v", "config"], ["config", "-v"], ["config", "--verbose"]])
def test_verbose_before_or_after_the_subcommand(argv, capsys):
    from slam.cli import build_parser

    assert build_parser().parse_args(argv).verbose is True
    assert build_parser().parse_args(["config"]).verbose is False


def test_quiet_after_the_subcommand_for_every_command():
    from slam.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["run", "SEQ", "-q"]).quiet is True
    assert parser.parse_args(["-q", "run", "SEQ"]).quiet is True
    assert parser.parse_args(["eval", "a", "b", "--quiet"]).quiet is True
    assert parser.parse_args(["run", "SEQ"]).quiet is False


def test_every_option_of_every_command_has_help():
    import argparse

    from slam.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}" for name, sub in commands.items()
               for a in sub._actions if not a.help and not isinstance(a, argparse._HelpAction)]
    assert not missing, missing


def test_demo_movers_list_every_generator_choice():
    from slam.cli import DEMO_MOVERS
    from slam.datasets.synthetic_movers import MOVER_PRESETS
    from slam.datasets.synthetic_scenes import HARD_SCENES

    assert DEMO_MOVERS == tuple(MOVER_PRESETS) + HARD_SCENES


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
