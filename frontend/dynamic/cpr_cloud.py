"""CPR-SLAM's point clouds (seed 000, Section 3.3): depth sampling, voxel filter, MLS smoothing, dense target.

Used by ``frontend.dynamic.cpr`` (which documents the method and the choices made) and ``cpr_icp`` (which
registers against these clouds). Everything is whole-array numpy: per-voxel sums with ``np.bincount``,
voxel and neighbour lookups through dense index tables, 3x3 eigenvectors in closed form.

The arithmetic deliberately repeats the straightforward formulation operation for operation (voxels in
``np.unique`` order, per-point sums added in neighbour order as ``np.bincount`` over a pair list adds them,
``np.cross``/``np.linalg.norm`` for the eigenvector): the faster code gives the same bytes, so the masks
did not change with it (checked on 480 Bonn frames).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from frontend.dynamic.cpr_assoc import ProjectiveGrid, ProjectiveTarget
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import CprConfig

_MAX_LOOKUP = 8_000_000          # cells of a dense index table (int32: 32 MB) before falling back to sorting
# Sliding-midpoint tree: builds in ~60 % of the time of the balanced (median) tree and queries as fast here.
# Nearest neighbours do not depend on the tree's shape (only the order of exact distance ties could).
_TREE_OPTIONS: dict = {"balanced_tree": False}
_OFFSETS = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T


def sample_grid(camera: PinholeCamera, height: int, width: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) of every ``step``-th row/column and its undistorted normalised ray (x/z, y/z)."""
    rows, cols = np.meshgrid(np.arange(step // 2, height, step), np.arange(step // 2, width, step), indexing="ij")
    pix = np.stack([rows.ravel(), cols.ravel()], axis=1)
    uv = camera.undistort_points(np.stack([pix[:, 1], pix[:, 0]], axis=1).astype(float))
    rays = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    return pix, rays


def _voxel_keys(cols: tuple[np.ndarray, ...], voxel: float, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer cell of every point, flattened row-major over the occupied box grown by ``margin`` cells on
    each side (so that neighbour offsets never wrap). Returns (flat keys, box size per axis)."""
    keys = [np.floor(c / voxel).astype(np.int64) for c in cols]
    keys = [k - (k.min() - margin) for k in keys]           # 1-D min/max: ~10x faster than axis=0 on (n, 3)
    span = np.array([k.max() + 1 + margin for k in keys])
    return (keys[0] * span[1] + keys[1]) * span[2] + keys[2], span


def _voxel_ids(flat: np.ndarray, volume: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(flat, return_inverse=True, return_counts=True)[1:]``: voxels numbered in key order. A dense
    occupancy table replaces the sort when the box is small enough (always, for depth <= a few metres)."""
    if volume > _MAX_LOOKUP:
        _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
        return inverse, counts
    occupied = np.zeros(volume, bool)
    occupied[flat] = True
    cells = np.flatnonzero(occupied)                       # sorted, like np.unique
    rank = np.empty(volume, np.intp)
    rank[cells] = np.arange(len(cells))
    inverse = rank[flat]
    return inverse, np.bincount(inverse, minlength=len(cells))


def _voxel_filter_cols(cols: tuple[np.ndarray, ...], intensity: np.ndarray, voxel: float
                       ) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray]:
    flat, span = _voxel_keys(cols, voxel, 0)
    inverse, counts = _voxel_ids(flat, int(np.prod(span)))
    m = len(counts)
    centroid = tuple(np.bincount(inverse, c, m) / counts for c in cols)
    return centroid, np.bincount(inverse, intensity, m) / counts, inverse


def voxel_filter(xyz: np.ndarray, intensity: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid and mean intensity per occupied voxel (voxels in lexicographic key order); ``inverse[i]`` is
    the voxel of input point i."""
    if len(xyz) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    cen, mean_i, inverse = _voxel_filter_cols(tuple(np.ascontiguousarray(xyz[:, a]) for a in range(3)),
                                              np.asarray(intensity, float), voxel)
    return np.stack(cen, axis=1), mean_i, inverse


def _eigvec_sym(a00, a11, a22, a01, a02, a12) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvector of the smallest eigenvalue of symmetric 3x3 matrices given by their six entries
    (1-D arrays). Trigonometric eigenvalue, then the largest cross product of two rows of A - lambda I.
    Returns (vectors (n,3), ok (n,) bool)."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01**2 + a02**2 + a12**2
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = np.sqrt(np.maximum(p2, 0.0) / 6.0)
    ok = p > 1e-12
    ps = np.where(ok, p, 1.0)
    b00, b11, b22 = (a00 - q) / ps, (a11 - q) / ps, (a22 - q) / ps
    b01, b02, b12 = a01 / ps, a02 / ps, a12 / ps
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    zero = lam * 0.0                                 # off-diagonal - lambda * 0, as A - lambda I computes it
    r0 = (a00 - lam, a01 - zero, a02 - zero)
    r1 = (a01 - zero, a11 - lam, a12 - zero)
    r2 = (a02 - zero, a12 - zero, a22 - lam)
    crosses = np.empty((3, 3, len(q)))               # r0 x r1, r0 x r2, r1 x r2 (np.cross's operation order)
    for c, (u, v) in zip(crosses, ((r0, r1), (r0, r2), (r1, r2))):
        c[0] = u[1] * v[2] - u[2] * v[1]
        c[1] = u[2] * v[0] - u[0] * v[2]
        c[2] = u[0] * v[1] - u[1] * v[0]
    norms = np.sqrt((crosses[:, 0] ** 2 + crosses[:, 1] ** 2) + crosses[:, 2] ** 2)    # (3, n)
    best = np.argmax(norms, axis=0)
    cols = np.arange(len(q))
    vec = crosses[best, :, cols]
    nrm = norms[best, cols]
    ok &= nrm > 1e-30
    return vec / np.where(ok, nrm, 1.0)[:, None], ok


def _smallest_eigvec(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvector of the smallest eigenvalue of each symmetric 3x3 in ``cov`` (n,3,3) (closed form,
    about 10x faster than ``np.linalg.eigh`` on thousands of matrices). Returns (vectors (n,3), ok (n,))."""
    return _eigvec_sym(cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2])


def _mls_cols(xyz: np.ndarray, cols: tuple[np.ndarray, ...], radius: float, voxel: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(xyz)
    flat, span = _voxel_keys(cols, voxel, 1)
    offs = (_OFFSETS[:, 0] * span[1] + _OFFSETS[:, 1]) * span[2] + _OFFSETS[:, 2]
    cand = offs[:, None] + flat[None, :]                   # (27, n): neighbour cell of every point
    volume = int(np.prod(span))
    if volume <= _MAX_LOOKUP:                              # dense table: one gather instead of a search
        table = np.full(volume, -1, np.int32)
        table[flat] = np.arange(n, dtype=np.int32)
        nb = table[cand]
        hit = nb >= 0
    else:
        order = np.argsort(flat, kind="stable")
        sorted_flat = flat[order]
        pos = np.minimum(np.searchsorted(sorted_flat, cand), n - 1)
        hit = sorted_flat[pos] == cand
        nb = order[pos]
    # (point i, neighbour j) pairs, offset-major: every point meets its neighbours in offset order, so the
    # bincount sums below add in the same order as a point-major pair list would.
    pair = np.flatnonzero(hit)
    i = pair - np.repeat(np.arange(len(offs)) * n, np.count_nonzero(hit, axis=1))   # ~3x faster than divmod
    j = np.take(nb.reshape(-1), pair)
    dx, dy, dz = (np.take(c, j) - np.take(c, i) for c in cols)
    d2 = dx * dx + dy * dy + dz * dz
    r2 = radius * radius
    close = d2 <= r2
    w = np.exp(-d2 / r2)
    w[~close] = 0.0                                        # exact zeros leave the sums bit-identical
    keep = np.bincount(i[close], minlength=n) >= 3
    sw = np.maximum(np.bincount(i, w, n), 1e-12)
    wx, wy, wz = w * dx, w * dy, w * dz
    mx, my, mz = np.bincount(i, wx, n) / sw, np.bincount(i, wy, n) / sw, np.bincount(i, wz, n) / sw

    def cov(wa: np.ndarray, db: np.ndarray, ma: np.ndarray, mb: np.ndarray) -> np.ndarray:
        return np.bincount(i, np.multiply(wa, db, out=d2), n) / sw - ma * mb    # d2 is free scratch now

    normal, ok = _eigvec_sym(cov(wx, dx, mx, mx), cov(wy, dy, my, my), cov(wz, dz, mz, mz),
                             cov(wx, dy, mx, my), cov(wx, dz, mx, mz), cov(wy, dz, my, mz))
    centre = xyz + np.stack([mx, my, mz], axis=1)          # weighted centre of the neighbourhood
    offset = np.einsum("na,na->n", xyz - centre, normal)
    out = xyz - offset[:, None] * normal
    fixed = ~(keep & ok)
    out[fixed] = xyz[fixed]
    normal[fixed] = 0.0
    return out, keep, normal


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
    return _mls_cols(xyz, tuple(np.ascontiguousarray(xyz[:, a]) for a in range(3)), radius, voxel)


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
                min_depth: float = 0.0) -> Cloud:
    """Section 3.3: sampled cloud (depth in (min_depth, max_depth]), voxel filter, MLS; plus the dense target."""
    h, w = depth.shape[:2]
    lin = pix[:, 0] * w + pix[:, 1]
    z = np.take(depth.reshape(-1), lin).astype(np.float64)
    ok = (z > min_depth) & (z <= cfg.max_depth) & np.isfinite(z)
    z, p, lin = z[ok], pix[ok], lin[ok]
    xyz = np.empty((len(z), 3))
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = rays[ok, 0] * z, rays[ok, 1] * z, z
    inten = np.take(gray.reshape(-1), lin).astype(np.float64) / 255.0
    if len(z) == 0:
        cen, mean_i, inverse = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        smooth, keep, normals = cen, np.zeros(0, bool), cen
    else:
        cols, mean_i, inverse = _voxel_filter_cols((xyz[:, 0].copy(), xyz[:, 1].copy(), z), inten, cfg.voxel_size)
        cen = np.stack(cols, axis=1)
        if len(cen) < 3:
            smooth, keep, normals = cen.copy(), np.zeros(len(cen), bool), np.zeros((len(cen), 3))
        else:
            smooth, keep, normals = _mls_cols(cen, cols, cfg.mls_radius, cfg.voxel_size)
    new_index = np.full(len(cen), -1, np.int64)
    new_index[keep] = np.arange(int(keep.sum()))
    cloud = Cloud(smooth[keep], mean_i[keep], p, new_index[inverse], (h, w), normals[keep])
    kept = keep[inverse]                       # the dense target: samples projected onto their voxel's plane
    v = inverse[kept]
    xk, nv = xyz[kept], normals[v]
    off = np.einsum("na,na->n", xk - smooth[v], nv)
    cloud.dense_xyz = xk - off[:, None] * nv
    cloud.dense_i = inten[kept]
    return cloud
