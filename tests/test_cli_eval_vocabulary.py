"""CLI smoke tests of the commands that read files other than a sequence, through
``slam.cli.main([...])`` in-process: ``dynslam eval`` (two TUM trajectories) and ``dynslam vocabulary``
(a folder of images)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from _cli_helpers import run_cli
from slam.run.evaluation import evaluate_files
from slam.run.trajectory import write_tum

pytestmark = pytest.mark.usefixtures("restore_warning_format")


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


# --- vocabulary ------------------------------------------------------------------------------------

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
