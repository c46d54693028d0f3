"""Typed configuration loaded from YAML and validated on load.

A config file holds any subset of the sections below; whatever it leaves out keeps its default.
Presets in ``configs/`` are such partial files. Validation names the file and the dotted key of the
first problem, so a typo in a user's YAML never silently falls back to a default.
"""
from __future__ import annotations

import importlib.resources

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from slam.core.dynamic_config import DETECTOR_MODELS, FUSION_MODES, METHOD_NAMES, DynamicConfig
from slam.core.loop_config import NON_NEGATIVE as LOOP_NON_NEGATIVE, POSITIVE as LOOP_POSITIVE
from slam.core.loop_config import UNIT_INTERVAL as LOOP_UNIT_INTERVAL, LoopConfig, validate_loop
from slam.core.errors import DynslamError



def _preset_dir() -> Path:
    """configs/ of the checkout, shipped in the wheel as the package slam.presets (pyproject.toml);
    a source tree that was never installed has only the folder beside the packages."""
    try:
        return Path(str(importlib.resources.files("slam.presets")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "configs"


CONFIG_DIR = _preset_dir()


class ConfigError(DynslamError, ValueError):
    """A config file or value is wrong; the message names the file and the key."""


@dataclass
class CameraConfig:
    name: str = "synthetic"
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    # OpenCV order k1 k2 p1 p2 k3; zeros for already undistorted images.
    distortion: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0])
    width: int = 640
    height: int = 480
    depth_scale: float = 5000.0
    # fx times the virtual stereo baseline (ORB-SLAM's Camera.bf): turns depth into a right-image u.
    bf: float = 40.0
    # Points closer than depth_threshold baselines count as "close" (ORB-SLAM's ThDepth).
    depth_threshold: float = 40.0
    min_depth: float = 0.1
    max_depth: float = 8.0
    fps: float = 30.0


@dataclass
class OrbConfig:
    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    # FAST threshold of the detector; a low one lets weak corners fill textureless cells,
    # the grid distribution then keeps only the strongest per cell.
    fast_threshold: int = 7
    # Detected before distribution, as a multiple of n_features.
    oversample: float = 3.0
    cell_size: int = 32
    edge_threshold: int = 19


@dataclass
class TrackingConfig:
    # Search radius (px at level 0) when matching by projection with the motion model.
    motion_search_radius: float = 15.0
    local_map_search_radius: float = 4.0
    max_descriptor_distance: int = 100
    strict_descriptor_distance: int = 50
    match_ratio: float = 0.8
    min_motion_matches: int = 20
    min_tracked_inliers: int = 30
    min_init_features: int = 300
    pose_iterations: int = 10
    pose_rounds: int = 4
    chi2_mono: float = 5.991
    chi2_stereo: float = 7.815
    # Features whose fused dynamic probability reaches this are kept out of tracking.
    dynamic_threshold: float = 0.5
    # When fewer static features remain (people filling the view), extract more from the static
    # part of the image (0 = never).
    min_static_features: int = 400
    local_keyframes: int = 20
    covisible_per_keyframe: int = 10


@dataclass
class KeyframeConfig:
    # A keyframe at least every max_frames frames, provided the camera moved enough since the last
    # one: frequent keyframes give iSAM2 more constraints (measured: 0.036 m -> 0.026 m ATE on
    # fr1/rpy going from 30 to 5), while a still camera does not flood the graph.
    max_frames: int = 5
    min_motion_t: float = 0.02
    min_motion_deg: float = 2.0
    min_frames: int = 0
    tracked_ratio: float = 0.75
    # ORB-SLAM's "need to insert close points": few tracked close points, many untracked ones.
    close_tracked_min: int = 100
    close_untracked_min: int = 70
    max_new_landmarks: int = 600
    min_new_landmarks: int = 100


