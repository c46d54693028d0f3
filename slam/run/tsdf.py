"""Dense static map: keyframes' RGB-D fused into a TSDF volume, dynamic pixels removed first.

Why a *uniform* volume: open3d 0.20's ``ScalableTSDFVolume`` integrated nothing here (empty meshes from
frames the uniform volume fuses fine), so the volume is one fixed cube whose memory (~47 bytes per
voxel) is known before fusing. Its extent comes from the keyframes' back-projected depth (robust
percentiles, so a few far outliers do not blow it up); when that cube would need more than
``max_voxels`` voxels the voxel is coarsened, with a warning, instead of growing memory.

Dynamic pixels (the front end's per-keyframe mask at or above ``mask_threshold``, dilated by
``mask_dilate_px``) get depth 0 before fusion, so the TSDF never sees a person: nothing of them is
fused and the background they hid is filled in from other keyframes. Flying pixels at depth edges and
depth beyond ``depth_max`` are dropped as well. Images are read twice (extent, then fusion) rather
than held in memory, so memory does not grow with the number of keyframes.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Optional

import cv2
import numpy as np

BYTES_PER_VOXEL = 47          # measured: open3d 0.20 UniformTSDFVolume, RGB8 colour
_BOUNDS_STEP_PX = 8           # every 8th pixel is plenty to find the scene's extent
_BOUNDS_PERCENTILES = (0.5, 99.5)
_EDGE_RADIUS_PX = 2


class VolumeSizeWarning(UserWarning):
    """The scene needs more voxels than allowed: the voxel was coarsened."""


@dataclass
class KeyframeSet:
    """The keyframes to fuse: poses, where their images and masks come from, and the camera."""
    frame_index: np.ndarray                 # (K,) frame index of each keyframe (names its mask file)
    timestamp: np.ndarray                   # (K,)
    T_wc: np.ndarray                        # (K,4,4) optimised camera-to-world poses
    camera: object                          # a CameraConfig: fx fy cx cy width height distortion
    read_images: Callable[[int], tuple[np.ndarray, np.ndarray]]   # k -> (BGR uint8, depth float32 m)
    mask_dir: Optional[Path] = None         # masks/<frame index:06d>.png, 8-bit dynamic probability

    def __len__(self) -> int:
        return len(self.frame_index)

    def subset(self, keep) -> "KeyframeSet":
        """The keyframes at positions ``keep`` (e.g. only those of a part of the run)."""
        keep = np.asarray(keep, np.int64)
        return KeyframeSet(self.frame_index[keep], self.timestamp[keep], self.T_wc[keep], self.camera,
                           lambda k: self.read_images(int(keep[k])), self.mask_dir)

    def read_mask(self, k: int) -> Optional[np.ndarray]:
        """Keyframe k's dynamic probability (0..255), or None when the run recorded none; the people who
        stood still in it and the flagged pixels other frames showed unmoved (``<index>_still.png``, 255)
        count as dynamic too: they must never be mapped."""
        if self.mask_dir is None:
            return None
        path = self.mask_dir / f"{int(self.frame_index[k]):06d}.png"
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        still = self.mask_dir / f"{int(self.frame_index[k]):06d}_still.png"
        if mask is not None and still.is_file():
            people = cv2.imread(str(still), cv2.IMREAD_GRAYSCALE)
            if people is not None and people.shape == mask.shape:
                mask = np.maximum(mask, people)
        return mask


@dataclass(frozen=True)
class VolumeGrid:
    origin: np.ndarray       # (3,) world corner of the cube
    length: float            # cube side (m)
    resolution: int          # voxels per side
    voxel_size: float
    truncation: float

    @property
    def voxels(self) -> int:
        return self.resolution ** 3


@dataclass
class FusionResult:
    mesh: object             # open3d TriangleMesh
    cloud: object            # open3d PointCloud
    grid: VolumeGrid
    keyframes_fused: int
    masked_fraction: float   # share of valid depth pixels removed as dynamic
    seconds: float


def plan_grid(lo: np.ndarray, hi: np.ndarray, voxel_size: float, truncation: float, max_voxels: int) -> VolumeGrid:
    """The cube holding [lo, hi] plus a truncation band, at ``voxel_size`` unless that needs more than
    ``max_voxels`` voxels: then the voxel grows (truncation with it, same ratio) and a warning says so."""
    centre = (np.asarray(lo, float) + np.asarray(hi, float)) / 2.0
    side = float(np.max(np.asarray(hi, float) - np.asarray(lo, float))) + 2.0 * truncation
    max_resolution = max(int(np.floor(max_voxels ** (1.0 / 3.0) + 1e-9)), 2)
    resolution = int(np.ceil(side / voxel_size))
    if resolution > max_resolution:
        coarse = side / max_resolution
        warnings.warn(f"the scene ({side:.1f} m across) needs {resolution}^3 voxels of {voxel_size} m, over "
                      f"export.max_voxels={max_voxels}: fusing with {coarse:.3f} m voxels instead "
                      f"(raise export.max_voxels for detail, ~{BYTES_PER_VOXEL} bytes per voxel)",
                      VolumeSizeWarning, stacklevel=2)
        truncation *= coarse / voxel_size
        voxel_size, resolution = coarse, max_resolution
    length = resolution * voxel_size
    return VolumeGrid(centre - length / 2.0, length, resolution, voxel_size, truncation)


def dynamic_pixels(mask: Optional[np.ndarray], threshold: float, dilate_px: int) -> Optional[np.ndarray]:
    """HxW bool of pixels to drop: 8-bit probability >= threshold, grown by ``dilate_px``."""
    if mask is None:
        return None
    hit = (mask.astype(np.float32) >= threshold * 255.0 - 1e-3).astype(np.uint8)
    if dilate_px > 0 and hit.any():
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
        hit = cv2.dilate(hit, kernel)
    return hit.astype(bool)


def depth_edges(depth: np.ndarray, ratio: float, radius: int = _EDGE_RADIUS_PX) -> np.ndarray:
    """HxW bool: valid pixels whose (2r+1)^2 neighbourhood spans more than ``ratio`` x their depth.

    Why: at depth discontinuities Kinect-class sensors return "flying pixels" between the near and far
    surface; fused, they leave streaks in free space along the keyframes' viewing rays."""
    if ratio <= 0:
        return np.zeros(depth.shape, bool)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    nearest = cv2.erode(np.where(depth > 0, depth, np.float32(np.inf)).astype(np.float32), kernel)
    farthest = cv2.dilate(depth, kernel)
    return (depth > 0) & (farthest - nearest > ratio * depth)


