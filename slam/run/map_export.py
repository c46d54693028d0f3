"""Maps from a finished run, without re-running SLAM: ``dynslam export``.

- Sparse map: the landmarks (``bad`` ones left out) as a binary PLY point cloud in the trajectory's
  world frame, coloured from the image (the BGR colour each landmark got at creation) or, with
  ``by_dynamic``, by its mean dynamic evidence (blue static .. red dynamic).
- Dense static map: the keyframes' RGB-D fused into a TSDF (``slam.run.tsdf``) at their optimised poses,
  with the pixels the front end judged dynamic removed; a coloured triangle mesh and a point cloud.

Inputs: a results folder (``keyframes.txt`` poses, ``config.yaml``, ``map.npz``, ``masks/``, and the
keyframe images from ``summary.json``'s ``dataset_path`` or the folder's own ``keyframes/``), or a
saved map file plus a dataset folder. See ``slam.run.run_artifacts`` for what a run leaves behind.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np
import yaml

from slam.core.atomic_io import fsync_directory
from slam.core.errors import DynslamError
from slam.run.run_artifacts import KEYFRAME_DEPTH_SCALE, KEYFRAME_DIR, MAP_FILE, MASK_DIR, SPARSE_PLY, read_keyframe_list
from slam.run.sparse_map import dynamic_colors, dynamic_evidence, sparse_points, write_ply_points, write_sparse_ply  # noqa: F401
from slam.run.tsdf import FusionResult, KeyframeSet, fuse_keyframes

SPARSE_DYNAMIC_PLY = "map_sparse_dynamic.ply"
MESH_PLY = "map_dense_mesh.ply"
CLOUD_PLY = "map_dense_cloud.ply"
_TIME_TOLERANCE_S = 1e-3      # keyframes.txt keeps 6 decimals; frames are >= 10 ms apart


class MapExportError(DynslamError, ValueError):
    """An export input is missing or inconsistent; the message names the path and the problem."""


# ------------------------------------------------------------------------------------------- dense
def write_geometry_atomic(path: Path, geometry, kind: str) -> None:
    """open3d writers want a file name: write to a temporary .ply beside ``path``, then rename."""
    import open3d as o3d

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.ply")
    writer = o3d.io.write_triangle_mesh if kind == "mesh" else o3d.io.write_point_cloud
    try:
        if not writer(str(tmp), geometry, write_ascii=False, compressed=False, print_progress=False):
            raise MapExportError(f"{path}: open3d could not write the {kind}")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    fsync_directory(path.parent)


def ghost_fraction(points_w: np.ndarray, T_wc: np.ndarray, depth: np.ndarray, camera, margin_m: float = 0.1,
                   margin_ratio: float = 0.03, window_px: int = 2) -> tuple[int, int]:
    """(points seen in front of the measured depth by more than margin_m + margin_ratio * depth, points
    checked). A map point the camera saw through is free space: a ghost of something that moved.
    Checked are points in front of the camera that project (with distortion) onto valid depth; the
    depth compared with is the nearest valid one within ``window_px``, so a point on a foreground
    edge that lands a pixel off, on the background, does not count: a ghost floats over an area."""
    T_cw = np.linalg.inv(T_wc)
    pts = points_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    pts = pts[pts[:, 2] > 0.1]
    # Only points inside the ideal (undistorted) view, with a margin: the polynomial distortion model
    # folds points far outside the field of view back into the image, where they would be compared
    # with the depth of unrelated pixels.
    margin = 0.05 * camera.width
    u_ideal = camera.fx * pts[:, 0] / pts[:, 2] + camera.cx
    v_ideal = camera.fy * pts[:, 1] / pts[:, 2] + camera.cy
    pts = pts[(u_ideal > -margin) & (u_ideal < camera.width + margin)
              & (v_ideal > -margin) & (v_ideal < camera.height + margin)]
    if len(pts) == 0:
        return 0, 0
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                              np.asarray(camera.distortion, np.float64))
    u, v = np.round(uv.reshape(-1, 2)).astype(np.int64).T
    h, w = depth.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    kernel = np.ones((2 * window_px + 1, 2 * window_px + 1), np.uint8)
    nearest = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32), kernel)
    measured = np.zeros(len(pts))
    measured[inside] = np.where(depth[v[inside], u[inside]] > 0, nearest[v[inside], u[inside]], 0.0)
    checked = measured > 0
    ghosts = checked & (pts[:, 2] < measured - (margin_m + margin_ratio * measured))
    return int(ghosts.sum()), int(checked.sum())


# ------------------------------------------------------------------------------------------ inputs
def config_from_yaml_text(text: str, source: str, overrides: Optional[dict] = None):
    """A validated SlamConfig from a run's resolved YAML (config.yaml or a map's config_yaml)."""
    from slam.core.config import ConfigError, SlamConfig, apply_overrides

    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping of config sections, got {type(data).__name__}")
    config = apply_overrides(SlamConfig(), _dotted(data), source)
    return apply_overrides(config, overrides, "--set") if overrides else config


def _dotted(data: dict, prefix: str = "") -> dict[str, Any]:
    """{'a': {'b': 1}} -> {'a.b': 1}: nested sections as the dotted keys apply_overrides takes."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        flat.update(_dotted(value, dotted) if isinstance(value, dict) else {dotted: value})
    return flat


