"""Tests for slam.run.trajectory: TUM I/O, atomic and streaming writers, quaternions."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.run.trajectory import (
    TrajectoryFormatError,
    TumStreamWriter,
    matrix_to_quaternion,
    quaternion_to_matrix,
    read_tum,
    write_tum,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """Random T_wc poses with metre-scale translations."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-5.0, 5.0, (n, 3))
    return poses


def test_write_read_round_trip_sorts_by_time(tmp_path: Path) -> None:
    n = 50
    t = 1305031102.0 + np.round(np.random.default_rng(1).permutation(n) * 0.033, 6)
    poses = random_poses(n)
    path = tmp_path / "traj.txt"
    write_tum(path, t, poses)
    t_read, poses_read = read_tum(path)
    order = np.argsort(t)
    np.testing.assert_allclose(t_read, t[order], rtol=0, atol=1e-6)
    np.testing.assert_allclose(poses_read, poses[order], rtol=0, atol=1e-8)
    assert np.all(np.diff(t_read) > 0)


def test_read_skips_comments_blank_lines_and_sorts(tmp_path: Path) -> None:
    path = tmp_path / "gt.txt"
    path.write_text("# ground truth\n\n2.0 1 2 3 0 0 0 1\n   \n# 1.5 LOST\n"
                    "1.0 4 5 6 0 0 0.7071068 0.7071068\n")
    t, poses = read_tum(path)
    np.testing.assert_array_equal(t, [1.0, 2.0])
    np.testing.assert_allclose(poses[0, :3, 3], [4, 5, 6])
    np.testing.assert_allclose(poses[0, :3, :3], Rotation.from_euler("z", 90, degrees=True).as_matrix(),
                               atol=1e-7)
    expected = np.eye(4)
    expected[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(poses[1], expected)


def test_read_empty_file_gives_empty_arrays(tmp_path: Path) -> None:
    path = tmp_path / "empty.txt"
    path.write_text("# nothing tracked\n")
    t, poses = read_tum(path)
    assert t.shape == (0,) and poses.shape == (0, 4, 4)


@pytest.mark.parametrize("bad_line, reason", [
    ("3.0 1 2 3 0 0 1", "expected 8 values"),
    ("3.0 1 2 x 0 0 0 1", "not a number"),
    ("3.0 1 2 nan 0 0 0 1", "non-finite"),
    ("3.0 1 2 3 0 0 0 0", "zero-norm quaternion"),
])
def test_malformed_line_names_file_and_line(tmp_path: Path, bad_line: str, reason: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(f"# header\n1.0 0 0 0 0 0 0 1\n\n{bad_line}\n")
    with pytest.raises(TrajectoryFormatError) as info:
        read_tum(path)
    assert info.value.line_number == 4
    assert str(path) in str(info.value) and "line 4" in str(info.value)
    assert reason in str(info.value)
    assert isinstance(info.value, ValueError)


def test_read_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_tum(tmp_path / "missing.txt")


def test_atomic_write_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "est.txt"
    write_tum(path, np.arange(3.0), random_poses(3))
    write_tum(path, np.arange(5.0), random_poses(5, seed=2))  # overwrite in place
    assert sorted(os.listdir(tmp_path)) == ["est.txt"]
    assert len(read_tum(path)[0]) == 5


def test_failed_write_keeps_old_file_and_cleans_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "est.txt"
    write_tum(path, np.arange(3.0), random_poses(3))
    before = path.read_text()

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        write_tum(path, np.arange(4.0), random_poses(4))
    assert path.read_text() == before
    assert os.listdir(tmp_path) == ["est.txt"]


def test_write_rejects_bad_shapes_and_nan(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="shape"):
        write_tum(tmp_path / "a.txt", np.arange(3.0), random_poses(2))
    poses = random_poses(2)
    poses[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        write_tum(tmp_path / "a.txt", np.arange(2.0), poses)
    assert os.listdir(tmp_path) == []


def test_stream_writer_flushes_each_line_before_close(tmp_path: Path) -> None:
    path = tmp_path / "live.txt"
    poses = random_poses(3)
    with TumStreamWriter(path) as writer:
        writer.append(0.0, poses[0])
        writer.append(0.033, poses[1])
        t, read = read_tum(path)  # the writer is still open
        np.testing.assert_allclose(t, [0.0, 0.033])
        np.testing.assert_allclose(read, poses[:2], atol=1e-8)
        writer.mark_lost(0.066)
        writer.append(0.1, poses[2])
        assert "# 0.066000 LOST" in path.read_text().splitlines()
    assert writer.closed
    t, read = read_tum(path)
    np.testing.assert_allclose(t, [0.0, 0.033, 0.1])
    with pytest.raises(ValueError, match="closed"):
        writer.append(0.2, poses[0])
    writer.close()  # idempotent


def test_quaternion_round_trip_random_rotations() -> None:
    R = Rotation.random(500, random_state=7).as_matrix()
    q = matrix_to_quaternion(R)
    assert q.shape == (500, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(q[:, 3] >= 0.0)
    np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-12)


def test_quaternion_round_trip_near_180_degrees() -> None:
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.pi - np.concatenate([[0.0, 1e-12, 1e-9, 1e-6], rng.uniform(0, 1e-3, 196)])
    R = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    q = matrix_to_quaternion(R)
    np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-12)
    # The axis is recovered even at exactly 180 degrees (up to the sign of q).
    np.testing.assert_allclose(np.abs(q[0, :3]), np.abs(axes[0]), atol=1e-12)


def test_quaternion_single_and_known_values() -> None:
    Rz = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(matrix_to_quaternion(Rz), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)
    np.testing.assert_allclose(matrix_to_quaternion(np.eye(4)), [0, 0, 0, 1])
    # Non-unit quaternions (TUM files keep 4 decimals) are normalised.
    np.testing.assert_allclose(quaternion_to_matrix([0, 0, 2.0, 2.0]), Rz, atol=1e-15)
    with pytest.raises(ValueError, match="zero-norm"):
        quaternion_to_matrix(np.zeros(4))
    with pytest.raises(ValueError, match="shape"):
        matrix_to_quaternion(np.eye(2))
