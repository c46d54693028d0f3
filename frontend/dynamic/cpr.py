"""Sub-point-cloud correlation (CPR-SLAM, Yu, Zheng & Ou 2024, seed 000): geometric, no detector.

Per frame (Sections 3.3-3.7 of the paper):

1. Point cloud from every ``sample_step``-th row/column of the depth image, depth > ``max_depth`` invalid.
2. Voxel filter (``voxel_size``): a voxel's point is the centroid of its samples, its intensity the mean grey
   value (Eq. 2); numpy ``unique`` + ``bincount`` (faster than open3d here).
3. Moving-least-squares smoothing (``mls_radius``), see "simplifications" below.
4. K-Means on xyz into ``clusters`` sub-clouds (``kmeans2``, k-means++, fixed seed). The paper clusters "the
   depth image", i.e. the geometry; intensity is not a clustering feature.
5. Reference frame ``sigma_frame`` frames back (Section 3.4).
6. A "sub-pose" per sub-cloud (Section 3.5): intensity-assisted ICP against the reference cloud (``candidates``
   nearest neighbours, the one with the largest product of Student-t weights of its geometric and intensity
   residual is the correspondence, Eqs. 4-9), then plain ICP refinement. Initial guess from the constant
   velocity model (Eq. 3).
7. Correlation score R(j) (Eq. 12): the whole source cloud moved by sub-pose j, mean over its points of the
   distance to the corresponding reference point plus the intensity difference.
8. Threshold eps = mean(R) + mad_scale * median(|R - median(R)|) (Eqs. 14-16); R > eps => dynamic sub-cloud.
9. Dynamic sub-clouds to the image: a disc of ``circle_radius`` px at every point, then a closing.
10. Keyframe refinement (Section 3.8, Algorithm 1) with the last ``refine_window`` masks.

Interpretation and deviations (all defaults are the paper's; the numbers live in ``CprConfig``):

* Eq. 3 as printed, (T_pre T_last)^-1 T_ref, does not chain (it multiplies camera->world by world->camera of
  another frame). What the ICP needs is the map from the current camera into the reference camera,
  T_ref_cw @ inv(T_cur_cw) with T_cur_cw = ``ctx.predicted_T_cw`` (ORB-SLAM's T_pre T_last, i.e. the same
  constant-velocity model) and T_ref_cw the pose ``end_frame`` stored for the reference frame. Identity when
  either is unknown (first frames, lost tracking).
* Eq. 7 is garbled in the paper. We use the Student-t weight of Kerl et al. [27] that the paper cites,
  w(r) = (nu + 1) / (nu + (r / s)^2), with the robust scale s = 1.4826 * median(|r - median(r)|) of Eqs. 8-9,
  computed per sub-cloud and iteration over all candidate residuals (per point over only 10 candidates it is
  meaningless; centring at the median would prefer a mid-distance candidate over the nearest one). Scales are
  floored (1 cm, 1 % intensity) so that exact synthetic data cannot divide by zero. The selected candidate's
  weight is also its weight in the weighted point-to-point (Kabsch/Umeyama) step of Eq. 10 ("weighted Euclidean
  distance"). Plain ICP = nearest neighbour with the geometric t-weight only (robust IRLS) so that the part of
  a sub-cloud not seen in the reference cannot drag it.
* Iterations: ``icp_iterations`` intensity-assisted, then ``plain_icp_iterations`` plain (the paper gives no
  split). All sub-clouds are registered together: one k-d tree query per iteration over all points, sums per
  sub-cloud with ``np.add.reduceat``, batched 3x3 SVDs. Stops early when no sub-pose moves by > 0.1 mm/0.01 deg.
* Eq. 12 "an additional intensity value is used as a penalty to find the corresponding point": each point's
  correspondence is the candidate (of ``candidates`` nearest) minimising distance + |intensity difference|,
  and R(j) is the mean of that minimum. Intensities are grey / 255, so 0.1 (25 grey levels) weighs like 10 cm.
  For speed R uses every ``score_stride``-th source point (a mean; the estimate barely changes).
* Eq. 14 subtracts the median without an absolute value; the brief and the MAD it names need |R - median(R)|.
* MLS (Section 3.3): we do what PCL's MLS does with a first-order (planar) fit: for every voxel point, a
  Gaussian-weighted (h = ``mls_radius``) plane through its neighbours within ``mls_radius`` (at most 16, from a
  cKDTree), and the point is projected onto it. Points with fewer than 3 neighbours are dropped as outliers
  (PCL also skips them). No second-order polynomial: at 5 cm voxels and 10 cm radius a quadric adds nothing.
* Mask: the paper projects the voxel points of dynamic sub-clouds. Voxel centroids are 5 cm apart (27 px at
  1 m), far sparser than the 6 px discs; we instead mark the *depth samples* (every 4th pixel) whose voxel lies
  in a dynamic sub-cloud - the same points before voxelisation, at their own pixels, so no reprojection and no
  distortion model are needed, and the mask is in raw image coordinates like ``uv_raw``. Discs = dilation
  with a disc kernel, then a closing with the same kernel.
* Reference frame and keyframes: the keyframe decision is made after tracking, so at ``process`` time the
  current frame's status is unknown. Every frame uses ``sigma_frame`` (2). ``sigma_keyframe`` (5) is used in
  ``end_frame`` when ``keyframe_recompute`` is set: the keyframe's mask is recomputed against the frame 5 back
  and refined; that mask (weight ``rho_keyframe``) is what later refinements see.  Off by default: it costs a
  second correlation pass per keyframe and, on Bonn crowd, changes little (see the report in docs).
* Keyframe refinement per frame: every frame may become a keyframe and the back end takes a keyframe's
  features before ``end_frame`` can say so, so the refinement is applied to every frame's output, exactly as
  Algorithm 1 would for a keyframe: weight(x) = sum_i rho_i M_i(x) over the last ``refine_window`` masks
  (``rho_keyframe`` for frames that became keyframes, ``rho_frame`` otherwise) plus the current raw mask with
  ``rho_keyframe`` (the "+1"). Eq. 19's threshold tau (N + 1) rho assumes one rho for all; we use tau times the
  total weight of the observations (the text: "tau times greater than the weight of total observation"), which
  equals Eq. 19 when all rho are equal. Pixels above it form the refined mask, dilated by ``circle_radius``
  ("properly expanded" edges). Like the paper, no refinement until ``refine_window`` masks exist. The history
  stores each ordinary frame's raw mask and each keyframe's refined mask. Masks are not motion-compensated
  (as in the paper). With ``refine=False`` the raw mask is output.
* Output: ``prob`` = refined mask at the keypoint (1/0); NaN (abstain) until a reference frame exists. The
  soft alternative (weight / total) was measured and not better; see the report.
"""
from __future__ import annotations