@dataclass
class BackendConfig:
    relinearize_threshold: float = 0.01
    relinearize_skip: int = 5
    extra_updates: int = 1
    pixel_sigma: float = 1.0
    # Depth noise sigma_z = depth_noise_coeff * z^2 (Kinect-class sensors).
    # Fitted on fr1/rpy residuals: disparity errors were ~2.5x those of the 0.0015 z^2 sensor model.
    depth_noise_coeff: float = 0.004
    huber_k: float = 2.8
    # Loose relative-pose prior between consecutive keyframes: keeps every keyframe constrained.
    odometry_sigma_t: float = 0.05
    odometry_sigma_r_deg: float = 2.0
    covisibility_min_shared: int = 15
    cull_found_ratio: float = 0.25
    cull_min_observations: int = 2
    cull_after_keyframes: int = 3
    # Dynamic probability inflates observation noise by 1 / (1 - p)^2, capped here.
    max_dynamic_inflation: float = 100.0
    dynamic_removal_threshold: float = 0.7
    # New landmarks only from features below this dynamic probability (stricter than tracking's).
    landmark_max_dynamic_prob: float = 0.25


# Trajectory file formats a run can write besides TUM (slam.run.trajectory_formats implements them).
TRAJECTORY_FORMATS = ("tum", "kitti", "euroc")


@dataclass
class OutputConfig:
    results_dir: str = "results"
    online_trajectory: bool = True
    # Formats of the trajectory files (TUM is always written; kitti/euroc add copies, see README "Outputs").
    trajectory_formats: list[str] = field(default_factory=lambda: ["tum"])
    report: bool = True   # report/ folder: plots and index.html (a plotting failure only logs a warning)


@dataclass
class MapExportConfig:
    """Maps a run leaves behind and ``dynslam export`` builds (slam.run.map_export, slam.run.tsdf)."""
    save_map: bool = True          # <results>/map.npz, so the sparse map can be regenerated
    sparse_ply: bool = True        # <results>/map_sparse.ply at the end of each run
    voxel_size: float = 0.025      # TSDF voxel edge (m); coarsened with a warning past max_voxels
    truncation: float = 0.1        # TSDF truncation distance (m), at least 2 voxels
    depth_max: float = 4.0         # depth beyond this (m) is not fused: far Kinect-class depth is noise
    # Depth pixels whose 5x5 neighbourhood spans more than this fraction of their depth are left out:
    # flying pixels at depth edges otherwise leave streaks in free space (0 = keep all).
    depth_edge_ratio: float = 0.05
    # Pixels whose dynamic probability reaches mask_threshold, grown by mask_dilate_px (silhouettes
    # are where the masks are least sure), get depth 0 before fusion, so movers leave no ghosts.
    mask_threshold: float = 0.5
    mask_dilate_px: int = 5
    # The uniform volume costs ~47 bytes per voxel: 8M voxels ~ 380 MB whatever the scene.
    max_voxels: int = 8_000_000


