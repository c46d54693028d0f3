"""SE(3) helpers on 4x4 numpy matrices. Convention: T_ab maps points from frame b into frame a."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of (3,) or (N,3) vectors: (3,3) or (N,3,3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for a rotation vector."""
    return _so3_exp_and_left_jacobian(omega)[0]


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, robust near 0 and pi (scipy's quaternion route)."""
    return Rotation.from_matrix(R).as_rotvec()


def _so3_left_jacobian(omega: np.ndarray) -> np.ndarray:
    """V in t = V v: how a twist's translation part becomes the pose's translation."""
    return _so3_exp_and_left_jacobian(omega)[1]


def _so3_exp_and_left_jacobian(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Rodrigues' R, left Jacobian V) from one K and K^2, the coefficients on Python floats: the pose
    optimiser calls ``se3_exp`` ~40 times a frame, and numpy scalars cost twice as much there."""
    wx, wy, wz = (float(w) for w in np.asarray(omega, dtype=float).reshape(3))
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    if theta < 1e-10:
        return np.eye(3) + K, np.eye(3) + 0.5 * K
    K2 = K @ K
    t2 = theta * theta
    one_minus_cos = (1 - math.cos(theta)) / t2
    R = np.eye(3) + (math.sin(theta) / theta) * K + one_minus_cos * K2
    V = np.eye(3) + one_minus_cos * K + ((theta - math.sin(theta)) / (t2 * theta)) * K2
    return R, V


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Pose from a twist (omega, v): rotation part first, as in GTSAM's Pose3.Expmap."""
    xi = np.asarray(xi, dtype=float)
    R, V = _so3_exp_and_left_jacobian(xi[:3])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ xi[3:]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist (omega, v) of a pose, the inverse of ``se3_exp``."""
    omega = so3_log(T[:3, :3])
    return np.r_[omega, np.linalg.solve(_so3_left_jacobian(omega), T[:3, 3])]


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.ravel(t)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4,4) or many (N,4,4) rigid transforms without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T, dtype=float)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T (4,4) to points (N,3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle of one or many rotation matrices in degrees."""
    trace = np.trace(R, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def pose_distance(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of the relative transform between two poses."""
    D = invert(T_a) @ T_b
    return float(np.linalg.norm(D[:3, 3])), float(rotation_angle_deg(D[:3, :3]))


def relative_pose_residual(T_wa: np.ndarray, T_wb: np.ndarray, T_ab: np.ndarray) -> tuple[float, float]:
    """How far poses a and b disagree with a measured relative pose T_ab (a loop, an odometry edge):
    translation (m) and rotation (deg) of T_ab^-1 T_wa^-1 T_wb."""
    E = np.linalg.solve(T_ab, np.linalg.solve(T_wa, T_wb))
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(E[:3, 3])), float(angle)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project a pose's rotation back onto SO(3) (nearest rotation by SVD).

    Chains of products (velocity model, composed relative poses) accumulate rounding error that
    otherwise grows geometrically, since each prediction multiplies the previous error in.
    """
    out = T.copy()
    out[:3, :3] = nearest_rotations(T[:3, :3])
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def nearest_rotations(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to each 3x3 matrix of ``R`` ((3, 3) or (n, 3, 3)), by SVD: U V^T, with U's last
    column negated where that product would be a reflection."""
    U, _, Vt = np.linalg.svd(R)
    out = U @ Vt
    flip = np.linalg.det(out) < 0
    if np.any(flip):
        U = U.copy()
        U[..., :, -1] = np.where(flip[..., None], -U[..., :, -1], U[..., :, -1])
        out = U @ Vt
    return out
