"""Compiled kernels of the cpr method's clouds (numba): sampling, voxel filter, MLS, the dense target.

Why compiled: the whole-array numpy formulation spent most of cpr's ~24 ms per Bonn frame in the overhead of
hundreds of array operations, not in arithmetic; issue 10 asks for <= 8 ms. The kernels are plain loops over
points that do the same arithmetic in the same order where it mattered for the masks (per-voxel and per-point
sums in input order, as ``np.bincount`` adds them; the same closed-form eigenvector). They run with the GIL
released (``nogil``), so cpr's thread no longer competes with the tracking thread for the interpreter.
``cache=True``: compiled once per machine into ``__pycache__`` beside this file (or numba's user-wide cache
where that is not writable). No ``fastmath``, no ``parallel``: the same input gives the same bits. The
registration half is ``cpr_icp_kernels``; ``docs/design.md`` ("Compiled loops") has the measurements.
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}
MAX_LOOKUP = 8_000_000          # cells of a dense index table before falling back to sorting the keys
_TWO_PI_3 = 2.0 * np.pi / 3.0


# --- the cloud ---------------------------------------------------------------------------------------------


@numba.njit(**_JIT)
def _cell_keys(x, y, z, voxel, margin):
    """Integer cell of every point, flattened row-major over the occupied box grown by ``margin`` cells per
    side (neighbour offsets never wrap). Returns (flat keys, span per axis)."""
    n = len(x)
    kx = np.empty(n, np.int64)
    ky = np.empty(n, np.int64)
    kz = np.empty(n, np.int64)
    for i in range(n):
        kx[i] = np.int64(np.floor(x[i] / voxel))
        ky[i] = np.int64(np.floor(y[i] / voxel))
        kz[i] = np.int64(np.floor(z[i] / voxel))
    lo = np.array([kx.min() - margin, ky.min() - margin, kz.min() - margin])
    span = np.array([kx.max() - lo[0] + 1 + margin, ky.max() - lo[1] + 1 + margin, kz.max() - lo[2] + 1 + margin])
    flat = np.empty(n, np.int64)
    for i in range(n):
        flat[i] = ((kx[i] - lo[0]) * span[1] + (ky[i] - lo[1])) * span[2] + (kz[i] - lo[2])
    return flat, span


@numba.njit(**_JIT)
def _cell_table(scratch, volume):
    """A cell -> index table of ``volume`` cells, all -1: ``scratch`` when it is large enough (its users put
    back every -1 they overwrite, so it never needs clearing: a 1.5 M-cell box cost ~1 ms a frame to fill),
    else a new one."""
    if volume <= len(scratch):
        return scratch
    return np.full(volume, -1, np.int32)


@numba.njit(**_JIT)
def voxel_filter_cols(x, y, z, intensity, voxel, scratch):
    """Centroid and mean intensity per occupied voxel, voxels numbered in key order (``np.unique``'s), sums in
    input order (``np.bincount``'s). ``scratch``: an int32 table of -1 (``_cell_table``). Returns (cx, cy, cz,
    mean intensity, voxel of every input point, cells the box needed)."""
    n = len(x)
    flat, span = _cell_keys(x, y, z, voxel, 0)
    volume = span[0] * span[1] * span[2]
    inverse = np.empty(n, np.int64)
    if volume <= MAX_LOOKUP:
        table = _cell_table(scratch, volume)
        occupied = np.empty(n, np.int64)
        m = 0
        for i in range(n):                         # the occupied cells, once each
            if table[flat[i]] == -1:
                table[flat[i]] = 0
                occupied[m] = flat[i]
                m += 1
        occupied = np.sort(occupied[:m])           # numbered in key order
        for v in range(m):
            table[occupied[v]] = v
        for i in range(n):
            inverse[i] = table[flat[i]]
        for v in range(m):
            table[occupied[v]] = -1
    else:
        order = np.argsort(flat, kind="mergesort")
        m = 0
        for a in range(n):
            if a > 0 and flat[order[a]] != flat[order[a - 1]]:
                m += 1
            inverse[order[a]] = m
        m += 1
    counts = np.zeros(m)
    cx = np.zeros(m)
    cy = np.zeros(m)
    cz = np.zeros(m)
    ci = np.zeros(m)
    for i in range(n):
        v = inverse[i]
        counts[v] += 1.0
        cx[v] += x[i]
        cy[v] += y[i]
        cz[v] += z[i]
        ci[v] += intensity[i]
    for v in range(m):
        cx[v] /= counts[v]
        cy[v] /= counts[v]
        cz[v] /= counts[v]
        ci[v] /= counts[v]
    return cx, cy, cz, ci, inverse, volume


@numba.njit(**_JIT)
def _smallest_eigvec(a00, a11, a22, a01, a02, a12):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 (trigonometric eigenvalue, then the
    largest cross product of two rows of A - lambda I). Returns (vx, vy, vz, ok)."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = np.sqrt(max(p2, 0.0) / 6.0)
    if not p > 1e-12:
        return 0.0, 0.0, 0.0, False
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = np.arccos(min(max(det / 2.0, -1.0), 1.0)) / 3.0
    lam = q + 2.0 * p * np.cos(phi + _TWO_PI_3)
    r0x, r0y, r0z = a00 - lam, a01, a02
    r1x, r1y, r1z = a01, a11 - lam, a12
    r2x, r2y, r2z = a02, a12, a22 - lam
    best_n, bx, by, bz = -1.0, 0.0, 0.0, 0.0
    for pair in range(3):                       # r0 x r1, r0 x r2, r1 x r2: the first largest wins
        if pair == 0:
            ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r1x, r1y, r1z
        elif pair == 1:
            ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r2x, r2y, r2z
        else:
            ux, uy, uz, vx, vy, vz = r1x, r1y, r1z, r2x, r2y, r2z
        cx = uy * vz - uz * vy
        cy = uz * vx - ux * vz
        cz = ux * vy - uy * vx
        nrm = np.sqrt((cx * cx + cy * cy) + cz * cz)
        if nrm > best_n:
            best_n, bx, by, bz = nrm, cx, cy, cz
    if not best_n > 1e-30:
        return 0.0, 0.0, 0.0, False
    return bx / best_n, by / best_n, bz / best_n, True


@numba.njit(**_JIT)
def smallest_eigvecs(cov):
    """``_smallest_eigvec`` of every symmetric 3x3 in ``cov`` (n,3,3): (vectors (n,3), ok (n,))."""
    n = len(cov)
    vec = np.zeros((n, 3))
    ok = np.zeros(n, np.bool_)
    for i in range(n):
        c = cov[i]
        vec[i, 0], vec[i, 1], vec[i, 2], ok[i] = _smallest_eigvec(c[0, 0], c[1, 1], c[2, 2], c[0, 1], c[0, 2],
                                                                  c[1, 2])
    return vec, ok


@numba.njit(**_JIT)
def mls_cols(x, y, z, radius, voxel, scratch):
    """First-order MLS on a voxelised cloud (see ``cpr_cloud.mls_smooth``): every point projected on the plane
    fitted with Gaussian weights exp(-d^2/r^2), d <= r, to the points of the 3x3x3 cells around its own.
    ``scratch``: an int32 table of -1 (``_cell_table``). Returns (smoothed (n,3), keep (n,), unit normals (n,3),
    0 where no plane, cells the box needed)."""
    n = len(x)
    flat, span = _cell_keys(x, y, z, voxel, 1)
    volume = span[0] * span[1] * span[2]
    offs = np.empty(27, np.int64)
    o = 0
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                offs[o] = (a * span[1] + b) * span[2] + c
                o += 1
    dense = volume <= MAX_LOOKUP
    if dense:
        table = _cell_table(scratch, volume)
        for i in range(n):
            table[flat[i]] = i
        order = np.zeros(1, np.int64)
        sorted_flat = np.zeros(1, np.int64)
    else:
        table = np.zeros(1, np.int32)
        order = np.argsort(flat, kind="mergesort")
        sorted_flat = flat[order]
    r2 = radius * radius
    out = np.empty((n, 3))
    normals = np.zeros((n, 3))
    keep = np.zeros(n, np.bool_)
    for i in range(n):
        xi, yi, zi = x[i], y[i], z[i]
        sw = swx = swy = swz = 0.0
        sxx = syy = szz = sxy = sxz = syz = 0.0
        close = 0
        for o in range(27):
            cell = flat[i] + offs[o]
            if dense:
                j = table[cell]
            else:
                pos = min(np.searchsorted(sorted_flat, cell), n - 1)
                j = order[pos] if sorted_flat[pos] == cell else -1
            if j < 0:
                continue
            dx, dy, dz = x[j] - xi, y[j] - yi, z[j] - zi
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > r2:
                continue
            close += 1
            w = np.exp(-d2 / r2)
            wx, wy, wz = w * dx, w * dy, w * dz
            sw += w
            swx += wx
            swy += wy
            swz += wz
            sxx += wx * dx
            syy += wy * dy
            szz += wz * dz
            sxy += wx * dy
            sxz += wx * dz
            syz += wy * dz
        out[i, 0], out[i, 1], out[i, 2] = xi, yi, zi
        if close < 3:
            continue
        sw = max(sw, 1e-12)
        mx, my, mz = swx / sw, swy / sw, swz / sw
        vx, vy, vz, ok = _smallest_eigvec(sxx / sw - mx * mx, syy / sw - my * my, szz / sw - mz * mz,
                                          sxy / sw - mx * my, sxz / sw - mx * mz, syz / sw - my * mz)
        if not ok:
            continue
        # the plane passes through the weighted centre xi + m; project xi onto it
        offset = (xi - (xi + mx)) * vx + (yi - (yi + my)) * vy + (zi - (zi + mz)) * vz
        out[i, 0], out[i, 1], out[i, 2] = xi - offset * vx, yi - offset * vy, zi - offset * vz
        normals[i, 0], normals[i, 1], normals[i, 2] = vx, vy, vz
        keep[i] = True
    if dense:
        for i in range(n):
            table[flat[i]] = -1
    return out, keep, normals, volume


@numba.njit(**_JIT)
def _depth_samples(depth, gray, pix, rays, min_depth, max_depth):
    """The samples with depth in (min_depth, max_depth]: camera-frame x, y, z, grey / 255 and their pixels."""
    s_all = len(pix)
    x = np.empty(s_all)
    y = np.empty(s_all)
    z = np.empty(s_all)
    inten = np.empty(s_all)
    sample = np.empty(s_all, np.int64)
    n = 0
    for s in range(s_all):
        r, c = pix[s, 0], pix[s, 1]
        d = np.float64(depth[r, c])
        if d > min_depth and d <= max_depth and np.isfinite(d):
            x[n], y[n], z[n] = rays[s, 0] * d, rays[s, 1] * d, d
            inten[n] = np.float64(gray[r, c]) / 255.0
            sample[n] = s
            n += 1
    sample_pix = np.empty((n, 2), pix.dtype)
    for i in range(n):
        sample_pix[i, 0], sample_pix[i, 1] = pix[sample[i], 0], pix[sample[i], 1]
    return x[:n], y[:n], z[:n], inten[:n], sample_pix


@numba.njit(**_JIT)
def _dense_target(x, y, z, inten, inverse, new_index, smooth, normals):
    """Every sample whose voxel is kept, projected on that voxel's MLS plane, and its intensity."""
    count = 0
    for i in range(len(x)):
        if new_index[inverse[i]] >= 0:
            count += 1
    dense = np.empty((count, 3))
    dense_i = np.empty(count)
    a = 0
    for i in range(len(x)):
        v = inverse[i]
        if new_index[v] < 0:
            continue
        nx, ny, nz = normals[v, 0], normals[v, 1], normals[v, 2]
        off = (x[i] - smooth[v, 0]) * nx + (y[i] - smooth[v, 1]) * ny + (z[i] - smooth[v, 2]) * nz
        dense[a, 0], dense[a, 1], dense[a, 2] = x[i] - off * nx, y[i] - off * ny, z[i] - off * nz
        dense_i[a] = inten[i]
        a += 1
    return dense, dense_i


@numba.njit(**_JIT)
def build_cloud_arrays(depth, gray, pix, rays, min_depth, max_depth, voxel, radius, scratch):
    """Section 3.3 in one pass: the depth samples in (min_depth, max_depth], their voxel filter, MLS, and
    the dense registration target (every kept sample projected on its voxel's plane). ``scratch``: an int32
    table of -1 (``_cell_table``).

    Returns (xyz (M,3), intensity (M,), normals (M,3), sample_pix (S,2), sample_point (S,) index into xyz or
    -1, dense_xyz (D,3), dense_intensity (D,), the most cells a box needed)."""
    x, y, z, inten, sample_pix = _depth_samples(depth, gray, pix, rays, min_depth, max_depth)
    n = len(x)
    if n == 0:
        return (np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), sample_pix, np.zeros(0, np.int64),
                np.zeros((0, 3)), np.zeros(0), 0)
    cx, cy, cz, ci, inverse, volume = voxel_filter_cols(x, y, z, inten, voxel, scratch)
    m = len(cx)
    if m < 3:
        return (np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), sample_pix, np.full(n, -1, np.int64),
                np.zeros((0, 3)), np.zeros(0), volume)
    smooth, keep, normals, mls_volume = mls_cols(cx, cy, cz, radius, voxel, scratch)
    new_index = np.full(m, -1, np.int64)
    kept = 0
    for v in range(m):
        if keep[v]:
            new_index[v] = kept
            kept += 1
    xyz = np.empty((kept, 3))
    out_i = np.empty(kept)
    out_n = np.empty((kept, 3))
    for v in range(m):
        t = new_index[v]
        if t >= 0:
            xyz[t] = smooth[v]
            out_i[t] = ci[v]
            out_n[t] = normals[v]
    sample_point = np.empty(n, np.int64)
    for i in range(n):
        sample_point[i] = new_index[inverse[i]]
    dense, dense_i = _dense_target(x, y, z, inten, inverse, new_index, smooth, normals)
    return xyz, out_i, out_n, sample_pix, sample_point, dense, dense_i, max(volume, mls_volume)