import time
import warnings
from collections import deque
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree

from frontend.dynamic.base import DynamicContext, MethodOutput, keypoints_in_mask
from slam.camera import PinholeCamera
from slam.dynamic_config import CprConfig

_MIN_CLUSTER_POINTS = 10
_MAX_LOOKUP = 8_000_000
DENSE_REF = True
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
    """First-order moving least squares on a voxelised cloud: every point is projected onto the plane fitted
    (Gaussian weights exp(-d^2/radius^2), d <= radius) to the points in the 3x3x3 voxels around its own.

    Returns (smoothed points, keep, unit normals (0 where no plane)); keep is False for points with fewer than 3 neighbours (incl. itself),
    which are outliers (PCL's MLS skips them too). The voxel neighbourhood replaces a radius search: exact
    up to one voxel, and ~10x cheaper than a k-d tree query here."""
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
    """Steps 1-3: sampled cloud, voxel filter, MLS."""
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
    if DENSE_REF:
        kept = keep[inverse]
        v = inverse[kept]
        x = xyz[kept]
        off = np.einsum("na,na->n", x - smooth[v], normals[v])
        cloud.dense_xyz = x - off[:, None] * normals[v]
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


def _point_to_plane(p: np.ndarray, q: np.ndarray, nq: np.ndarray, w: np.ndarray, starts: np.ndarray,
                    active: np.ndarray, damping: float = 1e-6) -> np.ndarray:
    """One Gauss-Newton step per segment of sum w (n.(R p + t - q))^2; (K,4,4), identity where inactive.
    The damping keeps directions the segment does not constrain (a plane's in-plane motion) where they are."""
    k = len(starts) - 1
    out = np.tile(np.eye(4), (k, 1, 1))
    use = active & (np.diff(starts) >= 6)
    if not np.any(use):
        return out
    jac = np.concatenate([np.cross(p, nq), nq], axis=1)            # (n,6)
    res = np.einsum("na,na->n", p - q, nq)
    wj = w[:, None] * jac
    jtj = _segment_sums(wj[:, :, None] * jac[:, None, :], starts)[use]
    jtr = _segment_sums(wj * res[:, None], starts)[use]
    scale = np.maximum(np.trace(jtj, axis1=1, axis2=2), 1e-12)
    jtj = jtj + (damping * scale)[:, None, None] * np.eye(6)
    x = -np.linalg.solve(jtj, jtr[:, :, None])[:, :, 0]
    out[use, :3, :3] = _rodrigues(x[:, :3])
    out[use, :3, 3] = x[:, 3:]
    return out


