"""Pose-only optimisation of one frame against fixed 3-D points (ORB-SLAM's PoseOptimization).

Gauss-Newton on SE(3) with a Huber kernel, run in rounds: after each round every observation is
classified by its chi-square (7.815 for 3-DOF stereo, 5.991 for 2-DOF mono) and outliers are left
out of the next round, but re-tested, so a point wrongly rejected early can come back. The robust
kernel is dropped in the last rounds, as ORB-SLAM does, once outliers are gone.

An optional prior (the motion model's prediction with a per-axis sigma) joins the normal equations as
one more Gaussian factor. The result also says how well the inliers alone fix the position (``sigma_t``):
a far wall is all a person filling the view may leave, and depth noise grows with z^2, so the forward
translation can be loose although every inlier agrees.

The per-observation work (residuals, Jacobians, the weighted normal equations) is a compiled loop (numba,
cache on disk): the optimisation runs up to 4 x 10 Gauss-Newton iterations twice a frame, and as numpy
array operations on a few hundred points each iteration cost ~0.1 ms of call overhead.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numba
import numpy as np

from slam.core.geometry import orthonormalize


@dataclass
class PoseObservations:
    points_w: np.ndarray    # (N,3) world points
    uv: np.ndarray          # (N,2) observed undistorted pixels
    u_right: np.ndarray     # (N,) virtual stereo u, NaN for mono observations
    information: np.ndarray  # (N,) scalar information (1/sigma^2), already weighted


@dataclass
class PosePrior:
    T_cw: np.ndarray         # the predicted pose
    information: np.ndarray  # (6,) 1/sigma^2 per twist axis (rotation rad, then translation m)


@dataclass
class PoseResult:
    T_cw: np.ndarray
    inliers: np.ndarray     # (N,) bool
    chi2: np.ndarray        # (N,)
    sigma_t: float = float("inf")   # largest translation standard deviation the inliers alone allow (m)
    # (3,3) covariance of the translation part of the left twist (points only, rotation marginalised;
    # NaN when the inliers do not fix it). To first order the camera centre moves by -R_cw^T v, so
    # R_cw^T cov_t R_cw is the centre's covariance in the world frame.
    cov_t: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))


# --- SE(3) in compiled code --------------------------------------------------------------------------------
# The exponential and logarithm of ``slam.core.geometry`` on 4 x 4 arrays and the 6 x 6 solve, for
# ``_gauss_newton``: called from Python, each of these small operations cost ~0.1 ms of numpy overhead, 40 times a
# frame. geometry's formulas (Rodrigues with its left Jacobian; the logarithm through the unit quaternion, as
# scipy's ``Rotation.as_rotvec``), with Taylor series below 1e-3 rad where geometry's closed forms lose digits
# (exp(xi) exp(-xi) is the identity to 4e-11 there at 1e-6 rad, to 1e-15 here; tests/test_pose_optimizer.py).
# They live in this module because numba's disk cache of ``_gauss_newton`` carries their machine code but is
# invalidated only by changes to *this* file: kept in another module, an edit there ran stale code (seen here).
# Not cached on their own: a function numba loads both inside a cached caller and alone returned arrays it
# could not hand back to Python ("NRT_adapt_ndarray_to_python: descr is NULL", numba 0.61, the tests' direct calls).
_UNCACHED = {"nogil": True}


@numba.njit(**_UNCACHED)
def _exp_so3_and_left_jacobian(wx, wy, wz):
    """(R, V) of the rotation vector (wx, wy, wz): Rodrigues' rotation and the left Jacobian that maps a
    twist's translation part to the pose's translation."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    R = np.eye(3)
    V = np.eye(3)
    if theta < 1e-10:
        return R + K, V + 0.5 * K
    K2 = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            K2[i, j] = K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j]
    t2 = theta * theta
    if theta < 1e-3:
        # Taylor series: 1 - cos and theta - sin cancel to a few digits at small angles (a Gauss-Newton step
        # near convergence is ~1e-6 rad), the series' next terms are below 1e-19.
        sin_over = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        one_minus_cos = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        theta_minus_sin = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        sin_over = math.sin(theta) / theta
        one_minus_cos = (1.0 - math.cos(theta)) / t2
        theta_minus_sin = (theta - math.sin(theta)) / (t2 * theta)
    R += sin_over * K + one_minus_cos * K2
    V += one_minus_cos * K + theta_minus_sin * K2
    return R, V


