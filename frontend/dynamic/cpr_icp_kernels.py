"""Compiled kernels of the cpr method's registration (numba): the projective association, the sub-pose ICP and
the correlation scores (K-Means: ``cpr_kmeans_kernels``).

The same arithmetic as the numpy formulation (``cpr_icp``), in loops over points: the Student-t weights, robust
scales and Kabsch step of the ICP.
GIL released, cached on disk, no ``fastmath`` / ``parallel`` (see ``cpr_cloud_kernels``).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}


# --- projective association --------------------------------------------------------------------------------


@numba.njit(**_JIT)
def _window_centre(px, py, pz, fx, fy, cx, cy, width, height, seen, cell, sentinel, clamp):
    """Padded grid cell whose window holds the candidates of a point in the reference camera (``sentinel``:
    none). ``cpr_assoc.ProjectiveTarget.query`` for one point."""
    if not pz > 1e-6:
        return sentinel
    u = np.rint(fx * px / pz + cx)
    v = np.rint(fy * py / pz + cy)
    inside = u >= 0 and u < width and v >= 0 and v < height
    ui = np.int64(min(max(u, 0.0), width - 1))
    vi = np.int64(min(max(v, 0.0), height - 1))
    lin = vi * width + ui
    if not clamp and not (inside and seen[lin]):
        return sentinel
    return cell[lin]


@numba.njit(**_JIT)
def projective_table(cells, xyz, intensity, size):
    """The reference samples on the padded sampling grid, one row (x, y, z, intensity) per cell plus the
    sentinel row: x, y, z = inf where a cell has no sample (a missing candidate's distance comes out inf by
    itself), intensity 0. One row per candidate keeps a window's reads on a few cache lines."""
    table = np.empty((size + 1, 4))
    for g in range(size + 1):
        table[g, 0], table[g, 1], table[g, 2], table[g, 3] = np.inf, np.inf, np.inf, 0.0
    for t in range(len(cells)):
        g = cells[t]
        table[g, 0], table[g, 1], table[g, 2], table[g, 3] = xyz[t, 0], xyz[t, 1], xyz[t, 2], intensity[t]
    return table


@numba.njit(**_JIT)
def window_query(p, table, fx, fy, cx, cy, width, height, seen, cell, offsets, sentinel, clamp):
    """Every point's window candidates: (distances (n, c), inf where no sample; table rows (n, c))."""
    n, c = len(p), len(offsets)
    dist = np.empty((n, c))
    rows = np.empty((n, c), np.int64)
    for t in range(n):
        centre = _window_centre(p[t, 0], p[t, 1], p[t, 2], fx, fy, cx, cy, width, height, seen, cell, sentinel,
                                clamp)
        for o in range(c):
            g = sentinel if centre == sentinel else centre + offsets[o]
            rows[t, o] = g
            dx, dy, dz = table[g, 0] - p[t, 0], table[g, 1] - p[t, 1], table[g, 2] - p[t, 2]
            dist[t, o] = np.sqrt((dx * dx + dy * dy) + dz * dz)
    return dist, rows


@numba.njit(**_JIT)
def _t_weight(r, scale, nu):
    q = r / scale
    return (nu + 1.0) / (nu + q * q)


# --- exact medians of non-negative values -------------------------------------------------------------------

# The robust scales take two medians of ~1,350 residuals per sub-cloud and iteration; with numba's np.median (a
# quickselect on a copy) they were over half of the sub-pose ICP (captured Bonn calls: 4.0 ms, 1.8 with the scales
# stubbed out; 2.8 with these). The residuals are non-negative doubles (distances, absolute differences: never
# -0.0, whose pattern is the sign bit), whose IEEE bit patterns are ordered as their values: counting them into
# buckets of their bit patterns finds the bucket of the k-th in two passes without a quickselect's mispredicted
# branches, and only that bucket is searched further. The order statistics are exact, so the medians are
# np.median's to the bit.
_BUCKETS = 1024
_SORT_BELOW = 24          # a bucket this small is sorted outright


@numba.njit(**_JIT)
def _insertion_sort(a, m):
    for i in range(1, m):
        x = a[i]
        j = i - 1
        while j >= 0 and a[j] > x:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = x


