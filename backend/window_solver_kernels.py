"""Compiled loops of the window's own bundle adjustment (``backend/window_solver.py``): the observation
factors linearised, the Schur complement that eliminates the landmarks, and the landmarks' back-substitution.

The factors are the ones ``backend.factors.FactorBuilder.observation`` gives GTSAM, written out: a keypoint with
depth is a virtual stereo measurement (u_L, u_R, v), one without is (u, v) (its u_R row whitened to zero), both
whitened by their noise's square-root information and reweighted by a Huber kernel on the whitened norm, as
``gtsam.noiseModel.Robust`` does (block reweighting: every row by sqrt(w)). A point behind its camera gives the
constant error 2 fx and zero Jacobians, as GTSAM's stereo and projection factors do when their cheirality
check throws. A pose moves on the right, T_wc Exp([w, v]), GTSAM's tangent order: the Jacobians agree with
GTSAM's at the linearisation point whichever of its retractions it was built with.

numba, ``nogil`` and ``cache``; no ``fastmath``, no ``parallel``: the same input gives the same bits.
"""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _projection_row(T, p, x, y, z, gx, gy, gz, Jp_row, Jl_row):
    """The Jacobians of one projection row whose derivative by the point in the camera is (gx, gy, gz):
    d(pc)/d(pose) = [skew(pc), -I] (rows (0, -z, y), (z, 0, -x), (-y, x, 0) for the rotation), d(pc)/d(point) =
    R', so column c of the point's row is g . (row c of R)."""
    Jp_row[0] = gy * z - gz * y
    Jp_row[1] = gz * x - gx * z
    Jp_row[2] = gx * y - gy * x
    Jp_row[3] = -gx
    Jp_row[4] = -gy
    Jp_row[5] = -gz
    for c in range(3):
        Jl_row[c] = gx * T[p, c, 0] + gy * T[p, c, 1] + gz * T[p, c, 2]


@numba.njit(cache=True, nogil=True)
def _whiten(S, raw_r, raw_Jp, raw_Jl, k, e, Jp, Jl):
    """e = S r, J = S J_raw, then GTSAM's Huber block reweighting (every row by sqrt(w) beyond ``k``); returns
    the factor's cost (0.5 |e|^2 inside, k (|e| - k / 2) beyond)."""
    sq = 0.0
    for r in range(3):
        v = S[r, 0] * raw_r[0] + S[r, 1] * raw_r[1] + S[r, 2] * raw_r[2]
        e[r] = v
        sq += v * v
        for c in range(6):
            Jp[r, c] = S[r, 0] * raw_Jp[0, c] + S[r, 1] * raw_Jp[1, c] + S[r, 2] * raw_Jp[2, c]
        for c in range(3):
            Jl[r, c] = S[r, 0] * raw_Jl[0, c] + S[r, 1] * raw_Jl[1, c] + S[r, 2] * raw_Jl[2, c]
    norm = math.sqrt(sq)
    if norm <= k:
        return 0.5 * sq
    w = math.sqrt(k / norm)
    for r in range(3):
        e[r] *= w
        for c in range(6):
            Jp[r, c] *= w
        for c in range(3):
            Jl[r, c] *= w
    return k * (norm - 0.5 * k)


@numba.njit(cache=True, nogil=True)
def linearize(T, n_adj, points, o_pose, o_pt, meas, sqrt_info, huber_k, fx, fy, cx, cy, baseline,
              Jp, Jl, e):
    """Every observation's whitened, reweighted Jacobians (``Jp`` (K,3,6) on its pose, zero for a fixed one,
    ``Jl`` (K,3,3) on its point) and error ``e`` (K,3), written in place; returns the observations' cost
    (GTSAM's: 0.5 e'e inside the Huber threshold, k (|e| - k / 2) beyond)."""
    cost = 0.0
    raw_r = np.zeros(3)
    raw_Jp = np.zeros((3, 6))
    raw_Jl = np.zeros((3, 3))
    for i in range(len(o_pose)):
        p = o_pose[i]
        q = o_pt[i]
        d0 = points[q, 0] - T[p, 0, 3]
        d1 = points[q, 1] - T[p, 1, 3]
        d2 = points[q, 2] - T[p, 2, 3]
        x = T[p, 0, 0] * d0 + T[p, 1, 0] * d1 + T[p, 2, 0] * d2     # R' (point - t)
        y = T[p, 0, 1] * d0 + T[p, 1, 1] * d1 + T[p, 2, 1] * d2
        z = T[p, 0, 2] * d0 + T[p, 1, 2] * d1 + T[p, 2, 2] * d2
        if z <= 0.0:
            raw_r[0] = raw_r[1] = raw_r[2] = 2.0 * fx
            raw_Jp[:] = 0.0
            raw_Jl[:] = 0.0
        else:
            iz = 1.0 / z
            raw_r[0] = fx * x * iz + cx - meas[i, 0]
            raw_r[1] = fx * (x - baseline) * iz + cx - meas[i, 1]
            raw_r[2] = fy * y * iz + cy - meas[i, 2]
            # rows u_L, u_R, v: d(projection)/d(point in the camera)
            _projection_row(T, p, x, y, z, fx * iz, 0.0, -fx * x * iz * iz, raw_Jp[0], raw_Jl[0])
            _projection_row(T, p, x, y, z, fx * iz, 0.0, -fx * (x - baseline) * iz * iz, raw_Jp[1], raw_Jl[1])
            _projection_row(T, p, x, y, z, 0.0, fy * iz, -fy * y * iz * iz, raw_Jp[2], raw_Jl[2])
        cost += _whiten(sqrt_info[i], raw_r, raw_Jp, raw_Jl, huber_k[i], e[i], Jp[i], Jl[i])
        if p >= n_adj:
            Jp[i] = 0.0
    return cost


