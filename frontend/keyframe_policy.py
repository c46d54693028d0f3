"""When a tracked frame becomes a keyframe (ORB-SLAM2's NeedNewKeyFrame for RGB-D).

Mapping runs synchronously here, so it is always "idle": a frame becomes a keyframe when it tracks
clearly fewer landmarks than its reference keyframe, when it could add many close points the map
lacks, or when too many frames have passed.
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


def close_point_counts(frame: FeatureFrame, landmark_of_keypoint: np.ndarray, close_depth: float,
                       dynamic_threshold: float) -> tuple[int, int]:
    """(tracked, untracked) static features with a close, valid depth."""
    close = frame.has_depth & (frame.depths < close_depth) & (frame.dynamic_prob < dynamic_threshold)
    tracked = close & (landmark_of_keypoint >= 0)
    return int(tracked.sum()), int((close & ~tracked).sum())


def need_keyframe(cfg: KeyframeConfig, ev: KeyframeEvidence) -> bool:
    if ev.frames_since_keyframe < cfg.min_frames:
        return False
    need_close = ev.tracked_close < cfg.close_tracked_min and ev.untracked_close > cfg.close_untracked_min
    moved = ev.motion_t >= cfg.min_motion_t or ev.motion_deg >= cfg.min_motion_deg
    timed_out = ev.frames_since_keyframe >= cfg.max_frames and moved
    weak = ev.tracked_landmarks < cfg.tracked_ratio * ev.reference_landmarks or need_close
    return (weak or timed_out) and ev.tracked_landmarks > 15
