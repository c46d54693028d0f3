"""Tests for slam.core.geometry (SO(3)/SE(3) maps, inverses, orthonormalisation) and slam.core.camera."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from slam.core.camera import PinholeCamera
from slam.core.config import load_config
from slam.core.geometry import (invert, make_pose, orthonormalize, pose_distance, rotation_angle_deg, se3_exp, se3_log,
                           skew, so3_exp, so3_log, transform_points)


def random_axes(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_pose(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3))


def assert_rotation(R: np.ndarray, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=atol)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=atol)


# --- SO(3) ---------------------------------------------------------------------------------------


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    v, w = rng.normal(size=(2, 3))
    np.testing.assert_allclose(skew(v) @ w, np.cross(v, w), atol=1e-15)
    batch = rng.normal(size=(5, 3))
    np.testing.assert_allclose(skew(batch)[2], skew(batch[2]))


def test_so3_exp_matches_scipy_and_is_a_rotation():
    rng = np.random.default_rng(1)
    for omega in rng.normal(scale=1.5, size=(50, 3)):
        R = so3_exp(omega)
        assert_rotation(R, 1e-12)
        np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=1e-12)


def test_so3_log_exp_round_trip_on_random_angles():
    rng = np.random.default_rng(2)
    axes = random_axes(rng, 300)
    angles = rng.uniform(0.0, np.pi - 1e-3, 300)
    for axis, angle in zip(axes, angles):
        omega = axis * angle
        np.testing.assert_allclose(so3_log(so3_exp(omega)), omega, atol=1e-8)


@pytest.mark.parametrize("angle", [0.0, 1e-14, 1e-11, 1e-9, 1e-7, 1e-6, 1e-4, 1e-2])
def test_so3_round_trip_near_zero(angle):
    rng = np.random.default_rng(3)
    for axis in random_axes(rng, 20):
        omega = axis * angle
        R = so3_exp(omega)
        assert_rotation(R, 1e-12)
        np.testing.assert_allclose(so3_log(R), omega, atol=1e-12 + 1e-9 * angle)


@pytest.mark.parametrize("delta", [1e-2, 3e-3, 1e-3])
def test_so3_round_trip_close_to_pi(delta):
    """Within a few mrad of pi, on the regular branch: the vector comes back."""
    rng = np.random.default_rng(4)
    for axis in random_axes(rng, 50):
        omega = axis * (np.pi - delta)
        np.testing.assert_allclose(so3_log(so3_exp(omega)), omega, atol=1e-8)


def test_so3_log_at_exactly_pi_gives_the_rotation_back():
    """At pi the axis sign is arbitrary; exp(log(R)) must still be R."""
    rng = np.random.default_rng(5)
    cases = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    cases += [Rotation.from_rotvec(a * np.pi).as_matrix() for a in random_axes(rng, 50)]
    for R in cases:
        omega = so3_log(R)
        assert np.linalg.norm(omega) == pytest.approx(np.pi, abs=1e-7)
        np.testing.assert_allclose(so3_exp(omega), R, atol=1e-7)


@pytest.mark.parametrize("delta", [5e-5, 1e-5, 1e-6, 1e-7])
def test_so3_round_trip_within_1e4_of_pi(delta):
    rng = np.random.default_rng(6)
    for axis in random_axes(rng, 50):
        R = so3_exp(axis * (np.pi - delta))
        np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-8)


# --- SE(3) ---------------------------------------------------------------------------------------


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    M = np.zeros((4, 4))
    M[:3, :3], M[:3, 3] = skew(xi[:3]), xi[3:]
    return M


def test_se3_exp_matches_the_matrix_exponential():
    rng = np.random.default_rng(7)
    twists = list(rng.normal(scale=1.0, size=(40, 6)))
    twists += [np.r_[random_axes(rng, 1)[0] * a, rng.normal(size=3)] for a in (0.0, 1e-12, 1e-8, 1e-5, np.pi - 1e-6)]
    for xi in twists:
        T = se3_exp(xi)
        np.testing.assert_allclose(T, expm(twist_matrix(xi)), atol=1e-10)
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        assert_rotation(T[:3, :3], 1e-12)


def test_se3_exp_rotation_first_and_inverse():
    rng = np.random.default_rng(8)
    for xi in rng.normal(size=(20, 6)):
        T = se3_exp(xi)
        np.testing.assert_allclose(T[:3, :3], so3_exp(xi[:3]), atol=1e-14)
        np.testing.assert_allclose(se3_exp(-xi) @ T, np.eye(4), atol=1e-12)
    # A pure translation twist is the translation itself.
    np.testing.assert_allclose(se3_exp(np.r_[0, 0, 0, 1.0, -2.0, 0.5]), make_pose(np.eye(3), [1.0, -2.0, 0.5]))


def test_se3_log_inverts_se3_exp():
    rng = np.random.default_rng(9)
    twists = [np.r_[random_axes(rng, 1)[0] * a, rng.normal(size=3)] for a in (0.0, 1e-9, 1e-4, 0.5, 2.0, 3.0)]
    for xi in twists + list(rng.normal(scale=0.8, size=(20, 6))):
        if np.linalg.norm(xi[:3]) >= np.pi:   # the log returns the equivalent twist of angle < pi
            continue
        np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-9)


def test_invert_single_and_batched():
    rng = np.random.default_rng(9)
    poses = np.stack([random_pose(rng) for _ in range(10)])
    for T in poses:
        np.testing.assert_allclose(invert(T), np.linalg.inv(T), atol=1e-12)
        np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)
    batched = invert(poses)
    assert batched.shape == (10, 4, 4)
    np.testing.assert_allclose(batched, np.linalg.inv(poses), atol=1e-12)
    np.testing.assert_allclose(invert(poses[None]), np.linalg.inv(poses)[None], atol=1e-12)


def test_transform_points_and_composition():
    rng = np.random.default_rng(10)
    T_ab, T_bc = random_pose(rng), random_pose(rng)
    p_c = rng.normal(size=(25, 3))
    p_b = transform_points(T_bc, p_c)
    homogeneous = (T_bc @ np.c_[p_c, np.ones(25)].T).T[:, :3]
    np.testing.assert_allclose(p_b, homogeneous, atol=1e-12)
    np.testing.assert_allclose(transform_points(T_ab, p_b), transform_points(T_ab @ T_bc, p_c), atol=1e-12)
    np.testing.assert_allclose(transform_points(invert(T_bc), p_b), p_c, atol=1e-12)
    assert transform_points(T_ab, np.zeros((0, 3))).shape == (0, 3)


def test_pose_distance_and_rotation_angle():
    R = so3_exp([0.0, 0.0, np.radians(30.0)])
    A = make_pose(np.eye(3), [1.0, 2.0, 3.0])
    B = A @ make_pose(R, [0.3, 0.0, 0.4])
    t, deg = pose_distance(A, B)
    assert t == pytest.approx(0.5)
    assert deg == pytest.approx(30.0)
    np.testing.assert_allclose(rotation_angle_deg(np.stack([np.eye(3), R])), [0.0, 30.0], atol=1e-6)


def test_orthonormalize_repairs_a_perturbed_rotation():
    rng = np.random.default_rng(11)
    for _ in range(20):
        T = random_pose(rng)
        noisy = T.copy()
        noisy[:3, :3] += rng.normal(scale=1e-3, size=(3, 3))
        noisy[3] = (1e-9, 0.0, 0.0, 1.0)
        fixed = orthonormalize(noisy)
        assert_rotation(fixed[:3, :3], 1e-12)
        np.testing.assert_allclose(fixed[:3, :3], T[:3, :3], atol=5e-3)
        assert pose_distance(T, fixed)[1] < 0.5
        np.testing.assert_allclose(fixed[:3, 3], T[:3, 3])
        np.testing.assert_allclose(fixed[3], [0, 0, 0, 1])
        # The input is left untouched and a proper rotation is a fixed point.
        assert not np.allclose(noisy[:3, :3] @ noisy[:3, :3].T, np.eye(3), atol=1e-6)
        np.testing.assert_allclose(orthonormalize(T), T, atol=1e-12)


def test_orthonormalize_never_returns_a_reflection():
    rng = np.random.default_rng(12)
    R = Rotation.random(random_state=12).as_matrix()
    for M in (-R, R @ np.diag([1.0, 1.0, -1.0]), rng.normal(size=(3, 3))):
        out = orthonormalize(make_pose(M, [1.0, 2.0, 3.0]))
        assert_rotation(out[:3, :3], 1e-12)


def test_accumulated_products_stay_on_so3_with_orthonormalize():
    step = se3_exp([0.01, -0.02, 0.015, 0.01, 0.0, 0.02])
    step[:3, :3] *= 1.0 + 1e-9  # rounding-level drift in every factor
    T = np.eye(4)
    for _ in range(2000):
        T = orthonormalize(step @ T)
    assert_rotation(T[:3, :3], 1e-12)


# --- camera --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fr1_camera() -> PinholeCamera:
    return PinholeCamera.from_config(load_config("tum_fr1").camera)


def distort(camera: PinholeCamera, ideal: np.ndarray) -> np.ndarray:
    """Distorted pixels of ideal pinhole pixels, by OpenCV's forward model."""
    rays = np.c_[(ideal[:, 0] - camera.cx) / camera.fx, (ideal[:, 1] - camera.cy) / camera.fy, np.ones(len(ideal))]
    pts, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, np.asarray(camera.distortion))
    return pts.reshape(-1, 2)