class Undistorter:
    """Remaps raw images to the ideal pinhole image the TSDF assumes (identity without distortion)."""

    def __init__(self, camera):
        self.K = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
        dist = np.asarray(camera.distortion, np.float64)
        self._maps = None
        if np.any(dist != 0.0):
            self._maps = cv2.initUndistortRectifyMap(self.K, dist, None, self.K, (camera.width, camera.height),
                                                     cv2.CV_32FC1)

    def __call__(self, bgr: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._maps is None:
            return bgr, depth
        # nearest for depth: interpolating across an edge (or a removed person) invents surfaces
        return (cv2.remap(bgr, *self._maps, cv2.INTER_LINEAR),
                cv2.remap(depth, *self._maps, cv2.INTER_NEAREST))


def prepared_frames(keyframes: KeyframeSet, cfg,
                    use_masks: bool) -> Iterator[tuple[int, np.ndarray, np.ndarray, int, int]]:
    """Per keyframe: (k, BGR, depth with dynamic/far/invalid pixels zeroed, valid pixels, removed pixels),
    undistorted."""
    undistort = Undistorter(keyframes.camera)
    for k in range(len(keyframes)):
        bgr, depth = keyframes.read_images(k)
        depth = np.nan_to_num(depth.astype(np.float32), nan=0.0)
        depth[(depth < 0) | (depth > cfg.depth_max)] = 0.0
        depth[depth_edges(depth, cfg.depth_edge_ratio)] = 0.0
        valid = int(np.count_nonzero(depth))
        drop = dynamic_pixels(keyframes.read_mask(k), cfg.mask_threshold, cfg.mask_dilate_px) if use_masks else None
        removed = 0
        if drop is not None:
            removed = int(np.count_nonzero(drop & (depth > 0)))
            depth[drop] = 0.0
        bgr, depth = undistort(bgr, depth)
        yield k, bgr, depth, valid, removed


def scene_bounds(keyframes: KeyframeSet, cfg, use_masks: bool) -> tuple[np.ndarray, np.ndarray]:
    """Robust world-frame extent of the depth that will be fused (plus the camera centres)."""
    cam = keyframes.camera
    chunks = [keyframes.T_wc[:, :3, 3]]
    for k, _bgr, depth, _valid, _removed in prepared_frames(keyframes, cfg, use_masks):
        v, u = np.nonzero(depth[::_BOUNDS_STEP_PX, ::_BOUNDS_STEP_PX])
        z = depth[::_BOUNDS_STEP_PX, ::_BOUNDS_STEP_PX][v, u].astype(np.float64)
        u, v = u * _BOUNDS_STEP_PX, v * _BOUNDS_STEP_PX
        pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
        chunks.append(pts @ keyframes.T_wc[k, :3, :3].T + keyframes.T_wc[k, :3, 3])
    points = np.concatenate(chunks)
    return np.percentile(points, _BOUNDS_PERCENTILES[0], axis=0), np.percentile(points, _BOUNDS_PERCENTILES[1], axis=0)


def fuse_keyframes(keyframes: KeyframeSet, cfg, use_masks: bool = True) -> FusionResult:
    """Fuse every keyframe into a uniform TSDF (``cfg`` is a MapExportConfig); mesh and point cloud out."""
    import open3d as o3d

    if len(keyframes) == 0:
        raise ValueError("no keyframes to fuse")
    start = time.perf_counter()
    grid = plan_grid(*scene_bounds(keyframes, cfg, use_masks), cfg.voxel_size, cfg.truncation, cfg.max_voxels)
    volume = o3d.pipelines.integration.UniformTSDFVolume(
        length=grid.length, resolution=grid.resolution, sdf_trunc=grid.truncation,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, origin=grid.origin)
    cam = keyframes.camera
    intrinsic = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    valid_total = removed_total = 0
    for k, bgr, depth, valid, removed in prepared_frames(keyframes, cfg, use_masks):
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(bgr[:, :, ::-1])), o3d.geometry.Image(depth),
            depth_scale=1.0, depth_trunc=cfg.depth_max, convert_rgb_to_intensity=False)
        volume.integrate(rgbd, intrinsic, np.linalg.inv(keyframes.T_wc[k]))
        valid_total, removed_total = valid_total + valid, removed_total + removed
    mesh = volume.extract_triangle_mesh()
    mesh.compute_vertex_normals()
    cloud = volume.extract_point_cloud()
    del volume
    return FusionResult(mesh, cloud, grid, len(keyframes), removed_total / max(valid_total, 1),
                        time.perf_counter() - start)
