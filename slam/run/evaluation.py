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

Module layout: the RPE lives in ``slam.run.evaluation_rpe`` and the pieces both metrics share (errors,
statistics, association) in ``slam.run.evaluation_common``; their public names are re-exported here.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam.run.evaluation_common import _STATS, ErrorStats, EvaluationError, _associate_checked, _inputs
from slam.run.evaluation_common import associate  # noqa: F401  (re-exported)
from slam.run.evaluation_rpe import RpeResult, rpe_frames, rpe_seconds
from slam.run.evaluation_rpe import rpe  # noqa: F401  (re-exported)
from slam.run.trajectory import PathLike, read_tum


@dataclass(frozen=True)
class AteResult(ErrorStats):
    """Absolute trajectory error: the statistics of the per-pose errors (``rmse`` ... ``max``) and what they
    came from. ``aligned_poses`` are the matched estimate poses after applying ``alignment`` (4x4, ``s*R | t``),
    row-aligned with ``errors``, and so are ``gt_positions`` (the matched ground-truth camera centres; None if
    built without them)."""

    n_matched: int
    errors: np.ndarray
    timestamps: np.ndarray
    gt_timestamps: np.ndarray
    alignment: np.ndarray
    aligned_poses: np.ndarray
    scale: float = 1.0
    gt_positions: np.ndarray | None = None

    @property
    def stats(self) -> ErrorStats:
        """The summary statistics alone, as a plain :class:`ErrorStats`."""
        return ErrorStats(**{k: getattr(self, k) for k in _STATS})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics and alignment; no per-pose arrays)."""
        out: dict[str, Any] = super().to_dict()
        out.update(n_matched=int(self.n_matched), scale=float(self.scale), unit="m",
                   alignment=[[float(v) for v in row] for row in self.alignment])
        return out


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


# ------------------------------------------------------------ alignment, ATE
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
                     gt_timestamps=gt_t[idx_gt], alignment=alignment, aligned_poses=aligned, scale=s,
                     gt_positions=gt_xyz)

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