@numba.njit(**_JIT)
def _kth_smallest(src, k, want_next, work, counts):
    """The k-th smallest (0-based) of the non-negative finite doubles ``src`` and, with ``want_next``, the
    (k+1)-th (NaN otherwise). ``work``: scratch as long as ``src``; ``counts``: (_BUCKETS,) int64 scratch."""
    data = src
    m = len(src)
    nxt = np.nan
    pending = want_next
    while True:
        if m <= _SORT_BELOW:
            for i in range(m):
                work[i] = data[i]
            _insertion_sort(work, m)
            if pending:
                nxt = work[k + 1]
            return work[k], nxt
        bits = data[:m].view(np.int64)
        lo, hi = bits[0], bits[0]
        for i in range(1, m):
            lo, hi = min(lo, bits[i]), max(hi, bits[i])
        if lo == hi:                                   # all equal
            return data[0], (data[0] if pending else nxt)
        shift = 0
        while ((hi - lo) >> shift) >= _BUCKETS:
            shift += 1
        for g in range(((hi - lo) >> shift) + 1):
            counts[g] = 0
        for i in range(m):
            counts[(bits[i] - lo) >> shift] += 1
        below, g = 0, 0
        while below + counts[g] <= k:
            below += counts[g]
            g += 1
        size, k = counts[g], k - below
        if pending and k + 1 >= size:                 # the next one is the smallest in the buckets above
            nxt = np.inf
            for i in range(m):
                if ((bits[i] - lo) >> shift) > g and data[i] < nxt:
                    nxt = data[i]
            pending = False
        w = 0
        for i in range(m):                            # in place once data is work: w never passes i
            if ((bits[i] - lo) >> shift) == g:
                work[w] = data[i]
                w += 1
        data, m = work, size


@numba.njit(**_JIT)
def median_nonneg(values, work, counts):
    """np.median of non-negative finite ``values`` (its mean of the two middle ones for an even count)."""
    n = len(values)
    half = n >> 1
    if n & 1 == 0:
        a, b = _kth_smallest(values, half - 1, True, work, counts)
        return (a + b) / 2
    return _kth_smallest(values, half, False, work, counts)[0]


@numba.njit(**_JIT)
def robust_scale_in_place(values, floor, work, counts):
    """1.4826 * median absolute deviation from the median (Eqs. 8-9), at least ``floor``. Overwrites ``values``
    with the deviations."""
    med = median_nonneg(values, work, counts)
    for i in range(len(values)):
        values[i] = abs(values[i] - med)
    return max(1.4826 * median_nonneg(values, work, counts), floor)


@numba.njit(**_JIT)
def _kabsch_step(sums, ws):
    """Weighted rigid transform from the sums of one sub-cloud (sum w p, sum w q, sum w p q^T): (4,4)."""
    out = np.eye(4)
    sp = sums[0:3] / ws
    sq = sums[3:6] / ws
    h = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            h[a, b] = sums[6 + 3 * a + b] / ws - sp[a] * sq[b]
    u, _, vt = np.linalg.svd(h)
    rot = vt.T @ u.T
    if np.linalg.det(rot) < 0:
        fix = np.eye(3)
        fix[2, 2] = -1.0
        rot = vt.T @ fix @ u.T
    out[:3, :3] = rot
    out[:3, 3] = sq - rot @ sp
    return out


@numba.njit(**_JIT)
def _gather_window(pose, p0, i0, a, n, table, fx, fy, cx, cy, width, height, seen, cell, offsets, sentinel,
                   p, cand, dist, r_int):
    """Points a..a+n moved by ``pose`` (into ``p``), and every point's window candidates: table rows (``cand``),
    distances (``dist``, inf where a cell has no sample) and intensity residuals (``r_int``)."""
    for t in range(n):
        s = a + t
        for e in range(3):
            p[t, e] = pose[e, 0] * p0[s, 0] + pose[e, 1] * p0[s, 1] + pose[e, 2] * p0[s, 2] + pose[e, 3]
        centre = _window_centre(p[t, 0], p[t, 1], p[t, 2], fx, fy, cx, cy, width, height, seen, cell, sentinel,
                                False)
        for o in range(len(offsets)):
            g = sentinel if centre == sentinel else centre + offsets[o]
            cand[t, o] = g
            dx, dy, dz = table[g, 0] - p[t, 0], table[g, 1] - p[t, 1], table[g, 2] - p[t, 2]
            dist[t, o] = np.sqrt((dx * dx + dy * dy) + dz * dz)
            r_int[t, o] = abs(i0[s] - table[g, 3])


