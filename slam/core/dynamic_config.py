"""Typed configuration of the dynamic front end: detector, class groups, fusion and the four methods.

Parameter defaults follow the papers in ``../shared/seeds`` (see ``docs/dynamic.md`` for where we
deviate and why). Lives in ``slam`` so the config loader validates it with everything else.
"""
from __future__ import annotations

from dataclasses import dataclass, field

METHOD_NAMES = ("cpr", "box_depth", "flow_epipolar", "depth_sdf")
FUSION_MODES = ("single", "max", "noisy_or")
DETECTOR_MODELS = ("yolox_nano", "nanodet")


@dataclass
class DetectorConfig:
    model: str = "yolox_nano"
    # Empty: $DYNSLAM_DETECTOR_MODEL, else the model cache (dynslam download model), else
    # ../shared/models/<model file> beside the checkout (frontend/model_lookup.py).
    path: str = ""
    score_threshold: float = 0.3
    nms_iou: float = 0.45
    threads: int = 1
    # Folder for per-sequence detection caches (empty = no cache).
    cache_dir: str = ""


@dataclass
class ClassGroups:
    """COCO class ids (0-based). Dynamic targets (PDT), high/low-probability passive movers."""

    dynamic: list[int] = field(default_factory=lambda: [0, 15, 16, 17])          # person, cat, dog, horse
    high_passive: list[int] = field(default_factory=lambda: [24, 25, 26, 28, 39, 41, 56, 63, 64, 65, 66, 67, 73])
    low_passive: list[int] = field(default_factory=lambda: [57, 58, 59, 60, 62])
    high_passive_prob: float = 0.8
    low_passive_prob: float = 0.25


@dataclass
class CprConfig:
    """Sub-point-cloud correlation (CPR-SLAM, seed 000)."""

    weight: float = 1.0
    sample_step: int = 4
    max_depth: float = 6.0
    voxel_size: float = 0.05
    mls_radius: float = 0.1
    clusters: int = 10
    sigma_frame: int = 2
    sigma_keyframe: int = 5
    candidates: int = 10
    student_nu: float = 5.0
    icp_iterations: int = 6
    mad_scale: float = 1.4826
    circle_radius: int = 6
    refine_window: int = 6
    rho_keyframe: float = 3.0
    rho_frame: float = 2.0
    tau: float = 0.6
    seed: int = 0
    # Choices where the paper gives no number (reasons in frontend/dynamic/cpr.py).
    icp_intensity_iterations: int = 3   # the first ones of icp_iterations; the rest are plain ICP
    icp_max_points: int = 150           # points per sub-cloud used for its sub-pose
    score_points: int = 800             # source points averaged in R(j)
    score_candidates: int = 4           # nearest reference points searched per point for R(j)
    min_score_ratio: float = 1.0        # dynamic also needs R(j) > ratio * median(R); 1.0 = paper only
    refine: bool = False                # Algorithm 1 on every frame's output (off: raw mask, see cpr.py)
    keyframe_recompute: bool = False    # keyframes: recompute the mask against sigma_keyframe in end_frame


@dataclass
class BoxDepthConfig:
    """Bounding box + depth continuity (Fang et al., seed 001)."""

    weight: float = 1.0
    omega_pixel: float = 0.05        # depth step (m) the flood fill may cross between neighbours
    omega_pixel_passive: float = 0.1
    height_ratio: float = 0.75
    alpha: float = 1.0
    omega: float = 0.01
    k_passive: float = 5.0           # Eqs. 9/11 compare ratios >= 1 with K*p_pas: K must exceed 1/p_pas
    reuse_radius_px: float = 3.0
    reuse_gray: float = 10.0
    reuse_depth: float = 0.05
    reuse_prob: float = 0.3          # probability given to effective (reused) dynamic features
    invalid_fill_px: int = 2         # invalid-depth pixels this close to a segment join it


@dataclass
class FlowEpipolarConfig:
    """Optical flow + epipolar geometry + region probability (PPS-SLAM, seed 002)."""

    weight: float = 1.0
    epipolar_px: float = 2.0
    sub_box_rows: int = 3
    sub_box_cols: int = 3
    region_ratio: float = 0.5
    grid: int = 10
    history: int = 10
    cover_ratio: float = 0.65
    likelihood_dynamic: float = 0.9
    likelihood_static: float = 0.1
    remove_threshold: float = 0.5
    detector_score: float = 0.6
    seed: int = 0
    # Not in the paper (see frontend/dynamic/flow_epipolar.py): LK window/levels, forward-backward
    # check (px, 0 = off), RANSAC threshold for F, minimum tracks, F from points outside the boxes,
    # grid prior without history, posterior clamp [c, 1 - c] so that cells never freeze at 0 or 1.
    lk_window: int = 21
    lk_levels: int = 3
    fb_max_px: float = 0.0
    ransac_px: float = 1.0
    min_tracks: int = 15
    f_outside_boxes: bool = True
    initial_prior: float = 0.5
    prob_clamp: float = 0.05


@dataclass
class DepthSdfConfig:
    """Depth standard-deviation fitting (CP-SLAM, seed 003)."""

    weight: float = 1.0
    iterations: int = 20
    base_threshold: float = 0.02
    min_sigma: float = 0.01          # floor of the two-point depth std (m): equal depths give sigma = 0
    # "union": the inliers of every iteration are dynamic (the paper's Algorithm 1, S1 collects them);
    # "best": only those of the model with the most inliers (see frontend/dynamic/depth_sdf.py).
    combine: str = "union"
    seed: int = 0


@dataclass
class DynamicConfig:
    # Any subset of METHOD_NAMES; empty = dynamic handling off (every feature static).
    methods: list[str] = field(default_factory=list)
    fusion: str = "noisy_or"
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    classes: ClassGroups = field(default_factory=ClassGroups)
    cpr: CprConfig = field(default_factory=CprConfig)
    box_depth: BoxDepthConfig = field(default_factory=BoxDepthConfig)
    flow_epipolar: FlowEpipolarConfig = field(default_factory=FlowEpipolarConfig)
    depth_sdf: DepthSdfConfig = field(default_factory=DepthSdfConfig)
    # Features inside (dilated) dynamic-class boxes get at least this probability, fused like a
    # method: below the tracking threshold, so a still person's features may still track, but above
    # the landmark-admission threshold (backend.landmark_max_dynamic_prob), so nothing inside a
    # person box enters the map (as ORB-SLAM3 with depth zeroed in person boxes). 0 = off;
    # the fused preset configs/dynamic_all.yaml uses 0.3.
    box_prior: float = 0.0
    box_prior_dilate_px: int = 10
    # Optional folder for PNG mask overlays (empty = off).
    dump_masks_dir: str = ""