@numba.njit(**_UNCACHED)
def _exp_se3(xi):
    """Pose (4, 4) of a twist (omega, v), rotation part first (GTSAM's Pose3.Expmap)."""
    R, V = _exp_so3_and_left_jacobian(xi[0], xi[1], xi[2])
    T = np.eye(4)
    for i in range(3):
        for j in range(3):
            T[i, j] = R[i, j]
        T[i, 3] = V[i, 0] * xi[3] + V[i, 1] * xi[4] + V[i, 2] * xi[5]
    return T


@numba.njit(**_UNCACHED)
def _log_so3(R):
    """Rotation vector of R through its unit quaternion (the largest of the four components first, so no
    division by a small number), angle 2 atan2(|xyz|, w) with w >= 0, as scipy's from_matrix / as_rotvec."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)   # x, y, z, w
    k = 3
    best = tr
    for i in range(3):
        if R[i, i] > best:
            best, k = R[i, i], i
    if k == 3:
        q[3] = 1.0 + tr
        q[0], q[1], q[2] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[m] = R[m, i] + R[i, m]
        q[3] = R[m, j] - R[j, m]
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = -1.0 if q[3] < 0 else 1.0
    x, y, z, w = sign * q[0] / norm, sign * q[1] / norm, sign * q[2] / norm, sign * q[3] / norm
    s = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * math.atan2(s, w)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        scale = angle / math.sin(angle / 2.0)
    return np.array([scale * x, scale * y, scale * z])


@numba.njit(**_UNCACHED)
def _log_se3(T):
    """Twist (omega, v) of a pose, the inverse of ``_exp_se3``: v = V^-1 t with the closed-form inverse of the
    left Jacobian, I - K/2 + (1 - theta sin(theta) / (2 (1 - cos(theta)))) K^2 / theta^2."""
    omega = _log_so3(T[:3, :3])
    wx, wy, wz = omega[0], omega[1], omega[2]
    theta2 = wx * wx + wy * wy + wz * wz
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    if theta2 < 1e-8:
        c = 1.0 / 12.0                       # the series' first term: the closed form loses digits here
    else:
        theta = math.sqrt(theta2)
        c = (1.0 - theta * math.sin(theta) / (2.0 * (1.0 - math.cos(theta)))) / theta2
    out = np.empty(6)
    out[:3] = omega
    for i in range(3):
        s = T[i, 3]
        for j in range(3):
            k2 = K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j]
            s += (-0.5 * K[i, j] + c * k2) * T[j, 3]
        out[3 + i] = s
    return out


@numba.njit(**_UNCACHED)
def _solve_spd(A, b):
    """x with A x = b for a symmetric positive definite A (Cholesky), and whether A was positive definite
    (otherwise x is zero)."""
    n = A.shape[0]
    L = np.zeros((n, n))
    x = np.zeros(n)
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return x, False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    y = np.zeros(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x, True


@numba.njit(**_UNCACHED)
def _compose(A, B):
    """A @ B of two 4 x 4 poses, in loops (no BLAS call)."""
    C = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j] + A[i, 3] * B[3, j]
    return C


@numba.njit(**_UNCACHED)
def _invert(T):
    """Inverse of a rigid 4 x 4 transform: (R^T, -R^T t)."""
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = T[j, i]
        out[i, 3] = -(T[0, i] * T[0, 3] + T[1, i] * T[1, 3] + T[2, i] * T[2, 3])
    out[3, 3] = 1.0
    return out


@numba.njit(nogil=True, cache=True)
def _point_terms(T, X, uv, u_right, fx, fy, cx, cy, bf, e, J):
    """One observation's residual e = z - h(T X) (into ``e`` (3,)) and its Jacobian wrt a left twist (into ``J``
    (3,6)); returns the point's depth in the camera (unclamped).

    Row by row in closed form: d(pc)/d(xi) = [-[pc]x | I] for T <- exp(xi) T, xi = (omega, v), times the
    projection's derivative (a, 0, c) for u, (0, b, d) for v, (a, 0, g) for the virtual right u (zero for a
    mono observation: ``u_right`` NaN)."""
    x = T[0, 0] * X[0] + T[0, 1] * X[1] + T[0, 2] * X[2] + T[0, 3]
    y = T[1, 0] * X[0] + T[1, 1] * X[1] + T[1, 2] * X[2] + T[1, 3]
    zc = T[2, 0] * X[0] + T[2, 1] * X[1] + T[2, 2] * X[2] + T[2, 3]
    iz = 1.0 / max(zc, 1e-6)
    u = fx * x * iz + cx
    e[0], e[1] = uv[0] - u, uv[1] - (fy * y * iz + cy)
    a, b = fx * iz, fy * iz
    iz2 = iz * iz
    c, d = -fx * x * iz2, -fy * y * iz2
    J[0, 0], J[0, 1], J[0, 2], J[0, 3], J[0, 4], J[0, 5] = c * y, a * zc - c * x, -a * y, a, 0.0, c
    J[1, 0], J[1, 1], J[1, 2], J[1, 3], J[1, 4], J[1, 5] = d * y - b * zc, -d * x, b * x, 0.0, b, d
    if np.isfinite(u_right):
        g = -(fx * x - bf) * iz2
        e[2] = u_right - (u - bf * iz)
        J[2, 0], J[2, 1], J[2, 2], J[2, 3], J[2, 4], J[2, 5] = g * y, a * zc - g * x, -a * y, a, 0.0, g
    else:
        e[2] = 0.0
        J[2, :] = 0.0
    return zc


@numba.njit(nogil=True, cache=True)
def _all_terms(T, points_w, uv, u_right, fx, fy, cx, cy, bf):
    n = len(points_w)
    e = np.empty((n, 3))
    J = np.empty((n, 3, 6))
    depth = np.empty(n)
    for i in range(n):
        depth[i] = _point_terms(T, points_w[i], uv[i], u_right[i], fx, fy, cx, cy, bf, e[i], J[i])
    return e, J, depth


def _residuals_and_jacobians(T_cw, obs: PoseObservations, fx, fy, cx, cy, bf):
    """Residuals e = z - h(T X) (N,3), Jacobians of h wrt a left twist (N,3,6), which observations are stereo
    and each point's depth in the camera (``_point_terms``)."""
    e, J, depth = _all_terms(np.ascontiguousarray(T_cw, dtype=np.float64), *_arrays(obs), float(fx), float(fy),
                             float(cx), float(cy), float(bf))
    return e, J, np.isfinite(obs.u_right), depth


