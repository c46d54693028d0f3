"""The map's indexed queries give exactly what a scan of every observation gives.

Tracking calls these every frame; they used to scan the whole observation table (dynslam issue 10).
The indexes must not change a single result (ids, counts and their order), or trajectories would
stop being byte-identical, so each query is compared with the old brute-force scan on a seeded
random map that grows keyframe by keyframe and has observations re-pointed by fusion.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from backend.map_index import Covisibility, KeyedRows
from backend.map_store import SlamMap
from conftest import grow_random_map


# --- the scans the indexes replaced (verbatim from the pre-index SlamMap) ---------------------------
def scan_keyframes_observing(m, landmark_ids):
    obs = m.observations
    counts = np.bincount(obs.kf[np.isin(obs.lm, landmark_ids)], minlength=m.num_keyframes)
    kfs = np.flatnonzero(counts)
    order = np.argsort(-counts[kfs], kind="stable")
    return kfs[order], counts[kfs][order]


def scan_landmarks_of_keyframes(m, kf_ids):
    obs = m.observations
    ids = np.unique(obs.lm[np.isin(obs.kf, kf_ids)])
    return ids[~m.landmarks.bad[ids]]


def scan_update_covisibility(m, covisibility, kf_id):
    obs = m.observations
    own = np.unique(obs.lm[obs.kf == kf_id])
    counts = np.bincount(obs.kf[np.isin(obs.lm, own)], minlength=m.num_keyframes)[: m.num_keyframes]
    counts[kf_id] = 0
    covisibility[kf_id, :] = counts
    covisibility[:, kf_id] = counts


def scan_covisible_keyframes(covisibility, kf_id, min_shared, limit):
    row = covisibility[kf_id]
    candidates = np.flatnonzero(row >= min_shared)
    return candidates[np.argsort(-row[candidates], kind="stable")][:limit]


def assert_same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and np.array_equal(a, b), (a, b)


@pytest.mark.parametrize("seed", [0, 1])
def test_indexed_queries_equal_the_full_scans_while_the_map_grows_and_fuses(seed):
    rng = np.random.default_rng(100 + seed)
    reference = np.zeros((0, 0), np.int64)
    fused = 0
    for m, touched in grow_random_map(seed, n_keyframes=60):
        K = m.num_keyframes
        grown = np.zeros((K, K), np.int64)
        grown[: K - 1, : K - 1] = reference
        reference = grown
        for t in touched:
            scan_update_covisibility(m, reference, int(t))
        fused += len(touched) > 1
        assert_same(m.covisibility, reference)
        L = len(m.landmarks)
        # Seeds as tracking passes them: recent landmarks, with repeats, -1 and ids past the end.
        seeds = np.concatenate([rng.integers(max(0, L - 150), L, 40), [-1, L + 3], rng.integers(0, L, 3)])
        for ids in (seeds, seeds[:0], np.array([-1]), rng.integers(0, L, 1)):
            got, want = m.keyframes_observing(ids), scan_keyframes_observing(m, ids)
            assert_same(got[0], want[0])
            assert_same(got[1], want[1])
            assert_same(m.observation_rows(ids), np.flatnonzero(np.isin(m.observations.lm, ids)))
        for kfs in (rng.integers(0, K, 5), np.array([K - 1, K - 1, -1, K + 2]), np.zeros(0, np.int64)):
            assert_same(m.landmarks_of_keyframes(kfs), scan_landmarks_of_keyframes(m, kfs))
        for k in {0, K // 2, K - 1}:
            for min_shared, limit in ((1, 10), (3, K), (0, K)):
                assert_same(m.covisible_keyframes(k, min_shared, limit),
                            scan_covisible_keyframes(reference, k, min_shared, limit))
    assert fused >= 5, "fusion must re-point observations of keyframes other than the newest"


def test_map_filled_in_bulk_answers_like_the_one_built_keyframe_by_keyframe():
    """As map_io.load_map fills a map: records, poses and covisibility set, tables appended at once."""
    *_, (m, _) = grow_random_map(2, n_keyframes=25)
    loaded = SlamMap()
    loaded.keyframes = list(m.keyframes)
    loaded.kf_T_wc = m.kf_T_wc.copy()
    loaded.covisibility = m.covisibility
    loaded.landmarks.append(**{n: getattr(m.landmarks, n) for n in m.landmarks._data})
    loaded.observations.append(**{n: getattr(m.observations, n) for n in m.observations._data})
    assert_same(loaded.covisibility, m.covisibility)
    for k in range(m.num_keyframes):
        assert_same(loaded.covisible_keyframes(k, 2, 50), m.covisible_keyframes(k, 2, 50))
        assert_same(loaded.landmarks_of_keyframes([k]), m.landmarks_of_keyframes([k]))
    ids = np.arange(0, len(m.landmarks), 7)
    assert_same(loaded.keyframes_observing(ids)[0], m.keyframes_observing(ids)[0])
    # A keyframe added after loading extends the poses and the covisibility.
    kf = loaded.add_keyframe(SimpleNamespace(index=99, timestamp=99.0, gray=None), 2 * np.eye(4), np.zeros(0))
    loaded.observations.append(kf=np.array([kf, kf]), lm=ids[:2], kp=np.arange(2))
    loaded.update_covisibility(kf)
    assert loaded.kf_T_wc.shape == (kf + 1, 4, 4) and loaded.kf_T_wc[kf, 0, 0] == 2
    reference = np.pad(m.covisibility.astype(np.int64), ((0, 1), (0, 1)))
    scan_update_covisibility(loaded, reference, kf)
    assert_same(loaded.covisibility, reference)


def test_keyed_rows_keep_every_row_through_block_moves_and_removals():
    rng = np.random.default_rng(7)
    index, keys = KeyedRows(), np.zeros(0, np.int64)
    for batch in range(30):
        new_keys = rng.integers(0, 50, rng.integers(1, 80))
        index.add(new_keys, np.arange(len(keys), len(keys) + len(new_keys)))
        keys = np.concatenate([keys, new_keys])
        if batch % 4 == 3:
            rows = rng.choice(len(keys), 10, replace=False)
            index.remove(keys[rows], rows)
            keys[rows] = 50 + rows % 3                  # re-pointed to other keys
            index.add(keys[rows], rows)
    for key in range(index.num_keys):
        # Per key, rows come back in insertion order except where re-pointing appended them.
        assert_same(np.sort(index.rows_of([key])), np.flatnonzero(keys == key))
    with pytest.raises(ValueError):
        index.add(np.array([-1]), np.array([0]))


def test_covisibility_row_update_clears_the_old_column():
    cov = Covisibility(4)
    cov.set_row(0, np.array([1, 2, 0]), np.array([5, 7, 9]))     # its own entry is ignored
    cov.set_row(0, np.array([2, 3]), np.array([1, 0]))           # 1 drops out, 3 stays zero
    expected = np.zeros((4, 4), np.int32)
    expected[0, 2] = expected[2, 0] = 1
    assert_same(cov.dense(), expected)
    assert_same(Covisibility.from_dense(expected).dense(), expected)