@dataclass
class SlamConfig:
    camera: CameraConfig = field(default_factory=CameraConfig)
    orb: OrbConfig = field(default_factory=OrbConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    dynamic: DynamicConfig = field(default_factory=DynamicConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    export: MapExportConfig = field(default_factory=MapExportConfig)
    seed: int = 0
    max_association_dt: float = 0.02

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# Values that must be strictly positive / non-negative; checked after types.
_POSITIVE = {
    "camera.fx", "camera.fy", "camera.width", "camera.height", "camera.depth_scale", "camera.bf",
    "camera.depth_threshold", "camera.max_depth", "keyframes.min_motion_t", "keyframes.min_motion_deg", "camera.fps", "orb.n_features", "orb.scale_factor",
    "orb.n_levels", "orb.oversample", "orb.cell_size", "tracking.motion_search_radius",
    "tracking.local_map_search_radius", "tracking.pose_iterations", "tracking.pose_rounds",
    "tracking.chi2_mono", "tracking.chi2_stereo", "keyframes.max_frames", "backend.relinearize_threshold",
    "backend.relinearize_skip", "backend.pixel_sigma", "backend.huber_k", "backend.odometry_sigma_t",
    "backend.odometry_sigma_r_deg", "backend.max_dynamic_inflation", "max_association_dt",
}
_NON_NEGATIVE = {"camera.cx", "camera.cy", "camera.min_depth", "backend.depth_noise_coeff",
                 "backend.extra_updates", "keyframes.min_frames", "seed"}
_POSITIVE |= LOOP_POSITIVE
_NON_NEGATIVE |= LOOP_NON_NEGATIVE
_UNIT_INTERVAL = LOOP_UNIT_INTERVAL | {"tracking.match_ratio", "tracking.dynamic_threshold", "keyframes.tracked_ratio",
                  "backend.cull_found_ratio", "backend.dynamic_removal_threshold",
                  "backend.landmark_max_dynamic_prob", "dynamic.box_prior"}


def _check_type(value: Any, annotation: Any, where: str) -> Any:
    """Coerce ints to floats where a float is expected; reject everything else that does not fit."""
    origin = typing.get_origin(annotation)
    if origin in (list,):
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__} {value!r}")
        (item_type,) = typing.get_args(annotation)
        return [_check_type(v, item_type, f"{where}[{i}]") for i, v in enumerate(value)]
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if annotation in (str, bool) and not isinstance(value, annotation):
        raise ConfigError(f"{where}: expected {annotation.__name__}, got {type(value).__name__} {value!r}")
    return value


def _merge_section(obj: Any, data: Any, prefix: str, source: str) -> None:
    """Overlay a YAML mapping onto a dataclass instance in place, checking keys and types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: '{prefix or 'top level'}' must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(type(obj))
    names = {f.name for f in dataclasses.fields(obj)}
    for key, value in data.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if key not in names:
            raise ConfigError(f"{source}: unknown key '{dotted}' (valid: {', '.join(sorted(names))})")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            _merge_section(current, value, dotted, source)
        else:
            setattr(obj, key, _check_type(value, hints[key], f"{source}: '{dotted}'"))


def _iter_values(obj: Any, prefix: str = ""):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        dotted = f"{prefix}.{f.name}" if prefix else f.name
        if dataclasses.is_dataclass(value):
            yield from _iter_values(value, dotted)
        else:
            yield dotted, value


def validate(config: SlamConfig, source: str = "<config>") -> SlamConfig:
    """Reject impossible values (negative focal length, zero depth scale, ...) naming the key."""
    for dotted, value in _iter_values(config):
        if dotted in _POSITIVE and not value > 0:
            raise ConfigError(f"{source}: '{dotted}' must be > 0, got {value!r}")
        if dotted in _NON_NEGATIVE and not value >= 0:  # 'not >=' also rejects NaN
            raise ConfigError(f"{source}: '{dotted}' must be >= 0, got {value!r}")
        if dotted in _UNIT_INTERVAL and not 0.0 <= value <= 1.0:  # NaN fails too
            raise ConfigError(f"{source}: '{dotted}' must be within [0, 1], got {value!r}")
    cam = config.camera
    if len(cam.distortion) not in (4, 5):
        raise ConfigError(f"{source}: 'camera.distortion' needs 4 or 5 coefficients (k1 k2 p1 p2 [k3]), "
                          f"got {len(cam.distortion)}")
    if cam.min_depth >= cam.max_depth:
        raise ConfigError(f"{source}: 'camera.min_depth' ({cam.min_depth}) must be below "
                          f"'camera.max_depth' ({cam.max_depth})")
    _validate_dynamic(config.dynamic, source)
    validate_loop(config.loop, source, ConfigError)
    _validate_export(config.export, source)
    unknown_formats = [f for f in config.output.trajectory_formats if f not in TRAJECTORY_FORMATS]
    if unknown_formats:
        raise ConfigError(f"{source}: 'output.trajectory_formats' has unknown format(s) {unknown_formats} "
                          f"(valid: {', '.join(TRAJECTORY_FORMATS)})")
    if config.orb.scale_factor <= 1.0:
        raise ConfigError(f"{source}: 'orb.scale_factor' must be > 1, got {config.orb.scale_factor}")
    return config


def _validate_export(exp: MapExportConfig, source: str) -> None:
    for key in ("voxel_size", "truncation", "depth_max", "max_voxels"):
        if not getattr(exp, key) > 0:  # 'not >' also rejects NaN
            raise ConfigError(f"{source}: 'export.{key}' must be > 0, got {getattr(exp, key)!r}")
    if not exp.depth_edge_ratio >= 0:
        raise ConfigError(f"{source}: 'export.depth_edge_ratio' must be >= 0, got {exp.depth_edge_ratio!r}")
    if not 0.0 <= exp.mask_threshold <= 1.0:
        raise ConfigError(f"{source}: 'export.mask_threshold' must be within [0, 1], got {exp.mask_threshold!r}")
    if exp.mask_dilate_px < 0:
        raise ConfigError(f"{source}: 'export.mask_dilate_px' must be >= 0, got {exp.mask_dilate_px!r}")
    if exp.truncation < 2 * exp.voxel_size:
        raise ConfigError(f"{source}: 'export.truncation' ({exp.truncation}) must be at least twice "
                          f"'export.voxel_size' ({exp.voxel_size}): thinner bands leave holes in the mesh")


def _validate_dynamic(dyn: DynamicConfig, source: str) -> None:
    unknown = [m for m in dyn.methods if m not in METHOD_NAMES]
    if unknown:
        raise ConfigError(f"{source}: 'dynamic.methods' has unknown method(s) {unknown} "
                          f"(valid: {', '.join(METHOD_NAMES)})")
    if len(set(dyn.methods)) != len(dyn.methods):
        raise ConfigError(f"{source}: 'dynamic.methods' lists a method twice: {dyn.methods}")
    if dyn.fusion not in FUSION_MODES:
        raise ConfigError(f"{source}: 'dynamic.fusion' must be one of {', '.join(FUSION_MODES)}, got '{dyn.fusion}'")
    if dyn.fusion == "single" and len(dyn.methods) > 1:
        raise ConfigError(f"{source}: 'dynamic.fusion' is 'single' but {len(dyn.methods)} methods are enabled")
    if dyn.detector.model not in DETECTOR_MODELS:
        raise ConfigError(f"{source}: 'dynamic.detector.model' must be one of {', '.join(DETECTOR_MODELS)}, "
                          f"got '{dyn.detector.model}'")
    if dyn.depth_sdf.combine not in ("union", "best"):
        raise ConfigError(f"{source}: 'dynamic.depth_sdf.combine' must be one of union, best, "
                          f"got '{dyn.depth_sdf.combine}'")
    for name in METHOD_NAMES:
        if getattr(dyn, name).weight < 0:
            raise ConfigError(f"{source}: 'dynamic.{name}.weight' must be >= 0")


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A path to a YAML file, or the name of a preset in configs/ (``tum_fr1`` → configs/tum_fr1.yaml)."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        return path
    preset = CONFIG_DIR / f"{name_or_path}.yaml"
    if not preset.is_file():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"no config file or preset named '{name_or_path}' (presets: {', '.join(known)})")
    return preset


def apply_yaml(config: SlamConfig, path: str | Path) -> SlamConfig:
    """Overlay one YAML file onto ``config`` in place and validate the result."""
    path = resolve_config_path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if data is not None:
        _merge_section(config, data, "", str(path))
    return validate(config, str(path))


def apply_overrides(config: SlamConfig, overrides: dict[str, Any], source: str = "<overrides>") -> SlamConfig:
    """Overlay dotted-key values ({'tracking.match_ratio': 0.8, ...}) in place and validate."""
    nested: dict[str, Any] = {}
    for dotted, value in overrides.items():
        node = nested
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{source}: '{dotted}' conflicts with another override")
        node[leaf] = value
    _merge_section(config, nested, "", source)
    return validate(config, source)


def load_config(*paths: str | Path, overrides: Optional[dict[str, Any]] = None) -> SlamConfig:
    """Defaults, then each file in order, then ``overrides`` ({'tracking.match_ratio': 0.8, ...})."""
    config = SlamConfig()
    for path in paths:
        apply_yaml(config, path)
    if overrides:
        apply_overrides(config, overrides)
    return config


def default_config_yaml() -> str:
    return SlamConfig().to_yaml()

