"""Fixed-interval smoothing of the final trajectory's camera positions with a motion model.

Each tracked frame's position is a measurement with the covariance its pose optimisation gives (the
inliers' information; a frame whose background is mostly hidden, e.g. by a person close to the camera,
is fixed loosely along some direction). Between frames the camera's acceleration is modelled as
zero-mean with ``sigma_acc`` per axis (the divided second difference of the positions). The smoothed
positions minimise

    sum_i (x_i - m_i)^T C_i^-1 (x_i - m_i)  +  sum_i |a_i(x)|^2 / sigma_acc^2

over each run of consecutive tracked frames (a LOST frame breaks the chain): a linear, sparse least
squares problem, solved exactly. A well-fixed frame (C_i of a few mm^2) barely moves; a loosely fixed
one follows its neighbours. A few Huber rounds (iteratively reweighted, at the pose optimisation's own
3-dof chi-square bound, ``tracking.chi2_stereo``) let a frame that is confidently wrong (a pose people
pulled: small C_i, far from its neighbours' motion) count less, as a robust kernel does for an outlier
observation. Rotations are left as estimated. The acceleration term is a discrete zero-mean
acceleration prior, as continuous-time trajectory estimators use; it needs the frames after a frame,
so it runs on the final trajectory, never online (``trajectory_online.txt`` keeps the causal estimate).
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

# A frame without a usable covariance (the first keyframe, whose pose is defined, not measured) is
# held at its position by this sigma.
_FIXED_SIGMA_M = 1e-4
# Robust rounds after the plain solve; a fixed number keeps the result deterministic.
_ROBUST_ROUNDS = 4


def smooth_positions(stamps: np.ndarray, positions: np.ndarray, covariances: np.ndarray, tracked: np.ndarray,
                     sigma_acc: float, huber_chi2: float) -> np.ndarray:
    """Smoothed copy of ``positions`` (N,3); untracked rows and runs shorter than 3 frames unchanged.

    ``covariances`` (N,3,3) of each position (NaN rows: held fixed); ``sigma_acc`` (m/s^2) > 0;
    ``huber_chi2``: the chi-square (3 dof) beyond which a frame's own term is down-weighted."""
    out = positions.copy()
    for start, stop in _runs(tracked):
        if stop - start >= 3:
            out[start:stop] = _smooth_run(stamps[start:stop], positions[start:stop], covariances[start:stop],
                                          sigma_acc, float(np.sqrt(huber_chi2)))
    return out


def _runs(tracked: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of consecutive True values."""
    edges = np.flatnonzero(np.diff(np.r_[0, tracked.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _smooth_run(t: np.ndarray, m: np.ndarray, cov: np.ndarray, sigma_acc: float, huber_k: float) -> np.ndarray:
    n = len(t)
    information = np.empty((n, 3, 3))
    usable = np.isfinite(cov).all(axis=(1, 2))
    information[~usable] = np.eye(3) / _FIXED_SIGMA_M**2
    if usable.any():
        # A tiny floor keeps a (numerically) singular covariance invertible: 0.1 mm is far below any noise.
        information[usable] = np.linalg.inv(cov[usable] + np.eye(3) * _FIXED_SIGMA_M**2)
    information = 0.5 * (information + information.transpose(0, 2, 1))
    h = np.maximum(np.diff(t), 1e-6)                           # (n-1,) frame intervals
    # a_i = 2/(h_{i-1}+h_i) * ((x_{i+1}-x_i)/h_i - (x_i-x_{i-1})/h_{i-1}),  i = 1..n-2
    c = 2.0 / (h[:-1] + h[1:]) / sigma_acc
    rows = np.repeat(np.arange(n - 2), 3)
    cols = (np.arange(n - 2)[:, None] + np.arange(3)).ravel()
    vals = np.stack([c / h[:-1], -c * (1.0 / h[:-1] + 1.0 / h[1:]), c / h[1:]], axis=1).ravel()
    D = sparse.csr_matrix((vals, (rows, cols)), shape=(n - 2, n))
    A = sparse.kron(D, sparse.identity(3), format="csr")
    AtA = A.T @ A
    blocks = np.arange(n)
    weights = np.ones(n)
    for round_idx in range(_ROBUST_ROUNDS + 1):
        W = sparse.bsr_matrix((information * weights[:, None, None], blocks, np.arange(n + 1)), shape=(3 * n, 3 * n))
        x = np.asarray(spsolve((W + AtA).tocsc(), W @ m.reshape(-1))).reshape(n, 3)
        if round_idx == _ROBUST_ROUNDS:
            break
        # Huber weights on each frame's own term (IRLS): a frame whose position disagrees with its
        # neighbours' motion by more than its covariance allows (a pose people pulled, confidently
        # wrong) counts less in the next round.
        d = x - m
        r = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", d, information, d), 0.0))
        weights = np.where(r <= huber_k, 1.0, huber_k / np.maximum(r, 1e-12))
        weights[~usable] = 1.0
    return x
