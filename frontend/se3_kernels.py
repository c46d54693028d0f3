"""SE(3) for compiled loops (numba): the exponential and logarithm of ``slam.core.geometry`` on 4 x 4 arrays,
and the 6 x 6 solve of a Gauss-Newton step.

The pose optimiser's iterations run inside one compiled function (``pose_optimizer._gauss_newton``); called
from Python, each of these small operations cost ~0.1 ms of numpy call overhead, 40 times a frame. The
formulas are ``geometry``'s (Rodrigues with its left Jacobian; the logarithm through the unit quaternion, as
scipy's ``Rotation.as_rotvec``), with Taylor series below 1e-3 rad where ``geometry``'s closed forms lose
digits (exp(xi) exp(-xi) is the identity to 4e-11 there at 1e-6 rad, to 1e-15 here;
tests/test_pose_optimizer.py).
"""
from __future__ import annotations

import math

import numba
import numpy as np

# Not cached on their own: the pose optimiser's cached ``_gauss_newton`` carries their machine code, and a
# function numba loads both inside a cached caller and on its own returns arrays it cannot hand back to
# Python ("NRT_adapt_ndarray_to_python: descr is NULL", seen with numba 0.61 on the tests' direct calls).
_JIT = {"nogil": True, "cache": False}


@numba.njit(**_JIT)
def so3_exp_and_left_jacobian(wx, wy, wz):
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


@numba.njit(**_JIT)
def se3_exp(xi):
    """Pose (4, 4) of a twist (omega, v), rotation part first (GTSAM's Pose3.Expmap)."""
    R, V = so3_exp_and_left_jacobian(xi[0], xi[1], xi[2])
    T = np.eye(4)
    for i in range(3):
        for j in range(3):
            T[i, j] = R[i, j]
        T[i, 3] = V[i, 0] * xi[3] + V[i, 1] * xi[4] + V[i, 2] * xi[5]
    return T


@numba.njit(**_JIT)
def _so3_log(R):
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


@numba.njit(**_JIT)
def se3_log(T):
    """Twist (omega, v) of a pose, the inverse of ``se3_exp``: v = V^-1 t with the closed-form inverse of the
    left Jacobian, I - K/2 + (1 - theta sin(theta) / (2 (1 - cos(theta)))) K^2 / theta^2."""
    omega = _so3_log(T[:3, :3])
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


@numba.njit(**_JIT)
def solve_spd(A, b):
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


@numba.njit(**_JIT)
def compose(A, B):
    """A @ B of two 4 x 4 poses, in loops (no BLAS call)."""
    C = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j] + A[i, 3] * B[3, j]
    return C


@numba.njit(**_JIT)
def invert(T):
    """Inverse of a rigid 4 x 4 transform: (R^T, -R^T t)."""
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = T[j, i]
        out[i, 3] = -(T[0, i] * T[0, 3] + T[1, i] * T[1, 3] + T[2, i] * T[2, 3])
    out[3, 3] = 1.0
    return out
