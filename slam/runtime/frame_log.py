"""Every processed frame's pose, kept relative to its reference keyframe so the trajectory follows the
keyframes' optimised estimates (ORB-SLAM's ``mlRelativeFramePoses``)."""
from __future__ import annotations

from typing import Optional

import numpy as np


class FrameLog:
    def __init__(self) -> None:
        self._stamps: list[float] = []
        self._reference_kf: list[int] = []
        self._T_kf_c: list[np.ndarray] = []   # NaN for frames that were not tracked

    def __len__(self) -> int:
        return len(self._stamps)

    def add_lost(self, timestamp: float) -> None:
        self.add(timestamp, -1, None)

    def add(self, timestamp: float, reference_kf: int, T_kf_c: Optional[np.ndarray]) -> None:
        self._stamps.append(float(timestamp))
        self._reference_kf.append(reference_kf if T_kf_c is not None else -1)
        self._T_kf_c.append(np.full((4, 4), np.nan) if T_kf_c is None else T_kf_c)

    @property
    def last_T_kf_c(self) -> np.ndarray:
        return self._T_kf_c[-1]

    def trajectory(self, kf_T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(timestamps (N,), T_wc (N,4,4), tracked (N,) bool) with the keyframes' poses ``kf_T_wc``;
        untracked frames hold NaN poses."""
        stamps = np.array(self._stamps)
        reference = np.array(self._reference_kf, dtype=np.int64)
        tracked = reference >= 0
        poses = np.full((len(stamps), 4, 4), np.nan)
        if tracked.any():
            relative = np.stack(self._T_kf_c)[tracked]
            poses[tracked] = kf_T_wc[reference[tracked]] @ relative
        return stamps, poses, tracked