@numba.njit(**_JIT)
def _intensity_matches(n, dist, r_int, cand, table, nu, floor_geom, floor_intensity, buf_g, buf_i, work, counts,
                       q, w):
    """Eqs. 4-9: each point's candidate with the largest product of Student-t weights of its distance and
    intensity residual, the scales over all candidates of the sub-cloud; into ``q`` and ``w`` (0 without a
    candidate). False when no point has a candidate."""
    count = 0
    for t in range(n):
        for o in range(dist.shape[1]):
            if np.isfinite(dist[t, o]):
                buf_g[count] = dist[t, o]
                buf_i[count] = r_int[t, o]
                count += 1
    if count == 0:
        return False
    sg = robust_scale_in_place(buf_g[:count], floor_geom, work, counts)
    si = robust_scale_in_place(buf_i[:count], floor_intensity, work, counts)
    for t in range(n):
        # the largest product of the two weights (nu+1)^2 / (den_g den_i) is the smallest product of their
        # denominators: one division per point instead of two per candidate
        best, best_den = -1, np.inf
        for o in range(dist.shape[1]):
            if np.isfinite(dist[t, o]):
                qg, qi = dist[t, o] / sg, r_int[t, o] / si
                den = (nu + qg * qg) * (nu + qi * qi)
                if den < best_den:
                    best, best_den = o, den
        if best < 0:
            w[t] = 0.0
            continue
        g = cand[t, best]
        q[t, 0], q[t, 1], q[t, 2] = table[g, 0], table[g, 1], table[g, 2]
        w[t] = _t_weight(dist[t, best], sg, nu) * _t_weight(r_int[t, best], si, nu)
    return True


@numba.njit(**_JIT)
def _nearest_matches(n, dist, cand, table, nu, floor_geom, buf_g, work, counts, q, w):
    """Plain robust ICP: each point's nearest candidate under the geometric Student-t weight (0 without a
    candidate); into ``q`` and ``w``. False when no point has a candidate."""
    m = 0
    for t in range(n):
        best, best_d = 0, np.inf
        for o in range(dist.shape[1]):
            if dist[t, o] < best_d:
                best, best_d = o, dist[t, o]
        g = cand[t, best]
        q[t, 0], q[t, 1], q[t, 2] = table[g, 0], table[g, 1], table[g, 2]
        w[t] = best_d
        if np.isfinite(best_d):
            buf_g[m] = best_d
            m += 1
    if m == 0:
        return False
    sg = robust_scale_in_place(buf_g[:m], floor_geom, work, counts)
    for t in range(n):
        w[t] = _t_weight(w[t], sg, nu) if np.isfinite(w[t]) else 0.0
    return True


@numba.njit(**_JIT)
def _weighted_sums(n, p, q, w):
    """(sum w p, sum w q, sum w p q^T) as 15 values, and sum w (Eq. 10's weighted point-to-point step)."""
    sums = np.zeros(15)
    ws = 0.0
    for t in range(n):
        wt = w[t]
        if wt == 0.0:
            continue
        ws += wt
        for e in range(3):
            sums[e] += wt * p[t, e]
            sums[3 + e] += wt * q[t, e]
        for e in range(3):
            we = wt * p[t, e]
            for f in range(3):
                sums[6 + 3 * e + f] += we * q[t, f]
    return sums, ws


