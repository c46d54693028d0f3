"""Configuration of place recognition, loop closing and relocalization (``loop:`` in YAML)."""
from __future__ import annotations

from typing import Literal, get_args

from pydantic import Field

from slam.core.config_base import ConfigSection

Kernel = Literal["cauchy", "huber", "none"]
KERNELS: tuple[str, ...] = get_args(Kernel)
PNP_MIN_POINTS = 4   # PnP needs 4 points: fewer inliers can never verify a loop or a relocalization


class LoopConfig(ConfigSection):
    """Loop detection (ORB-SLAM's DetectLoop), geometric verification, the loop factor, relocalization."""

    enabled: bool = True
    """Loop closing on/off; relocalization through the keyframe index works either way."""
    relocalization: bool = True
    vocabulary: str = ""
    """Vocabulary file (.npz from `dynslam vocabulary`); empty = the one shipped with the package."""
    # Detection: covisibility threshold that excludes neighbours, consecutive keyframes a candidate
    # group must persist over, the newest keyframes never considered.
    min_covisible_shared: int = Field(15, ge=1)
    consistency: int = Field(3, ge=1)
    exclude_recent: int = Field(5, ge=0)
    min_score_ratio: float = Field(0.75, ge=0, le=1)   # a fraction of the best neighbour's score
    max_candidates: int = Field(10, ge=1)
    min_keyframes_between: int = Field(10, ge=0)
    """After a loop closes, the next keyframes are only indexed (ORB-SLAM waits 10): a loop just fused
    this place, and re-closing it at every keyframe would cost an optimisation each time."""
    # Geometric verification: PnP-RANSAC inliers on static features, with a relative depth check.
    min_inliers: int = Field(30, ge=PNP_MIN_POINTS)
    reprojection_error: float = Field(3.0, gt=0)
    depth_tolerance: float = Field(0.1, gt=0)
    # The loop factor: a BetweenFactorPose3 under a robust kernel (Cauchy lets a wrong loop fade out).
    sigma_t: float = Field(0.02, gt=0)
    sigma_r_deg: float = Field(1.0, gt=0)
    kernel: Kernel = "cauchy"
    kernel_k: float = Field(1.0, gt=0)
    extra_updates: int = Field(8, ge=0)
    """iSAM2 updates after adding a loop: a loop moves many variables far from their linearisation point."""
    fuse_landmarks: bool = True
    max_residual_t: float = Field(0.05, gt=0)
    """A loop whose factor disagrees with the optimised graph by more than this is removed again."""
    max_residual_r_deg: float = Field(3.0, gt=0)
    reloc_candidates: int = Field(5, ge=1)
    """Relocalization: candidates tried per lost frame and inliers needed."""
    reloc_min_inliers: int = Field(30, ge=PNP_MIN_POINTS)
