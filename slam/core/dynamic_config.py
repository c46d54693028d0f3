"""Typed configuration of the dynamic front end: detector, class groups, fusion and the four methods.

Parameter defaults follow the papers in ``../shared/seeds`` (see ``docs/dynamic.md`` for where we
deviate and why). Lives in ``slam`` so the config loader validates it with everything else. Each limit
sits beside its field; method weights and every probability lie in [0, 1] (fusion multiplies them).
"""
from __future__ import annotations

from typing import Annotated, Literal, get_args

from pydantic import Field, field_validator, model_validator

from slam.core.config_base import ConfigSection, rule_error

MethodName = Literal["cpr", "box_depth", "flow_epipolar", "depth_sdf"]
FusionMode = Literal["single", "max", "noisy_or"]
DetectorModel = Literal["yolox_nano", "nanodet"]
METHOD_NAMES: tuple[str, ...] = get_args(MethodName)
FUSION_MODES: tuple[str, ...] = get_args(FusionMode)
DETECTOR_MODELS: tuple[str, ...] = get_args(DetectorModel)

CocoClass = Annotated[int, Field(ge=0, le=79)]   # the detectors' 80 COCO classes, 0-based
Lag = Annotated[float, Field(gt=0, le=10)]        # seconds back: 1.5x the longest is kept, ~150 kB a frame
_UNIT = dict(ge=0, le=1)   # weights and probabilities


class DetectorConfig(ConfigSection):
    model: DetectorModel = "yolox_nano"
    path: str = ""
    """Empty: $DYNSLAM_DETECTOR_MODEL, else the model cache (dynslam download model), else
    ../shared/models/<model file> beside the checkout (frontend/model_lookup.py)."""
    score_threshold: float = Field(0.3, **_UNIT)
    nms_iou: float = Field(0.45, **_UNIT)
    threads: int = Field(1, ge=1)
    fit_input: bool = False
    """Run YOLOX on the letterboxed image's own size rounded up to its largest stride (416 x 320 for
    640 x 480) instead of its exported 416 x 416 square: the same scale and weights, 22 % less detector
    time, boxes within IoU 0.9 of the square's (frontend/onnx_input_shape.py). Off by default: fr1/rpy-400
    over seeds 0-4 gave 0.0219-0.0268 m (median 0.0237) with it against 0.0218-0.0225 (0.0224) without
    (docs/design.md, "Detector input"). NanoDet-m keeps its square (its graph has fixed reshapes)."""
    hold_frames: int = Field(5, ge=0)
    """A dynamic-class box the detector loses is held this many frames, moved on at its corners' last
    velocity (frontend/dynamic/box_memory.py; 0 = off). Longer than the gaps a detector leaves on a
    person blurring past or filling the view (Bonn crowd: 3 frames), short enough (0.17 s at 30 Hz)
    that walking's accelerations (~1 m/s^2) move the person < 2 cm off the extrapolated box."""
    cache_dir: str = ""
    """Folder for per-sequence detection caches (empty = no cache)."""


class ClassGroups(ConfigSection):
    """COCO class ids (0-based). Dynamic targets (PDT), high/low-probability passive movers."""

    dynamic: list[CocoClass] = Field(default_factory=lambda: [0, 15, 16, 17])   # person, cat, dog, horse
    high_passive: list[CocoClass] = Field(
        default_factory=lambda: [24, 25, 26, 28, 39, 41, 56, 63, 64, 65, 66, 67, 73])
    low_passive: list[CocoClass] = Field(default_factory=lambda: [57, 58, 59, 60, 62])
    high_passive_prob: float = Field(0.8, **_UNIT)
    low_passive_prob: float = Field(0.25, **_UNIT)

    @model_validator(mode="after")
    def _disjoint(self) -> "ClassGroups":
        groups = {"dynamic": self.dynamic, "high_passive": self.high_passive, "low_passive": self.low_passive}
        names = list(groups)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                shared = sorted(set(groups[a]) & set(groups[b]))
                if shared:
                    raise rule_error(f"class id(s) {shared} are in both '{a}' and '{b}': a class has one "
                                     "role", a, b)
        if self.low_passive_prob > self.high_passive_prob:
            raise rule_error(f"'low_passive_prob' ({self.low_passive_prob}) must not exceed 'high_passive_prob' "
                             f"({self.high_passive_prob})", "low_passive_prob", "high_passive_prob")
        return self


