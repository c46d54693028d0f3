"""The sparse map: a run's good landmarks as a binary PLY point cloud in the trajectory's world frame,
coloured from the image (the BGR colour each landmark got at creation) or, with ``by_dynamic``, by its
mean dynamic evidence (blue static .. red dynamic). Written at the end of every run
(``slam.run.run_artifacts``) and again by ``dynslam export`` (``slam.run.map_export``)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from slam.core.atomic_io import write_atomic


def dynamic_evidence(landmarks) -> np.ndarray:
    """Mean dynamic probability over a landmark's observations (the back end's culling statistic)."""
    return landmarks.dynamic_sum / np.maximum(landmarks.n_obs + landmarks.dynamic_hits, 1)


def dynamic_colors(evidence: np.ndarray) -> np.ndarray:
    """(N,3) uint8 RGB from evidence in [0, 1]: OpenCV's JET colormap, blue = static, red = dynamic."""
    levels = np.round(np.clip(np.nan_to_num(evidence), 0.0, 1.0) * 255).astype(np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(levels, cv2.COLORMAP_JET).reshape(-1, 3)[:, ::-1].copy()


def sparse_points(slam_map, by_dynamic: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N,3) world, rgb (N,3) uint8) of the map's good landmarks, in landmark-id order."""
    lm = slam_map.landmarks
    keep = ~lm.bad
    if by_dynamic:
        return lm.xyz[keep].copy(), dynamic_colors(dynamic_evidence(lm)[keep])
    return lm.xyz[keep].copy(), lm.color[keep][:, ::-1].copy()   # stored BGR, PLY wants RGB


def write_ply_points(path: Path | str, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY: float x y z, uchar red green blue per vertex (open3d reads it)."""
    vertex = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for axis, name in enumerate("xyz"):
        vertex[name] = xyz[:, axis]
    for channel, name in enumerate(("red", "green", "blue")):
        vertex[name] = rgb[:, channel]
    header = ("ply\nformat binary_little_endian 1.0\ncomment dynslam sparse map (landmarks)\n"
              f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    write_atomic(path, lambda handle: (handle.write(header.encode("ascii")), handle.write(vertex.tobytes())))


def write_sparse_ply(path: Path | str, slam_map, by_dynamic: bool = False) -> int:
    """The landmarks of ``slam_map`` as a PLY point cloud; returns the number of points."""
    xyz, rgb = sparse_points(slam_map, by_dynamic)
    write_ply_points(path, xyz, rgb)
    return len(xyz)
