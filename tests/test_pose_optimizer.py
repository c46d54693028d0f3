"""Tests for frontend.pose_optimizer: motion-only Gauss-Newton with stereo/mono observations and outliers."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from frontend.pose_optimizer import PoseObservations, PosePrior, _residuals_and_jacobians, optimize_pose
from slam.core.camera import PinholeCamera
from slam.core.geometry import invert, se3_exp, so3_log, transform_points

CAMERA = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)


@dataclass
class Scene:
    T_true: np.ndarray     # T_cw
    T_start: np.ndarray    # perturbed T_cw
    obs: PoseObservations
    outlier: np.ndarray    # (N,) bool
    mono: np.ndarray       # (N,) bool


def make_scene(seed: int, n: int = 200, noise: float = 0.0, outlier_fraction: float = 0.0,
               mono_fraction: float = 0.3, rot_deg: float = 5.0, trans_m: float = 0.08) -> Scene:
    """Points in front of a random camera pose; exact (or noisy) stereo and mono observations."""
    rng = np.random.default_rng(seed)
    T_cw = se3_exp(np.r_[rng.normal(scale=0.5, size=3), rng.normal(scale=1.0, size=3)])
    uv = np.c_[rng.uniform(10, 630, n), rng.uniform(10, 470, n)]
    z = rng.uniform(0.6, 6.0, n)
    points_w = transform_points(invert(T_cw), CAMERA.backproject(uv, z))
    u_right = uv[:, 0] - CAMERA.bf / z
    mono = rng.random(n) < mono_fraction
    u_right[mono] = np.nan
    uv_obs = uv + rng.normal(scale=noise, size=uv.shape)
    ur_obs = u_right + rng.normal(scale=noise, size=n)
    outlier = np.zeros(n, bool)
    if outlier_fraction:
        outlier[rng.choice(n, int(round(outlier_fraction * n)), replace=False)] = True
        k = int(outlier.sum())
        uv_obs[outlier] = np.c_[rng.uniform(0, 640, k), rng.uniform(0, 480, k)]
        ur_obs[outlier] = uv_obs[outlier, 0] - CAMERA.bf / rng.uniform(0.6, 6.0, k)
        ur_obs[mono] = np.nan
    # Perturbation: rot_deg about a random axis, trans_m along a random direction (camera frame).
    axis, direction = rng.normal(size=(2, 3))
    xi = np.r_[axis / np.linalg.norm(axis) * np.radians(rot_deg), direction / np.linalg.norm(direction) * trans_m]
    T_start = se3_exp(xi) @ T_cw
    return Scene(T_cw, T_start, PoseObservations(points_w, uv_obs, ur_obs, np.ones(n)), outlier, mono)


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation rad) of T_a^-1 T_b, and of the camera centres."""
    D = invert(T_a) @ T_b
    centre = np.linalg.norm(invert(T_a)[:3, 3] - invert(T_b)[:3, 3])
    return max(float(np.linalg.norm(D[:3, 3])), float(centre)), float(np.linalg.norm(so3_log(D[:3, :3])))


def test_jacobian_matches_finite_differences():
    scene = make_scene(0, n=30)
    T = scene.T_start
    cam = CAMERA
    e0, J, stereo, _ = _residuals_and_jacobians(T, scene.obs, cam.fx, cam.fy, cam.cx, cam.cy, cam.bf)
    h = 1e-6
    numeric = np.zeros_like(J)
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        e_plus = _residuals_and_jacobians(se3_exp(step) @ T, scene.obs, cam.fx, cam.fy, cam.cx, cam.cy, cam.bf)[0]
        e_minus = _residuals_and_jacobians(se3_exp(-step) @ T, scene.obs, cam.fx, cam.fy, cam.cx, cam.cy, cam.bf)[0]
        # e = z - h(T X): the Jacobian of h is minus that of e.
        numeric[:, :, k] = -(e_plus - e_minus) / (2 * h)
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-4)
    assert (J[~stereo, 2] == 0).all() and (e0[~stereo, 2] == 0).all()
    assert stereo.sum() > 0 and (~stereo).sum() > 0


