"""The window back end chooses its keyframes, landmarks and factors with whole-array steps
(backend/window_index.py). These tests hold them to the dictionary formulation they replaced, on a graph
with many ties in the counts, observations removed, and landmarks seen by more keyframes than the cap of
recent observers: a different tie rule or cap would change the windows, and with them the trajectories."""
from __future__ import annotations

import numpy as np

from backend.factors import BackendParams
from backend.window_graph import LocalWindowBackend, WindowParams
from backend.window_index import ObservationIndex, ranked_by_count
from conftest import RING_CALIBRATION as CAL


def test_ranked_by_count_is_the_sorted_counts_with_newer_first_on_ties():
    rng = np.random.default_rng(3)
    for _ in range(50):
        ids = rng.integers(0, 12, rng.integers(0, 60))
        counts = {int(k): int(np.count_nonzero(ids == k)) for k in set(ids.tolist())}
        expected = sorted(counts, key=lambda k: (-counts[k], -k))[:5]
        assert ranked_by_count(ids, 5).tolist() == expected


def test_recent_keeps_the_last_cap_observations_then_the_live_ones():
    index = ObservationIndex()
    for kf in range(8):
        index.add_keyframe(kf)
    for lm in range(3):
        index.add_landmark(lm)
    rng = np.random.default_rng(0)
    handle = 5                              # handles count every factor: observations need not start at 0
    for _ in range(40):
        index.add(handle, int(rng.integers(8)), int(rng.integers(3)))
        handle += int(rng.integers(1, 3))
    removed = [h for h in range(handle) if h % 7 == 0]
    index.remove(removed + [10_000])        # a handle past the arrays (another factor type) is ignored
    for cap in (1, 4, 100):
        expected = [h for lm in (2, 0) for h in index.by_lm[lm][-cap:] if h not in removed]
        assert index.recent([2, 0], cap).tolist() == expected
    live = [h for k in (3, 1) for h in index.by_kf[k] if h not in removed]
    assert sorted(index.of_keyframes([3, 1]).tolist()) == sorted(live)
    assert index.of_landmarks([1]).tolist() == [h for h in index.by_lm[1] if h not in removed]


def _dicts(graph: LocalWindowBackend):
    """What the graph held before the arrays: live observation handle -> (kf, lm), and each keyframe's and
    landmark's observation handles in the order they were added."""
    obs = graph._obs
    ends = {h: (int(obs.kf[h]), int(obs.lm[h])) for h in np.flatnonzero(obs.live).tolist()}
    return ends, obs.by_kf, obs.by_lm


def _old_window(graph: LocalWindowBackend, focus: int, new: list[int]) -> set[int]:
    """``LocalWindowBackend._window`` before the arrays (dicts and sets)."""
    cap = 2 * (graph.window.window_keyframes + graph.window.max_fixed_keyframes)
    ends, kf_obs, lm_obs = _dicts(graph)

    def recent(lm):
        return [h for h in lm_obs[lm][-cap:] if h in ends]

    counts: dict[int, int] = {}
    for lm in {ends[h][1] for h in kf_obs[focus] if h in ends}:
        for kf in {ends[h][0] for h in recent(lm)}:
            counts[kf] = counts.get(kf, 0) + 1
    counts.pop(focus, None)
    ranked = sorted(counts, key=lambda k: (-counts[k], -k))[: graph.window.window_keyframes - 1]
    window = {focus, *ranked, *new}
    for h in graph._kf_relative[focus]:
        if h in graph._relative and len(window) < graph.window.window_keyframes:
            a, b, _ = graph._relative[h]
            window.add(a if b == focus else b)
    return window


def _old_problem(graph: LocalWindowBackend, window: set[int]):
    """``LocalWindowBackend._window_problem`` before the arrays."""
    cap = 2 * (graph.window.window_keyframes + graph.window.max_fixed_keyframes)
    ends, kf_obs, lm_obs = _dicts(graph)
    handles = {h for k in window for h in kf_obs[k] if h in ends}
    landmarks = sorted({ends[h][1] for h in handles})
    outside: dict[int, list[int]] = {}
    for lm in landmarks:
        for h in [h for h in lm_obs[lm][-cap:] if h in ends]:
            kf = ends[h][0]
            if kf not in window:
                outside.setdefault(kf, []).append(h)
    handles.update(graph._lm_prior[lm] for lm in landmarks if lm in graph._lm_prior)
    ranked = sorted(outside, key=lambda k: (-len(outside[k]), -k))[: graph.window.max_fixed_keyframes]
    fixed = set(ranked)
    for kf in ranked:
        handles.update(outside[kf])
    for k in window:
        for h in graph._kf_relative[k]:
            if h in graph._relative:
                handles.add(h)
                a, b, _ = graph._relative[h]
                fixed.update(x for x in (a, b) if x not in window)
    first_kf, first_handle = graph._first
    if first_kf in window or first_kf in fixed:
        handles.add(first_handle)
    elif not fixed:
        fixed.add(min(window))
        window = window - fixed
    return window, fixed, landmarks, handles


def test_windows_and_their_factors_are_those_of_the_dictionary_formulation():
    """40 keyframes, each observing 30 of 60 landmarks at random (counts tie often; a landmark is seen by
    up to ~20 keyframes, past the cap of 2 x (4 + 3) recent observers), a tenth of the observations and
    some relative factors removed on the way."""
    rng = np.random.default_rng(7)
    graph = LocalWindowBackend(BackendParams(), CAL, WindowParams(window_keyframes=4, max_fixed_keyframes=3))
    for lm in range(60):
        graph.add_landmark(lm, rng.normal(size=3) + [0.0, 0.0, 3.0])
    observations, relatives = [], []
    for kf in range(40):
        graph.add_keyframe(kf, np.eye(4))
        if kf and kf % 3:
            relatives.append(graph.add_relative_pose(kf - 1, kf, np.eye(4), 0.05, 2.0))
        for lm in rng.choice(60, 30, replace=False):
            observations.append(graph.add_observation(kf, int(lm), (320.0, 240.0), 2.0))
        if kf % 5 == 4:
            gone = rng.choice(observations, len(observations) // 10, replace=False).tolist()
            graph.remove_factors(gone + relatives[-1:])
            observations = [h for h in observations if h not in set(gone)]
            relatives = relatives[:-1]
        for focus in {kf, int(rng.integers(kf + 1))}:
            window = graph._window(focus, [kf])
            assert window == _old_window(graph, focus, [kf])
            assert graph._window_problem(window) == _old_problem(graph, window)
