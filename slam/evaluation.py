"""Trajectory accuracy metrics (ATE, RPE) that reproduce evo and the TUM scripts.

Conventions (see docs "Evaluation conventions"): poses are 4x4 ``T_wc``
matrices; the ground truth is the reference. Three metrics are provided:

* ATE: association by nearest timestamp (evo's ``associate_trajectories``),
  SE(3) Umeyama alignment of the estimate onto the ground truth (no scale for
  RGB-D), translation error per matched pose. Equals ``evo_ape tum gt est -a
  --t_max_diff <max_dt>`` (note evo's CLI default t_max_diff is 0.01 s, ours
  is 0.02 s).
* Per-frame RPE: consecutive associated poses, error ``inv(Q_rel) @ P_rel``;
  equals ``evo_rpe tum gt est -a --delta 1 --delta_unit f``. An SE(3)
  alignment cancels out of relative motions, so ``-a`` does not change it.
* RPE over 1 s: TUM ``evaluate_rpe.py --fixed_delta --delta 1``: each
  estimate pose i is paired with the estimate pose whose time is *closest*
  to t_i + 1 s (pairs ending on the last pose are dropped, as TUM does), the
  ground truth is looked up by closest time within twice its median period,
  and the error is ``P_rel @ inv(Q_rel)``. Errors are those of the relative
  motion over each ~1 s interval, not divided by its exact duration; so they
  read as m/s and deg/s (TUM prints them as m and deg). TUM samples 10000
  random pairs when there are more; we always use all of them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from slam.trajectory import PathLike, read_tum

_CHUNK = 1 << 22  # max elements of the distance matrix in unsorted association
_STATS = ("rmse", "mean", "median", "std", "min", "max")


class EvaluationError(ValueError):
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


@dataclass
class AteResult:
    """Absolute trajectory error. ``aligned_poses`` are the matched estimate poses
    after applying ``alignment`` (4x4, ``s*R | t``), row-aligned with ``errors``."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n_matched: int
    errors: np.ndarray
    timestamps: np.ndarray
    gt_timestamps: np.ndarray
    alignment: np.ndarray
    aligned_poses: np.ndarray
    scale: float = 1.0

    @property
    def stats(self) -> ErrorStats:
        """The summary statistics as an :class:`ErrorStats`."""
        return ErrorStats(**{k: getattr(self, k) for k in _STATS})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics and alignment; no per-pose arrays)."""
        out: dict[str, Any] = self.stats.to_dict()
        out.update(n_matched=int(self.n_matched), scale=float(self.scale), unit="m",
                   alignment=[[float(v) for v in row] for row in self.alignment])
        return out


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


@dataclass
class EvaluationReport:
    """ATE and both RPEs of one estimate file against one ground-truth file."""

    gt_path: str
    est_path: str
    n_gt: int
    n_est: int
    max_dt: float
    ate: AteResult
    rpe_frame: RpeResult
    rpe_time: RpeResult | None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready nested dict of plain Python floats/ints/strings."""
        return {"gt_path": self.gt_path, "est_path": self.est_path, "n_gt": int(self.n_gt),
                "n_est": int(self.n_est), "max_dt": float(self.max_dt), "ate": self.ate.to_dict(),
                "rpe_frame": self.rpe_frame.to_dict(),
                "rpe_time": None if self.rpe_time is None else self.rpe_time.to_dict(),
                "notes": list(self.notes)}


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


def umeyama_alignment(src: np.ndarray, dst: np.ndarray,
                      with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``(R, t, s)`` with ``dst ≈ s * R @ src + t`` (Umeyama 1991).

    ``src`` and ``dst`` are (m, N) point sets (columns are points). Raises
    :class:`EvaluationError` when the points are degenerate (rank < m-1, e.g.
    a camera that never moved), where the rotation is not determined.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] == 0:
        raise ValueError(f"src and dst must be equal (m, N) arrays, got {src.shape} and {dst.shape}")
    m, n = src.shape
    mu_src, mu_dst = src.mean(axis=1), dst.mean(axis=1)
    src_c, dst_c = src - mu_src[:, None], dst - mu_dst[:, None]
    U, d, Vt = np.linalg.svd(dst_c @ src_c.T / n)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < m - 1:
        raise EvaluationError("degenerate point configuration (all positions identical or collinear "
                              "in a way that fixes no rotation): Umeyama alignment is impossible")
    S = np.eye(m)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[-1, -1] = -1.0
    R = U @ S @ Vt
    s = float(np.sum(d * np.diag(S)) / (np.sum(src_c * src_c) / n)) if with_scale else 1.0
    return R, mu_dst - s * R @ mu_src, s


# --------------------------------------------------------------------- metrics
def _inputs(*arrays: np.ndarray) -> list[np.ndarray]:
    """Validate ``gt_t, gt_poses, est_t, est_poses`` as float64 (N,) and (N,4,4) arrays."""
    out: list[np.ndarray] = []
    for name, t, poses in (("ground truth", *arrays[:2]), ("estimate", *arrays[2:])):
        t, poses = np.asarray(t, dtype=np.float64).reshape(-1), np.asarray(poses, dtype=np.float64)
        if poses.shape != (len(t), 4, 4):
            raise ValueError(f"{name}: poses must have shape ({len(t)}, 4, 4), got {poses.shape}")
        out += [t, poses]
    return out


