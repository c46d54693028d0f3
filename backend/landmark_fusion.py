"""Fusing the duplicated landmarks on both sides of a loop (ORB-SLAM's SearchAndFuse, on our tables).

After a drift, the second pass over a place creates new landmarks for points the first pass already
mapped. Loop verification matched the query keyframe's features to the *old* landmarks; for each
such (keypoint, old landmark) pair:

* the keypoint had no landmark: it becomes a new observation of the old landmark;
* the keypoint had a different (new) landmark: the new one is a duplicate. Every observation of it
  moves to the old landmark (its graph factors are removed and re-added against the old variable,
  whose orphaned twin iSAM2 then drops), its statistics are added to the old one's, every keyframe's
  keypoint→landmark table is rewritten, and the duplicate is marked bad.

The old landmarks become graph variables if they were still anchored, so the query keyframe's
observations pull both sides of the loop together through the landmarks, not only through the
loop's pose factor. Everything per observation is numpy; Python loops run over affected keyframes.
"""
from __future__ import annotations

import numpy as np

from backend.local_mapping import LocalMapper


def fuse_loop_landmarks(mapper: LocalMapper, query_kf: int, pairs: np.ndarray) -> int:
    """Fuse (query keypoint, old landmark id) pairs into the map; returns the number of pairs used."""
    slam_map = mapper.map
    lm = slam_map.landmarks
    kf = slam_map.keyframes[query_kf]
    kp, old = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    current = kf.landmark_of_keypoint[kp]
    usable = ~lm.bad[old] & (current != old)
    # A "duplicate" that is itself some pair's old landmark would be merged into itself: skip it.
    usable &= ~np.isin(current, old)
    kp, old, current = kp[usable], old[usable], current[usable]
    fresh = current < 0
    touched = _merge_duplicates(mapper, current[~fresh], old[~fresh])
    _add_query_observations(mapper, query_kf, kp[fresh], old[fresh])
    mapper.promote_landmarks(old)
    rows = slam_map.observation_rows(old)
    mapper.add_factors(rows[~slam_map.observations.in_graph[rows]])
    for k in np.union1d(touched, [query_kf]):
        slam_map.update_covisibility(int(k))
    return int(usable.sum())


def _add_query_observations(mapper: LocalMapper, query_kf: int, kp: np.ndarray, lm_ids: np.ndarray) -> None:
    if len(kp) == 0:
        return
    kf = mapper.map.keyframes[query_kf]
    mapper.record_observations(query_kf, kf.features, kp, lm_ids)
    kf.landmark_of_keypoint[kp] = lm_ids


def _merge_duplicates(mapper: LocalMapper, duplicates: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Move every observation of ``duplicates[i]`` to ``targets[i]``; returns the keyframes touched."""
    if len(duplicates) == 0:
        return np.zeros(0, np.int64)
    slam_map = mapper.map
    lm, obs = slam_map.landmarks, slam_map.observations
    order = np.argsort(duplicates)
    dup_sorted, tgt_sorted = duplicates[order], targets[order]
    rows = slam_map.observation_rows(dup_sorted)
    handles = obs.factor[rows][obs.in_graph[rows] & (obs.factor[rows] >= 0)]
    if len(handles):
        mapper.graph.remove_factors(handles.tolist())
    obs.in_graph[rows] = False
    obs.factor[rows] = -1
    slam_map.relink_observations(rows, tgt_sorted[np.searchsorted(dup_sorted, obs.lm[rows])])
    for column in ("n_obs", "visible", "found", "dynamic_sum", "dynamic_hits"):
        values = getattr(lm, column)
        np.add.at(values, tgt_sorted, values[dup_sorted])
    lm.bad[dup_sorted] = True
    touched = np.unique(obs.kf[rows])
    for k in touched:
        table = slam_map.keyframes[int(k)].landmark_of_keypoint
        hit = np.flatnonzero(np.isin(table, dup_sorted))
        table[hit] = tgt_sorted[np.searchsorted(dup_sorted, table[hit])]
    return touched
