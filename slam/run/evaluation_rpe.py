"""Relative pose error as evo (per frame) and the TUM scripts (over 1 s) compute it.

The conventions are those of ``slam.run.evaluation`` (see its docstring), which re-exports everything
public here: ``rpe_frames`` pairs consecutive associated poses as ``evo_rpe ... --delta 1 --delta_unit f``,
``rpe_seconds`` pairs poses ~1 s apart as TUM's ``evaluate_rpe.py --fixed_delta``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from slam.run.evaluation_common import ErrorStats, EvaluationError, _associate_checked, _describe, _inputs


@dataclass
class RpeResult:
    """Relative pose error: translation and rotation statistics over pose pairs.

    ``pair_timestamps`` (K,2) are the estimate times of each pair, so the
    interval behind every error can be recovered.
    """

    translation: ErrorStats
    rotation: ErrorStats
    n_pairs: int
    delta: float
    delta_unit: Literal["frames", "s"]
    translation_unit: str
    rotation_unit: str
    translation_errors: np.ndarray
    rotation_errors: np.ndarray
    pair_timestamps: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics and units; no per-pair arrays)."""
        return {"translation": self.translation.to_dict(), "rotation": self.rotation.to_dict(),
                "n_pairs": int(self.n_pairs), "delta": float(self.delta), "delta_unit": self.delta_unit,
                "translation_unit": self.translation_unit, "rotation_unit": self.rotation_unit}


# ------------------------------------------------------------------ geometry
def _inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of (N,4,4) rigid transforms via the transposed rotation."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles of (N,3,3) matrices in degrees, via atan2 (accurate near 0 and 180)."""
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = 0.5 * np.linalg.norm(axis, axis=1)
    cos = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


# --------------------------------------------------------------------- metrics
def _rpe_result(E: np.ndarray, pair_t: np.ndarray, delta: float, unit: Literal["frames", "s"],
                per: str) -> RpeResult:
    """Package error transforms E (K,4,4) into an :class:`RpeResult`."""
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = _rotation_angle_deg(E[:, :3, :3])
    return RpeResult(translation=ErrorStats.from_errors(trans), rotation=ErrorStats.from_errors(rot),
                     n_pairs=len(trans), delta=float(delta), delta_unit=unit,
                     translation_unit="m" + per, rotation_unit="deg" + per,
                     translation_errors=trans, rotation_errors=rot, pair_timestamps=pair_t)


def rpe_frames(gt_t: np.ndarray, gt_poses: np.ndarray, est_t: np.ndarray, est_poses: np.ndarray,
               max_dt: float = 0.02, delta: int = 1) -> RpeResult:
    """Per-frame RPE as ``evo_rpe tum gt est -a --delta 1 --delta_unit f``.

    After association, pairs are consecutive matched poses ``(k, k+delta)``
    with k a multiple of delta (evo's non-all-pairs mode); the error is
    ``inv(Q_rel) @ P_rel`` (translation in m per pair, rotation in deg per
    pair). SE(3) alignment is not applied: it cancels out exactly.
    """
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be a positive integer number of frames, got {delta}")
    gt_t, gt_poses, est_t, est_poses = _inputs(gt_t, gt_poses, est_t, est_poses)
    idx_gt, idx_est = _associate_checked(gt_t, est_t, max_dt)
    ids = np.arange(0, len(idx_gt), int(delta))
    if len(ids) < 2:
        raise EvaluationError(f"{len(idx_gt)} matched poses give no pair with delta = {delta} frames")
    i, j = ids[:-1], ids[1:]
    Q, P = gt_poses[idx_gt], est_poses[idx_est]
    q_rel = _inverse(Q[i]) @ Q[j]
    p_rel = _inverse(P[i]) @ P[j]
    pair_t = np.stack([est_t[idx_est[i]], est_t[idx_est[j]]], axis=1)
    return _rpe_result(_inverse(q_rel) @ p_rel, pair_t, delta, "frames", "")


