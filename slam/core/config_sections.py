"""Config sections of the sensor, the ORB front end, tracking, keyframes, the back end, the run's pacing,
outputs and maps.

Each limit sits beside its field with the reason it holds; rules between fields are model validators
whose message says why. The dynamic front end and loop closing have their own modules
(slam.core.dynamic_config, slam.core.loop_config).
"""
from __future__ import annotations

from typing import Literal, Optional, get_args

from pydantic import Field, field_validator, model_validator

from slam.core.config_base import ConfigSection, rule_error

# Trajectory file formats a run can write besides TUM (slam.run.trajectory_formats implements them).
TrajectoryFormat = Literal["tum", "kitti", "euroc"]
TRAJECTORY_FORMATS: tuple[str, ...] = get_args(TrajectoryFormat)

_PROBABILITY = dict(ge=0, le=1)   # probabilities, ratios of counts and weights


class CameraConfig(ConfigSection):
    """The RGB-D sensor: pinhole intrinsics, distortion, image size, depth units and range."""

    name: str = "synthetic"
    fx: float = Field(525.0, gt=0)   # focal lengths in pixels are positive
    fy: float = Field(525.0, gt=0)
    cx: float = Field(319.5, ge=0)   # the principal point lies in the image (checked against its size)
    cy: float = Field(239.5, ge=0)
    distortion: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0])
    """OpenCV order k1 k2 p1 p2 [k3]; zeros for already undistorted images."""
    width: int = Field(640, ge=1)
    height: int = Field(480, ge=1)
    depth_scale: float = Field(5000.0, gt=0)
    """Depth image units per metre (TUM: 5000)."""
    bf: float = Field(40.0, gt=0)
    """fx times the virtual stereo baseline (ORB-SLAM's Camera.bf): turns depth into a right-image u."""
    depth_threshold: float = Field(40.0, gt=0)
    """Points closer than depth_threshold baselines count as "close" (ORB-SLAM's ThDepth)."""
    min_depth: float = Field(0.1, ge=0)   # metres; depth is never negative
    max_depth: float = Field(8.0, gt=0)
    fps: float = Field(30.0, gt=0)

    @field_validator("distortion")
    @classmethod
    def _four_or_five(cls, value: list[float]) -> list[float]:
        if len(value) not in (4, 5):
            raise rule_error(f"needs 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {len(value)}")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> "CameraConfig":
        if self.min_depth >= self.max_depth:
            raise rule_error(f"'min_depth' ({self.min_depth}) must be below 'max_depth' ({self.max_depth}): "
                             "no depth would be usable", "min_depth", "max_depth")
        if self.cx > self.width or self.cy > self.height:
            raise rule_error(f"the principal point ('cx' {self.cx}, 'cy' {self.cy}) must lie inside the image "
                             f"('width' {self.width}, 'height' {self.height})", "cx", "cy", "width", "height")
        return self


class OrbConfig(ConfigSection):
    """ORB extraction (OpenCV's detector, then an ORB-SLAM-style grid distribution)."""

    n_features: int = Field(1000, ge=1)
    scale_factor: float = Field(1.2, gt=1)   # each pyramid level must be smaller than the one before
    n_levels: int = Field(8, ge=1)
    fast_threshold: int = Field(7, ge=1, le=255)
    """FAST threshold (an 8-bit intensity step); a low one lets weak corners fill textureless cells,
    the grid distribution then keeps only the strongest per cell."""
    oversample: float = Field(3.0, ge=1)
    """Detected before distribution, as a multiple of n_features (below 1 the grid could never fill)."""
    cell_size: int = Field(32, ge=1)   # pixels
    edge_threshold: int = Field(19, ge=0)   # border in pixels where no feature is detected


