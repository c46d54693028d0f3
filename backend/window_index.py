"""Arrays behind ``LocalWindowBackend`` (backend/window_graph.py): estimates kept as rows of growing arrays,
and every observation factor's keyframe, landmark and liveness by factor handle, so that choosing a window's
keyframes, landmarks and factors is a few whole-array steps instead of ~10,000 dictionary lookups per update
(Bonn crowd-480: ~1,250 landmarks, ~6,800 observations and ~8,100 factors per window).
"""
from __future__ import annotations

from itertools import chain
from typing import Iterable, Optional, Sequence

import numpy as np


class GrowingRows:
    """ids -> rows of a numpy array that grows by doubling (estimates kept as arrays, not dicts)."""

    def __init__(self, shape: tuple[int, ...]):
        self.slot: dict[int, int] = {}
        self.ids = np.zeros(64, np.int64)
        self.values = np.zeros((64,) + shape)
        self._order: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.slot)

    def add(self, key: int, value: np.ndarray) -> None:
        n = len(self.slot)
        if n == len(self.ids):
            self.ids = np.concatenate([self.ids, np.zeros(n, np.int64)])
            self.values = np.concatenate([self.values, np.zeros_like(self.values)])
        self.slot[key] = n
        self.ids[n] = key
        self.values[n] = value
        self._order = None

    def sorted(self) -> tuple[np.ndarray, np.ndarray]:
        n = len(self.slot)
        if self._order is None:
            self._order = np.argsort(self.ids[:n], kind="stable")
        return self.ids[:n][self._order].copy(), self.values[:n][self._order].copy()


def ranked_by_count(ids: np.ndarray, top: int) -> np.ndarray:
    """The ``top`` distinct values of ``ids`` that occur most often, the newer (larger) first on a tie: the
    order of ``sorted(counts, key=lambda k: (-counts[k], -k))[:top]``."""
    values, counts = np.unique(ids, return_counts=True)
    return values[np.lexsort((-values, -counts))][:top]


class ObservationIndex:
    """Per factor handle (handles count every factor of the graph): the keyframe and landmark of an
    observation factor (-1 for any other factor) and whether it is still in the graph; and per keyframe and
    per landmark their observation handles in the order they were added (removed ones included: filter by
    ``live``)."""

    def __init__(self):
        self.kf = np.full(1024, -1, np.int64)
        self.lm = np.full(1024, -1, np.int64)
        self.live = np.zeros(1024, bool)
        self.by_kf: dict[int, list[int]] = {}
        self.by_lm: dict[int, list[int]] = {}

    def add_keyframe(self, kf_id: int) -> None:
        self.by_kf[kf_id] = []

    def add_landmark(self, lm_id: int) -> None:
        self.by_lm[lm_id] = []

    def add(self, handle: int, kf_id: int, lm_id: int) -> None:
        """A new observation factor (its keyframe and landmark added before)."""
        if handle >= len(self.kf):
            grow = max(handle + 1, 2 * len(self.kf)) - len(self.kf)
            self.kf = np.concatenate([self.kf, np.full(grow, -1, np.int64)])
            self.lm = np.concatenate([self.lm, np.full(grow, -1, np.int64)])
            self.live = np.concatenate([self.live, np.zeros(grow, bool)])
        self.kf[handle], self.lm[handle], self.live[handle] = kf_id, lm_id, True
        self.by_kf[kf_id].append(handle)
        self.by_lm[lm_id].append(handle)

    def remove(self, handles: Iterable[int]) -> None:
        """Mark factors gone (any handle: only observations were ever live here)."""
        handles = np.fromiter(handles, np.int64)
        self.live[handles[handles < len(self.live)]] = False

    def of_keyframes(self, kf_ids: Iterable[int]) -> np.ndarray:
        """The live observation handles of these keyframes."""
        handles = np.fromiter(chain.from_iterable(self.by_kf[k] for k in kf_ids), np.int64)
        return handles[self.live[handles]]

    def of_landmarks(self, lm_ids: Iterable[int]) -> np.ndarray:
        """The live observation handles of these landmarks."""
        handles = np.fromiter(chain.from_iterable(self.by_lm[lm] for lm in lm_ids), np.int64)
        return handles[self.live[handles]]

    def recent(self, lm_ids: Sequence[int], cap: int) -> np.ndarray:
        """Of each landmark's last ``cap`` observations (removed ones included, as they were added), the live
        ones, landmark by landmark: a place seen on every lap of a long run gathers observations without end,
        and a window needs only the freshest to hold it."""
        handles = np.fromiter(chain.from_iterable(self.by_lm[lm][-cap:] for lm in lm_ids), np.int64)
        return handles[self.live[handles]]
