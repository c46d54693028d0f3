"""Indexes that let the map's per-frame queries cost what they touch, not the size of the map.

Tracking asks every frame which keyframes observe its landmarks and which landmarks its local
keyframes observe; every keyframe asks which keyframes share its landmarks. Scanning all
observations for that makes each frame slower as the map grows (dynslam issue 10). Two structures
answer them instead:

* ``KeyedRows``: the observation rows of each key (a landmark, or a keyframe), in one pool array.
  Each key owns a block whose capacity doubles when it fills (the old block is abandoned), so an
  append costs amortised O(1) per row, a lookup O(rows returned), and the pool stays under about
  four times the rows it holds (each key's abandoned blocks add up to less than its live one).
* ``Covisibility``: the nonzero shared-landmark counts between keyframes, one dict per keyframe,
  instead of a dense K x K matrix that was copied on every keyframe.
"""
from __future__ import annotations

import numpy as np

_MIN_BLOCK = 4          # rows a key's first block holds: most landmarks are seen by a few keyframes


def ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, s + n)`` for each (s, n), without a Python loop."""
    lengths = np.asarray(lengths, np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(np.asarray(starts, np.int64) - offsets, lengths)


def _grow(arr: np.ndarray, size: int, fill=0) -> np.ndarray:
    """``arr`` with room for at least ``size`` entries (capacity doubles; new entries ``fill``)."""
    if size <= len(arr):
        return arr
    grown = np.full(max(size, 2 * len(arr), 16), fill, arr.dtype)
    grown[: len(arr)] = arr
    return grown


class KeyedRows:
    """Integer rows grouped by a non-negative integer key; rows keep their insertion order per key."""

    def __init__(self):
        self._start = np.zeros(0, np.int64)     # per key: block offset in the pool
        self._count = np.zeros(0, np.int64)     # per key: rows held
        self._cap = np.zeros(0, np.int64)       # per key: block capacity (0: no block yet)
        self._pool = np.zeros(0, np.int64)
        self._used = 0                          # pool entries handed out to blocks
        self.num_keys = 0                       # keys 0 .. num_keys - 1 are addressable

    def add(self, keys: np.ndarray, rows: np.ndarray) -> None:
        keys = np.asarray(keys, np.int64)
        rows = np.asarray(rows, np.int64)
        if len(keys) == 0:
            return
        if keys.min() < 0:
            raise ValueError("KeyedRows keys must be non-negative")
        order = np.argsort(keys, kind="stable")
        keys, rows = keys[order], rows[order]
        uk, first, n_new = np.unique(keys, return_index=True, return_counts=True)
        self._reserve_keys(int(uk[-1]) + 1)
        need = self._count[uk] + n_new
        full = need > self._cap[uk]
        if full.any():
            self._move_blocks(uk[full], need[full])
        rank = np.arange(len(keys)) - np.repeat(first, n_new)
        self._pool[self._start[keys] + self._count[keys] + rank] = rows
        self._count[uk] += n_new

    def rows_of(self, keys: np.ndarray) -> np.ndarray:
        """Rows of the given (unique, in-range) keys, key by key."""
        keys = np.asarray(keys, np.int64)
        return self._pool[ranges(self._start[keys], self._count[keys])]

    def remove(self, keys: np.ndarray, rows: np.ndarray) -> None:
        """Remove ``rows[i]`` from key ``keys[i]``'s rows; the others keep their order."""
        affected = np.unique(np.asarray(keys, np.int64))
        if len(affected) == 0:
            return
        held = ranges(self._start[affected], self._count[affected])
        values = self._pool[held]
        keep = ~np.isin(values, rows)
        owner = np.repeat(np.arange(len(affected)), self._count[affected])
        kept = np.bincount(owner[keep], minlength=len(affected)).astype(np.int64)
        self._pool[ranges(self._start[affected], kept)] = values[keep]
        self._count[affected] = kept

    def valid(self, keys: np.ndarray) -> np.ndarray:
        """The unique keys among ``keys`` that hold rows (others, e.g. -1, match nothing)."""
        keys = np.unique(np.asarray(keys).astype(np.int64, copy=False))
        return keys[(keys >= 0) & (keys < self.num_keys)]

    def _reserve_keys(self, n: int) -> None:
        if n > self.num_keys:
            self._start, self._count, self._cap = (_grow(a, n) for a in (self._start, self._count, self._cap))
            self.num_keys = n

    def _move_blocks(self, keys: np.ndarray, need: np.ndarray) -> None:
        """Give ``keys`` new blocks of at least ``need`` rows (next power of two) at the pool's end."""
        cap = np.maximum(_MIN_BLOCK, 1 << np.ceil(np.log2(need)).astype(np.int64))
        start = self._used + np.cumsum(cap) - cap
        self._used += int(cap.sum())
        if self._used > len(self._pool):
            self._pool = _grow(self._pool, self._used)
        count = self._count[keys]
        self._pool[ranges(start, count)] = self._pool[ranges(self._start[keys], count)]
        self._start[keys], self._cap[keys] = start, cap


class Covisibility:
    """Symmetric shared-landmark counts between keyframes; only nonzero entries are stored."""

    def __init__(self, n: int = 0):
        self._rows: list[dict[int, int]] = [{} for _ in range(n)]

    def __len__(self) -> int:
        return len(self._rows)

    def add_keyframe(self) -> None:
        self._rows.append({})

    def set_row(self, kf_id: int, kfs: np.ndarray, counts: np.ndarray) -> None:
        """Row and column ``kf_id`` become ``counts`` at ``kfs`` and zero elsewhere."""
        row = self._rows[kf_id]
        for other in list(row):
            self._rows[other].pop(kf_id, None)
        row.clear()
        for other, n in zip(kfs.tolist(), counts.tolist()):
            if n and other != kf_id:
                row[other] = n
                self._rows[other][kf_id] = n

    def row(self, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(keyframe ids ascending, counts) of the nonzero entries of row ``kf_id``."""
        row = self._rows[kf_id]
        kfs = np.fromiter(row.keys(), np.int64, len(row))
        counts = np.fromiter(row.values(), np.int64, len(row))
        order = np.argsort(kfs)
        return kfs[order], counts[order]

    def dense(self) -> np.ndarray:
        """The (K, K) int32 matrix (for map files and exports; O(K^2))."""
        k = len(self._rows)
        out = np.zeros((k, k), np.int32)
        for i, row in enumerate(self._rows):
            if row:
                out[i, np.fromiter(row.keys(), np.int64, len(row))] = np.fromiter(row.values(), np.int64, len(row))
        return out

    @classmethod
    def from_dense(cls, matrix: np.ndarray) -> "Covisibility":
        """From a (K, K) matrix as map files store it. Ours are symmetric with a zero diagonal (every
        update writes a row and its column alike); ``set_row`` relies on that to clear a column."""
        cov = cls(len(matrix))
        for i, j in zip(*np.nonzero(matrix)):
            cov._rows[int(i)][int(j)] = int(matrix[i, j])
        return cov