class TrackingConfig(ConfigSection):
    """Frame-to-frame and frame-to-local-map tracking, pose-only optimisation."""

    motion_search_radius: float = Field(15.0, gt=0)
    """Search radius (px at level 0) when matching by projection with the motion model."""
    local_map_search_radius: float = Field(4.0, gt=0)
    # Hamming distances between 256-bit ORB descriptors lie in [0, 256].
    max_descriptor_distance: int = Field(100, ge=0, le=256)
    strict_descriptor_distance: int = Field(50, ge=0, le=256)
    match_ratio: float = Field(0.8, gt=0, le=1)   # Lowe's ratio: best/second best, 0 would reject all
    min_motion_matches: int = Field(20, ge=0)   # minimum counts: 0 = no minimum
    min_tracked_inliers: int = Field(30, ge=0)
    max_pose_sigma_m: float = Field(0.010, gt=0)
    """A frame is LOST, not tracked, when its static inliers fix its position no better than this (1 sigma
    along the weakest direction, from the pose optimisation's information without the motion prior). The
    bound sits at twice the 95th percentile of the noisiest sensor we measure (Bonn's Xtion: 1-sigma median
    3 mm, p95 4.7 mm; fr1/rpy: median 0.7, max 4.4 mm; generated scenes: median 3 mm): beyond it the pose
    rests on a small, badly spread part of the view - a person filling it leaves a few far points that
    agree on a pose they barely determine - and such a frame, made a keyframe, places its new landmarks
    with that error for every later frame to inherit (three_close: frame 111 tracked at 22.8 mm and made
    a keyframe left the frames after the crowd 10-19 mm off; LOST, they are 3-5 mm off). Swept at 25 / 15 / 10 mm, seeds 0-2
    (docs/dynamic.md): three_close ATE 5.9 / 4.9 / 4.0 mm, close_pass 3.8 / 3.1 / 2.9 mm (0 / 13 / 15
    frames LOST), Bonn crowd 0.0103 m at all three (0 / 0-3 / 1-6 frames LOST: 319 and 446-450, its known
    weak stretch), fr1/rpy, stand_walk and border unchanged; at 5 mm ordinary frames go LOST (Bonn
    426/480 tracked, three_close 45/150)."""
    min_init_features: int = Field(300, ge=0)
    refine_frames: int = Field(0, ge=0)
    """With N > 0, the tracked frames between keyframes are solved again against the final map at the end of
    a run (slam/runtime/frame_refinement.py), the newest N of them (their matches kept meanwhile, ~8 KB a
    frame: 24 MB at 3,000, more frames than a TUM or Bonn sequence has). 0 = off, the default: every absolute
    error measured fell or held (fr1/rpy-400 0.0233 -> 0.0220 m, Bonn crowd-480 0.0102 -> 0.0103, the
    generated path without people 2.8 -> 2.0 mm, three_close 4.2 -> 3.5 mm), but the paths without people
    gain most, so the hard scenes' ratio to them, issue 11's bar, rose (three_close 1.49 -> 1.76 over 1.5,
    close_pass and stand_walk too; docs/design.md, "The frames between keyframes")."""
    pose_iterations: int = Field(10, ge=1)
    pose_rounds: int = Field(4, ge=1)
    chi2_mono: float = Field(5.991, gt=0)   # chi-square thresholds (95 %, 2 and 3 dof)
    chi2_stereo: float = Field(7.815, gt=0)
    dynamic_threshold: float = Field(0.5, **_PROBABILITY)
    """Features whose fused dynamic probability reaches this are kept out of tracking."""
    motion_prior_sigma_m: float = Field(0.0, ge=0)
    motion_prior_sigma_deg: float = Field(0.5, ge=0)
    """Per-axis sigmas of the constant-velocity prediction as a prior in the frame's pose optimisation
    (0 in either = no prior, the default). Sized to what a hand-held camera's motion changes in one 30 Hz
    frame (acceleration x dt^2: ~3 mm at 3 m/s^2, ~0.2 deg at 200 deg/s^2), 0.01 m / 0.5 deg is weak
    against a full view. Off by default, measured: on the hard scenes (close_pass, three_close, seeds
    0-2) it summed to 52 mm of ATE vs 34 mm without; it holds a weakly tracked frame near a velocity
    that its own noisy predecessors set, and through a crowded stretch the bias accumulates into drift
    (three_close seed 2: 24.9 vs 8.0 mm). On fr1/rpy and Bonn crowd it changed ATE by < 1 mm."""
    min_static_features: int = Field(400, ge=0)
    """When fewer static features remain (people filling the view), extract more from the static part
    of the image (0 = never)."""
    local_keyframes: int = Field(20, ge=1)
    covisible_per_keyframe: int = Field(10, ge=1)

    @model_validator(mode="after")
    def _strict_below_max(self) -> "TrackingConfig":
        if self.strict_descriptor_distance > self.max_descriptor_distance:
            raise rule_error(f"'strict_descriptor_distance' ({self.strict_descriptor_distance}) must not exceed "
                             f"'max_descriptor_distance' ({self.max_descriptor_distance}): the strict test is "
                             "the tighter one", "strict_descriptor_distance", "max_descriptor_distance")
        return self


