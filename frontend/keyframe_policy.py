"""When a tracked frame becomes a keyframe (ORB-SLAM2's NeedNewKeyFrame for RGB-D).

Mapping runs synchronously here, so it is always "idle": a frame becomes a keyframe when it tracks
clearly fewer landmarks than its reference keyframe, when it could add many close points the map
lacks, or when too many frames have passed and the camera has moved -- unless it is passing an older
keyframe: a camera that comes back to where it has been would otherwise add a keyframe every
``max_frames`` frames on every lap, so the map, the covisible sets the windows adjust and the cost per
frame would grow with the run's length rather than with the space explored (ORB-SLAM culls such
redundant keyframes after the fact; not making them is cheaper here, where a keyframe is a hand-over to
the worker process and a variable in its graph).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.core.config import KeyframeConfig
from slam.core.frame import FeatureFrame


@dataclass
class KeyframeEvidence:
    frames_since_keyframe: int
    tracked_landmarks: int
    reference_landmarks: int
    tracked_close: int
    untracked_close: int
    motion_t: float = float("inf")      # translation since the last keyframe (m)
    motion_deg: float = float("inf")    # rotation since the last keyframe (deg)
    nearest_ratio: float = 1.0
    """Distance (``keyframe_distances``) to the nearest keyframe sharing the tracked landmarks over the
    distance to the last keyframe: 1 while exploring, small where the camera passes an older keyframe."""


def close_point_counts(frame: FeatureFrame, landmark_of_keypoint: np.ndarray, close_depth: float,
                       dynamic_threshold: float) -> tuple[int, int]:
    """(tracked, untracked) static features with a close, valid depth."""
    close = frame.has_depth & (frame.depths < close_depth) & (frame.dynamic_prob < dynamic_threshold)
    tracked = close & (landmark_of_keypoint >= 0)
    return int(tracked.sum()), int((close & ~tracked).sum())


def keyframe_distances(kf_T_wc: np.ndarray, T_wc: np.ndarray, min_t: float, min_deg: float) -> np.ndarray:
    """How far ``T_wc`` is from each keyframe pose (``kf_T_wc``, (N, 4, 4)) in the keyframe rule's own units:
    translation over ``min_t`` or rotation over ``min_deg``, whichever is larger ("moved" is >= 1)."""
    dt = np.linalg.norm(kf_T_wc[:, :3, 3] - T_wc[:3, 3], axis=1)
    cos = (np.einsum("nij,ij->n", kf_T_wc[:, :3, :3], T_wc[:3, :3]) - 1.0) / 2.0   # trace(R_k^T R)
    deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.maximum(dt / min_t, deg / min_deg)


def need_keyframe(cfg: KeyframeConfig, ev: KeyframeEvidence) -> bool:
    if ev.frames_since_keyframe < cfg.min_frames:
        return False
    need_close = ev.tracked_close < cfg.close_tracked_min and ev.untracked_close > cfg.close_untracked_min
    moved = ev.motion_t >= cfg.min_motion_t or ev.motion_deg >= cfg.min_motion_deg
    passing_older = ev.nearest_ratio < cfg.revisit_ratio
    timed_out = ev.frames_since_keyframe >= cfg.max_frames and moved and not passing_older
    weak = ev.tracked_landmarks < cfg.tracked_ratio * ev.reference_landmarks or need_close
    return (weak or timed_out) and ev.tracked_landmarks > 15
