"""Tests for slam.run.evaluation: analytic cases, error messages, and agreement with evo."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.run.evaluation import (
    EvaluationError,
    associate,
    ate,
    evaluate_files,
    format_report,
    rpe,
    rpe_seconds,
    umeyama_alignment,
)
from slam.run.trajectory import TrajectoryFormatError, read_tum, write_tum

from conftest import XYZ, real_sequence


# ------------------------------------------------------------------ helpers
def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def smooth_trajectory(t: np.ndarray, seed: int) -> np.ndarray:
    """A wandering hand-held-like T_wc trajectory sampled at times t."""
    rng = np.random.default_rng(seed)
    freq, phase = rng.uniform(0.2, 1.0, (2, 6)), rng.uniform(0, 2 * np.pi, (2, 6))
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    rotvec = 0.6 * np.sin(freq[0] * t[:, None] * 2 + phase[0])[:, :3]
    poses[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    poses[:, :3, 3] = 1.5 * np.sin(freq[1] * t[:, None] + phase[1])[:, :3]
    return poses


def noisy_estimate(gt_t: np.ndarray, gt: np.ndarray, seed: int, keep: float = 0.3,
                   jitter: float = 0.006) -> tuple[np.ndarray, np.ndarray]:
    """Subsample, jitter the stamps, move to another world frame and add pose noise."""
    rng = np.random.default_rng(seed)
    sel = np.sort(rng.choice(len(gt_t), int(keep * len(gt_t)), replace=False))
    est_t = np.sort(gt_t[sel] + rng.normal(0.0, jitter, len(sel)))
    T = se3(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 2, 3))
    est = T @ gt[sel]
    est[:, :3, 3] += rng.normal(0.0, 0.03, (len(sel), 3))
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.02, (len(sel), 3))).as_matrix()
    return est_t, est


# ------------------------------------------------------------ association
def test_associate_picks_nearest_within_max_dt() -> None:
    ref = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    est = np.array([0.011, 0.19, 0.5])
    i_ref, i_est = associate(ref, est, max_dt=0.02)
    np.testing.assert_array_equal(i_ref, [0, 2])
    np.testing.assert_array_equal(i_est, [0, 1])


def test_associate_walks_the_shorter_side_and_ties_go_earlier() -> None:
    # Equal counts: evo walks the estimate; the tie at 0.5 goes to the earlier ref stamp.
    i_ref, i_est = associate(np.array([0.0, 1.0]), np.array([0.5, 3.0]), max_dt=0.5)
    np.testing.assert_array_equal(i_ref, [0])
    np.testing.assert_array_equal(i_est, [0])
    # A longer estimate is matched from the reference side, so matches may repeat.
    i_ref, i_est = associate(np.array([1.0, 1.001]), np.array([0.0, 1.0005, 5.0]), max_dt=0.01)
    np.testing.assert_array_equal(i_ref, [0, 1])
    np.testing.assert_array_equal(i_est, [1, 1])


def test_associate_handles_empty_and_unsorted_inputs() -> None:
    empty_ref, empty_est = associate(np.zeros(0), np.arange(3.0))
    assert len(empty_ref) == 0 and len(empty_est) == 0
    i_ref, i_est = associate(np.array([0.3, 0.0, 0.2, 0.1]), np.array([0.101, 0.299]), max_dt=0.02)
    np.testing.assert_array_equal(i_ref, [3, 0])
    np.testing.assert_array_equal(i_est, [0, 1])


# --------------------------------------------------------------- umeyama
def test_umeyama_recovers_known_se3_and_sim3() -> None:
    rng = np.random.default_rng(11)
    src = rng.normal(size=(3, 40))
    R = Rotation.random(random_state=11).as_matrix()
    t = rng.normal(size=3)
    R_est, t_est, s = umeyama_alignment(src, R @ src + t[:, None])
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    assert s == 1.0
    R_est, t_est, s = umeyama_alignment(src, 2.5 * R @ src + t[:, None], with_scale=True)
    np.testing.assert_allclose([s, *t_est], [2.5, *t], atol=1e-12)
    np.testing.assert_allclose(R_est, R, atol=1e-12)


def test_umeyama_rejects_degenerate_points() -> None:
    with pytest.raises(EvaluationError, match="degenerate"):
        umeyama_alignment(np.ones((3, 10)), np.zeros((3, 10)))


# ---------------------------------------------------------- analytic ATE/RPE
def test_ate_exact_for_rigid_transform_plus_paired_camera_jitter() -> None:
    """Frames come in pairs sharing one pose; the estimate puts them 1 cm to either side
    along the camera's x axis. The offsets sum to zero and are uncorrelated with the
    positions, so Umeyama recovers the rigid transform exactly and every error is 1 cm."""
    k = 60
    gt_t = np.arange(2 * k) * 0.05
    gt = np.repeat(smooth_trajectory(gt_t[::2], seed=4), 2, axis=0)
    T = se3(Rotation.random(random_state=5).as_matrix(), [3.0, -1.0, 0.5])
    side = np.tile([1.0, -1.0], k)
    offset = se3(np.eye(3), [0.0, 0.0, 0.0])[None].repeat(2 * k, axis=0)
    offset[:, 0, 3] = 0.01 * side
    est = T @ gt @ offset
    res = ate(gt_t, gt, gt_t, est)
    assert res.n_matched == 2 * k
    np.testing.assert_allclose(res.errors, 0.01, atol=1e-12)
    assert res.rmse == pytest.approx(0.01, abs=1e-12) and res.std == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(res.alignment, np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(res.aligned_poses, gt @ offset, atol=1e-12)


def test_ate_without_alignment_sees_constant_offset() -> None:
    gt_t = np.arange(30) * 0.1
    gt = smooth_trajectory(gt_t, seed=1)
    est = gt.copy()
    est[:, :3, 3] += [0.03, 0.04, 0.0]
    assert ate(gt_t, gt, gt_t, est, align=False).rmse == pytest.approx(0.05, abs=1e-12)
    assert ate(gt_t, gt, gt_t, est, align=True).rmse == pytest.approx(0.0, abs=1e-12)


def test_rpe_per_frame_is_zero_for_rigidly_moved_estimate() -> None:
    gt_t = np.arange(50) * 0.033
    gt = smooth_trajectory(gt_t, seed=2)
    est = se3(Rotation.random(random_state=3).as_matrix(), [1.0, 2.0, 3.0]) @ gt
    res = rpe(gt_t, gt, gt_t + 0.004, est, mode="frame")
    assert res.n_pairs == 49 and res.delta_unit == "frames" and res.translation_unit == "m"
    assert res.translation.max < 1e-12 and res.rotation.max < 1e-6


def test_rpe_seconds_measures_constant_drift_per_interval() -> None:
    """Pure translation with a drift velocity v: each ~1 s pair errs by |v| * dt."""
    gt_t = 100.0 + np.arange(600) * 0.01
    gt = np.tile(np.eye(4), (600, 1, 1))
    gt[:, :3, 3] = np.c_[np.sin(gt_t), np.cos(gt_t), 0.1 * gt_t]
    est_t = gt_t[::3]
    v = np.array([0.02, -0.01, 0.005])
    est = gt[::3].copy()
    est[:, :3, 3] += (est_t - est_t[0])[:, None] * v
    res = rpe(gt_t, gt, est_t, est, mode="time")
    dt = res.pair_timestamps[:, 1] - res.pair_timestamps[:, 0]
    np.testing.assert_allclose(dt, 0.99, atol=1e-9)  # closest stamp to t + 1 s on a 30 ms grid
    np.testing.assert_allclose(res.translation_errors, np.linalg.norm(v) * dt, atol=1e-12)
    assert res.rotation.max < 1e-9
    assert (res.translation_unit, res.rotation_unit, res.delta_unit) == ("m/s", "deg/s", "s")
    assert res.n_pairs == len(est_t) - 34  # TUM drops pairs that run past / end on the last pose


def test_rpe_seconds_measures_rotation_drift() -> None:
    t = np.arange(400) * 0.025
    gt = np.tile(np.eye(4), (400, 1, 1))
    gt[:, :3, :3] = Rotation.from_euler("z", 20 * np.sin(t)[:, None], degrees=True).as_matrix()
    est = gt.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_euler("z", 3.0 * t[:, None], degrees=True).as_matrix()
    res = rpe_seconds(t, gt, t, est)
    dt = res.pair_timestamps[:, 1] - res.pair_timestamps[:, 0]
    np.testing.assert_allclose(res.rotation_errors, 3.0 * dt, atol=1e-9)
    assert res.translation.max < 1e-12


# ----------------------------------------------------------- error messages
def test_no_association_error_reports_counts_and_ranges() -> None:
    gt_t = np.arange(10) * 0.1
    est_t = 1000.0 + np.arange(5) * 0.1
    poses = np.tile(np.eye(4), (10, 1, 1))
    with pytest.raises(EvaluationError) as info:
        ate(gt_t, poses, est_t, poses[:5])
    msg = str(info.value)
    assert "no timestamps associated within max_dt = 0.02 s" in msg
    assert "ground truth has 10 poses, t = 0.000000 .. 0.900000 s" in msg
    assert "estimate has 5 poses, t = 1000.000000 .. 1000.400000 s" in msg


def test_too_few_matches_is_an_error() -> None:
    poses = smooth_trajectory(np.arange(10.0), seed=0)
    with pytest.raises(EvaluationError, match="only 2 poses associated.*need at least 3"):
        ate(np.arange(10.0), poses, np.array([1.0, 5.0, 20.0]), poses[:3])


def test_evaluate_files_missing_and_malformed_files(tmp_path: Path) -> None:
    gt = tmp_path / "gt.txt"
    write_tum(gt, np.arange(20) * 0.1, smooth_trajectory(np.arange(20) * 0.1, seed=0))
    with pytest.raises(EvaluationError, match=r"estimate file not found: .*nope\.txt"):
        evaluate_files(gt, tmp_path / "nope.txt")
    with pytest.raises(EvaluationError, match=r"ground truth file not found: .*absent\.txt"):
        evaluate_files(tmp_path / "absent.txt", gt)
    bad = tmp_path / "est.txt"
    bad.write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"est\.txt, line 3: expected 8 values"):
        evaluate_files(gt, bad)


def test_evaluate_files_report_is_json_ready(tmp_path: Path) -> None:
    gt_t = 50.0 + np.arange(300) * 0.01
    gt = smooth_trajectory(gt_t, seed=8)
    est_t, est = noisy_estimate(gt_t, gt, seed=8)
    write_tum(tmp_path / "gt.txt", gt_t, gt)
    write_tum(tmp_path / "est.txt", est_t, est)
    report = evaluate_files(tmp_path / "gt.txt", tmp_path / "est.txt")
    data = json.loads(json.dumps(report.to_dict()))
    assert data["ate"]["n_matched"] == report.ate.n_matched and data["rpe_time"] is not None
    assert isinstance(data["ate"]["rmse"], float) and len(data["ate"]["alignment"]) == 4
    text = format_report(report)
    assert "ATE [m]" in text and "RPE/1s trans [m/s]" in text and "RPE/frame rot [deg]" in text
    # A sequence shorter than 1 s still evaluates, with a note instead of RPE/1s.
    write_tum(tmp_path / "short.txt", est_t[:10], est[:10])
    short = evaluate_files(tmp_path / "gt.txt", tmp_path / "short.txt")
    assert short.rpe_time is None and "RPE over 1 s not computed" in short.notes[0]


# --------------------------------------------------------- agreement with evo
def evo_results(gt_file: Path, est_file: Path, max_dt: float) -> dict[str, np.ndarray]:
    """Per-pose ATE and per-frame RPE errors as evo_ape/evo_rpe compute them."""
    pytest.importorskip("evo")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    out: dict[str, np.ndarray] = {}
    relations = {"ate": (metrics.APE, metrics.PoseRelation.translation_part),
                 "rpe_t": (metrics.RPE, metrics.PoseRelation.translation_part),
                 "rpe_r": (metrics.RPE, metrics.PoseRelation.rotation_angle_deg)}
    for key, (cls, relation) in relations.items():
        ref = file_interface.read_tum_trajectory_file(str(gt_file))
        est = file_interface.read_tum_trajectory_file(str(est_file))
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_dt)
        est.align(ref, correct_scale=False)  # the -a flag
        metric = cls(relation) if cls is metrics.APE else cls(relation, 1, metrics.Unit.frames)
        metric.process_data((ref, est))
        out[key] = metric.error
    return out


def assert_matches_evo(gt_file: Path, est_file: Path, max_dt: float) -> float:
    """Compare evaluate_files with evo on two files; return the max abs difference."""
    expected = evo_results(gt_file, est_file, max_dt)
    report = evaluate_files(gt_file, est_file, max_dt=max_dt)
    pairs = [(expected["ate"], report.ate.errors),
             (expected["rpe_t"], report.rpe_frame.translation_errors),
             (expected["rpe_r"], report.rpe_frame.rotation_errors)]
    worst = 0.0
    for want, got in pairs:
        assert want.shape == got.shape
        worst = max(worst, float(np.max(np.abs(want - got))))
    ate_rmse = float(np.sqrt(np.mean(expected["ate"] ** 2)))
    assert report.ate.rmse == pytest.approx(ate_rmse, abs=1e-9)
    assert worst < 1e-6
    return worst


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("max_dt", [0.01, 0.02])
def test_agrees_with_evo_on_noisy_trajectories(tmp_path: Path, seed: int, max_dt: float) -> None:
    gt_t = 1305031102.0 + np.arange(1000) * 0.01 + np.random.default_rng(seed).normal(0, 0.001, 1000)
    gt_t = np.round(np.sort(gt_t), 4)
    gt = smooth_trajectory(gt_t - gt_t[0], seed)
    est_t, est = noisy_estimate(gt_t, gt, seed + 100, jitter=0.008)
    est_t = np.round(est_t, 6)
    write_tum(tmp_path / "gt.txt", gt_t, gt)
    write_tum(tmp_path / "est.txt", est_t, est)
    assert_matches_evo(tmp_path / "gt.txt", tmp_path / "est.txt", max_dt)


@pytest.mark.parametrize("case", ["sorted_ties", "unsorted", "equal_counts", "est_longer"])
def test_associate_matches_evo_indices(case: str) -> None:
    """Encode each pose's index in its x position and read evo's choice back."""
    pytest.importorskip("evo")
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(len(case))
    t_ref = np.round(np.sort(rng.uniform(0, 5, 400)), 2)  # duplicates and exact ties
    t_est = np.round(np.sort(rng.uniform(-0.5, 5.5, 150)), 3)
    if case == "unsorted":
        t_ref = rng.permutation(t_ref)
    elif case == "equal_counts":
        t_est = np.round(np.sort(rng.uniform(0, 5, 400)), 3)
    elif case == "est_longer":
        t_ref, t_est = t_est, t_ref
    trajs = []
    for t in (t_ref, t_est):
        xyz = np.c_[np.arange(len(t)), np.zeros((len(t), 2))]
        trajs.append(PoseTrajectory3D(xyz, np.tile([1.0, 0, 0, 0], (len(t), 1)), t))
    ref, est = sync.associate_trajectories(trajs[0], trajs[1], max_diff=0.005)
    i_ref, i_est = associate(t_ref, t_est, max_dt=0.005)
    np.testing.assert_array_equal(i_ref, ref.positions_xyz[:, 0].astype(int))
    np.testing.assert_array_equal(i_est, est.positions_xyz[:, 0].astype(int))


@pytest.mark.real
def test_agrees_with_evo_on_fr1_xyz(tmp_path: Path) -> None:
    """GT of fr1/xyz vs an 'estimate' at the rgb.txt stamps: nearest GT pose with seeded
    noise, expressed in another world frame."""
    FR1_XYZ = real_sequence(XYZ)
    gt_t, gt = read_tum(FR1_XYZ / "groundtruth.txt")
    rgb_t = np.array([float(line.split()[0]) for line in (FR1_XYZ / "rgb.txt").read_text().splitlines()
                      if line.strip() and not line.startswith("#")])
    nearest = np.abs(gt_t[None, :] - rgb_t[:, None]).argmin(axis=1)
    rng = np.random.default_rng(37)
    est = se3(Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), [0.5, 0.1, -0.2]) @ gt[nearest]
    est[:, :3, 3] += rng.normal(0, 0.01, (len(rgb_t), 3))
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.01, (len(rgb_t), 3))).as_matrix()
    write_tum(tmp_path / "est.txt", rgb_t, est)
    worst = assert_matches_evo(FR1_XYZ / "groundtruth.txt", tmp_path / "est.txt", 0.02)
    report = evaluate_files(FR1_XYZ / "groundtruth.txt", tmp_path / "est.txt")
    assert report.ate.n_matched == len(rgb_t) == 37 and worst < 1e-9
    assert report.rpe_time is not None and report.rpe_time.n_pairs > 0
    assert 0.005 < report.ate.rmse < 0.03
