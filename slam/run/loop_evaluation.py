"""Checking loop closures against ground truth: is a verified loop's relative pose the true one?

A loop is *false* when its measured ``T_match_query`` disagrees with the ground-truth relative pose of
the two keyframes by more than 10 cm or 5 degrees (the acceptance bound of issue 4). Keyframes are
matched to ground truth by timestamp (nearest, within ``max_dt``), like trajectory evaluation.

Relative poses compare body frames, so the ground-truth body must be the camera. TUM's ground truth
is the camera's optical frame; Bonn's is the motion-capture marker, whose axes are turned about 170
degrees from the camera's. ``estimate_body_rotation`` recovers that fixed rotation from a tracked
trajectory (after the usual SE(3) alignment, R_gt,i = R_align R_est,i X for every frame i; X is
the rotation mean, and its spread shows whether one X explains all frames). The marker's lever arm
is not estimated: it changes relative translations by at most |R_rel - I| x its length (a few cm).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from slam.run.evaluation import umeyama_alignment
from slam.run.evaluation_common import associate

FALSE_LOOP_T = 0.10
FALSE_LOOP_DEG = 5.0


@dataclass
class LoopCheck:
    query_t: float
    match_t: float
    error_t: float            # metres
    error_deg: float
    active: bool

    @property
    def false(self) -> bool:
        return self.error_t > FALSE_LOOP_T or self.error_deg > FALSE_LOOP_DEG


def _nearest(stamps: np.ndarray, t: float, max_dt: float) -> Optional[int]:
    i = int(np.argmin(np.abs(stamps - t)))
    return i if abs(stamps[i] - t) <= max_dt else None


def estimate_body_rotation(est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray,
                           gt_poses: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, float]:
    """(X, median spread in degrees): the rotation from the camera to the ground truth's body frame."""
    i_gt, i_est = associate(gt_stamps, est_stamps, max_dt)
    R_align, _, _ = umeyama_alignment(est_poses[i_est, :3, 3].T, gt_poses[i_gt, :3, 3].T)
    per_frame = Rotation.from_matrix(np.transpose(est_poses[i_est, :3, :3], (0, 2, 1)) @ R_align.T
                                     @ gt_poses[i_gt, :3, :3])
    mean = per_frame.mean()
    spread = float(np.degrees(np.median((per_frame * mean.inv()).magnitude())))
    return mean.as_matrix(), spread


def check_loops(loops: Iterable[Mapping], gt_stamps: np.ndarray, gt_poses: np.ndarray,
                max_dt: float = 0.02, body_rotation: Optional[np.ndarray] = None) -> list[LoopCheck]:
    """One check per loop (``summary.json``'s ``loops`` entries); loops without ground truth at both
    ends are skipped. ``body_rotation``: X from ``estimate_body_rotation`` (None: the ground truth is
    already the camera frame)."""
    if body_rotation is not None:
        X = np.eye(4)
        X[:3, :3] = body_rotation
        gt_poses = gt_poses @ np.linalg.inv(X)
    checks = []
    for loop in loops:
        iq, im = _nearest(gt_stamps, loop["query_t"], max_dt), _nearest(gt_stamps, loop["match_t"], max_dt)
        if iq is None or im is None:
            continue
        T_true = np.linalg.solve(gt_poses[im], gt_poses[iq])
        E = np.linalg.solve(T_true, np.asarray(loop["T_match_query"], float))
        angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        checks.append(LoopCheck(float(loop["query_t"]), float(loop["match_t"]), float(np.linalg.norm(E[:3, 3])),
                                float(angle), bool(loop.get("active", True))))
    return checks
