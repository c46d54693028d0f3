"""The window's bundle adjustment solved here instead of by GTSAM (``backend.window_solver: schur``).

The same cost as the GTSAM graph ``LocalWindowBackend`` builds (``backend.factors``): every observation factor
(written out in ``window_solver_kernels``), each landmark's weak prior, and the pose factors (odometry and loop
relative poses, the first keyframe's prior), which are few and stay GTSAM's own (linearised by GTSAM, their
whitened Jacobians added to the pose system). Levenberg-Marquardt as GTSAM runs it (its defaults: lambda from
1e-5, x10 / /10, up to 1e5, the step kept when the cost falls by more than 1e-3 of what the linear model
promised; the same stopping rules), but each step solves the normal equations by eliminating the landmarks
first (the Schur complement of bundle adjustment: a 3x3 block per landmark, then a dense 6n system for the
window's n keyframes) in compiled loops. Why: GTSAM's elimination costs ~14 us per landmark in its generic
Bayes-net machinery (Bonn crowd-480: linearising 10-13 ms and eliminating 13-24 ms per step of a ~8,000-factor
window), the worker's largest CPU cost per keyframe.

Fixed keyframes are constants here (GTSAM holds them with a 1e-6 prior, which moves them by nanometres).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X
from scipy.linalg import cho_factor, cho_solve

from backend import window_solver_kernels as kernels
from backend.factors import BackendError, StereoCalibration, pose3

# GTSAM's LevenbergMarquardtParams defaults (the GTSAM path sets only the iterations, the relative tolerance,
# the ordering and the linear solver).
_LAMBDA_INITIAL = 1e-5
_LAMBDA_FACTOR = 10.0
_LAMBDA_UPPER = 1e5
_MIN_MODEL_FIDELITY = 1e-3
_ABSOLUTE_TOL = 1e-5


class ObservationArrays:
    """Per factor handle: an observation's measurement (u_L, u_R, v; u_R 0 without depth), its noise's
    square-root information (3x3; the u_R row 0 without depth) and its Huber threshold."""

    def __init__(self) -> None:
        self.meas = np.zeros((1024, 3))
        self.sqrt_info = np.zeros((1024, 3, 3))
        self.huber_k = np.zeros(1024)

    def add(self, handle: int, meas: np.ndarray, sqrt_info: np.ndarray, huber_k: float) -> None:
        if handle >= len(self.huber_k):
            grow = max(handle + 1, 2 * len(self.huber_k)) - len(self.huber_k)
            self.meas = np.concatenate([self.meas, np.zeros((grow, 3))])
            self.sqrt_info = np.concatenate([self.sqrt_info, np.zeros((grow, 3, 3))])
            self.huber_k = np.concatenate([self.huber_k, np.zeros(grow)])
        self.meas[handle], self.sqrt_info[handle], self.huber_k[handle] = meas, sqrt_info, huber_k


@dataclass
class WindowProblem:
    """One adjustment: poses (adjusted first, then fixed), landmarks, and the factors over them."""

    poses: np.ndarray            # (P,4,4) T_wc; the first ``n_adj`` are adjusted
    n_adj: int
    pose_ids: Sequence[int]      # keyframe id of each pose row
    points: np.ndarray           # (M,3)
    o_pose: np.ndarray           # (K,) pose row of each observation
    o_pt: np.ndarray             # (K,) point row
    meas: np.ndarray             # (K,3)
    sqrt_info: np.ndarray        # (K,3,3)
    huber_k: np.ndarray          # (K,)
    prior_xyz: np.ndarray        # (M,3) each landmark's prior mean
    prior_w2: float              # 1 / sigma^2 of the landmark priors (0: none)
    pose_factors: list           # GTSAM factors on poses only (odometry, loops, the first keyframe's prior)


def _retract(poses: np.ndarray, dp: np.ndarray) -> np.ndarray:
    """T Exp(w) on the rotation, t + R v on the translation, for each pose and its step (w, v)."""
    out = poses.copy()
    w = dp[:, :3]
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = w / safe[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    dR = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    dR[small] = np.eye(3)
    R = poses[:, :3, :3]
    out[:, :3, :3] = R @ dR
    out[:, :3, 3] = poses[:, :3, 3] + np.einsum("nij,nj->ni", R, dp[:, 3:])
    return out


class _PoseFactors:
    """The pose-only factors, through GTSAM: their cost, and their whitened linearisation on the adjusted
    poses' rows of the reduced system."""

    def __init__(self, factors: list, pose_ids: Sequence[int], n_adj: int, poses: np.ndarray):
        self.factors = factors
        self.row_of = {int(k): i for i, k in enumerate(pose_ids)}
        self.n_adj = n_adj
        used = sorted({self.row_of[int(gtsam.Symbol(key).index())] for f in factors for key in f.keys()})
        self._moving = [(X(int(pose_ids[i])), i) for i in used if i < n_adj]
        self._fixed = [(X(int(pose_ids[i])), pose3(poses[i])) for i in used if i >= n_adj]   # never change

    def _values(self, poses: np.ndarray) -> gtsam.Values:
        values = gtsam.Values()
        for key, pose in self._fixed:
            values.insert(key, pose)
        for key, i in self._moving:     # rows this solver's retraction keeps orthonormal: no re-orthonormalising
            values.insert(key, gtsam.Pose3(poses[i]))
        return values

    def cost(self, poses: np.ndarray) -> float:
        if not self.factors:
            return 0.0
        values = self._values(poses)
        return float(sum(f.error(values) for f in self.factors))

    def linearize(self, poses: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, list[int]]]:
        """Per factor (A on the adjusted poses' columns, b, their rows): GTSAM's |A d - b|^2."""
        if not self.factors:
            return []
        values = self._values(poses)
        out = []
        for f in self.factors:
            A, b = f.linearize(values).jacobian()
            keys = f.keys()
            cols, rows = [], []
            for j, key in enumerate(keys):
                row = self.row_of[int(gtsam.Symbol(key).index())]
                if row < self.n_adj:
                    cols.append(np.arange(6 * j, 6 * j + 6))
                    rows.append(row)
            if rows:
                out.append((np.asarray(A)[:, np.concatenate(cols)], np.asarray(b, float), rows))
        return out


