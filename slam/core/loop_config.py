"""Configuration of place recognition, loop closing and relocalization (``loop:`` in YAML)."""
from __future__ import annotations

from dataclasses import dataclass

KERNELS = ("cauchy", "huber", "none")


@dataclass
class LoopConfig:
    # Loop closing on/off; relocalization through the keyframe index works either way.
    enabled: bool = True
    relocalization: bool = True
    # Vocabulary file (.npz from `dynslam vocabulary`); empty = the one shipped with the package.
    vocabulary: str = ""
    # Detection (ORB-SLAM's DetectLoop): covisibility threshold that excludes neighbours, consecutive
    # keyframes a candidate group must persist over, the newest keyframes never considered.
    min_covisible_shared: int = 15
    consistency: int = 3
    exclude_recent: int = 5
    min_score_ratio: float = 0.75
    max_candidates: int = 10
    # After a loop closes, the next keyframes are only indexed (ORB-SLAM waits 10): a loop just fused
    # this place, and re-closing it at every keyframe would cost an optimisation each time.
    min_keyframes_between: int = 10
    # Geometric verification: PnP-RANSAC inliers on static features, with a relative depth check.
    min_inliers: int = 30
    reprojection_error: float = 3.0
    depth_tolerance: float = 0.1
    # The loop factor: a BetweenFactorPose3 under a robust kernel (Cauchy lets a wrong loop fade out).
    sigma_t: float = 0.02
    sigma_r_deg: float = 1.0
    kernel: str = "cauchy"
    kernel_k: float = 1.0
    # iSAM2 updates after adding a loop: a loop moves many variables far from their linearisation point.
    extra_updates: int = 8
    fuse_landmarks: bool = True
    # A loop whose factor disagrees with the optimised graph by more than this is removed again.
    max_residual_t: float = 0.05
    max_residual_r_deg: float = 3.0
    # Relocalization: candidates tried per lost frame and inliers needed.
    reloc_candidates: int = 5
    reloc_min_inliers: int = 30


POSITIVE = {f"loop.{name}" for name in (
    "min_covisible_shared", "consistency", "min_inliers", "reprojection_error", "depth_tolerance", "sigma_t",
    "sigma_r_deg", "kernel_k", "max_residual_t", "max_residual_r_deg", "max_candidates", "reloc_candidates",
    "reloc_min_inliers")}
NON_NEGATIVE = {"loop.exclude_recent", "loop.extra_updates", "loop.min_keyframes_between"}
UNIT_INTERVAL = {"loop.min_score_ratio"}


def validate_loop(cfg: LoopConfig, source: str, error: type) -> None:
    """Checks beyond signs and ranges (those are in slam.core.config's tables)."""
    if cfg.kernel not in KERNELS:
        raise error(f"{source}: 'loop.kernel' must be one of {', '.join(KERNELS)}, got '{cfg.kernel}'")
    if cfg.min_inliers < 4 or cfg.reloc_min_inliers < 4:
        raise error(f"{source}: 'loop.min_inliers' and 'loop.reloc_min_inliers' must be >= 4 (PnP needs 4 points)")
