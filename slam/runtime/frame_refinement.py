"""The tracked frames between keyframes solved again against the final map, at the end of a run.

A frame's pose is estimated against the map as it is when the frame comes, and kept relative to its
reference keyframe (ORB-SLAM's relative frame poses): it follows that keyframe's later corrections, but
not those of the landmarks it was measured against, which the windows, the loops and the final global
adjustment move on their own (the newest landmarks most: they have been adjusted least when the next
frames are tracked against them). So the final trajectory's keyframes are better than the frames between
them: on generated three_close (seed 3) 2.9 mm against 4.8 mm RMS, with the largest errors mid-way between
two keyframes (frame 122: 21 mm). Here each such frame's inlier matches, kept compactly while it is
tracked (``FrameMatches``), are solved again with the final landmark positions by the same pose-only
optimisation, started from the frame's final pose; its position covariance comes from the same solve, so
the smoother (trajectory_smoother.py) weighs the new estimate. Keyframes keep their adjusted poses.

Measured (2026-12-02, `--set tracking.refine_frames=3000`): `dynslam run` fr1/rpy-400 ATE 0.0233 -> 0.0220 m,
Bonn crowd-480 0.0102 -> 0.0103; `python tools/hard_scenes.py --repeats 3`: the path without people 2.8 ->
2.0 mm, three_close 4.2 -> 3.5 mm (docs/design.md, "The frames between keyframes", has why it is off).
A re-solve that keeps fewer than ``tracking.min_tracked_inliers`` inliers, or fixes the position worse than
``tracking.max_pose_sigma_m`` (what tracking would call LOST), keeps the tracked pose.
Matches are kept for the newest ``tracking.refine_frames`` frames only (20 bytes a match, ~8 KB a frame:
24 MB at 3,000), so a long live run's memory stays bounded; older frames keep their tracked poses.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import ItemsView

import numpy as np

from frontend.pose_optimizer import PoseObservations, optimize_pose
from frontend.tracker import pose_information
from slam.core.camera import PinholeCamera
from slam.core.config import TrackingConfig
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert
from slam.runtime.frame_log import FrameLog


@dataclass(frozen=True)
class FrameMatches:
    """A tracked frame's inlier matches to landmarks, as its pose optimisation weighed them."""

    landmark_ids: np.ndarray   # (N,) int32
    uv: np.ndarray             # (N,2) float32 undistorted pixels
    u_right: np.ndarray        # (N,) float32 virtual stereo u, NaN without depth
    information: np.ndarray    # (N,) float32, tracker.pose_information

    @classmethod
    def of(cls, frame: FeatureFrame, landmark_of_keypoint: np.ndarray) -> "FrameMatches":
        kp = np.flatnonzero(landmark_of_keypoint >= 0)
        return cls(landmark_of_keypoint[kp].astype(np.int32), frame.uv[kp].astype(np.float32),
                   frame.u_right[kp].astype(np.float32),
                   pose_information(frame, kp).astype(np.float32))


class MatchStore:
    """The newest ``capacity`` frames' matches, by frame position in the run's FrameLog."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self._matches: OrderedDict[int, FrameMatches] = OrderedDict()

    def __len__(self) -> int:
        return len(self._matches)

    def add(self, position: int, matches: FrameMatches) -> None:
        if self.capacity <= 0:
            return
        self._matches[position] = matches
        while len(self._matches) > self.capacity:
            self._matches.popitem(last=False)

    def items(self) -> ItemsView[int, FrameMatches]:
        return self._matches.items()

    def clear(self) -> None:
        self._matches.clear()


def refine_frames(frames: FrameLog, store: MatchStore, kf_T_wc: np.ndarray, landmark_xyz: np.ndarray,
                  landmark_bad: np.ndarray, camera: PinholeCamera, cfg: TrackingConfig) -> int:
    """Solve every stored frame again against the landmarks' final positions and put the result into
    ``frames`` (the pose relative to the same reference keyframe, and its covariance);
    returns how many frames changed. The store is emptied."""
    changed = 0
    for position, matches in store.items():
        reference = frames.reference_of(position)
        if reference < 0:
            continue
        usable = ~landmark_bad[matches.landmark_ids]
        if int(usable.sum()) < cfg.min_tracked_inliers:
            continue
        ids = matches.landmark_ids[usable]
        obs = PoseObservations(landmark_xyz[ids], matches.uv[usable].astype(float),
                               matches.u_right[usable].astype(float), matches.information[usable].astype(float))
        T_wc = kf_T_wc[reference] @ frames.relative_pose(position)
        result = optimize_pose(invert(T_wc), obs, camera, cfg.pose_iterations, cfg.pose_rounds, cfg.chi2_mono,
                               cfg.chi2_stereo)
        if int(result.inliers.sum()) < cfg.min_tracked_inliers or not result.sigma_t <= cfg.max_pose_sigma_m:
            continue
        R_cw = result.T_cw[:3, :3]
        frames.replace(position, invert(kf_T_wc[reference]) @ invert(result.T_cw), R_cw.T @ result.cov_t @ R_cw)
        changed += 1
    store.clear()
    return changed