@pytest.mark.parametrize("seed", range(5))
def test_recovers_exact_pose_without_noise(seed):
    scene = make_scene(seed)
    assert pose_error(scene.T_true, scene.T_start)[0] > 0.03          # several cm off at the start
    assert np.degrees(pose_error(scene.T_true, scene.T_start)[1]) > 4.0
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-6 and r_err < 1e-6
    assert result.inliers.all()
    assert result.chi2.max() < 1e-8
    R = result.T_cw[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(result.T_cw[3], [0, 0, 0, 1])


def test_does_not_modify_the_initial_pose():
    scene = make_scene(1)
    start = scene.T_start.copy()
    optimize_pose(scene.T_start, scene.obs, CAMERA)
    np.testing.assert_array_equal(scene.T_start, start)


def test_recovers_pose_from_mono_observations_only():
    scene = make_scene(2, mono_fraction=1.0)
    assert np.isnan(scene.obs.u_right).all()
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-6 and r_err < 1e-6


def test_recovers_pose_from_stereo_observations_only():
    scene = make_scene(3, mono_fraction=0.0)
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-6 and r_err < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_half_pixel_noise_gives_millimetre_accuracy(seed):
    scene = make_scene(seed, noise=0.5)
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 0.003
    assert np.degrees(r_err) < 0.05
    assert result.inliers.mean() > 0.97
    # Far better than where it started.
    assert t_err < 0.1 * pose_error(scene.T_true, scene.T_start)[0]


@pytest.mark.parametrize("seed", range(5))
def test_gross_outliers_are_rejected(seed):
    scene = make_scene(seed, noise=0.5, outlier_fraction=0.2)
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 0.01
    assert np.degrees(r_err) < 0.2
    assert (~result.inliers[scene.outlier]).mean() >= 0.9
    assert result.inliers[~scene.outlier].mean() >= 0.95
    # The chi-square of the reported inliers is under the thresholds (stereo 3 DOF, mono 2 DOF).
    threshold = np.where(scene.mono, 5.991, 7.815)
    assert (result.chi2[result.inliers] <= threshold[result.inliers]).all()


def test_outliers_exact_data_recovers_exact_pose():
    scene = make_scene(7, outlier_fraction=0.2)
    result = optimize_pose(scene.T_start, scene.obs, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-6 and r_err < 1e-6
    np.testing.assert_array_equal(result.inliers, ~scene.outlier)


def test_information_weights_downweight_bad_observations():
    """A large systematic error on zero-information observations must not pull the pose."""
    scene = make_scene(8, outlier_fraction=0.0)
    obs = scene.obs
    rng = np.random.default_rng(8)
    bad = rng.random(len(obs.uv)) < 0.3
    uv = obs.uv.copy()
    uv[bad] += 1.0  # a consistent 1 px shift: within the chi-square gates, so only the weights keep it out
    ur = obs.u_right.copy()
    ur[bad] += 1.0
    weighted = PoseObservations(obs.points_w, uv, ur, np.where(bad, 0.0, 1.0))
    result = optimize_pose(scene.T_start, weighted, CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-6 and r_err < 1e-6
    unweighted = optimize_pose(scene.T_start, PoseObservations(obs.points_w, uv, ur, np.ones(len(uv))), CAMERA)
    assert pose_error(scene.T_true, unweighted.T_cw)[0] > 1e-4


@pytest.mark.parametrize("n_behind", [1, 5])
def test_points_behind_the_camera_do_not_derail_the_solve(n_behind):
    """Gross mismatches (e.g. from descriptor matching before PnP) can lie behind the camera: they must
    simply be outliers, as in ORB-SLAM's pose optimisation."""
    scene = make_scene(9, n=100)
    obs = scene.obs
    points = obs.points_w.copy()
    # Mirror points through the camera centre: behind it.
    pc = transform_points(scene.T_true, points[:n_behind])
    points[:n_behind] = transform_points(invert(scene.T_true), -pc)
    result = optimize_pose(scene.T_start, PoseObservations(points, obs.uv, obs.u_right, obs.information), CAMERA)
    t_err, r_err = pose_error(scene.T_true, result.T_cw)
    assert t_err < 1e-4 and r_err < 1e-4
    assert not result.inliers[:n_behind].any()
    assert result.inliers[n_behind:].all()


# The motion prior's sigmas of the default config (tracking.motion_prior_sigma_deg / _m).
PRIOR_INFORMATION = 1.0 / np.r_[np.full(3, np.radians(0.5)), np.full(3, 0.01)] ** 2


def far_wall_scene(seed: int, n: int = 60, noise: float = 1.0) -> Scene:
    """What a person filling the view leaves: a few points on a wall 3.5 m away in one image corner,
    observed with a pixel of noise; the forward translation is barely determined."""
    rng = np.random.default_rng(seed)
    T_cw = se3_exp(np.r_[rng.normal(scale=0.3, size=3), rng.normal(size=3)])
    uv = np.c_[rng.uniform(10, 200, n), rng.uniform(10, 470, n)]
    z = rng.uniform(3.4, 3.6, n)
    points_w = transform_points(invert(T_cw), CAMERA.backproject(uv, z))
    uv_obs = uv + rng.normal(scale=noise, size=uv.shape)
    ur_obs = uv[:, 0] - CAMERA.bf / z + rng.normal(scale=noise, size=n)
    return Scene(T_cw, T_cw.copy(), PoseObservations(points_w, uv_obs, ur_obs, np.ones(n)), np.zeros(n, bool),
                 np.zeros(n, bool))


def test_a_weakly_held_pose_reports_its_uncertainty_and_a_strong_one_not():
    weak = optimize_pose(far_wall_scene(0).T_start, far_wall_scene(0).obs, CAMERA)
    strong_scene = make_scene(0, noise=1.0)
    strong = optimize_pose(strong_scene.T_start, strong_scene.obs, CAMERA)
    # 1 px of disparity on a 3.5 m wall (bf = 40 px m): ~0.3 m of depth per point, 4 cm for 60 of them; the
    # points' spread in the image tightens that to ~1.4 cm, still several times a full view's ~2 mm.
    assert weak.sigma_t > 0.01
    assert strong.sigma_t < 0.004
    # The prior does not enter the reported uncertainty: it says what the points alone fix.
    with_prior = optimize_pose(strong_scene.T_start, strong_scene.obs, CAMERA,
                               prior=PosePrior(strong_scene.T_true, PRIOR_INFORMATION))
    assert with_prior.sigma_t == pytest.approx(strong.sigma_t, rel=0.05)


@pytest.mark.parametrize("seed", range(5))
def test_the_motion_prior_steadies_a_weak_pose_and_leaves_a_strong_one(seed):
    # The prediction misses the true pose by what a frame's unmodelled motion gives (3 mm, 0.1 deg).
    miss = se3_exp(np.r_[np.radians(0.1), 0, 0, 0.003, 0, 0])
    weak_scene = far_wall_scene(seed)
    prior = PosePrior(miss @ weak_scene.T_true, PRIOR_INFORMATION)
    free = optimize_pose(weak_scene.T_start, weak_scene.obs, CAMERA)
    held = optimize_pose(weak_scene.T_start, weak_scene.obs, CAMERA, prior=prior)
    assert pose_error(weak_scene.T_true, held.T_cw)[0] < pose_error(weak_scene.T_true, free.T_cw)[0]
    assert pose_error(weak_scene.T_true, held.T_cw)[0] < 0.012
    # 200 points spread over the image: a prior 2 cm off moves the pose by well under a millimetre.
    strong_scene = make_scene(seed, noise=0.5)
    off = PosePrior(se3_exp(np.r_[0, 0, 0, 0.02, 0, 0]) @ strong_scene.T_true, PRIOR_INFORMATION)
    a = optimize_pose(strong_scene.T_start, strong_scene.obs, CAMERA)
    b = optimize_pose(strong_scene.T_start, strong_scene.obs, CAMERA, prior=off)
    assert pose_error(a.T_cw, b.T_cw)[0] < 0.001


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-6, 0.3, 3.0, np.pi - 1e-6])
def test_compiled_se3_agrees_with_the_geometry_module(scale):
    """The optimiser's compiled exp / log / inverse / solve (frontend/pose_optimizer.py) against
    slam.core.geometry and numpy, from no rotation to nearly half a turn."""
    from frontend import pose_optimizer as po
    from slam.core.geometry import se3_log

    rng = np.random.default_rng(int(scale * 1000))
    for _ in range(5):
        axis = rng.normal(size=3)
        xi = np.r_[scale * axis / np.linalg.norm(axis), rng.normal(size=3)]
        T = se3_exp(xi)
        # geometry's closed forms lose digits below ~1e-3 rad (1 - cos(theta)); the kernels use the series
        assert np.allclose(po._exp_se3(xi), T, rtol=0, atol=1e-10)
        assert np.allclose(po._log_se3(T), se3_log(T), rtol=0, atol=1e-9)
        assert np.allclose(po._log_se3(T), xi, rtol=0, atol=1e-9)
        assert np.allclose(po._invert(T), invert(T), rtol=0, atol=1e-15)
        inverse = po._exp_se3(-xi)
        assert np.allclose(po._compose(po._exp_se3(xi), inverse), np.eye(4), rtol=0, atol=1e-14)
    A = rng.normal(size=(6, 6))
    H, b = A @ A.T + 1e-3 * np.eye(6), rng.normal(size=6)
    x, ok = po._solve_spd(H, b)
    assert ok and np.allclose(x, np.linalg.solve(H, b), rtol=1e-9, atol=1e-12)
    _, ok = po._solve_spd(-H, b)        # not positive definite: refused, the optimiser stops
    assert not ok
