"""The point-cloud half of CPR-SLAM (seed 000, Sections 3.3-3.7): cloud construction, sub-poses, correlation.

Used by ``frontend.dynamic.cpr`` (which documents the method, the interpretation of the paper and the
deviations). Everything here is vectorised numpy/scipy: one k-d tree query per ICP iteration for all
sub-clouds together, per-sub-cloud sums with ``np.add.reduceat`` and batched 3x3 SVDs.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import CprConfig

_MIN_CLUSTER_POINTS = 10
_MAX_LOOKUP = 8_000_000
_SCALE_FLOOR_GEOM = 0.01
_SCALE_FLOOR_INTENSITY = 0.01


# --- point cloud construction ------------------------------------------------------------------------------


def sample_grid(camera: PinholeCamera, height: int, width: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) of every ``step``-th row/column and its undistorted normalised ray (x/z, y/z)."""
    rows, cols = np.meshgrid(np.arange(step // 2, height, step), np.arange(step // 2, width, step), indexing="ij")
    pix = np.stack([rows.ravel(), cols.ravel()], axis=1)
    uv = camera.undistort_points(np.stack([pix[:, 1], pix[:, 0]], axis=1).astype(float))
    rays = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    return pix, rays


def voxel_filter(xyz: np.ndarray, intensity: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid and mean intensity per occupied voxel; ``inverse[i]`` is the voxel of input point i."""
    if len(xyz) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    key = np.floor(xyz / voxel).astype(np.int64)
    key -= key.min(axis=0)
    span = key.max(axis=0) + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    m = len(counts)
    centroid = np.stack([np.bincount(inverse, xyz[:, a], m) for a in range(3)], axis=1) / counts[:, None]
    mean_i = np.bincount(inverse, intensity, m) / counts
    return centroid, mean_i, inverse


def _smallest_eigvec(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit eigenvector of the smallest eigenvalue of each symmetric 3x3 (closed form, vectorised; about 10x
    faster than ``np.linalg.eigh`` on thousands of matrices). Returns (vectors (n,3), ok (n,) bool)."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
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
    m = cov - lam[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], 1)
    norms = np.linalg.norm(crosses, axis=2)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(cov))
    vec = crosses[rows, best]
    nrm = norms[rows, best]
    ok &= nrm > 1e-30
    vec = vec / np.where(ok, nrm, 1.0)[:, None]
    return vec, ok


_OFFSETS = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T


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
    key = np.floor(xyz / voxel).astype(np.int64)
    key -= key.min(axis=0) - 1                        # margin of one voxel: offsets never wrap
    span = key.max(axis=0) + 2
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    offs = (_OFFSETS[:, 0] * span[1] + _OFFSETS[:, 1]) * span[2] + _OFFSETS[:, 2]
    cand = flat[:, None] + offs[None, :]               # (n, 27)
    volume = int(np.prod(span))
    if volume <= _MAX_LOOKUP:                          # dense table: one gather instead of a search
        table = np.full(volume, -1, np.int32)
        table[flat] = np.arange(n, dtype=np.int32)
        nb_idx = table[cand]
        hit = nb_idx >= 0
    else:
        order = np.argsort(flat, kind="stable")
        sorted_flat = flat[order]
        pos = np.minimum(np.searchsorted(sorted_flat, cand), n - 1)
        hit = sorted_flat[pos] == cand
        nb_idx = order[pos]
    i = np.nonzero(hit)[0]                             # (point, neighbour) pairs, neighbour = j
    j = nb_idx[hit]
    dx, dy, dz = (xyz[j, a] - xyz[i, a] for a in range(3))
    d2 = dx * dx + dy * dy + dz * dz
    close = d2 <= radius * radius
    i, dx, dy, dz = i[close], dx[close], dy[close], dz[close]
    w = np.exp(-d2[close] / (radius * radius))
    keep = np.bincount(i, minlength=n) >= 3
    sw = np.maximum(np.bincount(i, w, n), 1e-12)
    wx, wy, wz = w * dx, w * dy, w * dz
    mx, my, mz = (np.bincount(i, v, n) / sw for v in (wx, wy, wz))   # weighted centre - point
    cov = np.empty((n, 3, 3))
    for (a, b), wa, db, ma, mb in (((0, 0), wx, dx, mx, mx), ((1, 1), wy, dy, my, my), ((2, 2), wz, dz, mz, mz),
                                   ((0, 1), wx, dy, mx, my), ((0, 2), wx, dz, mx, mz), ((1, 2), wy, dz, my, mz)):
        cov[:, a, b] = cov[:, b, a] = np.bincount(i, wa * db, n) / sw - ma * mb
    centre = xyz + np.stack([mx, my, mz], axis=1)
    normal, ok = _smallest_eigvec(cov)
    offset = np.einsum("na,na->n", xyz - centre, normal)
    out = xyz - offset[:, None] * normal
    fixed = ~(keep & ok)
    out[fixed] = xyz[fixed]
    normal[fixed] = 0.0
    return out, keep, normal


def cluster(xyz: np.ndarray, k: int, seed: int) -> np.ndarray:
    """K-Means labels (k-means++, fixed seed); deterministic for the same input."""
    if len(xyz) <= k:
        return np.arange(len(xyz))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, labels = kmeans2(xyz, k, iter=10, minit="++", seed=np.random.default_rng(seed))
    return labels


@dataclass
class Cloud:
    """One frame's processed cloud (camera frame) and how its depth samples map into it."""

    xyz: np.ndarray              # (M,3) smoothed voxel points
    intensity: np.ndarray        # (M,) mean grey / 255
    tree: Optional[cKDTree]
    sample_pix: np.ndarray       # (S,2) (row, col) of the valid depth samples
    sample_point: np.ndarray     # (S,) index into xyz, -1 where the voxel was dropped
    shape: tuple[int, int]
    normals: Optional[np.ndarray] = None   # (M,3) MLS plane normals, 0 where none
    dense_xyz: Optional[np.ndarray] = None
    dense_i: Optional[np.ndarray] = None
    _dense_tree: Optional[cKDTree] = None

    def target(self) -> "Cloud":
        """The cloud a later frame registers against: the depth samples projected on their voxel's MLS
        plane when kept (dense, so nearest-neighbour distances measure the surface, not the voxel lattice)."""
        if self.dense_xyz is None:
            return self
        if self._dense_tree is None:
            self._dense_tree = cKDTree(self.dense_xyz)
        return Cloud(self.dense_xyz, self.dense_i, self._dense_tree, self.sample_pix, self.sample_point, self.shape)

    def __len__(self) -> int:
        return len(self.xyz)


def build_cloud(depth: np.ndarray, gray: np.ndarray, pix: np.ndarray, rays: np.ndarray, cfg: CprConfig,
                min_depth: float = 0.0) -> Cloud:
    """Section 3.3: sampled cloud (depth in (min_depth, max_depth]), voxel filter, MLS; plus the dense target."""
    z = depth[pix[:, 0], pix[:, 1]].astype(np.float64)
    ok = (z > min_depth) & (z <= cfg.max_depth) & np.isfinite(z)
    z, p = z[ok], pix[ok]
    xyz = np.stack([rays[ok, 0] * z, rays[ok, 1] * z, z], axis=1)
    inten = gray[p[:, 0], p[:, 1]].astype(np.float64) / 255.0
    cen, mean_i, inverse = voxel_filter(xyz, inten, cfg.voxel_size)
    smooth, keep, normals = mls_smooth(cen, cfg.mls_radius, cfg.voxel_size)
    new_index = np.full(len(cen), -1, np.int64)
    new_index[keep] = np.arange(int(keep.sum()))
    xyz_k = smooth[keep]
    cloud = Cloud(xyz_k, mean_i[keep], cKDTree(xyz_k) if len(xyz_k) else None, p, new_index[inverse],
                  depth.shape[:2], normals[keep])
    kept = keep[inverse]                       # the dense target: samples projected onto their voxel's plane
    v = inverse[kept]
    off = np.einsum("na,na->n", xyz[kept] - smooth[v], normals[v])
    cloud.dense_xyz = xyz[kept] - off[:, None] * normals[v]
    cloud.dense_i = inten[kept]
    return cloud


# --- sub-poses ---------------------------------------------------------------------------------------------


def robust_scale(r: np.ndarray, floor: float) -> float:
    """1.4826 * median absolute deviation from the median (Eqs. 8-9), at least ``floor``."""
    med = np.median(r)
    return max(1.4826 * float(np.median(np.abs(r - med))), floor)


def t_weight(r: np.ndarray, scale: float, nu: float) -> np.ndarray:
    """Student-t weight (Kerl et al.): (nu + 1) / (nu + (r / scale)^2)."""
    return (nu + 1.0) / (nu + (r / scale) ** 2)


def _segments(labels_sorted: np.ndarray, k: int) -> np.ndarray:
    """Start index of every label 0..k-1 in a sorted label array (length k + 1 with the end)."""
    return np.searchsorted(labels_sorted, np.arange(k + 1))


def _segment_sums(x: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sum of x over each segment [starts[j], starts[j+1]) (zeros for empty ones); x has starts[-1] rows."""
    out = np.zeros((len(starts) - 1,) + x.shape[1:])
    s = starts[:-1]
    nonempty = starts[1:] > s
    if np.any(nonempty):
        out[nonempty] = np.add.reduceat(x, s[nonempty], axis=0)
    return out


def _kabsch(p: np.ndarray, q: np.ndarray, w: np.ndarray, starts: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Weighted rigid transform per segment mapping p onto q (Eq. 10); (K,4,4), identity where inactive."""
    k = len(starts) - 1
    out = np.tile(np.eye(4), (k, 1, 1))
    ws = _segment_sums(w, starts)
    use = active & (ws > 1e-9)
    if not np.any(use):
        return out
    wp = w[:, None] * p
    sp = _segment_sums(wp, starts)[use] / ws[use, None]
    sq = _segment_sums(w[:, None] * q, starts)[use] / ws[use, None]
    outer = _segment_sums(wp[:, :, None] * q[:, None, :], starts)[use]         # sum w p q^T
    h = outer / ws[use, None, None] - sp[:, :, None] * sq[:, None, :]
    u, _, vt = np.linalg.svd(h)
    v, ut = np.swapaxes(vt, 1, 2), np.swapaxes(u, 1, 2)
    d = np.sign(np.linalg.det(v @ ut))
    d[d == 0] = 1.0
    fix = np.ones((len(d), 3))
    fix[:, 2] = d
    rot = v @ (fix[:, :, None] * ut)
    out[use, :3, :3] = rot
    out[use, :3, 3] = sq - np.einsum("kab,kb->ka", rot, sp)
    return out


def _apply(poses: np.ndarray, labels: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Each point moved by its segment's pose."""
    rot = poses[labels, :3, :3]
    return np.einsum("nab,nb->na", rot, xyz) + poses[labels, :3, 3]


def _even_subsample(starts: np.ndarray, cap: int) -> np.ndarray:
    """Indices of at most ``cap`` evenly spaced elements of every segment [starts[j], starts[j+1])."""
    parts = []
    for j in range(len(starts) - 1):
        a, b = int(starts[j]), int(starts[j + 1])
        m = b - a
        parts.append(np.arange(a, b) if m <= cap else a + (np.arange(cap) * m) // cap)
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def sub_poses(src: np.ndarray, src_i: np.ndarray, labels: np.ndarray, k: int, ref: Cloud, init: np.ndarray,
              cfg: CprConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pose of each of the ``k`` sub-clouds (current camera -> reference camera), Section 3.5.

    ``cfg.icp_iterations`` in all: the first ``cfg.icp_intensity_iterations`` intensity-assisted (Eqs. 4-11),
    the rest plain robust ICP. Each sub-cloud is registered with at most ``cfg.icp_max_points`` evenly spread
    points. Returns (poses (k,4,4), valid (k,) bool: sub-cloud large enough to register)."""
    order = np.argsort(labels, kind="stable")
    lab_all = labels[order]
    starts_all = _segments(lab_all, k)
    valid = np.diff(starts_all) >= _MIN_CLUSTER_POINTS
    pick = order[_even_subsample(starts_all, max(_MIN_CLUSTER_POINTS, int(cfg.icp_max_points)))]
    lab, p0, i0 = labels[pick], src[pick], src_i[pick]
    starts = _segments(lab, k)
    poses = np.tile(init, (k, 1, 1))
    nu = cfg.student_nu
    ref_xyz, ref_i = ref.xyz, ref.intensity
    n_cand = int(min(cfg.candidates, len(ref)))
    n_int = min(int(cfg.icp_intensity_iterations), int(cfg.icp_iterations))
    for intensity_stage, iters in ((True, n_int), (False, int(cfg.icp_iterations) - n_int)):
        active = valid.copy()
        for _ in range(iters):
            if not np.any(active):
                break
            sel = active[lab]                          # only points of sub-clouds still moving
            p = _apply(poses, lab[sel], p0[sel])
            seg = _segments(lab[sel], k)
            if intensity_stage and n_cand > 1:
                dist, idx = ref.tree.query(p, k=n_cand)
                r_i = np.abs(i0[sel][:, None] - ref_i[idx])
                w = np.zeros_like(dist)
                for j in np.flatnonzero(active):
                    a, b = seg[j], seg[j + 1]
                    sg = robust_scale(dist[a:b], _SCALE_FLOOR_GEOM)
                    si = robust_scale(r_i[a:b], _SCALE_FLOOR_INTENSITY)
                    w[a:b] = t_weight(dist[a:b], sg, nu) * t_weight(r_i[a:b], si, nu)
                best = np.argmax(w, axis=1)
                rows = np.arange(len(p))
                q = ref_xyz[idx[rows, best]]
                wt = w[rows, best]
            else:
                dist, idx = ref.tree.query(p, k=1)
                q = ref_xyz[idx]
                wt = np.zeros_like(dist)
                for j in np.flatnonzero(active):
                    a, b = seg[j], seg[j + 1]
                    wt[a:b] = t_weight(dist[a:b], robust_scale(dist[a:b], _SCALE_FLOOR_GEOM), nu)
            delta = _kabsch(p, q, wt, seg, active)
            poses = delta @ poses
            moved = np.linalg.norm(delta[:, :3, 3], axis=1)
            angle = np.arccos(np.clip((np.trace(delta[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
            active &= ~((moved < 1e-4) & (angle < np.deg2rad(0.01)))
    return poses, valid


def correlation_scores(src: np.ndarray, src_i: np.ndarray, poses: np.ndarray, ref: Cloud, cfg: CprConfig
                       ) -> np.ndarray:
    """R(j) of Eq. 12 for every sub-pose: mean over ``cfg.score_points`` evenly spread source points moved by
    pose j of the smallest distance + |intensity difference| among their ``cfg.score_candidates`` nearest
    reference points (the same points for every pose, so the scores differ only by the poses)."""
    n = len(src)
    m = int(cfg.score_points)
    pick = np.arange(n) if (m <= 0 or n <= m) else (np.arange(m) * n) // m
    s, si = src[pick], src_i[pick]
    k = len(poses)
    moved = np.einsum("kab,nb->kna", poses[:, :3, :3], s) + poses[:, None, :3, 3]
    n_cand = int(min(max(1, cfg.score_candidates), len(ref)))
    dist, idx = ref.tree.query(moved.reshape(-1, 3), k=n_cand)
    if n_cand == 1:
        dist, idx = dist[:, None], idx[:, None]
    cost = dist + np.abs(np.tile(si, k)[:, None] - ref.intensity[idx])
    return cost.min(axis=1).reshape(k, -1).mean(axis=1)


def mad_threshold(r: np.ndarray, scale: float = 1.4826) -> float:
    """eps = mean(R) + scale * median(|R - median(R)|)  (Eqs. 14-16)."""
    r = np.asarray(r, float)
    return float(np.mean(r) + scale * np.median(np.abs(r - np.median(r))))