def _tum_closest_index(values: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Vectorised replica of TUM's ``find_closest_index`` (a binary search that
    keeps the first strictly-closest probe), so ties resolve exactly as TUM's."""
    n = len(values)
    beg = np.zeros(len(queries), dtype=np.intp)
    end = np.full(len(queries), n, dtype=np.intp)
    best = np.zeros(len(queries), dtype=np.intp)
    diff = np.abs(values[0] - queries)
    active = beg < end
    while np.any(active):
        mid = np.minimum((beg + end) // 2, n - 1)
        probe = values[mid]
        d = np.abs(probe - queries)
        better = active & (d < diff)
        hit = active & (probe == queries)
        best = np.where(better | hit, mid, best)
        diff = np.where(better, d, diff)
        left = active & ~hit & (probe > queries)
        right = active & ~hit & ~(probe > queries)
        end, beg = np.where(left, mid, end), np.where(right, mid + 1, beg)
        active = active & ~hit & (beg < end)
    return best


def rpe_seconds(gt_t: np.ndarray, gt_poses: np.ndarray, est_t: np.ndarray, est_poses: np.ndarray,
                delta: float = 1.0, max_gt_dt: float | None = None) -> RpeResult:
    """RPE over ``delta`` seconds as TUM's ``evaluate_rpe.py --fixed_delta``.

    See the module docstring for the pairing rules. ``max_gt_dt`` bounds the
    estimate-to-ground-truth time gap (default: TUM's twice the median ground
    truth period). Units are m and deg per ``delta``-second interval.
    """
    gt_t, gt_poses, est_t, est_poses = _inputs(gt_t, gt_poses, est_t, est_poses)
    if len(gt_t) < 2 or len(est_t) < 2:
        raise EvaluationError(f"RPE needs 2+ poses per trajectory ({_describe('ground truth', gt_t)}; "
                              f"{_describe('estimate', est_t)})")
    go, eo = np.argsort(gt_t, kind="stable"), np.argsort(est_t, kind="stable")
    gt_t, gt_poses, est_t, est_poses = gt_t[go], gt_poses[go], est_t[eo], est_poses[eo]
    if max_gt_dt is None:
        max_gt_dt = 2.0 * float(np.median(np.diff(gt_t)))
    n = len(est_t)
    j = _tum_closest_index(est_t, est_t + delta)
    g = _tum_closest_index(gt_t, est_t)
    near_gt = np.abs(gt_t[g] - est_t) <= max_gt_dt
    i = np.nonzero((j != n - 1) & near_gt & near_gt[j])[0]
    j = j[i]
    if len(i) < 2:
        where = f"{_describe('ground truth', gt_t)}; {_describe('estimate', est_t)}"
        raise EvaluationError(f"fewer than 2 pose pairs {delta} s apart with ground truth "
                              f"within {max_gt_dt:.4f} s ({where})")
    p_rel = _inverse(est_poses[i]) @ est_poses[j]
    q_rel = _inverse(gt_poses[g[i]]) @ gt_poses[g[j]]
    per = "/s" if delta == 1.0 else f"/{delta:g}s"
    return _rpe_result(p_rel @ _inverse(q_rel), np.stack([est_t[i], est_t[j]], axis=1), delta, "s", per)


def rpe(gt_t: np.ndarray, gt_poses: np.ndarray, est_t: np.ndarray, est_poses: np.ndarray,
        mode: Literal["frame", "time"] = "frame", max_dt: float = 0.02,
        delta: float | None = None) -> RpeResult:
    """Relative pose error: ``mode="frame"`` (evo, per frame, default delta 1
    frame) or ``mode="time"`` (TUM, default delta 1 s); see :func:`rpe_frames`
    and :func:`rpe_seconds`. ``max_dt`` applies to the per-frame association."""
    if mode == "frame":
        return rpe_frames(gt_t, gt_poses, est_t, est_poses, max_dt, 1 if delta is None else int(delta))
    if mode == "time":
        return rpe_seconds(gt_t, gt_poses, est_t, est_poses, 1.0 if delta is None else float(delta))
    raise ValueError(f"mode must be 'frame' or 'time', got {mode!r}")