def _match_indices(keyframe_t: np.ndarray, frame_t: np.ndarray, frame_index: np.ndarray, where: str) -> np.ndarray:
    """Frame index of each keyframe timestamp (nearest frame within 1 ms, else an error)."""
    if len(frame_t) == 0:
        raise MapExportError(f"{where}: no frames to take the keyframe images from")
    order = np.argsort(frame_t)
    sorted_t = frame_t[order]
    pos = np.searchsorted(sorted_t, keyframe_t)
    before, after = np.clip(pos - 1, 0, len(sorted_t) - 1), np.clip(pos, 0, len(sorted_t) - 1)
    nearest = np.where(np.abs(keyframe_t - sorted_t[before]) <= np.abs(sorted_t[after] - keyframe_t), before, after)
    far = np.abs(sorted_t[nearest] - keyframe_t) > _TIME_TOLERANCE_S
    if far.any():
        raise MapExportError(f"{where}: no frame within 1 ms of keyframe timestamp(s) "
                             f"{', '.join(f'{t:.6f}' for t in keyframe_t[far][:5])}")
    return frame_index[order][nearest]


def _keyframe_folder_reader(folder: Path, timestamps: np.ndarray):
    """Images a generated run saved in keyframes/: (frame indices, reader by frame index)."""
    try:
        listed = read_keyframe_list(folder)
    except ValueError as exc:
        raise MapExportError(str(exc)) from None
    stamps = np.array(list(listed), float)
    indices = _match_indices(timestamps, stamps, np.array(list(listed.values()), np.int64), str(folder))

    def read(index: int) -> tuple[np.ndarray, np.ndarray]:
        color_path, depth_path = folder / "color" / f"{index:06d}.png", folder / "depth" / f"{index:06d}.png"
        bgr, raw = cv2.imread(str(color_path), cv2.IMREAD_COLOR), cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        if bgr is None or raw is None or raw.dtype != np.uint16:
            raise MapExportError(f"{color_path if bgr is None else depth_path}: missing or unreadable keyframe image")
        return bgr, raw.astype(np.float32) / np.float32(KEYFRAME_DEPTH_SCALE)

    return indices, read


