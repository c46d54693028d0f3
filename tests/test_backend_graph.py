"""The graph back ends driven directly, with no front end: FactorGraphBackend and LocalWindowBackend
on synthetic graphs with exact ground truth (accuracy, relative poses and robust kernels, dynamic
probability, errors). LocalMapper on top of them: tests/test_backend_mapper.py.

Nothing here imports ``frontend``: the back end's public API must be usable by another pipeline.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from backend.graph import BackendError, BackendParams, FactorGraphBackend, StereoCalibration
from backend.window_graph import LocalWindowBackend
from slam.core.config import BackendConfig
from slam.core.geometry import invert, make_pose, pose_distance, se3_exp, so3_exp, transform_points


FX, FY, CX, CY, W, H = 525.0, 525.0, 319.5, 239.5, 640, 480
BF = 40.0  # fx * baseline, as CameraConfig.bf
CAL = StereoCalibration(FX, FY, CX, CY, BF / FX)
N_KF, N_PTS = 8, 200
# These graphs are solved in one update (plus extra_updates) from guesses centimetres off, so they
# relinearise at every update; a run (relinearize_skip 5, the config default) updates once per keyframe
# and converges over many updates. The tolerances below were set with the 0.0015 z^2 depth model of a
# Kinect (runs use 0.004, fitted on fr1/rpy); the generated depth noise is 0.0005 z^2 at most.
SOLVE = BackendParams(relinearize_skip=1, depth_noise_coeff=0.0015)


# --- a synthetic graph with exact ground truth ------------------------------------------------------

def true_poses(n_kf: int = N_KF) -> np.ndarray:
    """Camera-to-world poses along a gently curving path: 0.1 m steps, a few degrees of rotation."""
    poses = []
    for k in range(n_kf):
        R = so3_exp(np.radians([2.0 * np.sin(k), 3.0 * k / n_kf, 1.0 * np.cos(k)]))
        poses.append(make_pose(R, [0.1 * k, 0.02 * np.sin(k), 0.03 * k]))
    return np.array(poses)


def project(T_wc: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """uv = K (T_cw X) and depth z of world points (N,3)."""
    Xc = transform_points(invert(T_wc), np.atleast_2d(X))
    return np.stack([FX * Xc[:, 0] / Xc[:, 2] + CX, FY * Xc[:, 1] / Xc[:, 2] + CY], 1), Xc[:, 2]


def visible_points(poses: np.ndarray, n: int, rng: np.random.Generator, margin: float = 10.0) -> np.ndarray:
    """n world points 2-4 m ahead that every keyframe sees inside the image."""
    pts = np.zeros((0, 3))
    while len(pts) < n:
        X = rng.uniform([-1.5, -1.0, 2.0], [2.2, 1.0, 4.0], size=(4 * n, 3))
        ok = np.ones(len(X), bool)
        for T in poses:
            uv, z = project(T, X)
            ok &= (uv[:, 0] > margin) & (uv[:, 0] < W - margin) & (uv[:, 1] > margin) & (uv[:, 1] < H - margin)
            ok &= z > 0.5
        pts = np.vstack([pts, X[ok]])
    return pts[:n]


def perturb(T: np.ndarray, rng: np.random.Generator, sigma_t: float = 0.03, sigma_deg: float = 2.0) -> np.ndarray:
    xi = np.r_[np.radians(sigma_deg) * rng.normal(size=3), sigma_t * rng.normal(size=3)] / np.sqrt(3)
    return T @ se3_exp(xi)


@pytest.fixture(params=[FactorGraphBackend, LocalWindowBackend], ids=["isam2", "window"])
def graph_type(request):
    """Both graph back ends answer the same calls and must reach the same solutions here: the first
    update's window holds every keyframe added since the last one (all 8), and later updates adjust 6
    of them against the other 2 held fixed at values already solved."""
    return request.param


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    poses = true_poses()
    return poses, visible_points(poses, N_PTS, np.random.default_rng(0))


def build_graph(poses: np.ndarray, points: np.ndarray, seed: int = 1, px_noise: float = 0.0,
                depth_noise: float = 0.0, stereo_keyframes=None, params: BackendParams | None = None,
                graph_type=FactorGraphBackend) -> FactorGraphBackend:
    """Keyframes with noisy guesses (3 cm, 2 deg; keyframe 0 exact, it carries the gauge prior),
    landmarks with 5 cm noisy guesses, and one observation per (keyframe, point) computed from the
    true poses. ``stereo_keyframes``: keyframes whose observations carry depth (default all)."""
    rng = np.random.default_rng(seed)
    graph = graph_type(params or SOLVE, CAL)
    for k, T in enumerate(poses):
        graph.add_keyframe(k, T if k == 0 else perturb(T, rng))
    for j, X in enumerate(points):
        graph.add_landmark(j, X + rng.normal(scale=0.05, size=3))
    for k, T in enumerate(poses):
        uv, z = project(T, points)
        uv = uv + rng.normal(scale=px_noise, size=uv.shape)
        z = z + rng.normal(scale=1.0, size=z.shape) * depth_noise * z**2
        stereo = stereo_keyframes is None or k in stereo_keyframes
        for j in range(len(points)):
            graph.add_observation(k, j, uv[j], depth=float(z[j]) if stereo else 0.0)
    return graph


def pose_errors(graph: FactorGraphBackend, poses: np.ndarray) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) error over all keyframes."""
    ids, est = graph.keyframe_poses()
    assert list(ids) == list(range(len(poses)))
    errs = np.array([pose_distance(est[i], poses[k]) for i, k in enumerate(ids)])
    return float(errs[:, 0].max()), float(errs[:, 1].max())


