"""The vocabulary tree's descent compiled (numba): each ORB descriptor's word, as ``Vocabulary.transform`` defines
it (from the root, the child at the least Hamming distance, the first of equal ones, until a leaf or ``levels``
steps). A keyframe's ~1,000 descriptors took ~1.2 ms as four levels of whole-array steps, on the tracking thread
at every keyframe (loop detection) and every lost frame (relocalisation). GIL released, cached on disk; the bit
count is this module's own copy (a cached kernel calls compiled functions of its own module only:
tests/test_compiled_kernels.py)."""
from __future__ import annotations

import numba
import numpy as np

_JIT = {"nogil": True, "cache": True}
_NO_CHILD = 1 << 20          # an empty child slot's distance: more than any two descriptors differ by (256)


@numba.njit(**_JIT)
def _popcount64(x):
    """Set bits of a uint64 (the SWAR count; exact)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@numba.njit(**_JIT)
def descend(words, node_words, children, levels, node_word):
    """Word (int32) of each descriptor (``words``: (N, 4) uint64) in the tree of ``node_words`` ((M, 4) uint64
    centres), ``children`` ((M, k) int32, -1 where a slot is empty, a leaf's first slot -1) and ``node_word``
    ((M,) int32, the leaves' word ids)."""
    n, k = words.shape[0], children.shape[1]
    out = np.empty(n, np.int32)
    for i in range(n):
        cur = 0
        for _ in range(levels):
            if children[cur, 0] < 0:
                break
            best, best_d = 0, np.int64(_NO_CHILD) + 1
            for s in range(k):
                c = children[cur, s]
                d = np.int64(_NO_CHILD)
                if c >= 0:
                    d = np.int64(0)
                    for j in range(words.shape[1]):
                        d += np.int64(_popcount64(words[i, j] ^ node_words[c, j]))
                if d < best_d:
                    best, best_d = s, d
            cur = children[cur, best]
        out[i] = node_word[cur]
    return out