@numba.njit(**_JIT)
def sub_poses_projective(p0, i0, starts, valid, init, table, fx, fy, cx, cy, width,
                         height, seen, cell, offsets, sentinel, nu, intensity_iterations, iterations,
                         window_candidates, floor_geom, floor_intensity):
    """Sub-pose ICP of ``cpr_icp.sub_poses`` with projective association. ``p0``/``i0`` are the registered
    points sorted by sub-cloud (segments [starts[j], starts[j+1])). Intensity-assisted iterations first
    (``_intensity_matches``), then plain robust ICP (``_nearest_matches``). A sub-cloud stops when a step moves
    it < 0.1 mm and 0.01 deg."""
    k = len(starts) - 1
    poses = np.empty((k, 4, 4))
    for j in range(k):
        poses[j] = init
    c = len(offsets)
    n_max = 0
    for j in range(k):
        n_max = max(n_max, starts[j + 1] - starts[j])
    dist = np.empty((n_max, c))
    r_int = np.empty((n_max, c))
    cand = np.empty((n_max, c), np.int64)
    buf_g = np.empty(n_max * c)
    buf_i = np.empty(n_max * c)
    work = np.empty(n_max * c)
    counts = np.empty(_BUCKETS, np.int64)
    p = np.empty((n_max, 3))
    q = np.empty((n_max, 3))
    w = np.empty(n_max)
    min_angle = np.deg2rad(0.01)
    for stage in range(2):
        intensity = stage == 0 and window_candidates
        iters = intensity_iterations if stage == 0 else iterations - intensity_iterations
        for j in range(k):
            if not valid[j]:
                continue
            pose = poses[j]
            a, n = starts[j], starts[j + 1] - starts[j]
            for _ in range(iters):
                _gather_window(pose, p0, i0, a, n, table, fx, fy, cx, cy, width, height, seen, cell, offsets,
                               sentinel, p, cand, dist, r_int)
                if intensity:
                    found = _intensity_matches(n, dist, r_int, cand, table, nu, floor_geom, floor_intensity, buf_g,
                                               buf_i, work, counts, q, w)
                else:
                    found = _nearest_matches(n, dist, cand, table, nu, floor_geom, buf_g, work, counts, q, w)
                if not found:
                    break
                sums, ws = _weighted_sums(n, p, q, w)
                if not ws > 1e-9:
                    break
                delta = _kabsch_step(sums, ws)
                pose = delta @ pose
                moved = np.sqrt(delta[0, 3] ** 2 + delta[1, 3] ** 2 + delta[2, 3] ** 2)
                cos_a = min(max((delta[0, 0] + delta[1, 1] + delta[2, 2] - 1.0) / 2.0, -1.0), 1.0)
                if moved < 1e-4 and np.arccos(cos_a) < min_angle:
                    break
            poses[j] = pose
    return poses


@numba.njit(**_JIT)
def correlation_scores_projective(src, src_i, poses, table, fx, fy, cx, cy, width,
                                  height, seen, cell, offsets, sentinel, cap, nearest_only):
    """R(j) of Eq. 12 for every pose with projective candidates (``clamp``: a point projecting outside the
    image takes the border cell's window): the mean over the points of the smallest distance + |intensity
    difference| among the window's candidates (``nearest_only``: of the nearest one). With ``cap`` > 0 a
    distance counts at most ``cap`` and a point without any candidate costs ``cap``; with 0 such a point is
    left out of its pose's mean."""
    k = len(poses)
    n = len(src)
    out = np.empty(k)
    c = len(offsets)
    for j in range(k):
        pose = poses[j]
        total = 0.0
        used = 0
        for t in range(n):
            px = pose[0, 0] * src[t, 0] + pose[0, 1] * src[t, 1] + pose[0, 2] * src[t, 2] + pose[0, 3]
            py = pose[1, 0] * src[t, 0] + pose[1, 1] * src[t, 1] + pose[1, 2] * src[t, 2] + pose[1, 3]
            pz = pose[2, 0] * src[t, 0] + pose[2, 1] * src[t, 1] + pose[2, 2] * src[t, 2] + pose[2, 3]
            centre = _window_centre(px, py, pz, fx, fy, cx, cy, width, height, seen, cell, sentinel, True)
            best = np.inf
            nearest = np.inf
            for o in range(c):
                g = sentinel if centre == sentinel else centre + offsets[o]
                dx, dy, dz = table[g, 0] - px, table[g, 1] - py, table[g, 2] - pz
                d = np.sqrt((dx * dx + dy * dy) + dz * dz)
                if nearest_only:                  # the window's nearest by distance, then its cost
                    if not d < nearest:
                        continue
                    nearest = d
                    best = np.inf
                if cap > 0 and d > cap and np.isfinite(d):
                    d = cap
                cost = d + abs(src_i[t] - table[g, 3])
                if cost < best:
                    best = cost
            if np.isfinite(best):
                total += best
                used += 1
            elif cap > 0:
                total += cap
                used += 1
        out[j] = total / max(used, 1)
    return out
