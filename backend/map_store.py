"""The map's data: keyframes, landmarks and observations as growable struct-of-arrays tables.

Landmarks start "anchored": created from one keyframe's depth, their position is that keyframe's
pose applied to a fixed camera-frame point. Only when a second keyframe observes them do they
become iSAM2 variables. This keeps the graph to landmarks that actually link keyframes, which is
what bounds iSAM2's cost, while single-view landmarks still help tracking.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.core.frame import FeatureFrame, MapPoints


class GrowableTable:
    """Columns that grow by appending rows, with amortised O(1) appends."""

    def __init__(self, columns: dict[str, tuple[tuple[int, ...], np.dtype]]):
        self._size = 0
        self._capacity = 1024
        self._data = {name: np.zeros((self._capacity,) + shape, dtype) for name, (shape, dtype) in columns.items()}

    def __len__(self) -> int:
        return self._size

    def __getattr__(self, name: str) -> np.ndarray:
        data = self.__dict__.get("_data")
        if data is None or name not in data:
            raise AttributeError(name)
        return data[name][: self._size]

    def append(self, **columns: np.ndarray) -> np.ndarray:
        """Append rows (all columns the same length); returns the new row indices."""
        n = len(next(iter(columns.values())))
        while self._size + n > self._capacity:
            self._capacity *= 2
            for name, arr in self._data.items():
                grown = np.zeros((self._capacity,) + arr.shape[1:], arr.dtype)
                grown[: self._size] = arr[: self._size]
                self._data[name] = grown
        for name, values in columns.items():
            self._data[name][self._size: self._size + n] = values
        self._size += n
        return np.arange(self._size - n, self._size)


def landmark_table() -> GrowableTable:
    return GrowableTable({
        "xyz": ((3,), np.float64), "local_xyz": ((3,), np.float64), "descriptors": ((32,), np.uint8),
        "octave": ((), np.int32), "anchor_kf": ((), np.int64), "n_obs": ((), np.int32),
        "visible": ((), np.int32), "found": ((), np.int32), "dynamic_sum": ((), np.float64),
        "dynamic_hits": ((), np.int32),
        "bad": ((), np.bool_), "in_graph": ((), np.bool_),
        "color": ((3,), np.uint8),          # BGR, sampled from the creating keyframe's image
    })


def observation_table() -> GrowableTable:
    return GrowableTable({
        "kf": ((), np.int64), "lm": ((), np.int64), "kp": ((), np.int64), "uv": ((2,), np.float64),
        "depth": ((), np.float64), "level_scale": ((), np.float64), "dynamic_prob": ((), np.float64),
        "in_graph": ((), np.bool_),
        "factor": ((), np.int64),           # back-end factor handle while in the graph, else -1
    })


@dataclass
class KeyframeRecord:
    id: int
    frame_index: int
    timestamp: float
    features: FeatureFrame
    landmark_of_keypoint: np.ndarray


class SlamMap:
    """Keyframes, landmarks, observations and the covisibility weights between keyframes."""

    def __init__(self):
        self.keyframes: list[KeyframeRecord] = []
        self.kf_T_wc = np.zeros((0, 4, 4))
        self.landmarks = landmark_table()
        self.observations = observation_table()
        self.covisibility = np.zeros((0, 0), np.int32)

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframes)

    def add_keyframe(self, frame: FeatureFrame, T_wc: np.ndarray, landmark_of_keypoint: np.ndarray) -> int:
        kf_id = len(self.keyframes)
        frame.gray = None  # keyframes keep features, not images
        self.keyframes.append(KeyframeRecord(kf_id, frame.index, frame.timestamp, frame,
                                             landmark_of_keypoint.copy()))
        self.kf_T_wc = np.concatenate([self.kf_T_wc, T_wc[None]], axis=0)
        k = kf_id + 1
        grown = np.zeros((k, k), np.int32)
        grown[: k - 1, : k - 1] = self.covisibility
        self.covisibility = grown
        return kf_id

    def update_covisibility(self, kf_id: int) -> None:
        """Shared-landmark counts between ``kf_id`` and every other keyframe."""
        obs = self.observations
        own = np.unique(obs.lm[obs.kf == kf_id])
        counts = np.bincount(obs.kf[np.isin(obs.lm, own)], minlength=self.num_keyframes)[: self.num_keyframes]
        counts[kf_id] = 0
        self.covisibility[kf_id, :] = counts
        self.covisibility[:, kf_id] = counts

    def covisible_keyframes(self, kf_id: int, min_shared: int = 1, limit: int = 10) -> np.ndarray:
        """Keyframes sharing at least ``min_shared`` landmarks with ``kf_id``, most shared first."""
        row = self.covisibility[kf_id]
        candidates = np.flatnonzero(row >= min_shared)
        return candidates[np.argsort(-row[candidates], kind="stable")][:limit]

    def keyframes_observing(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(keyframe ids, number of the given landmarks each observes), most first."""
        obs = self.observations
        counts = np.bincount(obs.kf[np.isin(obs.lm, landmark_ids)], minlength=self.num_keyframes)
        kfs = np.flatnonzero(counts)
        order = np.argsort(-counts[kfs], kind="stable")
        return kfs[order], counts[kfs][order]

    def landmarks_of_keyframes(self, kf_ids: np.ndarray) -> np.ndarray:
        obs = self.observations
        ids = np.unique(obs.lm[np.isin(obs.kf, kf_ids)])
        return ids[~self.landmarks.bad[ids]]

    def map_points(self, ids: np.ndarray) -> MapPoints:
        ids = np.asarray(ids, np.int64)
        ids = ids[(ids >= 0) & (ids < len(self.landmarks))]
        ids = ids[~self.landmarks.bad[ids]]
        lm = self.landmarks
        return MapPoints(ids, lm.xyz[ids], lm.descriptors[ids], lm.octave[ids])

    def refresh_anchored(self) -> None:
        """Move landmarks that are not graph variables with their anchor keyframe's estimate."""
        lm = self.landmarks
        idx = np.flatnonzero(~lm.in_graph)
        T = self.kf_T_wc[lm.anchor_kf[idx]]
        lm.xyz[idx] = np.einsum("nij,nj->ni", T[:, :3, :3], lm.local_xyz[idx]) + T[:, :3, 3]