def _pose_system(linear_pose: list, n_adj: int) -> tuple[np.ndarray, np.ndarray]:
    """The pose factors' normal equations (A'A, A'b) on the adjusted poses' 6n unknowns; the landmarks' Schur
    complement is added to them (``window_solver_kernels.reduced_system``)."""
    S, g = np.zeros((6 * n_adj, 6 * n_adj)), np.zeros(6 * n_adj)
    for A, b, rows in linear_pose:
        idx = np.concatenate([np.arange(6 * r, 6 * r + 6) for r in rows])
        S[np.ix_(idx, idx)] += A.T @ A
        g[idx] += A.T @ b
    return S, g


def _pose_linear_cost(linear_pose: list, dp: np.ndarray) -> float:
    """0.5 |A d - b|^2 of the pose factors' linearisation for the poses' step ``dp``."""
    return 0.5 * sum(float(np.sum((A @ np.concatenate([dp[6 * r:6 * r + 6] for r in rows]) - b) ** 2))
                     for A, b, rows in linear_pose)


class _Observations:
    """The observation factors of one problem, linearised where their cost is evaluated: a trial step's cost
    leaves its Jacobians in ``trial``, which become ``current`` when the step is kept (each point is
    linearised once)."""

    def __init__(self, pb: WindowProblem, calibration: StereoCalibration):
        c = calibration
        self.n_adj, m = pb.n_adj, len(pb.points)
        order = np.argsort(pb.o_pt, kind="stable")                 # observations grouped by landmark
        self.lm_start = np.searchsorted(pb.o_pt[order], np.arange(m + 1)).astype(np.int64)
        self.lm_obs = order.astype(np.int64)
        self.o_pose, self.o_pt = pb.o_pose.astype(np.int64), pb.o_pt.astype(np.int64)
        k = len(self.o_pose)
        self.current = (np.zeros((k, 3, 6)), np.zeros((k, 3, 3)), np.zeros((k, 3)))     # Jp, Jl, e
        self.trial = (np.zeros((k, 3, 6)), np.zeros((k, 3, 3)), np.zeros((k, 3)))
        self._args = (pb.meas, pb.sqrt_info, pb.huber_k, c.fx, c.fy, c.cx, c.cy, c.baseline)

    def trial_cost(self, poses: np.ndarray, points: np.ndarray) -> float:
        return kernels.linearize(poses, self.n_adj, points, self.o_pose, self.o_pt, *self._args, *self.trial)

    def keep_trial(self) -> None:
        self.current, self.trial = self.trial, self.current


