"""Every processed frame's pose, kept relative to its reference keyframe so the trajectory follows the
keyframes' optimised estimates (ORB-SLAM's ``mlRelativeFramePoses``)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from slam.runtime.trajectory_smoother import smooth_positions


class FrameLog:
    def __init__(self) -> None:
        self._stamps: list[float] = []
        self._reference_kf: list[int] = []
        self._T_kf_c: list[np.ndarray] = []   # NaN for frames that were not tracked
        self._position_cov: list[np.ndarray] = []   # (3,3) world-frame camera-centre covariance, NaN: unknown

    def __len__(self) -> int:
        return len(self._stamps)

    def add_lost(self, timestamp: float) -> None:
        self.add(timestamp, -1, None)

    def add(self, timestamp: float, reference_kf: int, T_kf_c: Optional[np.ndarray],
            position_cov: Optional[np.ndarray] = None) -> None:
        self._stamps.append(float(timestamp))
        self._reference_kf.append(reference_kf if T_kf_c is not None else -1)
        self._T_kf_c.append(np.full((4, 4), np.nan) if T_kf_c is None else T_kf_c)
        self._position_cov.append(np.full((3, 3), np.nan) if position_cov is None else position_cov)

    @property
    def last_T_kf_c(self) -> np.ndarray:
        return self._T_kf_c[-1]

    def reference_of(self, position: int) -> int:
        """The reference keyframe of the frame at ``position`` (-1: not tracked)."""
        return self._reference_kf[position]

    def relative_pose(self, position: int) -> np.ndarray:
        """The frame's pose relative to its reference keyframe."""
        return self._T_kf_c[position]

    def replace(self, position: int, T_kf_c: np.ndarray, position_cov: np.ndarray) -> None:
        """A tracked frame's new estimate (frame_refinement): the same reference keyframe, a new relative pose
        and camera-centre covariance."""
        if self._reference_kf[position] < 0:
            raise ValueError(f"frame {position} was not tracked: it has no pose to replace")
        self._T_kf_c[position] = T_kf_c
        self._position_cov[position] = position_cov

    def trajectory(self, kf_T_wc: np.ndarray, sigma_acc: float = 0.0,
                   huber_chi2: float = float("inf")) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(timestamps (N,), T_wc (N,4,4), tracked (N,) bool) with the keyframes' poses ``kf_T_wc``;
        untracked frames hold NaN poses. ``sigma_acc`` > 0: positions smoothed (trajectory_smoother,
        robust beyond ``huber_chi2``; inf: plain least squares)."""
        stamps = np.array(self._stamps)
        reference = np.array(self._reference_kf, dtype=np.int64)
        tracked = reference >= 0
        poses = np.full((len(stamps), 4, 4), np.nan)
        if tracked.any():
            relative = np.stack(self._T_kf_c)[tracked]
            poses[tracked] = kf_T_wc[reference[tracked]] @ relative
            if sigma_acc > 0:
                poses[:, :3, 3] = smooth_positions(stamps, poses[:, :3, 3], np.stack(self._position_cov), tracked,
                                                   sigma_acc, huber_chi2)
        return stamps, poses, tracked