class KeyframeConfig(ConfigSection):
    """When a frame becomes a keyframe.

    A keyframe at least every max_frames frames, provided the camera moved enough since the last one:
    frequent keyframes give iSAM2 more constraints (measured: 0.036 m -> 0.026 m ATE on fr1/rpy going
    from 30 to 5), while a still camera does not flood the graph."""

    max_frames: int = Field(5, ge=1)
    min_motion_t: float = Field(0.02, gt=0)   # metres
    min_motion_deg: float = Field(2.0, gt=0)
    min_frames: int = Field(0, ge=0)
    tracked_ratio: float = Field(0.75, **_PROBABILITY)
    close_tracked_min: int = Field(100, ge=0)
    """ORB-SLAM's "need to insert close points": few tracked close points, many untracked ones."""
    close_untracked_min: int = Field(70, ge=0)
    revisit_ratio: float = Field(0.5, ge=0, le=1)
    """A keyframe due by max_frames is not made while an older keyframe sharing the tracked landmarks is
    nearer than this fraction of the distance to the last one (0 = off): the frame then lies between
    keyframes the map already has, at most half a keyframe spacing from one, so it would add a
    redundant view (a camera passing its old path every lap would otherwise grow the map per lap)."""
    max_new_landmarks: int = Field(600, ge=1)
    min_new_landmarks: int = Field(100, ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> "KeyframeConfig":
        if self.min_new_landmarks > self.max_new_landmarks:
            raise rule_error(f"'min_new_landmarks' ({self.min_new_landmarks}) must not exceed 'max_new_landmarks' "
                             f"({self.max_new_landmarks})", "min_new_landmarks", "max_new_landmarks")
        return self


class BackendConfig(ConfigSection):
    """iSAM2 back end: noise models, robust kernel, culling, dynamic down-weighting.

    backend.graph.BackendParams takes its defaults from here (one source of truth)."""

    worker_process: bool = True
    """Solve the graph in a worker process so tracking does not wait for it (slam/runtime/graph_process.py);
    results are applied at the next keyframe, so runs stay deterministic. False: solve in line (what a
    debugger or a profiler wants)."""
    loop_result_keyframes: int = Field(0, ge=0)
    """With the worker process (dataset mode): 0, the keyframe that closes (or drops) a loop waits for the
    loop's correction (0.5-2 s of the worker's CPU on Bonn crowd-480; every later pose, landmark and loop
    check builds on the corrected map). k >= 1: tracking goes on; the loop's query side moves rigidly in the
    map at once (ORB-SLAM's first step of CorrectLoop), the keyframes between hand the worker nothing (their
    windows folded into one, as ORB-SLAM's local mapping stops while a loop is corrected), and the
    correction is applied at the k-th keyframe after, waiting only if the worker is not done; still
    deterministic. 4 covers a 2 s correction at this machine's ~0.8 s per keyframe. Measured with 4 against
    0 (2026-12-01, `tools/benchmark.py --set backend.loop_result_keyframes=4`; docs/design.md "Runtime"):
    tracking's wait for the back end Bonn 14.2 -> 3.7 ms/frame (longest 2.1 s -> 0.3 s), fr1/rpy 7.7 ->
    2.8; Bonn's whole run 166 -> 149 ms/frame; ATE fr1/rpy 0.0233 -> 0.0225 m, Bonn 0.0102 -> 0.0101 m but
    frames 447-450 LOST, its dense map's ghost share 0.0030 -> 0.0032 (over the gate of
    tests/test_map_export.py), the drift room of tests/test_loop_closing.py 0.0185 -> 0.0226 m. Not the
    default yet: accuracy first."""
    optimizer: Literal["window", "isam2"] = "window"
    """"window": local bundle adjustment around each new keyframe, loops through a pose graph and a
    bundle adjustment of the loop's span (backend/window_graph.py; cost per keyframe flat as the map
    grows). "isam2": one iSAM2 graph over the whole map (backend/graph.py; cost per keyframe grows with
    the map and its loops: 74 -> 2,069 ms per keyframe over a generated 1,500-frame orbit)."""
    window_keyframes: int = Field(6, ge=2)
    """Keyframes adjusted per new keyframe (the newest and its most covisible); a window needs two."""
    window_fixed_keyframes: int = Field(10, ge=1)
    """Keyframes outside the window held fixed (those seeing most of its landmarks); the rest's views of
    those landmarks are left out of that adjustment, so revisiting a place does not grow its cost."""
    window_iterations: int = Field(10, ge=1)
    """Levenberg-Marquardt iterations of a window. ORB-SLAM's local BA runs 5, removes outliers, then 10
    more; with Huber kernels instead of removal, 10 in one pass. Measured on fr1/rpy, default config:
    0.0224 m with 10, 0.0244 m with 5 (which halves the worker's time per keyframe)."""
    window_relative_tol: float = Field(1e-2, gt=0, lt=1)
    """A window's or a loop's adjustment stops when an iteration lowers its cost by less than this fraction.
    Each keyframe is adjusted again in the next ~window_keyframes windows and by the final adjustment, so
    one window need not converge: on three captured fr1/rpy windows an iteration costs 21-28 ms, and where
    an iteration first gained less than 1 % the cameras were within 3 mm of the converged solution, which
    the next windows take up. Measured (``python tools/sweep.py``, seeds 0-2, default config, ATE median
    (min-max)): 1e-3 -> 1e-2 cut the worker's time per keyframe (solved in line) 142 -> 75 ms on fr1/rpy
    and 134 -> 105 ms on Bonn-480, ATE fr1/rpy 0.0242 (0.0222-0.0248) -> 0.0227 (0.0227-0.0236) m, Bonn-480
    0.0104 (0.0098-0.0111) -> 0.0103 (0.0099-0.0108) m; 3e-3 gave 0.0222 / 0.0104 m; the drift room of
    tests/test_loop_closing.py 0.0181 -> 0.0185 m. Loops at 1e-3 with windows at 1e-2 (tried) changed which
    Bonn frames became keyframes and put the dense map's ghost share from frame 230 at 0.0040 (the seeds'
    spread at 1e-3 is 0.0030-0.0037; tests/test_map_export.py), so one tolerance serves both. (Earlier,
    1e-5 -> 1e-3 cut the worker's CPU time by 28-39 %.) The final adjustment stops at
    ``WindowParams.final_relative_tol`` (1e-3: the same final trajectory within 0.25 mm as 1e-5, a third of
    its time)."""
    window_solver: Literal["gtsam", "schur"] = "schur"
    """What solves a window's, a loop's and the final bundle adjustment (``optimizer: window``): "gtsam",
    GTSAM's Levenberg-Marquardt on the factor graph; "schur", the same cost and the same Levenberg-Marquardt
    rules with the landmarks eliminated per 3x3 block in compiled loops (backend/window_solver.py)."""
    essential_min_shared: int = Field(100, ge=1)
    """Loop correction: keyframe pairs sharing this many landmarks are tied in the pose graph (ORB-SLAM: 100)."""
    final_global_ba: bool = True
    """One bundle adjustment of the whole map after the last frame, before the results are written (as
    ORB-SLAM's full BA after a loop). The windows leave the map locally right but globally bent where a
    window never saw the whole: fr1/rpy with the default config 0.0337 m without, 0.0243 m with. Its cost
    grows with the map but is paid once, when nobody waits for a pose."""
    smoothing_sigma_acc: float = Field(2.0, ge=0)
    """The final trajectory's camera positions are smoothed with a motion model whose
    acceleration has this sigma per axis (m/s^2), each frame weighed by its own tracking covariance
    (slam/runtime/trajectory_smoother.py); 0 = off. 2 m/s^2 per axis covers the 99th percentile of the
    ground-truth camera accelerations (norm, at 30 Hz, mocap noise included) of TUM fr1 rpy/xyz/desk
    (1.5-3.1) and Bonn crowd (1.1): hand-held motion. The online trajectory is never smoothed."""
    final_global_ba_max_keyframes: int = Field(300, ge=2)
    """Bound of that adjustment: beyond it only the newest keyframes are adjusted (against fixed neighbours).
    The whole of a 1,000-keyframe map (5,000 generated frames) took minutes and 6 GB; 300 keyframes cover
    the full TUM/Bonn sequences (100-200 keyframes)."""
    relinearize_threshold: float = Field(0.01, gt=0)
    relinearize_skip: int = Field(5, ge=1)   # relinearise every n-th update (gtsam needs n >= 1)
    extra_updates: int = Field(1, ge=0)
    pixel_sigma: float = Field(1.0, gt=0)   # noise sigmas are positive
    depth_noise_coeff: float = Field(0.004, ge=0)
    """Depth noise sigma_z = depth_noise_coeff * z^2 (Kinect-class sensors). Fitted on fr1/rpy
    residuals: disparity errors were ~2.5x those of the 0.0015 z^2 sensor model."""
    huber_k: float = Field(2.8, gt=0)
    odometry_sigma_t: float = Field(0.05, gt=0)
    """Loose relative-pose prior between consecutive keyframes: keeps every keyframe constrained."""
    odometry_sigma_r_deg: float = Field(2.0, gt=0)
    covisibility_min_shared: int = Field(15, ge=1)
    cull_found_ratio: float = Field(0.25, **_PROBABILITY)
    cull_min_observations: int = Field(2, ge=0)
    cull_after_keyframes: int = Field(3, ge=0)
    max_dynamic_inflation: float = Field(100.0, ge=1)
    """Dynamic probability inflates observation noise by 1 / (1 - p)^2, capped here (a cap below 1
    would shrink the noise of the features most likely to move)."""
    dynamic_removal_threshold: float = Field(0.7, **_PROBABILITY)
    landmark_max_dynamic_prob: float = Field(0.25, **_PROBABILITY)
    """New landmarks only from features below this dynamic probability (stricter than tracking's)."""


class RuntimeConfig(ConfigSection):
    """How a run keeps pace with its source (slam.run.pipeline, slam.runtime.graph_process)."""

    realtime: Optional[bool] = None
    """true: realtime mode, nothing waits for SLAM and SLAM never waits for its back end. The graph
    worker's (backend.worker_process) results are applied whenever they arrive (the keyframe that closes a loop does not wait for
    its correction either), and a recording is replayed at its recorded rate: a frame whose successor is
    already due when the system is ready is dropped (summary.json: dropped_frames). Not deterministic:
    which frames are dropped and when results land depend on the machine's speed.
    false: dataset mode, every frame processed and results applied at fixed points: the same input and
    config give the same files byte for byte.
    null (default): realtime for a live camera (it drops frames anyway), dataset mode for a recording."""


class OutputConfig(ConfigSection):
    """What a run writes besides the trajectory (see README "Outputs")."""

    results_dir: str = "results"
    online_trajectory: bool = True
    trajectory_formats: list[TrajectoryFormat] = Field(default_factory=lambda: ["tum"])
    """Formats of the trajectory files (TUM is always written; kitti/euroc add copies)."""
    report: bool = True
    """report/ folder: plots and index.html (a plotting failure only logs a warning)."""


class MapExportConfig(ConfigSection):
    """Maps a run leaves behind and ``dynslam export`` builds (slam.run.map_export, slam.run.tsdf)."""

    save_map: bool = True
    """<results>/map.npz, so the sparse map can be regenerated."""
    sparse_ply: bool = True
    """<results>/map_sparse.ply at the end of each run."""
    voxel_size: float = Field(0.025, gt=0)
    """TSDF voxel edge (m); coarsened with a warning past max_voxels."""
    truncation: float = Field(0.1, gt=0)
    """TSDF truncation distance (m), at least 2 voxels."""
    depth_max: float = Field(4.0, gt=0)
    """Depth beyond this (m) is not fused: far Kinect-class depth is noise."""
    depth_edge_ratio: float = Field(0.05, ge=0)
    """Depth pixels whose 5x5 neighbourhood spans more than this fraction of their depth are left out:
    flying pixels at depth edges otherwise leave streaks in free space (0 = keep all)."""
    mask_threshold: float = Field(0.5, **_PROBABILITY)
    """Pixels whose dynamic probability reaches mask_threshold, grown by mask_dilate_px (silhouettes
    are where the masks are least sure), get depth 0 before fusion, so movers leave no ghosts."""
    mask_dilate_px: int = Field(5, ge=0)
    max_voxels: int = Field(8_000_000, ge=1)
    """The uniform volume costs ~47 bytes per voxel: 8M voxels ~ 380 MB whatever the scene."""

    @model_validator(mode="after")
    def _truncation_spans_voxels(self) -> "MapExportConfig":
        if self.truncation < 2 * self.voxel_size:
            raise rule_error(f"'truncation' ({self.truncation}) must be at least twice 'voxel_size' "
                             f"({self.voxel_size}): thinner bands leave holes in the mesh",
                             "truncation", "voxel_size")
        return self