class CprConfig(ConfigSection):
    """Sub-point-cloud correlation (CPR-SLAM, seed 000)."""

    weight: float = Field(0.2, **_UNIT)
    """Trust in the noisy-OR fusion (ignored by fusion 'single'): its MAD threshold flags 1-2 static
    sub-clouds in most frames, so alone it removes nothing (configs/dynamic_all.yaml)."""
    sample_step: int = Field(4, ge=1)   # pixels between samples
    max_depth: float = Field(6.0, gt=0)
    voxel_size: float = Field(0.05, gt=0)
    mls_radius: float = Field(0.1, gt=0)
    clusters: int = Field(10, ge=1)
    sigma_frame: int = Field(2, ge=1)   # frames back to the reference
    sigma_keyframe: int = Field(5, ge=1)
    candidates: int = Field(10, ge=1)   # kdtree; projective: 1 = the window's nearest, more = the window
    student_nu: float = Field(5.0, gt=0)   # Student-t degrees of freedom
    icp_iterations: int = Field(6, ge=1)
    mad_scale: float = Field(1.4826, gt=0)
    circle_radius: int = Field(6, ge=0)   # pixels painted around each dynamic sample
    refine_window: int = Field(6, ge=1)
    rho_keyframe: float = Field(3.0, gt=0)   # mask weights of Algorithm 1 (the total must be > 0)
    rho_frame: float = Field(2.0, gt=0)
    tau: float = Field(0.6, **_UNIT)   # fraction of the total weight (Algorithm 1)
    seed: int = Field(0, ge=0)
    # Choices where the paper gives no number (reasons in frontend/dynamic/cpr.py).
    icp_intensity_iterations: int = Field(3, ge=0)
    """The first ones of icp_iterations; the rest are plain ICP."""
    icp_max_points: int = Field(150, ge=3)
    """Points per sub-cloud used for its sub-pose (a rigid pose needs 3)."""
    score_points: int = Field(800, ge=1)
    """Source points averaged in R(j)."""
    score_candidates: int = Field(4, ge=1)
    """Nearest reference points searched per point for R(j) (kdtree; projective: 1 = the window's nearest,
    more = the whole window)."""
    association: Literal["projective", "kdtree"] = "projective"
    """Candidates for the ICP and R(j): reference samples in a pixel window around the projection (O(1), no
    tree) or the exact nearest neighbours in 3-D (the paper; ~15 ms more per frame on Bonn). See cpr.py."""
    projective_window: int = Field(1, ge=1, le=4)
    """projective: window half-width in sampling-grid cells ((2w+1)^2 candidates; 1 = 9, like the
    paper's 10 nearest); above 4 the window spans more than +-16 px: the projection is no longer local."""
    score_max_distance: float = Field(0.05, ge=0, le=1.0)
    """R(j): a point's distance counts at most this (m; 0 = unbounded, the paper). Projective candidates lie
    on the point's ray, so a point off every surface (moved people, occlusions) would otherwise add the
    depth gap behind it, metres; 5 cm = one voxel. Above 1 m it bounds nothing in a room."""
    min_score_ratio: float = Field(1.0, ge=0)
    """Dynamic also needs R(j) > ratio * median(R); 1.0 (or less) = the paper only."""
    refine: bool = False
    """Algorithm 1 on every frame's output (off: raw mask, see cpr.py)."""
    keyframe_recompute: bool = False
    """Keyframes: recompute the mask against sigma_keyframe in end_frame."""

    @model_validator(mode="after")
    def _intensity_within_icp(self) -> "CprConfig":
        if self.icp_intensity_iterations > self.icp_iterations:
            raise rule_error(f"'icp_intensity_iterations' ({self.icp_intensity_iterations}) must not exceed "
                             f"'icp_iterations' ({self.icp_iterations}): they are the first of those",
                             "icp_intensity_iterations", "icp_iterations")
        return self


