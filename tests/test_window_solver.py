"""The window's own bundle adjustment (backend/window_solver.py) against GTSAM's: each observation factor
linearised as GTSAM linearises it (stereo and projection, inside and beyond the Huber threshold, behind the
camera), and whole adjustments ending where GTSAM's Levenberg-Marquardt ends."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from backend import window_solver_kernels as kernels
from backend.factors import BackendParams, FactorBuilder, pose3
from backend.window_graph import LocalWindowBackend, WindowParams
from conftest import RING_CALIBRATION as CAL, ring_poses, wall_points
from slam.core.geometry import make_pose, pose_distance, so3_exp, transform_points


def _kernel_linearization(T_wc, xyz, meas, sqrt_info, huber_k):
    Jp, Jl, e = np.zeros((1, 3, 6)), np.zeros((1, 3, 3)), np.zeros((1, 3))
    cost = kernels.linearize(T_wc[None], 1, xyz[None], np.zeros(1, np.int64), np.zeros(1, np.int64), meas[None],
                             sqrt_info[None], np.array([huber_k]), CAL.fx, CAL.fy, CAL.cx, CAL.cy, CAL.baseline,
                             Jp, Jl, e)
    return cost, np.concatenate([Jp[0], Jl[0]], axis=1), e[0]


@pytest.mark.parametrize("case", ["stereo", "stereo beyond huber", "mono", "mono beyond huber", "stereo behind",
                                  "mono behind"])
def test_an_observation_linearises_as_gtsams_factor(case):
    """The normal equations' contribution (J'J, J'e) and the cost of one observation equal GTSAM's for the
    factor ``FactorBuilder.observation`` builds from the same measurement (whitening may differ by a
    rotation of the rows, which neither changes)."""
    builder = FactorBuilder(BackendParams(), CAL)
    T_wc = make_pose(so3_exp([0.1, -0.2, 0.05]), [0.3, -0.1, 0.2])
    xyz = transform_points(T_wc, np.array([[0.4, -0.3, 2.5]]))[0]
    if "behind" in case:
        xyz = transform_points(T_wc, np.array([[0.4, -0.3, -1.0]]))[0]
    true_uv = np.array([CAL.fx * 0.4 / 2.5 + CAL.cx, CAL.fy * -0.3 / 2.5 + CAL.cy])
    offset = np.array([9.0, -7.0]) if "beyond" in case else np.array([0.4, -0.3])
    depth = 2.45 if case.startswith("stereo") else 0.0
    uv = true_uv + offset
    factor = builder.observation(0, 0, uv, depth=depth, level_scale=1.2, dynamic_prob=0.3)
    meas, sqrt_info, huber_k = builder.observation_arrays(uv, depth=depth, level_scale=1.2, dynamic_prob=0.3)
    values = gtsam.Values()
    values.insert(X(0), pose3(T_wc))
    values.insert(L(0), xyz)
    A, b = factor.linearize(values).jacobian()
    cost, J, e = _kernel_linearization(T_wc, xyz, meas, sqrt_info, huber_k)
    np.testing.assert_allclose(cost, factor.error(values), rtol=1e-9)
    np.testing.assert_allclose(J.T @ J, A.T @ A, rtol=1e-7, atol=1e-9 * np.abs(A.T @ A).max())
    np.testing.assert_allclose(-J.T @ e, A.T @ b, rtol=1e-7, atol=1e-9 * np.abs(A.T @ b).max() + 1e-12)
    if "behind" in case:
        assert not J.any()                # GTSAM's factors give up on a point behind the camera


def _noisy_problem(solver: str, seed: int = 5) -> tuple[LocalWindowBackend, np.ndarray]:
    """Twelve keyframes round the ring with guesses 5 cm / 2 deg off, 1 px noise, a fifth of the keypoints
    without depth and 3 % gross outliers (20-40 px), an odometry factor per step; no update on the way."""
    n = 12
    poses = ring_poses(n)
    local, owner = wall_points(np.tile(np.eye(4), (n, 1, 1)), np.random.default_rng(3))
    points = np.vstack([transform_points(poses[k], local[owner == k]) for k in range(n)])
    rng = np.random.default_rng(seed)
    graph = LocalWindowBackend(BackendParams(), CAL, WindowParams(window_keyframes=4, max_fixed_keyframes=3,
                                                                  solver=solver))
    guesses = [poses[0]] + [poses[k] @ make_pose(so3_exp(np.radians(rng.normal(0, 2.0, 3))), rng.normal(0, 0.05, 3))
                            for k in range(1, n)]
    for k in range(n):
        graph.add_keyframe(k, guesses[k])
        if k:
            graph.add_relative_pose(k - 1, k, np.linalg.solve(poses[k - 1], poses[k]), 0.05, 2.0)
        for j in np.flatnonzero(owner == k):
            graph.add_landmark(int(j), points[j] + rng.normal(0, 0.05, 3))
    for k in range(n):
        ids = np.flatnonzero((owner >= k - 2) & (owner <= k))
        Xc = transform_points(np.linalg.inv(poses[k]), points[ids])
        uv = np.column_stack([CAL.fx * Xc[:, 0] / Xc[:, 2] + CAL.cx, CAL.fy * Xc[:, 1] / Xc[:, 2] + CAL.cy])
        uv += rng.normal(0, 1.0, uv.shape)
        outlier = rng.random(len(uv)) < 0.03
        uv[outlier] += rng.uniform(20, 40, (outlier.sum(), 2)) * rng.choice([-1, 1], (outlier.sum(), 2))
        with_depth = rng.random(len(uv)) > 0.2
        for j, p, z, d in zip(ids, uv, Xc[:, 2], with_depth):
            graph.add_observation(k, int(j), p, depth=float(z) if d else 0.0, level_scale=1.0)
    return graph, poses


def test_a_window_ends_where_gtsams_levenberg_marquardt_ends():
    """One window adjustment with the run's rules (10 iterations at most, stop under 1 % gain) from the same
    state: the keyframes end within 1 % of how far the adjustment moved them from where GTSAM's end (GTSAM's
    fixed keyframes are variables under a 1e-6 prior, and the two retract a step differently at second
    order, so the iterates differ slightly)."""
    results = {}
    for solver in ("gtsam", "schur"):
        graph, _ = _noisy_problem(solver)
        start = graph._poses.sorted()[1]
        graph.update()
        results[solver] = graph.keyframe_poses()
    ids, gtsam_poses = results["gtsam"]
    np.testing.assert_array_equal(ids, results["schur"][0])
    moved = max(pose_distance(a, b)[0] for a, b in zip(start, gtsam_poses))
    apart = [pose_distance(a, b) for a, b in zip(gtsam_poses, results["schur"][1])]
    assert moved > 0.01                                  # the window did move (guesses 5 cm off)
    assert max(t for t, _ in apart) < 0.01 * moved, (moved, apart)
    assert max(r for _, r in apart) < 0.01, apart        # degrees


def test_the_whole_map_converges_to_gtsams_optimum():
    """optimize_all to convergence with both solvers: the same optimum (keyframes within 0.01 mm, landmarks
    within 0.1 mm), closer to the truth than the guesses."""
    results = {}
    for solver in ("gtsam", "schur"):
        graph, poses = _noisy_problem(solver)
        graph.window = WindowParams(**{**graph.window.__dict__, "final_relative_tol": 1e-12})
        graph.optimize_all(iterations=100)
        results[solver] = (graph.keyframe_poses()[1], graph.landmark_positions()[1])
    (pg, lg), (ps, ls) = results["gtsam"], results["schur"]
    assert max(pose_distance(a, b)[0] for a, b in zip(pg, ps)) < 1e-5
    assert np.abs(lg - ls).max() < 1e-4
    assert max(pose_distance(a, b)[0] for a, b in zip(ps, poses)) < 0.01
