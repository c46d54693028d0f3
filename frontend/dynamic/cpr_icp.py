"""CPR-SLAM's registration half (seed 000, Sections 3.4-3.7): K-Means, sub-poses, correlation scores.

Used by ``frontend.dynamic.cpr`` (which documents the method, the interpretation of the paper and the
deviations); the clouds come from ``cpr_cloud``. K-Means, and the sub-poses and scores against a projective
target (the default association), are compiled kernels (``cpr_icp_kernels``). Against the k-d tree (``association:
kdtree``) everything is whole-array numpy/scipy: one tree query per ICP iteration for all sub-clouds together,
per-sub-cloud sums with ``np.add.reduceat``, per-sub-cloud medians from one row-wise partition, batched 3x3 SVDs.
"""
from __future__ import annotations

import numpy as np

from frontend.dynamic import cpr_icp_kernels as kernels
from frontend.dynamic import cpr_kmeans_kernels as kmeans_kernels
from frontend.dynamic.cpr_assoc import ProjectiveTarget
from frontend.dynamic.cpr_cloud import Cloud
from slam.core.dynamic_config import CprConfig

_MIN_CLUSTER_POINTS = 10
_SCALE_FLOOR_GEOM = 0.01
_SCALE_FLOOR_INTENSITY = 0.01


def cluster(xyz: np.ndarray, k: int, seed: int, iterations: int = 10) -> np.ndarray:
    """K-Means labels (k-means++, fixed seed); deterministic for the same input.

    ``scipy.cluster.vq.kmeans2(xyz, k, iter=iterations, minit="++", seed=default_rng(seed))`` bit for bit
    (tests/test_cpr_vectorised.py), compiled (``cpr_kmeans_kernels.kmeans_labels``): the generator's draws are taken
    here in kmeans2's order (they do not depend on the data), the seeding and the Lloyd iterations there."""
    n = len(xyz)
    if n <= k:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    first = int(rng.integers(n))
    uniforms = np.array([rng.uniform() for _ in range(k - 1)])
    return kmeans_kernels.kmeans_labels(np.ascontiguousarray(xyz, dtype=np.float64), int(k), first, uniforms,
                                 int(iterations))


# --- robust statistics -------------------------------------------------------------------------------------


def robust_scale(r: np.ndarray, floor: float) -> float:
    """1.4826 * median absolute deviation from the median (Eqs. 8-9), at least ``floor``."""
    med = np.median(r)
    return max(1.4826 * float(np.median(np.abs(r - med))), floor)


def t_weight(r: np.ndarray, scale, nu: float) -> np.ndarray:
    """Student-t weight (Kerl et al.): (nu + 1) / (nu + (r / scale)^2); ``scale`` may broadcast."""
    return (nu + 1.0) / (nu + (r / scale) ** 2)


class _Rows:
    """Segments [starts[j], starts[j+1]) of a flat array laid out as the rows of a (k, width) table padded
    so that every row's lower middle order statistic lands in one column: per-segment medians are then one
    row-wise partition at that column instead of a ``np.median`` call per segment and value array (~40 us
    each, ~90 calls per frame)."""

    def __init__(self, starts: np.ndarray):
        self.lengths = np.diff(starts)
        self.k, self.width = len(self.lengths), max(int(self.lengths.max(initial=0)), 1)
        self.segment = np.repeat(np.arange(self.k), self.lengths)       # segment of every value
        # A row holds lead[j] values of -inf, its segment, then +inf: its order statistic r sits in column
        # lead[j] + r, so the lower middle one ((L - 1) // 2) in column (width - 1) // 2 for every row
        # (0 <= lead <= width - L for all L <= width). The upper middle (L // 2) is the next value up.
        self.column = (self.width - 1) // 2
        self.lead = self.column - np.maximum(self.lengths - 1, 0) // 2
        if np.all(self.lengths == self.width):
            self.slot = None                                            # equal segments: a plain reshape
        else:
            self.slot = (self.segment * self.width + np.repeat(self.lead, self.lengths)
                         + (np.arange(int(starts[-1])) - np.repeat(starts[:-1], self.lengths)))

    def medians(self, values: np.ndarray) -> np.ndarray:
        """``np.median`` of every segment, bit for bit (it is the mean of the two middle order statistics,
        (a + b) / 2, which a selection gives exactly); NaN for an empty segment."""
        if self.slot is None:
            table = values.reshape(self.k, self.width)
        else:
            table = np.full((self.k, self.width), np.inf)
            table[:, :self.column] = -np.inf        # every row's lead lies in these columns (the rest: +inf)
            table.reshape(-1)[self.slot] = values
        # One selection at the shared column (~6x cheaper than a selection at every row's own middle
        # positions, 10 x 1350 values); the upper middle of an even row is the smallest value above it.
        c = self.column
        table = np.partition(table, c, axis=1)
        lo = table[:, c]
        hi = np.where(self.lengths % 2 == 0, table[:, c + 1:].min(axis=1, initial=np.inf), lo)
        med = (lo + hi) / 2
        return np.where(self.lengths > 0, med, np.nan)

    def robust_scales(self, values: np.ndarray, floor: float) -> np.ndarray:
        """``robust_scale`` of every segment (NaN for an empty one)."""
        med = self.medians(values)
        return np.maximum(1.4826 * self.medians(np.abs(values - med[self.segment])), floor)