@numba.njit(cache=True, nogil=True)
def _inverse3(A, out):
    """out = A^-1 of a symmetric positive definite 3x3 (its adjugate over the determinant)."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]
    c02 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
    c11 = A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]
    c12 = A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]
    c22 = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    det = A[0, 0] * c00 + A[1, 0] * c01 + A[2, 0] * c02
    inv = 1.0 / det
    out[0, 0], out[0, 1], out[0, 2] = c00 * inv, c01 * inv, c02 * inv
    out[1, 0], out[1, 1], out[1, 2] = c01 * inv, c11 * inv, c12 * inv
    out[2, 0], out[2, 1], out[2, 2] = c02 * inv, c12 * inv, c22 * inv


@numba.njit(cache=True, nogil=True)
def _pose_blocks(n_adj, o_pose, Jp, e, S, g):
    """Every observation's own pose block Jp'Jp and gradient -Jp'e, added to ``S`` and ``g``."""
    for i in range(len(o_pose)):
        p = o_pose[i]
        if p >= n_adj:
            continue
        for a in range(6):
            acc = 0.0
            for r in range(3):
                acc += Jp[i, r, a] * e[i, r]
            g[6 * p + a] -= acc
            for b in range(6):
                h = 0.0
                for r in range(3):
                    h += Jp[i, r, a] * Jp[i, r, b]
                S[6 * p + a, 6 * p + b] += h


@numba.njit(cache=True, nogil=True)
def _landmark_block(j, lm_start, lm_obs, Jp, Jl, e, prior_w2, prior_res, lam, H, gl, W):
    """Landmark ``j``'s damped 3x3 block (into ``H``), its gradient (``gl[j]``) and every one of its observations'
    Jp' Jl (``W``), its prior included."""
    for a in range(3):
        for b in range(3):
            H[a, b] = 0.0
        H[a, a] = prior_w2 + lam
        gl[j, a] = -prior_w2 * prior_res[j, a]
    for s in range(lm_start[j], lm_start[j + 1]):
        i = lm_obs[s]
        for a in range(3):
            acc = 0.0
            for r in range(3):
                acc += Jl[i, r, a] * e[i, r]
            gl[j, a] -= acc
            for b in range(3):
                h = 0.0
                for r in range(3):
                    h += Jl[i, r, a] * Jl[i, r, b]
                H[a, b] += h
        for a in range(6):                  # W = Jp' Jl
            for b in range(3):
                h = 0.0
                for r in range(3):
                    h += Jp[i, r, a] * Jl[i, r, b]
                W[s, a, b] = h


