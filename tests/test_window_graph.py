"""LocalWindowBackend beyond what it shares with FactorGraphBackend (tests/test_backend_graph.py runs those
tests on both): the window stays bounded on a long run, keyframes outside it stay put, a loop corrects
every keyframe through the pose graph and the landmarks follow, and optimize_all solves the whole map."""
from __future__ import annotations

import numpy as np
import pytest

from backend.factors import BackendParams
from backend.window_graph import LocalWindowBackend, WindowParams
from conftest import RING_CALIBRATION as CAL, observe, ring_poses, run_ring, wall_points
from slam.core.geometry import invert, make_pose, pose_distance, so3_exp, transform_points

def test_window_stays_bounded_and_old_keyframes_stay_put():
    graph = LocalWindowBackend(BackendParams(), CAL, WindowParams(window_keyframes=4, max_fixed_keyframes=3))
    poses, points, owner = run_ring(graph, 24)
    n_window, n_fixed, n_landmarks = graph.last_window
    assert n_window <= 4 and n_fixed <= 3
    # the landmarks of the window's keyframes, not of the map (24 keyframes x 60 points)
    assert n_landmarks <= 4 * 3 * 60
    before = graph.keyframe_pose(2)
    graph.add_keyframe(99, poses[-1])
    graph.add_relative_pose(23, 99, np.eye(4), 0.05, 2.0)
    graph.update()
    np.testing.assert_array_equal(graph.keyframe_pose(2), before)   # far outside the window: untouched
    # noise-free measurements from exact guesses: every estimate stays exact
    ids, est = graph.keyframe_poses()
    assert max(pose_distance(est[i], poses[k])[0] for i, k in enumerate(ids[:-1])) < 1e-6


def test_a_loop_corrects_every_keyframe_and_the_landmarks_follow():
    """Drift of 0.5 deg per step over 30 steps (15 deg, ~0.9 m at the end); an exact loop factor between
    the last and the first keyframe, solved through the pose graph, brings every keyframe back. The
    bundle adjustment that follows it in a run is off here (``loop_iterations=0``): the ring's measurements
    are drifted consistently among themselves, so a maximum-likelihood adjustment would rightly keep most
    of that drift against one loop factor (tests/test_loop_closing.py covers it with real fused landmarks)."""
    n = 30
    graph = LocalWindowBackend(BackendParams(), CAL, WindowParams(window_keyframes=5, loop_iterations=0))
    poses, points, owner = run_ring(graph, n, drift_deg=0.5)
    ids, est = graph.keyframe_poses()
    drift_before = pose_distance(est[-1], poses[-1])[0]
    assert drift_before > 0.3
    lm_ids, xyz = graph.landmark_positions()
    last_points = lm_ids[owner[lm_ids] == n - 1]
    before = np.linalg.norm(xyz[np.searchsorted(lm_ids, last_points)] - points[last_points], axis=1)
    loop = graph.add_relative_pose(0, n - 1, invert(poses[0]) @ poses[n - 1], 0.02, 1.0, kernel=None)
    t_before, r_before = graph.relative_pose_error(loop)
    assert t_before > 0.3
    graph.update(relinearize=True)
    ids, est = graph.keyframe_poses()
    errors = np.array([pose_distance(est[i], poses[k])[0] for i, k in enumerate(ids)])
    # The pose graph spreads the loop's error over the ring: what is left is the shape error of a
    # uniformly bent ring (a few cm), not the drift.
    assert errors.max() < 0.2 * drift_before, (drift_before, errors.max())
    lm_ids, xyz = graph.landmark_positions()
    after = np.linalg.norm(xyz[np.searchsorted(lm_ids, last_points)] - points[last_points], axis=1)
    # They move with their keyframe: what stays is that keyframe's remaining error, times the lever of
    # 2-3 m for its rotation error.
    assert np.median(after) < 0.5 * np.median(before), (np.median(before), np.median(after))
    t, r = graph.relative_pose_error(loop)
    assert t < 0.1 * t_before and r < 0.2 * r_before, (t_before, t, r_before, r)


def test_optimize_all_solves_the_whole_map():
    """Exact measurements, guesses 5 cm / 2 deg off and no update on the way: optimize_all brings every
    keyframe to the truth."""
    n = 12
    poses = ring_poses(n)
    local, owner = wall_points(np.tile(np.eye(4), (n, 1, 1)), np.random.default_rng(3))
    points = np.vstack([transform_points(poses[k], local[owner == k]) for k in range(n)])
    rng = np.random.default_rng(4)

    def build() -> LocalWindowBackend:
        graph = LocalWindowBackend(BackendParams(), CAL, WindowParams(window_keyframes=3, max_fixed_keyframes=2))
        for k in range(n):
            off = make_pose(so3_exp(np.radians(rng.normal(0, 2.0, 3))), rng.normal(0, 0.05, 3))
            graph.add_keyframe(k, poses[k] if k == 0 else poses[k] @ off)
            for j in np.flatnonzero(owner == k):
                graph.add_landmark(int(j), points[j] + rng.normal(0, 0.05, 3))
        for k in range(n):
            observe(graph, k, poses[k], np.flatnonzero((owner >= k - 2) & (owner <= k)), points)
        return graph

    def worst_guess(graph: LocalWindowBackend) -> float:
        return max(pose_distance(graph._poses.values[graph._poses.slot[k]], poses[k])[0] for k in range(n))

    def worst(graph: LocalWindowBackend) -> float:
        ids, est = graph.keyframe_poses()
        return max(pose_distance(est[i], poses[k])[0] for i, k in enumerate(ids))

    whole = build()
    assert worst_guess(whole) > 0.02
    whole.optimize_all(iterations=30)
    assert worst(whole) < 1e-4


def test_update_before_any_keyframe_and_unknown_handles():
    graph = LocalWindowBackend(BackendParams(), CAL)
    graph.update()
    assert len(graph.keyframe_poses()[0]) == 0
    with pytest.raises(Exception, match="unknown factor handle"):
        graph.remove_factors([5])