class BoxDepthConfig(ConfigSection):
    """Bounding box + depth continuity (Fang et al., seed 001)."""

    weight: float = Field(1.0, **_UNIT)
    omega_pixel: float = Field(0.05, gt=0)
    """Depth step (m) the flood fill may cross between neighbours."""
    omega_pixel_passive: float = Field(0.1, gt=0)
    height_ratio: float = Field(0.75, gt=0, le=1)   # fraction of the box height a segment must span
    alpha: float = Field(1.0, gt=0)   # Eq. 8: alpha * mean depth bounds the segment's depth
    omega: float = Field(0.01, ge=0)   # Eq. 8: metres per pixel from the box side
    k_passive: float = Field(5.0, gt=0)
    """Eqs. 9/11 compare ratios >= 1 with K*p_pas: K must exceed 1/p_pas (checked with dynamic.classes)."""
    reuse_radius_px: float = Field(3.0, ge=0)
    reuse_gray: float = Field(10.0, ge=0, le=255)   # an 8-bit intensity difference
    reuse_depth: float = Field(0.05, ge=0)
    reuse_prob: float = Field(0.3, **_UNIT)
    """Probability given to effective (reused) dynamic features."""
    invalid_fill_px: int = Field(2, ge=0)
    """Invalid-depth pixels this close to a segment join it."""
    seed_past_occluder: bool = True
    """When the box's centre lies on something in front of the person (a monitor), seed the fill on the
    person's depth layer first (frontend/dynamic/box_depth.py); False: the paper's five seeds only."""
    eq8_border_on_body: bool = True
    """Eq. 8 trims pixels deeper than the fill's mean near a box side (overflow into the background). A side on
    the image border is where the view ends, not the person: there, pixels within 0.2 m of the person's depth
    layer are measured to the sides inside the image only (a person cut by the border keeps their pixels at
    it); False: all four sides for every pixel, as the paper prints it."""


class FlowEpipolarConfig(ConfigSection):
    """Optical flow + epipolar geometry + region probability (PPS-SLAM, seed 002)."""

    weight: float = Field(0.45, **_UNIT)
    """Noisy-OR trust: below 0.5 alone, so a second method must agree (configs/dynamic_all.yaml)."""
    epipolar_px: float = Field(2.0, gt=0)
    sub_box_rows: int = Field(3, ge=1)
    sub_box_cols: int = Field(3, ge=1)
    region_ratio: float = Field(0.5, **_UNIT)
    grid: int = Field(10, ge=1)
    history: int = Field(10, ge=1)
    cover_ratio: float = Field(0.65, **_UNIT)
    likelihood_dynamic: float = Field(0.9, **_UNIT)
    likelihood_static: float = Field(0.1, **_UNIT)
    remove_threshold: float = Field(0.5, **_UNIT)
    detector_score: float = Field(0.6, **_UNIT)
    seed: int = Field(0, ge=0)
    """Given to ``cv2.setRNGSeed`` before F's RANSAC; OpenCV 4 and 5 draw RANSAC's samples from a generator of
    their own with a fixed state, so today it changes nothing (the fit is the same in every run)."""
    # Not in the paper (see frontend/dynamic/flow_epipolar.py): LK window/levels, forward-backward
    # check (px, 0 = off), RANSAC threshold for F, minimum tracks, F from points outside the boxes,
    # grid prior without history, posterior clamp [c, 1 - c] so that cells never freeze at 0 or 1.
    lk_window: int = Field(21, ge=3)   # OpenCV's LK needs a window of a few pixels
    lk_levels: int = Field(3, ge=0)   # 0 = no pyramid
    lk_start_level: int = Field(0, ge=0, le=2)
    """Pyramid level the flow is measured on: 0 = full resolution, 1 = half (with ``lk_window`` 11 the
    window spans 22 full-resolution pixels, like 21 at full size, at about a quarter of the CPU; see
    frontend/dynamic/flow_epipolar.py); above 2 a 640 px image is 80 px wide, too coarse to track corners."""
    fb_max_px: float = Field(0.0, ge=0)
    ransac_px: float = Field(1.0, gt=0)
    min_tracks: int = Field(15, ge=8)   # the eight-point algorithm needs 8 correspondences for F
    f_outside_boxes: bool = True
    initial_prior: float = Field(0.5, **_UNIT)
    prob_clamp: float = Field(0.05, ge=0, lt=0.5)   # [c, 1 - c] is empty from 0.5 on

    @model_validator(mode="after")
    def _likelihoods_ordered(self) -> "FlowEpipolarConfig":
        if self.likelihood_static > self.likelihood_dynamic:
            raise rule_error(f"'likelihood_static' ({self.likelihood_static}) must not exceed 'likelihood_dynamic' "
                             f"({self.likelihood_dynamic}): covered cells would become less likely dynamic",
                             "likelihood_static", "likelihood_dynamic")
        return self


