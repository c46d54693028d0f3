"""Pieces shared by the trajectory metrics in ``slam.run.evaluation`` (ATE) and ``slam.run.evaluation_rpe`` (RPE):
the error type, summary statistics, input checks and evo-compatible timestamp association.

Why a module of its own: both metric modules need these, and ``slam.run.evaluation`` re-exports the RPE
functions; keeping the shared parts here avoids an import cycle between the two.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.core.errors import DynslamError

_CHUNK = 1 << 22  # max elements of the distance matrix in unsorted association
_STATS = ("rmse", "mean", "median", "std", "min", "max")


class EvaluationError(DynslamError, ValueError):
    """Trajectories that cannot be evaluated (no overlap, too few poses, missing file)."""


@dataclass(frozen=True)
class ErrorStats:
    """Summary statistics of a 1-D error array (std is the population std, as in evo)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> "ErrorStats":
        e = np.asarray(errors, dtype=np.float64)
        return cls(float(np.sqrt(np.mean(e * e))), float(np.mean(e)), float(np.median(e)),
                   float(np.std(e)), float(np.min(e)), float(np.max(e)))

    def to_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in _STATS}


# ---------------------------------------------------------------- association
def _nearest_sorted(short: np.ndarray, long_: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Binary-search matching against sorted ``long_`` with evo's exact tie rules:
    the later neighbour wins only if strictly closer, out-of-range stamps skip."""
    n = len(long_)
    inside = ~((short < long_[0] - max_dt) | (short > long_[-1] + max_dt))
    k = np.minimum(np.searchsorted(long_, short, side="right"), n - 1)
    diff_ub = long_[k] - short
    diff_lb = np.where(k > 0, short - long_[np.maximum(k - 1, 0)], np.inf)
    take_ub = (diff_ub <= max_dt) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_dt) & (diff_lb <= diff_ub)
    ok = inside & (take_ub | take_lb)
    best = np.where(take_ub, k, k - 1)
    return np.nonzero(ok)[0], best[ok]


def _nearest_unsorted(short: np.ndarray, long_: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """evo's fallback for unsorted stamps: first arg-min of |long - s|, in bounded chunks."""
    rows = max(1, _CHUNK // max(len(long_), 1))
    idx_s: list[np.ndarray] = []
    idx_l: list[np.ndarray] = []
    for start in range(0, len(short), rows):
        diffs = np.abs(long_[None, :] - short[start:start + rows, None])
        best = np.argmin(diffs, axis=1)
        ok = diffs[np.arange(len(best)), best] <= max_dt
        idx_s.append(start + np.nonzero(ok)[0])
        idx_l.append(best[ok])
    return np.concatenate(idx_s), np.concatenate(idx_l)


def associate(t_ref: np.ndarray, t_est: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Match timestamps exactly like ``evo.core.sync.associate_trajectories(ref, est)``.

    evo walks the trajectory with *fewer* poses (the estimate when both have
    the same count) and gives each of its stamps the nearest stamp of the other
    one within ``max_dt`` (ties go to the earlier stamp). Matches are not
    one-to-one: two short-side stamps may share a long-side partner. Returns
    index arrays ``(idx_ref, idx_est)`` ordered by the short side.
    """
    t_ref = np.asarray(t_ref, dtype=np.float64).reshape(-1)
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    if len(t_ref) == 0 or len(t_est) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty.copy()
    est_longer = len(t_est) > len(t_ref)
    short, long_ = (t_ref, t_est) if est_longer else (t_est, t_ref)
    match = _nearest_sorted if np.all(np.diff(long_) >= 0) else _nearest_unsorted
    i_short, i_long = match(short, long_, float(max_dt))
    i_short, i_long = i_short.astype(np.intp), i_long.astype(np.intp)
    return (i_short, i_long) if est_longer else (i_long, i_short)


def _describe(name: str, t: np.ndarray) -> str:
    span = f", t = {t.min():.6f} .. {t.max():.6f} s" if len(t) else ""
    return f"{name} has {len(t)} poses{span}"


def _associate_checked(gt_t: np.ndarray, est_t: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`associate` plus clear errors for no overlap or fewer than 3 matches."""
    idx_gt, idx_est = associate(gt_t, est_t, max_dt)
    where = f"{_describe('ground truth', np.asarray(gt_t))}; {_describe('estimate', np.asarray(est_t))}"
    if len(idx_gt) == 0:
        raise EvaluationError(f"no timestamps associated within max_dt = {max_dt} s ({where}); "
                              "do both files use the same clock?")
    if len(idx_gt) < 3:
        raise EvaluationError(f"only {len(idx_gt)} poses associated within max_dt = {max_dt} s, "
                              f"need at least 3 ({where})")
    return idx_gt, idx_est


# ---------------------------------------------------------------------- inputs
def _inputs(*arrays: np.ndarray) -> list[np.ndarray]:
    """Validate ``gt_t, gt_poses, est_t, est_poses`` as float64 (N,) and (N,4,4) arrays."""
    out: list[np.ndarray] = []
    for name, t, poses in (("ground truth", *arrays[:2]), ("estimate", *arrays[2:])):
        t, poses = np.asarray(t, dtype=np.float64).reshape(-1), np.asarray(poses, dtype=np.float64)
        if poses.shape != (len(t), 4, 4):
            raise ValueError(f"{name}: poses must have shape ({len(t)}, 4, 4), got {poses.shape}")
        out += [t, poses]
    return out

