"""Compiled kernels of the cpr method's registration (numba): K-Means, the projective association, the
sub-pose ICP and the correlation scores.

The same arithmetic as the numpy formulation (``cpr_icp``), in loops over points: K-Means draws and sums in
scipy's kmeans2 order (the same labels), the Student-t weights, robust scales and Kabsch step of the ICP.
GIL released, cached on disk, no ``fastmath`` / ``parallel`` (see ``cpr_cloud_kernels``).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}


# --- K-Means ------------------------------------------------------------------------------------------------


@numba.njit(**_JIT)
def _block_sum(a, lo, n):
    """numpy's pairwise-sum leaf (n <= 128): 8 accumulators, combined as a tree, then the rest in order."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(**_JIT)
def _pairwise_sum(a):
    """``a.sum()`` as numpy adds a contiguous float64 array: halves (the first a multiple of 8) until a part
    has <= 128 values, each part by ``_block_sum``, the halves' sums added back up the tree. k-means++ draws
    from cumulative probabilities divided by this sum, so the same draws need the same bits. Iterative (an
    explicit stack): numba's on-disk cache crashed on the recursive version (a segfault when loaded)."""
    span_lo = np.empty(64, np.int64)
    span_n = np.empty(64, np.int64)
    stage = np.empty(64, np.int64)
    values = np.empty(64)
    top, n_values = 0, 0
    span_lo[0], span_n[0], stage[0] = 0, len(a), 0
    while top >= 0:
        lo, n = span_lo[top], span_n[top]
        if n <= 128:
            values[n_values] = _block_sum(a, lo, n)
            n_values += 1
            top -= 1
            continue
        half = n // 2
        half -= half % 8
        if stage[top] == 0:                  # the first half next
            stage[top] = 1
            top += 1
            span_lo[top], span_n[top], stage[top] = lo, half, 0
        elif stage[top] == 1:                # then the second
            stage[top] = 2
            top += 1
            span_lo[top], span_n[top], stage[top] = lo + half, n - half, 0
        else:                                # both done: their sum
            n_values -= 1
            values[n_values - 1] = values[n_values - 1] + values[n_values]
            top -= 1
    return values[0]


@numba.njit(**_JIT)
def _sq_dist(data, t, c0, c1, c2):
    d0, d1, d2 = data[t, 0] - c0, data[t, 1] - c1, data[t, 2] - c2
    return (d0 * d0 + d1 * d1) + d2 * d2


@numba.njit(**_JIT)
def kmeans_labels(data, k, first, uniforms, iterations):
    """``scipy.cluster.vq.kmeans2(data, k, iter=iterations, minit="++")`` labels for (n, 3) ``data`` with the
    random draws given (``first`` = the generator's ``integers(n)``, then ``uniforms`` = its k - 1
    ``uniform()`` draws): k-means++ seeding with a running minimum of the squared distances, then Lloyd
    iterations (nearest code, first on ties; an empty cluster keeps its code), stopping early at a fixed
    point (the same labels twice: nothing can change after). The sums and distances add in scipy's order."""
    n = len(data)
    code = np.empty((k, 3))
    code[0] = data[first]
    d2 = np.empty(n)
    probs = np.empty(n)
    for i in range(1, k):
        c0, c1, c2 = code[i - 1, 0], code[i - 1, 1], code[i - 1, 2]
        for t in range(n):
            new = _sq_dist(data, t, c0, c1, c2)
            d2[t] = new if i == 1 else min(d2[t], new)
        total = _pairwise_sum(d2)
        acc = 0.0
        idx = n - 1
        found = False
        for t in range(n):                     # searchsorted(cumsum(d2 / total), u), side="left"
            acc += d2[t] / total
            probs[t] = acc
            if not found and acc >= uniforms[i - 1]:
                idx, found = t, True
        code[i] = data[idx]
    label = np.full(n, -1, np.int64)
    new_label = np.empty(n, np.int64)
    for _ in range(iterations):
        same = True
        for t in range(n):
            best, best_d = 0, np.inf
            for j in range(k):
                d = _sq_dist(data, t, code[j, 0], code[j, 1], code[j, 2])
                if d < best_d:
                    best, best_d = j, d
            new_label[t] = best
            same &= best == label[t]
        if same:
            break
        label[:] = new_label
        sums = np.zeros((k, 3))
        counts = np.zeros(k, np.int64)
        for t in range(n):
            j = label[t]
            sums[j, 0] += data[t, 0]
            sums[j, 1] += data[t, 1]
            sums[j, 2] += data[t, 2]
            counts[j] += 1
        for j in range(k):
            if counts[j] > 0:
                for e in range(3):
                    code[j, e] = sums[j, e] / counts[j]
    return label


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


@numba.njit(**_JIT)
def _robust_scale(values, floor):
    """1.4826 * median absolute deviation from the median (Eqs. 8-9), at least ``floor``."""
    med = np.median(values)
    return max(1.4826 * np.median(np.abs(values - med)), floor)


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
def _intensity_matches(n, dist, r_int, cand, table, nu, floor_geom, floor_intensity, buf_g, buf_i, q, w):
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
    sg = _robust_scale(buf_g[:count], floor_geom)
    si = _robust_scale(buf_i[:count], floor_intensity)
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
def _nearest_matches(n, dist, cand, table, nu, floor_geom, buf_g, q, w):
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
    sg = _robust_scale(buf_g[:m], floor_geom)
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
                                               buf_i, q, w)
                else:
                    found = _nearest_matches(n, dist, cand, table, nu, floor_geom, buf_g, q, w)
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
