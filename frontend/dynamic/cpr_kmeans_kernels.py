"""Compiled K-Means of the cpr method (numba): ``scipy.cluster.vq.kmeans2(..., minit="++")`` with its draws given,
the seeding's sums and the Lloyd iterations in scipy's order, so the same labels bit for bit
(``tests/test_cpr_vectorised.py``). Used by ``cpr_icp.cluster``. GIL released, cached on disk, no ``fastmath`` /
``parallel`` (see ``cpr_cloud_kernels``); self-contained, as a cached kernel must be (tests/test_compiled_kernels.py).
"""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}


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
