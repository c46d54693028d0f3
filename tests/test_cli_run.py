"""CLI smoke tests of ``dynslam run`` through ``slam.cli.main([...])`` in-process: argument and config
errors, a run on a generated sequence written to disk, and what a run writes and needs (the detector
model, --blackout, the keyframe graph)."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import yaml

from _cli_helpers import data_lines, run_cli
from slam.cli import main
from slam.datasets import SyntheticSequence, write_tum_layout
from slam.run.evaluation import evaluate_files

pytestmark = pytest.mark.usefixtures("restore_warning_format")

SYNTH_FX = 550.0  # differs from both the config default (525) and the freiburg1 preset (517.3)


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
    least the recording; whatever this machine drops is counted, and every frame processed is written or
    counted LOST (on a busy machine most frames are dropped, and the gap to the next one processed can be
    more motion than tracking follows: a CI run processed 3 of the 30 and lost the third)."""
    code, out, _ = run_cli(capsys, "run", synthetic_folder, "-o", tmp_path / "out", "-q", "-c", "static",
                           "--realtime", "--set", "output.report=false")
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["realtime"] is True and isinstance(summary["dropped_frames"], int)
    assert summary["frames"] + summary["dropped_frames"] == 30
    assert summary["wall_time_s"] >= 29 / 30 * 0.95   # the last frame is due 29 intervals after the first
    assert yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())["runtime"]["realtime"] is True
    assert summary["tracked"] + summary["lost"] == summary["frames"] and summary["tracked"] >= 1
    assert len(data_lines(tmp_path / "out" / "trajectory.txt")) == summary["tracked"]
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
    # The demo's detector (the scene's boxes) serves the person-box prior: people standing still are counted;
    # the near-occluder rule (on in the default) counts the features only it flagged.
    assert lines[0] == "timestamp,cpr,near_occluders,fused,standing_people"
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
    from slam.datasets import DatasetWarning, SyntheticSequence, write_tum_layout

    folder = write_tum_layout(SyntheticSequence(n_frames=20), tmp_path / "seq")
    out = tmp_path / "out"
    with pytest.warns(DatasetWarning, match=r"frame 8 .* has no valid depth; tracking without depth"):
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
