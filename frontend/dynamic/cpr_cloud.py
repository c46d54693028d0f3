"""CPR-SLAM's point clouds (seed 000, Section 3.3): depth sampling, voxel filter, MLS smoothing, dense target.

Used by ``frontend.dynamic.cpr`` (which documents the method and the choices made) and ``cpr_icp`` (which
registers against these clouds). The per-point work (sampling, voxel filter, MLS, the dense target) is one
compiled pass in ``cpr_cloud_kernels``: per-voxel sums in input order, voxel and neighbour lookups through dense
index tables, 3x3 eigenvectors in closed form. The k-d tree of ``association: kdtree`` stays scipy's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from frontend.dynamic import cpr_cloud_kernels as kernels
from frontend.dynamic.cpr_assoc import ProjectiveGrid, ProjectiveTarget
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import CprConfig

# Sliding-midpoint tree: builds in ~60 % of the time of the balanced (median) tree and queries as fast here.
# Nearest neighbours do not depend on the tree's shape (only the order of exact distance ties could).
_TREE_OPTIONS: dict = {"balanced_tree": False}


def sample_grid(camera: PinholeCamera, height: int, width: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) of every ``step``-th row/column and its undistorted normalised ray (x/z, y/z)."""
    rows, cols = np.meshgrid(np.arange(step // 2, height, step), np.arange(step // 2, width, step), indexing="ij")
    pix = np.stack([rows.ravel(), cols.ravel()], axis=1)
    uv = camera.undistort_points(np.stack([pix[:, 1], pix[:, 0]], axis=1).astype(float))
    rays = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    return pix, rays


class CellTable:
    """The cloud kernels' cell -> index table (int32, -1 in every cell between uses), kept from frame to frame
    and grown to the largest box seen: filling a fresh 1.5 M-cell table (a 6 m deep view at 5 cm voxels) cost
    ~1 ms per frame."""

    def __init__(self) -> None:
        self.cells = np.full(0, -1, np.int32)

    def fit(self, volume: int) -> None:
        """Room for ``volume`` cells next time (a box larger than the kernels' dense limit sorts instead)."""
        if len(self.cells) < volume <= kernels.MAX_LOOKUP:
            self.cells = np.full(int(volume * 1.25) if volume * 1.25 <= kernels.MAX_LOOKUP else volume, -1, np.int32)


def voxel_filter(xyz: np.ndarray, intensity: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid and mean intensity per occupied voxel (voxels in lexicographic key order); ``inverse[i]`` is
    the voxel of input point i."""
    if len(xyz) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    cols = tuple(np.ascontiguousarray(xyz[:, a], dtype=np.float64) for a in range(3))
    cx, cy, cz, mean_i, inverse, _ = kernels.voxel_filter_cols(*cols, np.asarray(intensity, np.float64),
                                                               float(voxel), CellTable().cells)
    return np.stack([cx, cy, cz], axis=1), mean_i, inverse


def _smallest_eigvec(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvector of the smallest eigenvalue of each symmetric 3x3 in ``cov`` (n,3,3), in closed form
    (the MLS normals' formula). Returns (vectors (n,3), ok (n,))."""
    return kernels.smallest_eigvecs(np.ascontiguousarray(cov, dtype=np.float64))


def mls_smooth(xyz: np.ndarray, radius: float, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First-order moving least squares on a voxelised cloud (one point per ``voxel`` cell): every point is
    projected onto the plane fitted (Gaussian weights exp(-d^2/radius^2), d <= radius) to the points in the
    3x3x3 cells around its own.

    Returns (smoothed points, keep, unit normals (0 where no plane)); keep is False for points with fewer than
    3 neighbours (itself included), which are outliers (PCL's MLS skips them too). The cell neighbourhood
    replaces a radius search: it sees every neighbour closer than one cell (of those up to ``radius``), and
    is ~10x cheaper than a k-d tree query here."""
    n = len(xyz)
    if n < 3:
        return xyz.copy(), np.zeros(n, bool), np.zeros((n, 3))
    cols = tuple(np.ascontiguousarray(xyz[:, a], dtype=np.float64) for a in range(3))
    return kernels.mls_cols(*cols, float(radius), float(voxel), CellTable().cells)[:3]


@dataclass
class Cloud:
    """One frame's processed cloud (camera frame) and how its depth samples map into it."""

    xyz: np.ndarray              # (M,3) smoothed voxel points
    intensity: np.ndarray        # (M,) mean grey / 255
    sample_pix: np.ndarray       # (S,2) (row, col) of the valid depth samples
    sample_point: np.ndarray     # (S,) index into xyz, -1 where the voxel was dropped
    shape: tuple[int, int]
    normals: Optional[np.ndarray] = None   # (M,3) MLS plane normals, 0 where none
    dense_xyz: Optional[np.ndarray] = None
    dense_i: Optional[np.ndarray] = None
    _tree: Optional[cKDTree] = field(default=None, repr=False)
    _target: Optional["Cloud"] = field(default=None, repr=False)
    _projective: Optional[ProjectiveTarget] = field(default=None, repr=False)

    @property
    def tree(self) -> cKDTree:
        """k-d tree over ``xyz``, built on first use: only a registration target needs one."""
        if self._tree is None:
            self._tree = cKDTree(self.xyz, **_TREE_OPTIONS)
        return self._tree

    def query(self, p: np.ndarray, k: int, clamp: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest points of each of ``p`` (n, 3): (dist (n, k), idx (n, k)); the interface of
        ``cpr_assoc.ProjectiveTarget`` (every candidate exists here, ``clamp`` has no meaning)."""
        dist, idx = self.tree.query(p, k=k)
        return (dist[:, None], idx[:, None]) if k == 1 else (dist, idx)

    def projective_target(self, grid: ProjectiveGrid) -> ProjectiveTarget:
        """The registration target for projective association: the same dense points as ``target()``, on
        their sampling grid (no tree). Built once and cached."""
        if self._projective is None:
            kept = self.sample_point >= 0
            if self.dense_xyz is None:                 # a cloud without dense points: its own points
                self._projective = ProjectiveTarget(grid, self.sample_pix[kept], self.xyz[self.sample_point[kept]],
                                                    self.intensity[self.sample_point[kept]])
            else:
                self._projective = ProjectiveTarget(grid, self.sample_pix[kept], self.dense_xyz, self.dense_i)
        return self._projective

    def target(self) -> "Cloud":
        """The cloud a later frame registers against: the depth samples projected on their voxel's MLS
        plane when kept (dense, so nearest-neighbour distances measure the surface, not the voxel lattice).
        Built once, with its k-d tree, and cached."""
        if self.dense_xyz is None:
            return self
        if self._target is None:                 # the k-d tree is built here, not at first query (timed step)
            self._target = Cloud(self.dense_xyz, self.dense_i, self.sample_pix, self.sample_point, self.shape,
                                 _tree=cKDTree(self.dense_xyz, **_TREE_OPTIONS))
        return self._target

    def __len__(self) -> int:
        return len(self.xyz)


def build_cloud(depth: np.ndarray, gray: np.ndarray, pix: np.ndarray, rays: np.ndarray, cfg: CprConfig,
                min_depth: float = 0.0, table: Optional[CellTable] = None) -> Cloud:
    """Section 3.3: sampled cloud (depth in (min_depth, max_depth]), voxel filter, MLS; plus the dense target
    (the kept samples projected on their voxel's MLS plane). One compiled pass (``cpr_cloud_kernels``); ``table``:
    a cell table kept between frames (a fresh one otherwise)."""
    h, w = depth.shape[:2]
    table = table or CellTable()
    xyz, inten, normals, sample_pix, sample_point, dense, dense_i, volume = kernels.build_cloud_arrays(
        np.ascontiguousarray(depth), np.ascontiguousarray(gray), np.ascontiguousarray(pix, dtype=np.int64),
        np.ascontiguousarray(rays, dtype=np.float64), float(min_depth), float(cfg.max_depth),
        float(cfg.voxel_size), float(cfg.mls_radius), table.cells)
    table.fit(volume)
    return Cloud(xyz, inten, sample_pix, sample_point, (h, w), normals, dense, dense_i)