def test_camera_from_config_and_properties():
    cfg = load_config("tum_fr1").camera
    cam = PinholeCamera.from_config(cfg)
    np.testing.assert_allclose(cam.K, [[cfg.fx, 0, cfg.cx], [0, cfg.fy, cfg.cy], [0, 0, 1]])
    assert cam.distortion == tuple(cfg.distortion)
    assert cam.has_distortion
    assert cam.baseline == pytest.approx(cfg.bf / cfg.fx)
    assert cam.close_depth == pytest.approx(cfg.bf / cfg.fx * cfg.depth_threshold)
    assert not PinholeCamera.from_config(load_config("tum_fr3").camera).has_distortion


def test_project_backproject_round_trip(fr1_camera):
    rng = np.random.default_rng(13)
    cam = fr1_camera
    uv = np.c_[rng.uniform(0, cam.width, 200), rng.uniform(0, cam.height, 200)]
    depth = rng.uniform(0.2, 7.0, 200)
    points = cam.backproject(uv, depth)
    np.testing.assert_allclose(points[:, 2], depth)
    uv2, z = cam.project(points)
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(z, depth)
    # And the other way round, for points anywhere in front of the camera.
    pts = np.c_[rng.uniform(-2, 2, (100, 2)), rng.uniform(0.3, 6, 100)]
    uv3, z3 = cam.project(pts)
    np.testing.assert_allclose(cam.backproject(uv3, z3), pts, atol=1e-12)
    # The principal point projects the optical axis.
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 2.0]]))[0], [[cam.cx, cam.cy]])