class DepthSdfConfig(ConfigSection):
    """Depth standard-deviation fitting (CP-SLAM, seed 003)."""

    weight: float = Field(0.45, **_UNIT)
    """Noisy-OR trust: below 0.5 alone, so a second method must agree (configs/dynamic_all.yaml)."""
    iterations: int = Field(20, ge=1)
    base_threshold: float = Field(0.02, gt=0)   # metres
    min_sigma: float = Field(0.01, gt=0)
    """Floor of the two-point depth std (m): equal depths give sigma = 0."""
    combine: Literal["union", "best"] = "union"
    """"union": the inliers of every iteration are dynamic (the paper's Algorithm 1, S1 collects them);
    "best": only those of the model with the most inliers (see frontend/dynamic/depth_sdf.py)."""
    seed: int = Field(0, ge=0)


class DynamicConfig(ConfigSection):
    """Dynamic-object handling: which methods run and how their probabilities are fused."""

    methods: list[MethodName] = Field(default_factory=lambda: list(METHOD_NAMES))
    """Any subset of the methods; empty (configs/static.yaml) = dynamic handling off, every feature
    static. All four by default: a dynamic SLAM system handles people without being asked to."""
    fusion: FusionMode = "noisy_or"
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    classes: ClassGroups = Field(default_factory=ClassGroups)
    cpr: CprConfig = Field(default_factory=CprConfig)
    box_depth: BoxDepthConfig = Field(default_factory=BoxDepthConfig)
    flow_epipolar: FlowEpipolarConfig = Field(default_factory=FlowEpipolarConfig)
    depth_sdf: DepthSdfConfig = Field(default_factory=DepthSdfConfig)
    box_prior: float = Field(0.3, **_UNIT)
    """Features inside (dilated) dynamic-class boxes get at least this probability, fused like a method:
    below the tracking threshold, so a still person's features may still track, but above the
    landmark-admission threshold (backend.landmark_max_dynamic_prob), so nothing inside a person box
    enters the map (as ORB-SLAM3 with depth zeroed in person boxes). 0 = off."""
    box_prior_dilate_px: int = Field(10, ge=0)
    box_prior_on_body: bool = True
    """The prior only where a feature could be on the person, in the boxes ``box_prior_on_body_max_fill``
    admits: a feature in such a person box more than a body's reach (0.7 m) in depth from the person layer of
    every box holding it, and more than ``box_prior_dilate_px`` from the rest of the boxes, keeps the methods'
    own probability (``keyframe_masks.features_off_body``), so the desk or wall a box frames may be mapped.
    False: the prior on every feature in every box (the preset ``dynamic_box_prior``, the box-mask baseline)."""
    box_prior_on_body_max_fill: float = Field(0.33, gt=0.0, le=1.0)
    """Boxes where ``box_prior_on_body`` applies: those whose person layer (within 0.2 m of its depth) fills
    less than this share of the box, and no pixel of any other box. A third: an upright person in full view
    fills half their box or more (generated three_close: median 0.65, quartile 0.56), while a walker crossing a
    rolled camera's view diagonally, or a person mostly hidden, leaves most of it to what lies behind.
    Measured 2026-12-01 (docs/dynamic.md, "The box prior off the body, in sparse boxes only"): in every box
    (1.0) it fixed composited two_walk at 150 frames but took generated three_close over its 1.5x bar; with a
    third, three_close and the other generated scenes are unchanged, two_walk at 150 frames goes 2.28 / 1.28 /
    2.16x -> 1.11 / 0.86 / 2.46x (seeds 0-2), Bonn crowd-480 0.0104 -> 0.0102 m (median of seeds 0-2)."""
    motion_region_votes: int = Field(3, ge=0)
    """Detector-free evidence (frontend/dynamic/region_motion.py): a connected region of cpr's mask in
    which at least this many of flow_epipolar's tracks move against the epipolar geometry, and at least
    ``motion_region_share`` of its tracks, is moving (probability 0.9 on its features and pixels). Needs
    cpr and flow_epipolar; 0 = off. Three: more than a RANSAC outlier or two in one region."""
    motion_region_share: float = Field(0.2, **_UNIT)
    """A fifth: the share of a walking person's tracks the epipolar test flags (per-pixel recall
    0.17-0.33 on the generated scenes), far above its false alarms on static surfaces."""
    near_occluders: bool = True
    """Hole regions of the depth image that hide a surface the frame before measured (a person nearer than the
    sensor's ~0.5 m range; frontend/dynamic/near_occluder.py) are moving (probability 0.9 on their features
    and pixels, as a confirmed motion region). Exact synthetic depth has no holes: no change there."""
    still_window_s: float = Field(0.5, ge=0)
    """A person whose torso stayed within ``still_max_move_m`` in the world for this long (or whose surface,
    followed by the point tracks on it, did for twice as long) stands still: in their box the keyframe masks
    (moving surfaces) count only cpr and flow_epipolar (motion evidence), and ``masks/<index>_still.png``
    keeps them out of dense maps (frontend/dynamic/region_motion.py, surface_drift.py). Tracking and the
    map keep them out either way. 0 = off: every person counts as moving."""
    still_max_move_m: float = Field(0.15, gt=0)
    """0.15 m in 0.5 s is 0.3 m/s: half the slowest walking pace, 5x a standing person's sway."""
    mask_free_space_lags_s: list[Lag] = Field(default_factory=lambda: [0.5, 1.0])
    """The keyframe masks keep as moving only pixels that stand where a frame this long before saw a surface
    clearly behind them, where such a frame can tell (frontend/dynamic/free_space.py: 0.5 / 1.0 s, a slow
    walker's 0.25 / 0.5 m). Empty = off. Tracking and the map are unaffected."""
    mask_region_lags_s: list[Lag] = Field(default_factory=lambda: [0.25])
    """Frames this long before a keyframe add to its moving *regions* only (free space; never "unmoved": 0.25 s
    back a walker still covers much of where they are). On a fast turn they still see the part of the view
    the long lags no longer do (fr1/rpy's median turn: 14 degrees in 0.25 s, 56 in 1 s). Needs the lags above."""
    mask_clear_lags_s: list[Lag] = Field(default_factory=lambda: [2.0, 3.0])
    """Frames this long before and after a keyframe may only *clear* its flagged pixels, and only those the
    lags above could not tell about (out of their view on a turn, or hidden then), where every such frame
    that can tell shows them unmoved (free space). By then a walker at 0.5 m/s has moved 1-1.5 m, clear of
    where they stood; their "moved" is never evidence (the poses drift apart over seconds). Needs the lags above.
    Frames are kept for 1.5x the longest lag: 4.5 s, ~20 MB at 30 Hz. Empty = off."""
    mask_free_space_margin_m: float = Field(0.1, ge=0)
    """A point counts as in front of the earlier surface by more than this plus 3 sigma of depth noise."""
    mask_free_space_window_px: int = Field(20, ge=1)
    """The earlier depth is the nearest within this window (px): 2 degrees of pose or edge error."""
    dump_masks_dir: str = ""
    """Optional folder for PNG mask overlays (empty = off)."""

    @field_validator("methods")
    @classmethod
    def _no_repeats(cls, methods: list[str]) -> list[str]:
        if len(set(methods)) != len(methods):
            raise rule_error(f"lists a method twice: {methods}")
        return methods

    @model_validator(mode="after")
    def _consistent(self) -> "DynamicConfig":
        if self.fusion == "single" and len(self.methods) > 1:
            raise rule_error(f"'fusion' is 'single' but {len(self.methods)} methods are enabled in 'methods' "
                             "(use max or noisy_or to fuse several)", "fusion", "methods")
        # Only box_depth reads k_passive; a passive probability of 0 switches that group off.
        p_pas = self.classes.low_passive_prob   # the smaller one (ClassGroups checks)
        if "box_depth" in self.methods and p_pas > 0 and not self.box_depth.k_passive * p_pas > 1:
            raise rule_error(f"'box_depth.k_passive' ({self.box_depth.k_passive}) times 'classes.low_passive_prob' "
                             f"({p_pas}) must exceed 1: Eqs. 9/11 compare ratios >= 1 with it",
                             "box_depth.k_passive", "classes.low_passive_prob")
        return self
