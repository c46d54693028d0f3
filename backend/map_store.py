"""The map's data: keyframes, landmarks and observations as growable struct-of-arrays tables.

Landmarks start "anchored": created from one keyframe's depth, their position is that keyframe's
pose applied to a fixed camera-frame point. Only when a second keyframe observes them do they
become iSAM2 variables. This keeps the graph to landmarks that actually link keyframes, which is
what bounds iSAM2's cost, while single-view landmarks still help tracking.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from backend.map_index import Covisibility, KeyedRows
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
    """Keyframes, landmarks, observations and the covisibility weights between keyframes.

    Observation rows are indexed by landmark and by keyframe (``backend.map_index``) so the
    per-frame queries touch only the rows they return. Rows may be appended to ``observations``
    by anyone (the index catches up on the next query), but an observation's landmark must only be
    changed through ``relink_observations``; its keyframe never changes.
    """

    def __init__(self):
        self.keyframes: list[KeyframeRecord] = []
        self._poses = np.zeros((0, 4, 4))      # capacity-doubling; kf_T_wc is its first K rows
        self._n_poses = 0
        self.landmarks = landmark_table()
        self.observations = observation_table()
        self._covis = Covisibility()
        self._reset_index()

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframes)

    @property
    def kf_T_wc(self) -> np.ndarray:
        """(K, 4, 4) camera-to-world keyframe poses (a view: writes go to the map)."""
        return self._poses[: self._n_poses]

    @kf_T_wc.setter
    def kf_T_wc(self, poses: np.ndarray) -> None:
        self._poses, self._n_poses = poses, len(poses)

    @property
    def covisibility(self) -> np.ndarray:
        """(K, K) int32 shared-landmark counts, built on request (O(K^2): for files and exports)."""
        return self._covis.dense()

    @covisibility.setter
    def covisibility(self, matrix: np.ndarray) -> None:
        self._covis = Covisibility.from_dense(np.asarray(matrix))

    def add_keyframe(self, frame: FeatureFrame, T_wc: np.ndarray, landmark_of_keypoint: np.ndarray) -> int:
        kf_id = len(self.keyframes)
        frame.gray = None  # keyframes keep features, not images
        self.keyframes.append(KeyframeRecord(kf_id, frame.index, frame.timestamp, frame,
                                             landmark_of_keypoint.copy()))
        if self._n_poses == len(self._poses):
            grown = np.zeros((max(16, 2 * self._n_poses), 4, 4), np.result_type(self._poses, T_wc))
            grown[: self._n_poses] = self._poses[: self._n_poses]
            self._poses = grown
        self._poses[self._n_poses] = T_wc
        self._n_poses += 1
        while len(self._covis) < len(self.keyframes):
            self._covis.add_keyframe()
        return kf_id

    # --- observation index -------------------------------------------------------------------------
    def _reset_index(self) -> None:
        self._by_landmark, self._by_keyframe = KeyedRows(), KeyedRows()
        self._indexed_rows, self._indexed_table = 0, self.observations

    def _sync_index(self) -> None:
        """Index the observation rows appended since the last query."""
        obs = self.observations
        if obs is not self._indexed_table or len(obs) < self._indexed_rows:   # table replaced
            self._reset_index()
        if len(obs) > self._indexed_rows:
            rows = np.arange(self._indexed_rows, len(obs))
            self._by_landmark.add(obs.lm[rows], rows)
            self._by_keyframe.add(obs.kf[rows], rows)
            self._indexed_rows = len(obs)

    def observation_rows(self, landmark_ids: np.ndarray) -> np.ndarray:
        """Rows of ``observations`` whose landmark is one of ``landmark_ids``, ascending
        (what ``np.flatnonzero(np.isin(obs.lm, landmark_ids))`` gives, without the scan)."""
        self._sync_index()
        return np.sort(self._by_landmark.rows_of(self._by_landmark.valid(landmark_ids)))

    def relink_observations(self, rows: np.ndarray, landmark_ids: np.ndarray) -> None:
        """Point observation ``rows`` at ``landmark_ids`` (landmark fusion), index included."""
        self._sync_index()
        rows = np.asarray(rows, np.int64)
        landmark_ids = np.asarray(landmark_ids, np.int64)
        obs = self.observations
        self._by_landmark.remove(obs.lm[rows], rows)
        obs.lm[rows] = landmark_ids
        self._by_landmark.add(landmark_ids, rows)

    # --- queries (each costs the rows it touches) ----------------------------------------------------
    def update_covisibility(self, kf_id: int) -> None:
        """Shared-landmark counts between ``kf_id`` and every other keyframe."""
        self._sync_index()
        obs = self.observations
        own = np.unique(obs.lm[self._by_keyframe.rows_of(self._by_keyframe.valid([kf_id]))])
        kfs, counts = np.unique(obs.kf[self._by_landmark.rows_of(own)], return_counts=True)
        inside = kfs < self.num_keyframes
        self._covis.set_row(kf_id, kfs[inside], counts[inside])

    def covisible_keyframes(self, kf_id: int, min_shared: int = 1, limit: int = 10) -> np.ndarray:
        """Keyframes sharing at least ``min_shared`` landmarks with ``kf_id``, most shared first
        (ties: lower keyframe id first)."""
        if min_shared <= 0:   # zero counts qualify too: every keyframe is a candidate
            kfs, counts = np.arange(self.num_keyframes), np.zeros(self.num_keyframes, np.int64)
            nz_kfs, nz_counts = self._covis.row(kf_id)
            counts[nz_kfs] = nz_counts
        else:
            kfs, counts = self._covis.row(kf_id)
            keep = counts >= min_shared
            kfs, counts = kfs[keep], counts[keep]
        return kfs[np.argsort(-counts, kind="stable")][:limit]

    def keyframes_observing(self, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(keyframe ids, number of the given landmarks each observes), most first (ties: lower id first)."""
        self._sync_index()
        rows = self._by_landmark.rows_of(self._by_landmark.valid(landmark_ids))
        kfs, counts = np.unique(self.observations.kf[rows], return_counts=True)
        order = np.argsort(-counts, kind="stable")
        return kfs[order], counts[order]

    def landmarks_of_keyframes(self, kf_ids: np.ndarray) -> np.ndarray:
        """Sorted ids of the landmarks (not culled) that the given keyframes observe."""
        self._sync_index()
        rows = self._by_keyframe.rows_of(self._by_keyframe.valid(kf_ids))
        # A flag per landmark instead of np.unique's sort: the same sorted ids, ~50x faster for the local
        # map's ~20 k observations (tracking asks every frame).
        seen = np.zeros(len(self.landmarks), bool)
        seen[self.observations.lm[rows]] = True
        return np.flatnonzero(seen & ~self.landmarks.bad)

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