def landmark_errors(graph: FactorGraphBackend, points: np.ndarray) -> np.ndarray:
    ids, xyz = graph.landmark_positions()
    assert list(ids) == list(range(len(points)))
    return np.linalg.norm(xyz - points[ids], axis=1)


def max_pose_change(a: np.ndarray, b: np.ndarray) -> float:
    return max(pose_distance(x, y)[0] for x, y in zip(a, b))


# --- isolation --------------------------------------------------------------------------------------

def test_backend_params_defaults_are_the_config_defaults():
    """One set of defaults: a standalone FactorGraphBackend(BackendParams(), ...) computes what a run
    with the default config does."""
    params, config = BackendParams(), BackendConfig()
    shared = [name for name in vars(params) if name in BackendConfig.model_fields]
    assert len(shared) == 7
    for name in shared:
        assert getattr(params, name) == getattr(config, name), name
    assert BackendParams.from_config(config) == params
    custom = config.model_copy(update={"relinearize_skip": 2, "depth_noise_coeff": 0.05})
    assert (BackendParams.from_config(custom).relinearize_skip, BackendParams.from_config(custom).depth_noise_coeff) \
        == (2, 0.05)


def test_backend_imports_without_frontend():
    code = ("import backend.graph, backend.local_mapping, sys; "
            "assert not any(m.startswith('frontend') for m in sys.modules), "
            "sorted(m for m in sys.modules if m.startswith('frontend'))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


# --- FactorGraphBackend: accuracy -------------------------------------------------------------------

def test_noise_free_stereo_recovers_exact_poses_and_landmarks(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    t_err, r_err = pose_errors(graph, poses)
    assert t_err < 1e-4 and r_err < 1e-2
    assert landmark_errors(graph, points).max() < 1e-4
    # The gauge prior, every observation and one weak prior per landmark.
    assert graph.num_factors == 1 + N_KF * N_PTS + N_PTS
    np.testing.assert_allclose(graph.keyframe_pose(3), poses[3], atol=1e-4)


def test_noisy_stereo_recovers_poses_within_5mm_and_landmarks_within_1cm(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, seed=10, px_noise=0.3, depth_noise=0.0005, graph_type=graph_type)
    graph.update()
    t_err, r_err = pose_errors(graph, poses)
    assert t_err < 0.005, t_err
    assert r_err < 0.2, r_err
    assert landmark_errors(graph, points).max() < 0.01


def test_mono_observations_work_when_the_landmark_has_a_stereo_observation(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, stereo_keyframes={0}, graph_type=graph_type)  # depth from keyframe 0 only
    graph.update()
    t_err, _ = pose_errors(graph, poses)
    assert t_err < 1e-4
    assert landmark_errors(graph, points).max() < 1e-4

    noisy = build_graph(poses, points, seed=11, px_noise=0.3, depth_noise=0.0005, stereo_keyframes={0, 4},
                        graph_type=graph_type)
    noisy.update()
    assert pose_errors(noisy, poses)[0] < 0.005
    errors = landmark_errors(noisy, points)  # depth from 2 of 8 keyframes: the depth noise averages less
    assert np.sqrt(np.mean(errors**2)) < 0.01 and errors.max() < 0.02


def test_keyframe_and_landmark_ids_need_not_be_contiguous_or_sorted(graph_type):
    poses = true_poses(4)
    points = visible_points(poses, 60, np.random.default_rng(5))
    kf_ids, lm_ids = [7, 2, 30, 11], list(range(1000, 1060))[::-1]
    graph = graph_type(BackendParams(), CAL)
    for kf, T in zip(kf_ids, poses):
        graph.add_keyframe(kf, T)
    for lm, X in zip(lm_ids, points):
        graph.add_landmark(lm, X)
    for kf, T in zip(kf_ids, poses):
        uv, z = project(T, points)
        for lm, p, d in zip(lm_ids, uv, z):
            graph.add_observation(kf, lm, p, depth=float(d))
    graph.update()
    ids, est = graph.keyframe_poses()
    assert list(ids) == sorted(kf_ids)
    for i, kf in enumerate(ids):
        np.testing.assert_allclose(est[i], poses[kf_ids.index(kf)], atol=1e-6)
    lids, xyz = graph.landmark_positions()
    assert list(lids) == sorted(lm_ids)
    np.testing.assert_allclose(xyz, points[[lm_ids.index(j) for j in lids]], atol=1e-6)
    assert graph.has_keyframe(30) and not graph.has_keyframe(3)
    assert graph.has_landmark(1000) and not graph.has_landmark(0)


# --- relative poses and robust kernels ---------------------------------------------------------------

def test_relative_pose_alone_places_a_keyframe(scene, graph_type):
    """A keyframe without observations is determined by its relative-pose factor only."""
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    T_extra = poses[-1] @ make_pose(so3_exp(np.radians([0.0, 5.0, 0.0])), [0.2, 0.0, 0.05])
    graph.add_keyframe(100, perturb(T_extra, np.random.default_rng(3)))
    handle = graph.add_relative_pose(N_KF - 1, 100, invert(poses[-1]) @ T_extra, sigma_t=0.01, sigma_r_deg=0.5,
                                     kernel=None)
    assert isinstance(handle, int)
    graph.update(extra_updates=3)
    np.testing.assert_allclose(graph.keyframe_pose(100), T_extra, atol=1e-4)
    ids, _ = graph.keyframe_poses()
    assert list(ids) == list(range(N_KF)) + [100]


def test_consistent_relative_pose_keeps_the_solution(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    before = graph.keyframe_poses()[1]
    for kernel in ("huber", "cauchy", None):
        graph.add_relative_pose(1, 6, invert(poses[1]) @ poses[6], sigma_t=0.002, sigma_r_deg=0.1, kernel=kernel)
    graph.update()
    assert max_pose_change(graph.keyframe_poses()[1], before) < 1e-4
    assert pose_errors(graph, poses)[0] < 1e-4


def _wrong_loop(poses: np.ndarray) -> np.ndarray:
    T = invert(poses[2]) @ poses[6]
    T[:3, 3] += [1.0, 0.0, 0.0]  # 1 m off
    return T


def test_cauchy_kernel_ignores_a_wrong_loop_and_removal_restores(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    base = graph.keyframe_poses()[1]
    n_factors = graph.num_factors
    handle = graph.add_relative_pose(2, 6, _wrong_loop(poses), sigma_t=0.002, sigma_r_deg=0.1, kernel="cauchy")
    graph.update()
    assert graph.num_factors == n_factors + 1
    assert max_pose_change(graph.keyframe_poses()[1], base) < 0.01
    graph.remove_factors([handle])
    graph.update()
    assert graph.num_factors == n_factors
    assert max_pose_change(graph.keyframe_poses()[1], base) < 1e-4
    assert pose_errors(graph, poses)[0] < 1e-4


def test_wrong_loop_without_kernel_does_move_the_solution_and_removal_restores(scene, graph_type):
    """The same wrong constraint without a robust kernel: shows the previous test has teeth."""
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    base = graph.keyframe_poses()[1]
    handle = graph.add_relative_pose(2, 6, _wrong_loop(poses), sigma_t=0.002, sigma_r_deg=0.1, kernel=None)
    graph.update()
    assert max_pose_change(graph.keyframe_poses()[1], base) > 0.05
    graph.remove_factors([handle])
    graph.update(extra_updates=3)
    assert max_pose_change(graph.keyframe_poses()[1], base) < 1e-3


def test_remove_factors_before_update_drops_the_pending_factor(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    base = graph.keyframe_poses()[1]
    n_factors = graph.num_factors
    handle = graph.add_relative_pose(2, 6, _wrong_loop(poses), sigma_t=0.002, sigma_r_deg=0.1, kernel=None)
    graph.remove_factors([handle])
    graph.update()
    assert graph.num_factors == n_factors
    assert max_pose_change(graph.keyframe_poses()[1], base) < 1e-3


# --- dynamic probability --------------------------------------------------------------------------

def test_dynamic_probability_reduces_the_influence_of_a_moving_point(scene, graph_type):
    """20 points that jump 0.5 m between keyframes 3 and 4: with dynamic_prob=0.99 on their
    observations they pull the keyframes far less than with dynamic_prob=0."""
    poses, points = scene
    moving = visible_points(poses, 20, np.random.default_rng(42))
    reference = build_graph(poses, points, graph_type=graph_type)
    reference.update(extra_updates=3)
    base = reference.keyframe_poses()[1]

    def solve(dynamic_prob: float) -> float:
        graph = build_graph(poses, points, graph_type=graph_type)
        for j, X in enumerate(moving):
            graph.add_landmark(500 + j, X)
            for k, T in enumerate(poses):
                uv, z = project(T, X + (np.array([0.5, 0.0, 0.0]) if k >= 4 else 0.0))
                graph.add_observation(k, 500 + j, uv[0], depth=float(z[0]), dynamic_prob=dynamic_prob)
        graph.update(extra_updates=3)
        return max_pose_change(graph.keyframe_poses()[1], base)

    static_influence, dynamic_influence = solve(0.0), solve(0.99)
    assert static_influence > 5e-4, "the moving points should visibly disturb an unweighted solution"
    assert dynamic_influence < 0.25 * static_influence, (static_influence, dynamic_influence)


# --- errors -----------------------------------------------------------------------------------------

@pytest.fixture
def small_graph(graph_type) -> FactorGraphBackend:
    graph = graph_type(BackendParams(), CAL)
    graph.add_keyframe(0, np.eye(4))
    graph.add_keyframe(1, make_pose(np.eye(3), [0.1, 0.0, 0.0]))
    graph.add_landmark(5, np.array([0.0, 0.0, 2.0]))
    return graph


def test_unknown_keyframe_in_observation_names_the_id(small_graph):
    with pytest.raises(BackendError, match=r"keyframe 77\b"):
        small_graph.add_observation(77, 5, (320.0, 240.0), depth=2.0)


def test_unknown_landmark_in_observation_names_the_id(small_graph):
    with pytest.raises(BackendError, match=r"landmark 4242\b"):
        small_graph.add_observation(0, 4242, (320.0, 240.0), depth=2.0)
    with pytest.raises(BackendError, match=r"landmark 4242\b"):
        small_graph.add_observation(0, 4242, (320.0, 240.0))


def test_duplicate_variables_raise(small_graph):
    with pytest.raises(BackendError, match=r"keyframe 1\b"):
        small_graph.add_keyframe(1, np.eye(4))
    with pytest.raises(BackendError, match=r"landmark 5\b"):
        small_graph.add_landmark(5, np.zeros(3))


def test_unknown_kernel_raises(small_graph):
    with pytest.raises(BackendError, match="tukey"):
        small_graph.add_relative_pose(0, 1, np.eye(4), sigma_t=0.05, sigma_r_deg=2.0, kernel="tukey")


def test_relative_pose_to_unknown_keyframe_raises(small_graph):
    with pytest.raises(BackendError, match=r"keyframe 9\b"):
        small_graph.add_relative_pose(0, 9, np.eye(4), sigma_t=0.05, sigma_r_deg=2.0)
    with pytest.raises(BackendError, match=r"keyframe 9\b"):
        small_graph.add_relative_pose(9, 0, np.eye(4), sigma_t=0.05, sigma_r_deg=2.0)


def test_pose_before_update_raises(small_graph):
    with pytest.raises(BackendError, match="update"):
        small_graph.keyframe_pose(0)
    ids, poses = small_graph.keyframe_poses()
    assert len(ids) == 0 and len(poses) == 0


def test_remove_factors_rejects_unknown_handles(scene, graph_type):
    poses, points = scene
    graph = build_graph(poses, points, graph_type=graph_type)
    graph.update()
    with pytest.raises(BackendError, match="unknown factor handle"):
        graph.remove_factors([10**9])