@numba.njit(cache=True, nogil=True)
def _eliminate_landmark(j, n_adj, o_pose, lm_start, lm_obs, W, Hi, gl, S, g):
    """Subtract landmark ``j``'s Schur terms, W_s Hinv W_t' for every pair of its observations by adjusted poses
    and W_s Hinv gl, from ``S`` (its upper triangle, diagonal blocks whole) and ``g``."""
    for s in range(lm_start[j], lm_start[j + 1]):
        pi = o_pose[lm_obs[s]]
        if pi >= n_adj:
            continue
        # V = W_s Hinv (6x3)
        for a in range(6):
            v0 = W[s, a, 0] * Hi[0, 0] + W[s, a, 1] * Hi[1, 0] + W[s, a, 2] * Hi[2, 0]
            v1 = W[s, a, 0] * Hi[0, 1] + W[s, a, 1] * Hi[1, 1] + W[s, a, 2] * Hi[2, 1]
            v2 = W[s, a, 0] * Hi[0, 2] + W[s, a, 1] * Hi[1, 2] + W[s, a, 2] * Hi[2, 2]
            g[6 * pi + a] -= v0 * gl[j, 0] + v1 * gl[j, 1] + v2 * gl[j, 2]
            for t in range(s, lm_start[j + 1]):      # the pair (t, s) is the transpose of (s, t)
                pj = o_pose[lm_obs[t]]
                if pj >= n_adj:
                    continue
                for b in range(6):
                    update = v0 * W[t, b, 0] + v1 * W[t, b, 1] + v2 * W[t, b, 2]
                    if pi < pj:
                        S[6 * pi + a, 6 * pj + b] -= update
                    elif pi > pj:
                        S[6 * pj + b, 6 * pi + a] -= update
                    else:                           # a diagonal block: both orders
                        S[6 * pi + a, 6 * pj + b] -= update
                        if t != s:
                            S[6 * pj + b, 6 * pi + a] -= update


@numba.njit(cache=True, nogil=True)
def reduced_system(n_adj, o_pose, lm_start, lm_obs, Jp, Jl, e, prior_w2, prior_res, lam, S, g, Hinv, gl):
    """The pose system with every landmark eliminated (Schur complement), damped by ``lam`` on every variable
    (GTSAM's LM without diagonal damping): ``S`` (6n, 6n) and ``g`` (6n) are added to in place (they hold the
    pose-only factors already). The landmarks' blocks go to ``S``'s upper triangle only (its diagonal blocks
    whole): the Cholesky factorisation reads nothing else, and the mirrored copy, a column-wise write, cost a
    quarter of the kernel's time on a final adjustment (Bonn crowd-480, 5,348 landmarks: 35 -> 26 ms). Per
    landmark (observations ``lm_obs[lm_start[j]:lm_start[j+1]]``) keeps its damped block's inverse ``Hinv``
    (M,3,3) and its gradient ``gl`` (M,3) for the back-substitution; its prior is ``prior_w2 * |x - x0|^2 / 2``
    with ``prior_res`` = x - x0 (M,3). Returns every observation's Jp' Jl (K,6,3)."""
    _pose_blocks(n_adj, o_pose, Jp, e, S, g)
    for k in range(6 * n_adj):
        S[k, k] += lam
    H = np.zeros((3, 3))
    W = np.zeros((lm_start[-1] if len(lm_start) else 0, 6, 3))
    for j in range(len(lm_start) - 1):
        _landmark_block(j, lm_start, lm_obs, Jp, Jl, e, prior_w2, prior_res, lam, H, gl, W)
        _inverse3(H, Hinv[j])
        _eliminate_landmark(j, n_adj, o_pose, lm_start, lm_obs, W, Hinv[j], gl, S, g)
    return W


@numba.njit(cache=True, nogil=True)
def back_substitute(n_adj, o_pose, lm_start, lm_obs, W, Hinv, gl, dp, dl):
    """Each landmark's step given the poses' ``dp`` (6n): Hinv (gl - sum W' dp), into ``dl`` (M,3)."""
    r = np.zeros(3)
    for j in range(len(lm_start) - 1):
        r[0], r[1], r[2] = gl[j, 0], gl[j, 1], gl[j, 2]
        for s in range(lm_start[j], lm_start[j + 1]):
            p = o_pose[lm_obs[s]]
            if p >= n_adj:
                continue
            for b in range(3):
                acc = 0.0
                for a in range(6):
                    acc += W[s, a, b] * dp[6 * p + a]
                r[b] -= acc
        for a in range(3):
            dl[j, a] = Hinv[j, a, 0] * r[0] + Hinv[j, a, 1] * r[1] + Hinv[j, a, 2] * r[2]


@numba.njit(cache=True, nogil=True)
def linear_cost(o_pose, o_pt, n_adj, Jp, Jl, e, dp, dl):
    """0.5 |Jp dp + Jl dl + e|^2 over the observations: the linearised model's cost of a step."""
    total = 0.0
    for i in range(len(o_pose)):
        p = o_pose[i]
        q = o_pt[i]
        for r in range(3):
            v = e[i, r] + Jl[i, r, 0] * dl[q, 0] + Jl[i, r, 1] * dl[q, 1] + Jl[i, r, 2] * dl[q, 2]
            if p < n_adj:
                for a in range(6):
                    v += Jp[i, r, a] * dp[6 * p + a]
            total += v * v
    return 0.5 * total
