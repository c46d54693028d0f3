"""KITTI / EuRoC trajectory files (slam.run.trajectory_formats): round trips, naming, the
``export-trajectory`` command, and that evo reads every exported file to the TUM file's ATE."""
from __future__ import annotations

import copy
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.cli import TRAJECTORY_FORMAT_NAMES, main
from slam.core.config import TRAJECTORY_FORMATS, ConfigError, SlamConfig, apply_overrides
from slam.run.evaluation import evaluate, evaluate_files
from slam.run.trajectory import TrajectoryFormatError, read_tum, tum_rows_from_poses, write_tum
from slam.run.trajectory_formats import (EUROC_HEADER, export_formats, export_trajectory, kitti_times_path,
                                     read_euroc, read_kitti, seconds_to_nanoseconds, trajectory_kind,
                                     trajectory_path, write_trajectory)

T0 = 1305031102.175304   # a TUM-style Unix time: nanoseconds must stay exact there


@pytest.fixture(autouse=True)
def _restore_warning_format(monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)


def smooth_path(n: int, seed: int = 0) -> np.ndarray:
    """A camera path that moves and turns (Umeyama needs a non-degenerate one)."""
    s = np.linspace(0.0, 2.0 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("xyz", np.stack([0.1 * np.sin(s), s / 2, 0.2 * np.cos(s)], 1)).as_matrix()
    poses[:, :3, 3] = np.stack([np.cos(s), np.sin(s), 0.3 * np.sin(2 * s)], axis=1) + seed
    return poses


def noisy(poses: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = poses.copy()
    out[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (len(poses), 3))).as_matrix() @ poses[:, :3, :3]
    out[:, :3, 3] += rng.normal(0.0, 0.02, (len(poses), 3))
    return out


@pytest.fixture
def results_dir(tmp_path: Path) -> Path:
    """A results folder as a run leaves it: ground truth, a per-frame TUM file with LOST frames,
    the online file and keyframes."""
    n = 60
    stamps = T0 + np.arange(n) / 30.0
    gt = smooth_path(n)
    write_tum(tmp_path / "groundtruth.txt", stamps, gt)
    estimate = noisy(gt, seed=1)
    lost = {7, 8, 30}
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for i, (t, row) in enumerate(zip(stamps, tum_rows_from_poses(estimate))):
        lines.append(f"# {t:.6f} LOST" if i in lost else f"{t:.6f} " + " ".join(f"{v:.9f}" for v in row))
    (tmp_path / "trajectory.txt").write_text("\n".join(lines) + "\n")
    write_tum(tmp_path / "trajectory_online.txt", stamps, noisy(gt, seed=2))
    write_tum(tmp_path / "keyframes.txt", stamps[::6], estimate[::6])
    return tmp_path


# --- naming ------------------------------------------------------------------------------------------

def test_file_names_of_every_kind_and_format(tmp_path):
    names = {(fmt, kind): trajectory_path(tmp_path, fmt, kind).name
             for fmt in ("tum", "kitti", "euroc") for kind in ("final", "online", "keyframes")}
    assert names == {
        ("tum", "final"): "trajectory.txt", ("tum", "online"): "trajectory_online.txt",
        ("tum", "keyframes"): "keyframes.txt",
        ("kitti", "final"): "trajectory.kitti.txt", ("kitti", "online"): "trajectory_online.kitti.txt",
        ("kitti", "keyframes"): "keyframes.kitti.txt",
        ("euroc", "final"): "trajectory.euroc.csv", ("euroc", "online"): "trajectory_online.euroc.csv",
        ("euroc", "keyframes"): "keyframes.euroc.csv"}
    assert kitti_times_path(tmp_path / "trajectory.kitti.txt").name == "trajectory.kitti.times.txt"
    assert trajectory_kind() == "final" and trajectory_kind(online=True) == "online"
    assert trajectory_kind(keyframes=True) == "keyframes"
    with pytest.raises(ValueError, match="exclude each other"):
        trajectory_kind(online=True, keyframes=True)


def test_cli_format_names_match_the_config():
    assert tuple(TRAJECTORY_FORMAT_NAMES) == tuple(TRAJECTORY_FORMATS)


def test_unknown_format_in_the_config_is_a_clear_error():
    config = apply_overrides(SlamConfig(), {"output.trajectory_formats": ["tum", "kitti", "euroc"]})
    assert config.output.trajectory_formats == ["tum", "kitti", "euroc"]
    with pytest.raises(ConfigError, match=r"'output.trajectory_formats' item \[0\] must be one of 'tum', 'kitti' or 'euroc', got 'kiti'"):
        apply_overrides(SlamConfig(), {"output.trajectory_formats": ["kiti"]})


# --- files -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])
def test_round_trip_sorts_and_keeps_poses(tmp_path, fmt):
    n = 25
    stamps = T0 + np.random.default_rng(3).permutation(n) / 30.0
    poses = noisy(smooth_path(n), seed=4)
    path = tmp_path / {"tum": "t.txt", "kitti": "t.kitti.txt", "euroc": "t.euroc.csv"}[fmt]
    written = write_trajectory(path, fmt, stamps, poses)
    assert len(written) == (2 if fmt == "kitti" else 1)
    read = {"tum": read_tum, "kitti": read_kitti, "euroc": read_euroc}[fmt]
    t, P = read(path)
    order = np.argsort(stamps)
    np.testing.assert_allclose(t, stamps[order], rtol=0, atol=1e-6)
    np.testing.assert_allclose(P, poses[order], rtol=0, atol=1e-8)


def test_euroc_layout_nanoseconds_and_scalar_first_quaternion(tmp_path):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    pose[:3, 3] = [1.0, -2.0, 0.5]
    write_trajectory(tmp_path / "a.euroc.csv", "euroc", np.array([T0]), pose[None])
    header, line = (tmp_path / "a.euroc.csv").read_text().splitlines()
    assert header == EUROC_HEADER
    fields = line.split(",")
    assert fields[0] == "1305031102175304000"       # integer ns, exact at Unix-epoch magnitudes
    np.testing.assert_allclose([float(f) for f in fields[1:]],
                               [1.0, -2.0, 0.5, np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-9)
    assert seconds_to_nanoseconds(np.array([0.5, 12.000001])) == [500_000_000, 12_000_001_000]


def test_kitti_layout_is_the_3x4_matrix_and_a_times_file(tmp_path):
    poses = smooth_path(3)
    write_trajectory(tmp_path / "k.kitti.txt", "kitti", T0 + np.arange(3), poses)
    rows = np.loadtxt(tmp_path / "k.kitti.txt")
    np.testing.assert_allclose(rows.reshape(3, 3, 4), poses[:, :3, :4], atol=1e-12)
    assert (tmp_path / "k.kitti.times.txt").read_text().splitlines()[0] == f"{T0:.6f}"


def test_readers_name_file_and_line_of_a_bad_row(tmp_path):
    bad = tmp_path / "bad.kitti.txt"
    bad.write_text(" ".join(["1"] * 12) + "\n" + " ".join(["1"] * 11) + "\n")
    (tmp_path / "bad.kitti.times.txt").write_text("0\n1\n")
    with pytest.raises(TrajectoryFormatError, match=r"bad.kitti.txt, line 2: expected 12 values"):
        read_kitti(bad)
    csv = tmp_path / "bad.euroc.csv"
    csv.write_text(EUROC_HEADER + "\n1000,0,0,0,0,0,0,0\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 2: zero-norm quaternion"):
        read_euroc(csv)
    good = tmp_path / "n.kitti.txt"
    good.write_text(" ".join(["1"] * 12) + "\n")
    (tmp_path / "n.kitti.times.txt").write_text("0\n1\n")
    with pytest.raises(ValueError, match="1 poses but .* 2 timestamps"):
        read_kitti(good)


# --- results folders and evo ---------------------------------------------------------------------------

def evo_trajectory(path: Path, fmt: str):
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    if fmt == "tum":
        return file_interface.read_tum_trajectory_file(str(path))
    if fmt == "euroc":
        return file_interface.read_euroc_csv_trajectory(str(path))
    poses = file_interface.read_kitti_poses_file(str(path))     # no stamps: pair by order with times.txt
    stamps = np.loadtxt(kitti_times_path(path), ndmin=1)
    assert len(stamps) == poses.num_poses
    return PoseTrajectory3D(poses_se3=poses.poses_se3, timestamps=stamps)


def evo_ate_rmse(gt_path: Path, est_path: Path, fmt: str) -> float:
    from evo.core import metrics, sync
    from evo.main_ape import ape
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    ref, est = sync.associate_trajectories(ref, evo_trajectory(est_path, fmt), max_diff=0.02)
    result = ape(copy.deepcopy(ref), copy.deepcopy(est), metrics.PoseRelation.translation_part, align=True)
    return float(result.stats["rmse"])


@pytest.mark.parametrize("kind", ["final", "online", "keyframes"])
def test_every_exported_format_gives_the_tum_files_ate_in_evo(results_dir, kind):
    pytest.importorskip("evo")
    gt = results_dir / "groundtruth.txt"
    tum = trajectory_path(results_dir, "tum", kind)
    reference = evaluate_files(gt, tum).ate.rmse
    assert evo_ate_rmse(gt, tum, "tum") == pytest.approx(reference, abs=1e-9)
    for fmt, reader in (("kitti", read_kitti), ("euroc", read_euroc)):
        (path, *_) = export_trajectory(results_dir, fmt, kind)
        assert path == trajectory_path(results_dir, fmt, kind)
        assert evo_ate_rmse(gt, path, fmt) == pytest.approx(reference, abs=1e-9), (fmt, kind)
        gt_t, gt_poses = read_tum(gt)
        est_t, est_poses = reader(path)
        assert evaluate(gt_t, gt_poses, est_t, est_poses).ate.rmse == pytest.approx(reference, abs=1e-9)


def test_lost_frames_are_left_out_of_kitti_and_euroc(results_dir):
    export_formats(results_dir, ["kitti", "euroc"])
    tracked = len(read_tum(results_dir / "trajectory.txt")[0])
    assert tracked == 57
    assert len((results_dir / "trajectory.kitti.txt").read_text().splitlines()) == tracked
    assert len((results_dir / "trajectory.kitti.times.txt").read_text().splitlines()) == tracked
    assert len((results_dir / "trajectory.euroc.csv").read_text().splitlines()) == tracked + 1


def test_export_formats_writes_every_kind_and_skips_tum(results_dir):
    written = {p.name for p in export_formats(results_dir, ["tum", "euroc", "kitti", "euroc"])}
    assert written == {"trajectory.euroc.csv", "trajectory_online.euroc.csv", "keyframes.euroc.csv",
                       "trajectory.kitti.txt", "trajectory.kitti.times.txt", "trajectory_online.kitti.txt",
                       "trajectory_online.kitti.times.txt", "keyframes.kitti.txt", "keyframes.kitti.times.txt"}


# --- the command ---------------------------------------------------------------------------------------

def test_export_trajectory_command(results_dir, capsys):
    assert main(["export-trajectory", str(results_dir), "--format", "euroc", "--online"]) == 0
    assert capsys.readouterr().out.strip() == str(results_dir / "trajectory_online.euroc.csv")
    assert main(["export-trajectory", str(results_dir), "-f", "kitti", "--keyframes"]) == 0
    out = capsys.readouterr().out.split()
    assert out == [str(results_dir / "keyframes.kitti.txt"), str(results_dir / "keyframes.kitti.times.txt")]
    assert main(["export-trajectory", str(results_dir), "-f", "tum"]) == 0
    assert capsys.readouterr().out.strip() == str(results_dir / "trajectory.txt")


def test_export_trajectory_command_errors(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert main(["export-trajectory", str(missing), "-f", "kitti"]) == 2
    assert str(missing) in capsys.readouterr().err
    assert main(["export-trajectory", str(tmp_path), "-f", "kitti"]) == 2
    assert "trajectory.txt not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["export-trajectory", str(tmp_path), "-f", "kitti", "--online", "--keyframes"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        main(["export-trajectory", str(tmp_path), "-f", "csv"])
    capsys.readouterr()