def _dataset_reader(dataset_path: Path, config, timestamps: np.ndarray):
    """Images of a TUM/Bonn-layout folder: (frame indices, reader by frame index)."""
    from slam.datasets import DatasetError, TumDataset

    try:
        dataset = TumDataset(dataset_path, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
    except DatasetError as exc:
        raise MapExportError(f"cannot read the keyframe images: {exc} (pass --dataset PATH)") from None
    stamps = np.asarray(dataset.timestamps, float)
    indices = _match_indices(timestamps, stamps, np.arange(len(stamps)), str(dataset_path))

    def read(index: int) -> tuple[np.ndarray, np.ndarray]:
        frame = dataset[int(index)]
        return frame.rgb, frame.depth

    return indices, read


def _image_source(folder: Path, dataset: Optional[Path], config, timestamps: np.ndarray):
    """Where keyframe images come from: --dataset, else the run's keyframes/, else summary.json's dataset_path."""
    if dataset is not None:
        return _dataset_reader(Path(dataset), config, timestamps)
    if (folder / KEYFRAME_DIR / "frames.txt").is_file():
        return _keyframe_folder_reader(folder / KEYFRAME_DIR, timestamps)
    summary = folder / "summary.json"
    recorded = json.loads(summary.read_text()).get("dataset_path") if summary.is_file() else None
    if not recorded:
        raise MapExportError(f"{folder}: no keyframes/ folder and no dataset_path in summary.json to read the "
                             "keyframe images from (pass --dataset PATH)")
    return _dataset_reader(Path(recorded), config, timestamps)


def _keyframe_set(folder: Path, dataset: Optional[Path], config, timestamps: np.ndarray,
                  T_wc: np.ndarray) -> KeyframeSet:
    indices, read = _image_source(folder, dataset, config, timestamps)
    mask_dir = folder / MASK_DIR if (folder / MASK_DIR).is_dir() else None
    return KeyframeSet(indices, timestamps, T_wc, config.camera, lambda k: read(int(indices[k])), mask_dir)


# ------------------------------------------------------------------------------------------ export
@dataclass
class ExportRequest:
    results_dir: Optional[Path] = None     # a run's results folder ...
    map_path: Optional[Path] = None        # ... or a saved map (then the folder beside it is searched)
    dataset: Optional[Path] = None         # keyframe images from here instead of what the run recorded
    out_dir: Optional[Path] = None         # default: the results folder (or the map's folder)
    sparse: bool = True
    dense: bool = True
    by_dynamic: bool = False
    use_masks: bool = True
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass
class ExportReport:
    outputs: dict[str, Path] = field(default_factory=dict)
    sparse_points: int = 0
    fusion: Optional[FusionResult] = None

    def format(self) -> str:
        lines = [f"{name}: {path}" for name, path in self.outputs.items()]
        if self.sparse_points:
            lines.insert(0, f"sparse map: {self.sparse_points} landmarks")
        f = self.fusion
        if f is not None:
            lines.insert(0, f"dense map: {f.keyframes_fused} keyframes fused in {f.seconds:.1f} s, "
                            f"{len(f.mesh.vertices)} vertices / {len(f.mesh.triangles)} triangles, "
                            f"{len(f.cloud.points)} points, voxel {f.grid.voxel_size:.3f} m "
                            f"({f.grid.resolution}^3), {100 * f.masked_fraction:.1f} % of depth masked as dynamic")
        return "\n".join(lines)


def _load_inputs(req: ExportRequest):
    """(config, folder, keyframe timestamps, poses, map or None, map path or None) of a results folder or map."""
    from backend.map_io import load_map
    from slam.run.trajectory import read_tum

    if req.map_path is not None:
        slam_map, _camera, config_yaml = load_map(req.map_path)
        config = config_from_yaml_text(config_yaml, f"{req.map_path} (config_yaml)", req.overrides)
        stamps = np.array([k.timestamp for k in slam_map.keyframes], float)
        return config, Path(req.map_path).parent, stamps, slam_map.kf_T_wc, slam_map, Path(req.map_path)
    folder = Path(req.results_dir)
    for name in ("config.yaml", "keyframes.txt"):
        if not (folder / name).is_file():
            raise MapExportError(f"{folder}: not a dynslam results folder (no {name})")
    config = config_from_yaml_text((folder / "config.yaml").read_text(), str(folder / "config.yaml"), req.overrides)
    stamps, poses = read_tum(folder / "keyframes.txt")
    return config, folder, stamps, poses, None, folder / MAP_FILE


def load_keyframe_set(req: ExportRequest) -> tuple[KeyframeSet, Any]:
    """(the keyframes ``req`` points at, ready to fuse; the run's config with ``req.overrides``)."""
    config, folder, stamps, poses, _map, _path = _load_inputs(req)
    return _keyframe_set(folder, req.dataset, config, stamps, poses), config


def export_maps(req: ExportRequest) -> ExportReport:
    """Write the requested maps; returns what was written and the fusion statistics."""
    from backend.map_io import load_map

    config, folder, stamps, poses, slam_map, map_path = _load_inputs(req)
    out = Path(req.out_dir) if req.out_dir is not None else folder
    report = ExportReport()
    if req.sparse:
        if slam_map is None:
            if not map_path.is_file():
                raise MapExportError(f"{folder}: no {MAP_FILE} to build the sparse map from (runs write it "
                                     "unless export.save_map is off; or pass --map)")
            slam_map = load_map(map_path)[0]
        name = SPARSE_DYNAMIC_PLY if req.by_dynamic else SPARSE_PLY
        report.sparse_points = write_sparse_ply(out / name, slam_map, req.by_dynamic)
        report.outputs["sparse"] = out / name
    if req.dense:
        if len(stamps) == 0:
            raise MapExportError(f"{folder}: the run has no keyframes to fuse")
        keyframes = _keyframe_set(folder, req.dataset, config, stamps, poses)
        report.fusion = fuse_keyframes(keyframes, config.export, req.use_masks)
        write_geometry_atomic(out / MESH_PLY, report.fusion.mesh, "mesh")
        write_geometry_atomic(out / CLOUD_PLY, report.fusion.cloud, "cloud")
        report.outputs.update(mesh=out / MESH_PLY, cloud=out / CLOUD_PLY)
    return report
