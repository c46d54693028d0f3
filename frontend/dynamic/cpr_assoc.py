"""CPR-SLAM's data association (seed 000, Sections 3.5-3.6): which reference points a source point may match.

Two interchangeable targets with the same interface (``xyz``, ``intensity``, ``query(p, k, clamp)`` returning
(dist (n, c), idx (n, c)) into ``xyz``, ``inf`` distance where a candidate does not exist):

* ``cpr_cloud.Cloud`` (``association: kdtree``): the ``k`` exact nearest neighbours in 3-D (its cKDTree), as
  the paper.
* ``ProjectiveTarget`` (``association: projective``, default): the reference's depth samples lie on the
  organised sampling grid of its depth image (every ``sample_step``-th pixel), so a source point moved into
  the reference camera is projected to a pixel and its candidates are the samples of the
  (2 ``projective_window`` + 1)^2 grid cells around it - projective data association as in dense RGB-D
  odometry (KinectFusion; Kerl et al., whom the paper cites). O(1) per point, no tree to build or search.
  Why and what it changed: ``frontend.dynamic.cpr``.

The projection goes through a per-camera table (ideal pixel -> grid cell of the nearest raw-image sample,
lens distortion included), built once like the sampling grid.
"""
from __future__ import annotations

import cv2
import numpy as np

from frontend.dynamic import cpr_icp_kernels as kernels
from slam.core.camera import PinholeCamera

def _distort(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """Raw (distorted) pixel of ideal pixels: OpenCV's model written out for (k1, k2, p1, p2[, k3]) (~10x
    faster than cv2.projectPoints on a whole image); cv2 for longer coefficient lists."""
    x, y = (uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy
    d = np.asarray(camera.distortion, float)
    if len(d) > 5:
        rays = np.stack([x, y, np.ones(len(x))], axis=1)
        return cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, d)[0].reshape(-1, 2)
    k1, k2, p1, p2, k3 = np.concatenate([d, np.zeros(5 - len(d))])
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)


class ProjectiveGrid:
    """Per camera / image size / sample step: the lookup from an ideal (undistorted) pixel to the padded flat
    index of the sampling-grid cell whose raw-image sample is nearest, and the window's index offsets."""

    def __init__(self, camera: PinholeCamera, height: int, width: int, step: int, radius: int):
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy
        self.height, self.width, self.step, self.radius = height, width, step, radius
        self.gh, self.gw = len(range(step // 2, height, step)), len(range(step // 2, width, step))
        self.pw = self.gw + 2 * radius                       # padded width: window offsets never wrap
        self.size = (self.gh + 2 * radius) * self.pw         # + 1 sentinel cell (never valid) at the end
        u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
        raw = np.stack([u.ravel(), v.ravel()], axis=1)
        if camera.has_distortion:                            # ideal pixel -> raw pixel (OpenCV model)
            raw = _distort(camera, raw)
        seen = (raw[:, 0] > -0.5) & (raw[:, 0] < width - 0.5) & (raw[:, 1] > -0.5) & (raw[:, 1] < height - 0.5)
        gc = np.clip(np.rint((raw[:, 0] - step // 2) / step), 0, self.gw - 1).astype(np.int64)
        gr = np.clip(np.rint((raw[:, 1] - step // 2) / step), 0, self.gh - 1).astype(np.int64)
        self.cell = ((gr + radius) * self.pw + gc + radius).astype(np.int32)   # clamped: the border cell
        self.seen = seen
        dr, dc = np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1), indexing="ij")
        self.offsets = (dr * self.pw + dc).ravel()

    def cells(self, sample_pix: np.ndarray) -> np.ndarray:
        """Padded flat cell of every (row, col) sample pixel."""
        return (sample_pix[:, 0] // self.step + self.radius) * self.pw + sample_pix[:, 1] // self.step + self.radius


class ProjectiveTarget:
    """The reference's samples on its padded sampling grid; candidates by projection (see the module). The
    table and the association are ``cpr_icp_kernels``' (``projective_table``, ``window_query``), which the
    compiled ICP and scores read through ``kernel_args``."""

    def __init__(self, grid: ProjectiveGrid, sample_pix: np.ndarray, xyz: np.ndarray, intensity: np.ndarray):
        self.grid = grid
        self.table = kernels.projective_table(grid.cells(sample_pix), np.ascontiguousarray(xyz, dtype=np.float64),
                                              np.ascontiguousarray(intensity, dtype=np.float64), int(grid.size))
        self.n = len(xyz)

    @property
    def xyz(self) -> np.ndarray:
        """(cells + 1, 3) sample points by table row, inf where a cell has none."""
        return self.table[:, :3]

    @property
    def intensity(self) -> np.ndarray:
        """(cells + 1,) sample intensities by table row, 0 where a cell has none."""
        return self.table[:, 3]

    def __len__(self) -> int:
        return self.n

    def kernel_args(self) -> tuple:
        """What the compiled association reads: the table, the camera, the lookup tables, the window offsets
        and the sentinel cell."""
        g = self.grid
        return (self.table, float(g.fx), float(g.fy), float(g.cx), float(g.cy), int(g.width), int(g.height),
                g.seen, g.cell, g.offsets, int(g.size))

    def query(self, p: np.ndarray, k: int, clamp: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Window candidates of every point (all of them; ``k`` = 1: only the nearest): (distances (n, c), inf
        where a cell has no sample; table rows (n, c)). A point behind the camera has none; one projecting
        outside the image has none, or with ``clamp`` those of the nearest border cell (what a
        nearest-neighbour search would find there, roughly)."""
        dist, idx = kernels.window_query(np.ascontiguousarray(p, dtype=np.float64), *self.kernel_args(), bool(clamp))
        if k == 1:
            best = np.argmin(dist, axis=1)[:, None]
            return np.take_along_axis(dist, best, 1), np.take_along_axis(idx, best, 1)
        return dist, idx