def solve(problem: WindowProblem, calibration: StereoCalibration, iterations: int,
          relative_tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Levenberg-Marquardt on ``problem``; returns (poses, points, iterations run). The fixed poses come back
    unchanged."""
    pb = problem
    n_adj = pb.n_adj
    obs = _Observations(pb, calibration)
    pose_factors = _PoseFactors(pb.pose_factors, pb.pose_ids, n_adj, pb.poses)

    def cost_of(poses, points) -> float:
        res = points - pb.prior_xyz
        return obs.trial_cost(poses, points) + 0.5 * pb.prior_w2 * float(np.sum(res * res)) + pose_factors.cost(poses)

    poses, points = pb.poses.copy(), pb.points.copy()
    lam = _LAMBDA_INITIAL
    current = cost_of(poses, points)
    obs.keep_trial()
    done = 0
    while done < iterations:
        before = current
        prior_res = points - pb.prior_xyz
        linear_pose = pose_factors.linearize(poses)
        old_linear = _linear_cost_now(obs, pb.prior_w2, prior_res, linear_pose)
        while True:
            step = _damped_step(obs, pb.prior_w2, prior_res, linear_pose, lam)
            success, stop = False, False
            if step is not None:
                dp, dl = step
                linear_change = old_linear - _linear_cost_of_step(obs, pb.prior_w2, prior_res, linear_pose, dp, dl)
                if linear_change >= 0:
                    new_poses = poses.copy()
                    new_poses[:n_adj] = _retract(poses[:n_adj], dp.reshape(-1, 6))
                    new_points = points + dl
                    new_cost = cost_of(new_poses, new_points)
                    cost_change = current - new_cost
                    if linear_change > np.finfo(float).eps * old_linear:
                        success = cost_change / linear_change > _MIN_MODEL_FIDELITY
                    else:
                        success = True
                    stop = abs(cost_change) < relative_tol * current
            if success:
                poses, points, current = new_poses, new_points, new_cost
                obs.keep_trial()                 # the new estimate's linearisation, made by its cost
                lam = lam / _LAMBDA_FACTOR
                break
            if stop:
                break
            lam *= _LAMBDA_FACTOR
            if lam >= _LAMBDA_UPPER:
                break
        done += 1
        decrease = before - current
        if current <= 0.0 or decrease <= _ABSOLUTE_TOL or decrease / before <= relative_tol:
            break
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(points))):
        raise BackendError("local bundle adjustment failed: the window's solution is not finite")
    return poses, points, done


def _linear_cost_now(obs: _Observations, prior_w2: float, prior_res: np.ndarray, linear_pose: list) -> float:
    """The linearised model's cost at the current estimate (no step): observations, landmark priors, pose factors."""
    e = obs.current[2]
    return 0.5 * float(np.sum(e * e)) + 0.5 * prior_w2 * float(np.sum(prior_res * prior_res)) \
        + 0.5 * sum(float(b @ b) for _, b, _ in linear_pose)


def _linear_cost_of_step(obs: _Observations, prior_w2: float, prior_res: np.ndarray, linear_pose: list,
                         dp: np.ndarray, dl: np.ndarray) -> float:
    """The linearised model's cost after the step (poses' ``dp``, landmarks' ``dl``)."""
    moved_prior = prior_res + dl
    return kernels.linear_cost(obs.o_pose, obs.o_pt, obs.n_adj, *obs.current, dp, dl) \
        + 0.5 * prior_w2 * float(np.sum(moved_prior * moved_prior)) + _pose_linear_cost(linear_pose, dp)


def _damped_step(obs: _Observations, prior_w2: float, prior_res: np.ndarray, linear_pose: list,
                 lam: float) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The step (poses' dp (6n), landmarks' dl (M,3)) of the system damped by ``lam``; None when it is not
    positive definite or not finite (GTSAM's Cholesky fails there too, and lambda grows)."""
    m = len(obs.lm_start) - 1
    S, g = _pose_system(linear_pose, obs.n_adj)
    Hinv, gl = np.zeros((m, 3, 3)), np.zeros((m, 3))
    W = kernels.reduced_system(obs.n_adj, obs.o_pose, obs.lm_start, obs.lm_obs, *obs.current, prior_w2, prior_res,
                               lam, S, g, Hinv, gl)
    try:
        dp = cho_solve(cho_factor(S, lower=False), g) if obs.n_adj else np.zeros(0)   # reads S's upper triangle
    except (np.linalg.LinAlgError, ValueError):     # ValueError: a non-finite system
        return None
    if not np.all(np.isfinite(dp)):
        return None
    dl = np.zeros((m, 3))
    kernels.back_substitute(obs.n_adj, obs.o_pose, obs.lm_start, obs.lm_obs, W, Hinv, gl, dp, dl)
    return dp, dl