def _arrays(obs: PoseObservations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.ascontiguousarray(obs.points_w, dtype=np.float64), np.ascontiguousarray(obs.uv, dtype=np.float64),
            np.ascontiguousarray(obs.u_right, dtype=np.float64))


@numba.njit(nogil=True, cache=True)
def _normal_equations(T, points_w, uv, u_right, information, active, threshold, robust, fx, fy, cx, cy, bf):
    """H = sum w J^T J and b = sum w J^T e over the observations, w = information, 0 for an inactive point or
    one behind the camera, times the Huber weight (threshold: the chi-square) when ``robust``."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    e = np.empty(3)
    J = np.empty((3, 6))
    for i in range(len(points_w)):
        if not active[i]:
            continue
        depth = _point_terms(T, points_w[i], uv[i], u_right[i], fx, fy, cx, cy, bf, e, J)
        if not depth > 1e-3:           # no meaningful projection: it must not vote
            continue
        w = information[i]
        if robust:
            r = np.sqrt(information[i] * (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]))
            delta = np.sqrt(threshold[i])
            if r > delta:
                w *= delta / max(r, 1e-12)
        for row in range(3):
            for j in range(6):
                wj = w * J[row, j]
                g[j] += wj * e[row]
                for k in range(j, 6):
                    H[j, k] += wj * J[row, k]
    for j in range(6):
        for k in range(j):
            H[j, k] = H[k, j]
    return H, g


@numba.njit(nogil=True, cache=True)
def _gauss_newton(T, points_w, uv, u_right, information, active, threshold, robust, fx, fy, cx, cy, bf,
                  iterations, use_prior, prior_T, prior_information):
    """Up to ``iterations`` Gauss-Newton steps T <- exp(step) T; stops early on a step under 1e-7 or a normal
    matrix that is not positive definite. The prior's residual log(T_prior T^-1) shrinks by the step (left
    twist): its Jacobian is the identity."""
    for _ in range(iterations):
        H, b = _normal_equations(T, points_w, uv, u_right, information, active, threshold, robust,
                                 fx, fy, cx, cy, bf)
        if use_prior:
            r = _log_se3(_compose(prior_T, _invert(T)))
            for j in range(6):
                H[j, j] += prior_information[j]
                b[j] += prior_information[j] * r[j]
        for j in range(6):
            H[j, j] += 1e-9
        step, ok = _solve_spd(H, b)
        if not ok:
            break
        T = _compose(_exp_se3(step), T)
        if math.sqrt(np.sum(step * step)) < 1e-7:
            break
    return T


def optimize_pose(T_cw: np.ndarray, obs: PoseObservations, camera, iterations: int = 10, rounds: int = 4,
                  chi2_mono: float = 5.991, chi2_stereo: float = 7.815,
                  prior: Optional[PosePrior] = None) -> PoseResult:
    """Refine T_cw; returns the pose, the inlier mask and each observation's final chi-square."""
    fx, fy, cx, cy, bf = camera.fx, camera.fy, camera.cx, camera.cy, camera.bf
    n = len(obs.points_w)
    active = np.ones(n, bool)
    T = np.array(T_cw, dtype=np.float64)
    chi2 = np.zeros(n)
    threshold = np.where(np.isfinite(obs.u_right), chi2_stereo, chi2_mono)
    points_w, uv, u_right = _arrays(obs)
    information = np.ascontiguousarray(obs.information, dtype=np.float64)
    args = (float(fx), float(fy), float(cx), float(cy), float(bf))
    use_prior = prior is not None
    prior_T = np.ascontiguousarray(prior.T_cw, dtype=np.float64) if use_prior else np.eye(4)
    prior_information = np.ascontiguousarray(prior.information, dtype=np.float64) if use_prior else np.zeros(6)
    for round_idx in range(rounds):
        T = _gauss_newton(T, points_w, uv, u_right, information, active, threshold, round_idx < 2, *args,
                          int(iterations), use_prior, prior_T, prior_information)
        e, J, depth = _all_terms(T, points_w, uv, u_right, *args)
        chi2 = information * np.einsum("ij,ij->i", e, e)
        active = (chi2 <= threshold) & (depth > 1e-3)
        if active.sum() < 10:
            break
    cov_t = _translation_covariance(J, obs.information, active)
    sigma_t = float(np.sqrt(max(np.linalg.eigvalsh(cov_t).max(), 0.0))) if np.isfinite(cov_t).all() else float("inf")
    return PoseResult(orthonormalize(T), active, chi2, sigma_t, cov_t)


def _translation_covariance(J: np.ndarray, information: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """Translation block of the points-only covariance (H^-1); sqrt of its largest eigenvalue is how far
    along its weakest direction the inliers let the camera slide (the prior left out: it says how well
    the map alone places the frame). NaN when fewer than 3 inliers or H is singular."""
    nan = np.full((3, 3), np.nan)
    if inliers.sum() < 3:
        return nan
    Jw = (J * (information * inliers)[:, None, None]).reshape(-1, 6)
    H = Jw.T @ J.reshape(-1, 6)
    try:
        covariance = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return nan
    return covariance[3:, 3:]