def _rodrigues(omega: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(omega, axis=1)
    k = omega / np.maximum(theta, 1e-12)[:, None]
    kx = np.zeros((len(omega), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + st * kx + (1 - ct) * (kx @ kx)


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
            if getattr(cfg, "icp_metric", "point_to_point") == "point_to_plane" and ref.normals is not None:
                nq = ref.normals[idx[np.arange(len(p)), best]] if (intensity_stage and n_cand > 1) else ref.normals[idx]
                delta = _point_to_plane(p, q, nq, wt, seg, active)
            else:
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


# --- masks -------------------------------------------------------------------------------------------------


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def samples_to_mask(shape: tuple[int, int], pix: np.ndarray, radius: int) -> np.ndarray:
    """Disc of ``radius`` px around every (row, col) in ``pix``, then a closing: uint8 {0,1} mask."""
    mask = np.zeros(shape, np.uint8)
    if len(pix) == 0:
        return mask
    mask[pix[:, 0], pix[:, 1]] = 1
    kernel = _disc(radius)
    mask = cv2.dilate(mask, kernel)
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)


def refine_mask(history: list[tuple[np.ndarray, float]], current: np.ndarray, rho_current: float, tau: float,
                dilate_radius: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 1: weight = sum rho_i M_i over history + rho_current * current; dynamic where the weight
    exceeds tau times the total weight. Returns (refined uint8 mask, weight / total weight)."""
    weight = current.astype(np.float32) * np.float32(rho_current)
    total = float(rho_current)
    for mask, rho in history:
        weight += mask.astype(np.float32) * np.float32(rho)
        total += float(rho)
    refined = (weight > tau * total).astype(np.uint8)
    if dilate_radius > 0 and refined.any():
        refined = cv2.dilate(refined, _disc(dilate_radius))
    return refined, weight / np.float32(total)


# --- the method --------------------------------------------------------------------------------------------


@dataclass
class _Past:
    cloud: Cloud
    T_cw: Optional[np.ndarray]
    is_keyframe: bool = False


class CprMethod:
    """Sub-point-cloud correlation. See the module docstring for the algorithm and the choices made."""

    name = "cpr"
    needs_detector = False

    def __init__(self, cfg: Optional[CprConfig] = None):
        self.cfg = cfg or CprConfig()
        self._past: deque[_Past] = deque(maxlen=max(self.cfg.sigma_frame, self.cfg.sigma_keyframe) + 1)
        self._masks: deque[tuple[np.ndarray, float]] = deque(maxlen=max(1, self.cfg.refine_window))
        self._grid_key = None
        self._pending: Optional[dict] = None
        self.timings: dict[str, float] = {}

    # -- public --
    def process(self, ctx: DynamicContext) -> MethodOutput:
        self._flush_pending()
        n = len(ctx.frame)
        times: dict[str, float] = {}
        t0 = time.perf_counter()
        cloud = self._cloud(ctx)
        times["cloud"] = (time.perf_counter() - t0) * 1e3
        pending = {"cloud": cloud, "raw": None, "refined": None, "labels": None}
        self._pending = pending
        ref = self._reference(self.cfg.sigma_frame)
        if ref is None or len(cloud) < self.cfg.clusters * _MIN_CLUSTER_POINTS or len(ref.cloud) < 10:
            self.timings = times
            return MethodOutput(np.full(n, np.nan), None, {"abstain": 1, **{f"ms_{k}": v for k, v in times.items()}})
        raw, info = self._raw_mask(cloud, ref, ctx.predicted_T_cw, times)
        pending["raw"], pending["labels"] = raw, info.pop("_labels")
        t0 = time.perf_counter()
        out_mask = raw
        if self.cfg.refine and len(self._masks) >= self.cfg.refine_window:
            out_mask, _ = refine_mask(list(self._masks), raw, self.cfg.rho_keyframe, self.cfg.tau, self.cfg.circle_radius)
            pending["refined"] = out_mask
        times["refine"] = (time.perf_counter() - t0) * 1e3
        prob = keypoints_in_mask(out_mask, ctx.frame.uv_raw).astype(float) if n else np.zeros(0)
        info.update({f"ms_{k}": v for k, v in times.items()})
        self.timings = times
        return MethodOutput(prob, out_mask.astype(bool), info)

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        pending = self._pending
        if pending is None:
            return
        self._pending = None
        T = None if T_cw is None else np.asarray(T_cw, float).copy()
        if is_keyframe and self.cfg.keyframe_recompute:
            ref = self._reference(self.cfg.sigma_keyframe)
            if ref is not None and pending["raw"] is not None:
                raw, _ = self._raw_mask(pending["cloud"], ref, T if T is not None else ctx.predicted_T_cw, {})
                pending["raw"] = raw
                pending["refined"] = None
                if len(self._masks) >= self.cfg.refine_window:
                    pending["refined"], _ = refine_mask(list(self._masks), raw, self.cfg.rho_keyframe, self.cfg.tau,
                                                        self.cfg.circle_radius)
        self._store(pending, T, is_keyframe)

    # -- internals --
    def _flush_pending(self) -> None:
        """A frame whose end_frame never came is kept as an ordinary frame with an unknown pose."""
        if self._pending is not None:
            self._store(self._pending, None, False)
            self._pending = None

    def _store(self, pending: dict, T_cw: Optional[np.ndarray], is_keyframe: bool) -> None:
        self._past.append(_Past(pending["cloud"], T_cw, is_keyframe))
        mask = pending["refined"] if (is_keyframe and pending["refined"] is not None) else pending["raw"]
        if mask is not None:
            self._masks.append((mask, self.cfg.rho_keyframe if is_keyframe else self.cfg.rho_frame))

    def _reference(self, sigma: int) -> Optional[_Past]:
        if sigma < 1 or len(self._past) < sigma:
            return None
        return self._past[-sigma]

    def _cloud(self, ctx: DynamicContext) -> Cloud:
        h, w = ctx.depth.shape[:2]
        cam = ctx.camera
        key = (h, w, self.cfg.sample_step, cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion)
        if key != self._grid_key:
            self._pix, self._rays = sample_grid(cam, h, w, self.cfg.sample_step)
            self._grid_key = key
        gray = ctx.gray if ctx.gray is not None else cv2.cvtColor(ctx.rgb, cv2.COLOR_BGR2GRAY)
        return build_cloud(ctx.depth, gray, self._pix, self._rays, self.cfg, cam.min_depth)

    def _raw_mask(self, cloud: Cloud, ref: _Past, predicted_T_cw: Optional[np.ndarray],
                  times: dict[str, float]) -> tuple[np.ndarray, dict]:
        cfg = self.cfg
        t0 = time.perf_counter()
        labels = cluster(cloud.xyz, cfg.clusters, cfg.seed)
        times["kmeans"] = (time.perf_counter() - t0) * 1e3
        init = np.eye(4)
        if predicted_T_cw is not None and ref.T_cw is not None:
            init = ref.T_cw @ _inv(np.asarray(predicted_T_cw, float))
        t0 = time.perf_counter()
        target = ref.cloud.target()
        poses, valid = sub_poses(cloud.xyz, cloud.intensity, labels, cfg.clusters, target, init, cfg)
        times["icp"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        r = np.full(cfg.clusters, np.nan)
        if np.any(valid):
            r[valid] = correlation_scores(cloud.xyz, cloud.intensity, poses[valid], target, cfg)
        eps = mad_threshold(r[valid], cfg.mad_scale) if np.any(valid) else np.inf
        dynamic = valid & (r > eps)
        if cfg.min_score_ratio > 1.0 and np.any(valid):
            dynamic &= r > cfg.min_score_ratio * np.median(r[valid])
        times["score"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        point_dyn = np.zeros(len(cloud) + 1, bool)       # last slot: samples whose voxel was dropped
        point_dyn[:-1] = dynamic[labels]
        sample_dyn = point_dyn[cloud.sample_point]
        mask = samples_to_mask(cloud.shape, cloud.sample_pix[sample_dyn], cfg.circle_radius)
        times["mask"] = (time.perf_counter() - t0) * 1e3
        info = {"points": len(cloud), "dynamic_clusters": int(dynamic.sum()), "threshold": eps,
                "scores": r, "_labels": labels}
        return mask, info


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out