def ate(gt_t: np.ndarray, gt_poses: np.ndarray, est_t: np.ndarray, est_poses: np.ndarray,
        max_dt: float = 0.02, align: bool = True, with_scale: bool = False) -> AteResult:
    """Absolute trajectory error (translation, metres), as ``evo_ape tum gt est -a``.

    Associates by timestamp (:func:`associate`, ground truth as reference),
    aligns the matched estimate positions onto the ground truth with Umeyama
    (SE(3); Sim(3) if ``with_scale``, for monocular) unless ``align`` is
    False, and returns per-pose position errors with their statistics.
    """
    gt_t, gt_poses, est_t, est_poses = _inputs(gt_t, gt_poses, est_t, est_poses)
    idx_gt, idx_est = _associate_checked(gt_t, est_t, max_dt)
    gt_xyz = gt_poses[idx_gt, :3, 3]
    est = est_poses[idx_est]
    R, t, s = np.eye(3), np.zeros(3), 1.0
    if align:
        R, t, s = umeyama_alignment(est[:, :3, 3].T, gt_xyz.T, with_scale)
    alignment = np.eye(4)
    alignment[:3, :3], alignment[:3, 3] = s * R, t
    aligned = est.copy()
    aligned[:, :3, :3] = R @ est[:, :3, :3]
    aligned[:, :3, 3] = s * est[:, :3, 3] @ R.T + t
    errors = np.linalg.norm(aligned[:, :3, 3] - gt_xyz, axis=1)
    stats = ErrorStats.from_errors(errors)
    return AteResult(**stats.to_dict(), n_matched=len(errors), errors=errors, timestamps=est_t[idx_est],
                     gt_timestamps=gt_t[idx_gt], alignment=alignment, aligned_poses=aligned, scale=s)


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


# ------------------------------------------------------------------- reports
def _load(path: PathLike, role: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file, turning a missing or empty file into an EvaluationError."""
    if not Path(path).is_file():
        raise EvaluationError(f"{role} file not found: {path}")
    t, poses = read_tum(path)
    if len(t) == 0:
        raise EvaluationError(f"{role} file has no poses: {path}")
    return t, poses


def evaluate_files(gt_path: PathLike, est_path: PathLike, max_dt: float = 0.02) -> EvaluationReport:
    """Evaluate a TUM estimate file against a TUM ground-truth file (see :func:`evaluate`).

    Malformed lines raise ``TrajectoryFormatError`` with file and line; a missing or empty file
    raises :class:`EvaluationError` naming it.
    """
    gt_t, gt_poses = _load(gt_path, "ground truth")
    est_t, est_poses = _load(est_path, "estimate")
    return evaluate(gt_t, gt_poses, est_t, est_poses, max_dt, str(gt_path), str(est_path))


def evaluate(gt_t: np.ndarray, gt_poses: np.ndarray, est_t: np.ndarray, est_poses: np.ndarray,
             max_dt: float = 0.02, gt_label: str = "ground truth", est_label: str = "estimate") -> EvaluationReport:
    """ATE, per-frame RPE and RPE over 1 s of an estimate against ground truth.

    A sequence too short for 1 s pairs gets ``rpe_time=None`` and a note instead of an error;
    every other failure raises :class:`EvaluationError` naming both inputs.
    """
    try:
        ate_res = ate(gt_t, gt_poses, est_t, est_poses, max_dt)
        frame = rpe_frames(gt_t, gt_poses, est_t, est_poses, max_dt)
    except EvaluationError as exc:
        raise EvaluationError(f"{est_label} vs {gt_label}: {exc}") from None
    notes: list[str] = []
    try:
        per_second: RpeResult | None = rpe_seconds(gt_t, gt_poses, est_t, est_poses)
    except EvaluationError as exc:
        per_second = None
        notes.append(f"RPE over 1 s not computed: {exc}")
    return EvaluationReport(gt_path=gt_label, est_path=est_label, n_gt=len(gt_t), n_est=len(est_t),
                            max_dt=float(max_dt), ate=ate_res, rpe_frame=frame, rpe_time=per_second,
                            notes=notes)


def format_report(report: EvaluationReport) -> str:
    """A short fixed-width table of the report's statistics, for logs and the CLI."""
    columns = ("rmse", "mean", "median", "std", "max")
    head = f"{'metric':<24}{'n':>6}" + "".join(f"{k:>10}" for k in columns)
    rows = [("ATE [m]", report.ate.n_matched, report.ate.stats)]
    for label, res in (("RPE/frame", report.rpe_frame), ("RPE/1s", report.rpe_time)):
        if res is not None:
            rows.append((f"{label} trans [{res.translation_unit}]", res.n_pairs, res.translation))
            rows.append((f"{label} rot [{res.rotation_unit}]", res.n_pairs, res.rotation))
    lines = [f"{report.est_path} vs {report.gt_path} ({report.n_est} / {report.n_gt} poses, "
             f"max_dt {report.max_dt:g} s)", head]
    for label, n, st in rows:
        lines.append(f"{label:<24}{n:>6}" + "".join(f"{getattr(st, k):>10.4f}" for k in columns))
    lines.extend(f"note: {note}" for note in report.notes)
    return "\n".join(lines)
