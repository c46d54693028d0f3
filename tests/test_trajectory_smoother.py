"""The final trajectory's position smoother (slam/runtime/trajectory_smoother.py): what a frame's own
covariance fixes stays, what it leaves loose follows the motion model, and nothing crosses a LOST gap."""
from __future__ import annotations

import numpy as np
import pytest

from slam.runtime.frame_log import FrameLog
from slam.runtime.trajectory_smoother import smooth_positions

RATE_HZ = 30.0
SIGMA_ACC = 2.0
CHI2 = 7.815          # tracking.chi2_stereo's default, what System passes


def _path(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A hand-held-like path: smooth, accelerations below 1 m/s^2."""
    t = np.arange(n) / RATE_HZ
    return t, np.c_[0.5 * np.sin(0.8 * t), 0.3 * np.cos(0.5 * t), 0.1 * t]


def _isotropic(sigmas: np.ndarray) -> np.ndarray:
    return np.eye(3)[None] * (sigmas**2)[:, None, None]


def test_a_loosely_fixed_stretch_follows_its_well_fixed_neighbours():
    rng = np.random.default_rng(0)
    t, truth = _path(300)
    sigma = np.full(len(t), 0.002)
    sigma[120:150] = 0.02          # a person close to the camera: the background fixes the pose loosely
    measured = truth + rng.normal(size=truth.shape) * sigma[:, None]
    smoothed = smooth_positions(t, measured, _isotropic(sigma), np.ones(len(t), bool), SIGMA_ACC, CHI2)
    raw_err = np.linalg.norm(measured - truth, axis=1)
    err = np.linalg.norm(smoothed - truth, axis=1)
    assert err[120:150].mean() < 0.3 * raw_err[120:150].mean(), (err[120:150].mean(), raw_err[120:150].mean())
    assert err[120:150].max() < 0.02
    assert err.mean() < raw_err.mean()


def test_a_well_fixed_frame_keeps_its_position():
    rng = np.random.default_rng(1)
    t, truth = _path(100)
    sigma = np.full(len(t), 0.02)
    sigma[50] = 1e-4               # one frame fixed to 0.1 mm among loose ones
    measured = truth + rng.normal(size=truth.shape) * sigma[:, None]
    smoothed = smooth_positions(t, measured, _isotropic(sigma), np.ones(len(t), bool), SIGMA_ACC, CHI2)
    assert np.linalg.norm(smoothed[50] - measured[50]) < 5e-4


def test_exact_constant_velocity_with_a_dropped_frame_is_left_as_it_is():
    """Zero acceleration is no residual, also across an interval twice as long (divided differences)."""
    t = np.delete(np.arange(60) / RATE_HZ, 30)
    positions = np.c_[0.4 * t, -0.2 * t, 0.05 * t + 1.0]
    smoothed = smooth_positions(t, positions, _isotropic(np.full(len(t), 0.01)), np.ones(len(t), bool), SIGMA_ACC, CHI2)
    np.testing.assert_allclose(smoothed, positions, atol=1e-9)


def test_a_lost_frame_breaks_the_chain():
    """Relocalised after LOST: the jump between the two runs is the map's, not an acceleration."""
    t = np.arange(40) / RATE_HZ
    positions = np.c_[0.3 * t, 0 * t, 0 * t]
    positions[21:] += [1.0, 0.5, 0.0]
    tracked = np.ones(len(t), bool)
    tracked[20] = False
    positions[20] = np.nan
    smoothed = smooth_positions(t, positions, _isotropic(np.full(len(t), 0.01)), tracked, SIGMA_ACC, CHI2)
    np.testing.assert_allclose(smoothed[tracked], positions[tracked], atol=1e-9)
    assert np.isnan(smoothed[20]).all()


def test_a_frame_without_covariance_is_held_and_short_runs_are_untouched():
    rng = np.random.default_rng(2)
    t, truth = _path(50)
    measured = truth + rng.normal(size=truth.shape) * 0.01
    cov = _isotropic(np.full(len(t), 0.01))
    cov[0] = np.nan                # the first keyframe: defined, not measured
    tracked = np.ones(len(t), bool)
    tracked[[45, 48]] = False      # runs of 2 and 1 frames after them: nothing to smooth with
    smoothed = smooth_positions(t, measured, cov, tracked, SIGMA_ACC, CHI2)
    assert np.linalg.norm(smoothed[0] - measured[0]) < 1e-3
    np.testing.assert_array_equal(smoothed[46:48], measured[46:48])
    np.testing.assert_array_equal(smoothed[49], measured[49])


def test_frame_log_smooths_only_when_asked_and_keeps_rotations():
    rng = np.random.default_rng(3)
    log = FrameLog()
    t, truth = _path(60)
    for i, stamp in enumerate(t):
        T = np.eye(4)
        T[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
        T[:3, 3] = truth[i] + rng.normal(size=3) * 0.01
        log.add(stamp, 0, T, np.eye(3) * 0.01**2)
    kf_T_wc = np.eye(4)[None]
    _, raw, _ = log.trajectory(kf_T_wc)
    _, same, _ = log.trajectory(kf_T_wc, 0.0)
    _, smoothed, tracked = log.trajectory(kf_T_wc, SIGMA_ACC, CHI2)
    np.testing.assert_array_equal(raw, same)
    assert tracked.all()
    np.testing.assert_array_equal(smoothed[:, :3, :3], raw[:, :3, :3])
    err_raw = np.linalg.norm(raw[:, :3, 3] - truth, axis=1).mean()
    err = np.linalg.norm(smoothed[:, :3, 3] - truth, axis=1).mean()
    assert err < 0.6 * err_raw, (err, err_raw)


@pytest.mark.parametrize("sigma_acc", [0.5, 2.0, 8.0])
def test_smoothing_is_deterministic(sigma_acc):
    rng = np.random.default_rng(4)
    t, truth = _path(200)
    measured = truth + rng.normal(size=truth.shape) * 0.005
    cov = _isotropic(np.full(len(t), 0.005))
    a = smooth_positions(t, measured, cov, np.ones(len(t), bool), sigma_acc, CHI2)
    b = smooth_positions(t, measured.copy(), cov.copy(), np.ones(len(t), bool), sigma_acc, CHI2)
    assert a.tobytes() == b.tobytes()


def _run_system(n_frames: int, **overrides):
    from conftest import synthetic_config, synthetic_sequence
    from slam.run.evaluation import ate
    from slam.runtime.system import System

    sequence = synthetic_sequence(n_frames)
    system = System(synthetic_config(sequence, **overrides))
    for frame in sequence:
        system.process(frame.rgb, frame.depth, frame.timestamp, frame.index)
    system.close()
    stamps, poses, tracked = system.trajectory()
    gt_t, gt_poses = sequence.groundtruth()
    return poses, ate(gt_t, gt_poses, stamps[tracked], poses[tracked]).rmse


@pytest.mark.slow
def test_system_writes_the_smoothed_positions_and_the_estimated_rotations():
    """Same run with the smoother off and on: rotations identical, positions moved, ATE better (the
    generated depth's noise leaves each frame ~2-3 mm of jitter that the motion model removes; measured
    3.1 -> 1.9 mm)."""
    raw, ate_raw = _run_system(60, **{"backend.smoothing_sigma_acc": 0.0})
    smoothed, ate_smoothed = _run_system(60)
    np.testing.assert_array_equal(smoothed[:, :3, :3], raw[:, :3, :3])
    moved = np.linalg.norm(smoothed[:, :3, 3] - raw[:, :3, 3], axis=1)
    assert moved.max() > 1e-5, "the default smooths"
    assert moved.max() < 0.01, "a well-tracked room moves by less than a centimetre"
    assert ate_smoothed < 0.9 * ate_raw, (ate_smoothed, ate_raw)


def test_a_confidently_wrong_frame_counts_less_than_its_covariance_says(monkeypatch):
    """A pose that people pulled 4 cm off with a 5 mm covariance (Bonn frames 445-448): the Huber rounds
    leave it mostly to its neighbours' motion; with plain least squares it keeps far more of the error."""
    import slam.runtime.trajectory_smoother as smoother

    t, truth = _path(120)
    sigma = np.full(len(t), 0.005)
    measured = truth.copy()
    measured[60] += [0.04, 0.0, 0.0]
    cov, tracked = _isotropic(sigma), np.ones(len(t), bool)
    robust = np.linalg.norm(smooth_positions(t, measured, cov, tracked, SIGMA_ACC, CHI2)[60] - truth[60])
    monkeypatch.setattr(smoother, "_ROBUST_ROUNDS", 0)
    plain = np.linalg.norm(smooth_positions(t, measured, cov, tracked, SIGMA_ACC, CHI2)[60] - truth[60])
    assert robust < 0.25 * 0.04, robust
    assert robust < 0.6 * plain, (robust, plain)   # measured 4.6 vs 9.9 mm