def test_in_image_margin(fr1_camera):
    uv = np.array([[0.0, 0.0], [639.9, 479.9], [640.0, 10.0], [-0.1, 10.0], [5.0, 5.0]])
    np.testing.assert_array_equal(fr1_camera.in_image(uv), [True, True, False, False, True])
    np.testing.assert_array_equal(fr1_camera.in_image(uv, margin=10.0), [False, False, False, False, False])


def test_undistort_points_matches_opencv(fr1_camera):
    rng = np.random.default_rng(14)
    raw = np.c_[rng.uniform(0, 640, 300), rng.uniform(0, 480, 300)]
    # OpenCV's default 5 iterations are not converged near the corners; compare with a converged run.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    expected = cv2.undistortPoints(raw.reshape(-1, 1, 2), fr1_camera.K, np.asarray(fr1_camera.distortion),
                                   R=None, P=fr1_camera.K, criteria=criteria).reshape(-1, 2)
    np.testing.assert_allclose(fr1_camera.undistort_points(raw), expected, atol=1e-6)
    # Distortion really moves pixels: near the corners by several pixels.
    assert np.abs(fr1_camera.undistort_points(np.array([[5.0, 5.0]])) - [5.0, 5.0]).max() > 3.0


def test_undistort_without_distortion_is_identity_copy():
    cam = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
    pts = np.array([[1.0, 2.0], [600.5, 400.25]])
    out = cam.undistort_points(pts)
    np.testing.assert_array_equal(out, pts)
    out[0, 0] = 99.0
    assert pts[0, 0] == 1.0
    assert cam.undistort_points(np.zeros((0, 2))).shape == (0, 2)


def test_undistort_inverts_distortion_in_the_image_centre(fr1_camera):
    u, v = np.meshgrid(np.linspace(120, 520, 21), np.linspace(40, 440, 21))
    ideal = np.c_[u.ravel(), v.ravel()]
    ideal = ideal[np.linalg.norm(ideal - [fr1_camera.cx, fr1_camera.cy], axis=1) < 200]
    back = fr1_camera.undistort_points(distort(fr1_camera, ideal))
    assert np.linalg.norm(back - ideal, axis=1).max() < 1e-3


def test_undistort_inverts_distortion_over_the_whole_image(fr1_camera):
    u, v = np.meshgrid(np.linspace(-40, 680, 73), np.linspace(-40, 520, 57))
    ideal = np.c_[u.ravel(), v.ravel()]
    raw = distort(fr1_camera, ideal)
    inside = fr1_camera.in_image(raw)   # every ideal point whose distorted pixel lies in the image
    assert inside.sum() > 1000
    back = fr1_camera.undistort_points(raw[inside])
    assert np.linalg.norm(back - ideal[inside], axis=1).max() < 0.01


def test_right_u_and_depth_range(fr1_camera):
    cam = fr1_camera
    u = np.array([100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 50.0])
    depth = np.array([0.5, 1.0, 4.0, 0.05, 9.0, 0.0, np.nan])
    ur = cam.right_u(u, depth)
    np.testing.assert_allclose(ur[:3], u[:3] - cam.bf / depth[:3])
    assert np.isnan(ur[3:]).all()
    # Closer points have more disparity.
    assert (u[:3] - ur[:3])[0] > (u[:3] - ur[:3])[1] > (u[:3] - ur[:3])[2] > 0
    inside = np.array([cam.min_depth + 1e-6, cam.max_depth - 1e-6])
    assert np.isfinite(cam.right_u(np.array([10.0, 10.0]), inside)).all()
    outside = np.array([cam.min_depth - 1e-6, cam.max_depth + 1e-6])
    assert np.isnan(cam.right_u(np.array([10.0, 10.0]), outside)).all()