# --- sub-poses ---------------------------------------------------------------------------------------------


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
    for j in range(len(starts) - 1):                      # one slice per sub-cloud
        a, b = int(starts[j]), int(starts[j + 1])
        m = b - a
        parts.append(np.arange(a, b) if m <= cap else a + (np.arange(cap) * m) // cap)
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _intensity_correspondences(p: np.ndarray, intensity: np.ndarray, lab_s: np.ndarray, seg: np.ndarray, k: int,
                               ref: Cloud, n_cand: int, nu: float) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 4-9: of each point's ``n_cand`` candidates, the one with the largest product of Student-t
    weights of its distance and intensity residuals (a sub-cloud's scales cover all its candidates);
    returns the chosen reference points and their weights (0 for a point without candidates)."""
    dist, idx = ref.query(p, n_cand)
    r_i = np.abs(intensity[:, None] - ref.intensity[idx])
    ok = np.isfinite(dist)                 # projective: window cells without a sample
    if ok.all():
        rows, dv, iv = _Rows(seg * dist.shape[1]), dist.reshape(-1), r_i.reshape(-1)
    else:                                  # scales over the existing candidates only
        rows = _Rows(np.concatenate([[0], np.cumsum(np.bincount(lab_s, ok.sum(axis=1), k))]).astype(np.int64))
        dv, iv = dist[ok], r_i[ok]
    sg = rows.robust_scales(dv, _SCALE_FLOOR_GEOM)[lab_s, None]
    si = rows.robust_scales(iv, _SCALE_FLOOR_INTENSITY)[lab_s, None]
    w = t_weight(dist, sg, nu) * t_weight(r_i, si, nu)
    w[~ok] = -1.0
    best = np.argmax(w, axis=1)
    pts = np.arange(len(p))
    return ref.xyz[idx[pts, best]], np.maximum(w[pts, best], 0.0)


def _nearest_correspondences(p: np.ndarray, lab_s: np.ndarray, seg: np.ndarray, k: int, ref: Cloud,
                             nu: float) -> tuple[np.ndarray, np.ndarray]:
    """Plain robust ICP: each point's nearest reference point under the geometric Student-t weight
    (0 for a point without a candidate)."""
    dist, idx = ref.query(p, 1)
    dist, idx = dist[:, 0], idx[:, 0]
    q = ref.xyz[idx]
    ok = np.isfinite(dist)
    if ok.all():
        return q, t_weight(dist, _Rows(seg).robust_scales(dist, _SCALE_FLOOR_GEOM)[lab_s], nu)
    scale = _Rows(_segments(lab_s[ok], k)).robust_scales(dist[ok], _SCALE_FLOOR_GEOM)
    return q, np.where(ok, t_weight(np.where(ok, dist, 0.0), scale[lab_s], nu), 0.0)


def sub_poses(src: np.ndarray, src_i: np.ndarray, labels: np.ndarray, k: int, ref: Cloud, init: np.ndarray,
              cfg: CprConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pose of each of the ``k`` sub-clouds (current camera -> reference camera), Section 3.5.

    ``cfg.icp_iterations`` in all: the first ``cfg.icp_intensity_iterations`` intensity-assisted (Eqs. 4-11),
    the rest plain robust ICP. Each sub-cloud is registered with at most ``cfg.icp_max_points`` evenly spread
    points. Returns (poses (k,4,4), valid (k,) bool: sub-cloud large enough to register)."""
    order = np.argsort(labels, kind="stable")
    starts_all = _segments(labels[order], k)
    valid = np.diff(starts_all) >= _MIN_CLUSTER_POINTS
    pick = order[_even_subsample(starts_all, max(_MIN_CLUSTER_POINTS, int(cfg.icp_max_points)))]
    lab, p0, i0 = labels[pick], src[pick], src_i[pick]
    nu = cfg.student_nu
    n_cand = int(min(cfg.candidates, len(ref)))
    n_int = min(int(cfg.icp_intensity_iterations), int(cfg.icp_iterations))
    if isinstance(ref, ProjectiveTarget):
        poses = kernels.sub_poses_projective(
            np.ascontiguousarray(p0), np.ascontiguousarray(i0), _segments(lab, k), valid,
            np.ascontiguousarray(init, dtype=np.float64), *ref.kernel_args(), float(nu), n_int,
            int(cfg.icp_iterations), n_cand > 1, _SCALE_FLOOR_GEOM, _SCALE_FLOOR_INTENSITY)
        return poses, valid
    poses = np.tile(init, (k, 1, 1))
    for intensity_stage, iters in ((True, n_int), (False, int(cfg.icp_iterations) - n_int)):
        active = valid.copy()
        for _ in range(iters):
            if not np.any(active):
                break
            ids = np.flatnonzero(active[lab])          # only points of sub-clouds still moving
            lab_s = lab[ids]
            p = _apply(poses, lab_s, p0[ids])
            seg = _segments(lab_s, k)
            if intensity_stage and n_cand > 1:
                q, wt = _intensity_correspondences(p, i0[ids], lab_s, seg, k, ref, n_cand, nu)
            else:
                q, wt = _nearest_correspondences(p, lab_s, seg, k, ref, nu)
            delta = _kabsch(p, q, wt, seg, active)
            poses = delta @ poses
            moved = np.linalg.norm(delta[:, :3, 3], axis=1)
            angle = np.arccos(np.clip((np.trace(delta[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
            active &= ~((moved < 1e-4) & (angle < np.deg2rad(0.01)))
    return poses, valid


# --- correlation -------------------------------------------------------------------------------------------


def correlation_scores(src: np.ndarray, src_i: np.ndarray, poses: np.ndarray, ref: Cloud, cfg: CprConfig
                       ) -> np.ndarray:
    """R(j) of Eq. 12 for every sub-pose: mean over ``cfg.score_points`` evenly spread source points moved by
    pose j of the smallest distance + |intensity difference| among their ``cfg.score_candidates`` nearest
    reference points (the same points for every pose, so the scores differ only by the poses)."""
    n = len(src)
    m = int(cfg.score_points)
    pick = np.arange(n) if (m <= 0 or n <= m) else (np.arange(m) * n) // m
    s, si = src[pick], src_i[pick]
    if isinstance(ref, ProjectiveTarget):
        return kernels.correlation_scores_projective(
            np.ascontiguousarray(s), np.ascontiguousarray(si), np.ascontiguousarray(poses, dtype=np.float64),
            *ref.kernel_args(), float(cfg.score_max_distance), int(min(max(1, cfg.score_candidates), len(ref))) == 1)
    k = len(poses)
    rot = np.ascontiguousarray(poses[:, :3, :3])         # einsum runs ~2x faster on a contiguous operand
    moved = np.einsum("kab,nb->kna", rot, s) + poses[:, None, :3, 3]
    # Query point-major (a point under all k poses, then the next point): consecutive queries land in the
    # same part of the tree, ~15 % faster than pose-major. Queries are independent, so the results are the
    # same; they go back to pose-major before the means (the same summation order as before).
    moved = np.ascontiguousarray(moved.transpose(1, 0, 2))
    n_cand = int(min(max(1, cfg.score_candidates), len(ref)))
    dist, idx = ref.query(moved.reshape(-1, 3), n_cand, clamp=True)
    cap = cfg.score_max_distance
    if cap > 0:
        # A point's distance counts at most ``cap``: projective candidates lie on its ray, so a point off every
        # surface (people that moved, occlusions) would add the depth gap behind it (metres) and swamp R.
        # inf (no such candidate) stays inf; a point without any candidate (a hole, outside the view) costs cap.
        dist = np.where(dist > cap, np.where(np.isinf(dist), np.inf, cap), dist)
    cost = dist + np.abs(np.repeat(si, k)[:, None] - ref.intensity[idx])
    point = cost.min(axis=1)
    if cap > 0:
        point[np.isinf(point)] = cap
    best = np.ascontiguousarray(point.reshape(-1, k).T)
    ok = np.isfinite(best)
    if ok.all():
        return best.mean(axis=1)
    # no cap: a point without a candidate has no correspondence and is left out of that pose's mean
    return np.where(ok, best, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)


def mad_threshold(r: np.ndarray, scale: float = 1.4826) -> float:
    """eps = mean(R) + scale * median(|R - median(R)|)  (Eqs. 14-16)."""
    r = np.asarray(r, float)
    return float(np.mean(r) + scale * np.median(np.abs(r - np.median(r))))
