"""Loop closing in the running System: a room walked twice with injected drift.

The camera walks an ellipse (1.0 x 0.8 m) in the generated 6 x 5 m room looking outwards, 150 frames
per lap, two laps. The renderer is exact, so on its own the system hardly drifts; drift is injected
the way it arises in practice: from frame 30 on, every keyframe's *new* landmarks are measured 0.3
degrees rotated about the camera (their creating observation is rewritten, so the graph keeps the
error, as it keeps a biased measurement). Each keyframe inherits the previous error and adds its
own, so the map's heading walks off; with loop closing off, nothing ever pulls it back.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.core.config import KeyframeConfig
from slam.datasets import SyntheticSequence
from slam.run.evaluation import ate
from slam.runtime.system import System

from conftest import (LAPS, PERIOD, drift_room_config as _config, inject_drift as _inject_drift, report_figures,
                      walk_laps)


@pytest.fixture(scope="module")
def renders() -> dict:
    """The lap path's images, rendered by the first walk for the others (``walk_laps``)."""
    return {}


def _walk(loop: bool, renders: dict, revisit_ratio: float = 0.0, loop_result_keyframes: int = 0
          ) -> tuple[System, np.ndarray]:
    """Two laps of the room. By default lap 2 is mapped anew (``keyframes.revisit_ratio`` 0): these tests
    are about what loops do to a map that drifted on both laps. With the default policy the camera
    re-uses lap 1's keyframes once the first loop has joined them, makes few keyframes on lap 2 and so
    finds one loop, not three (drift room: ATE 0.0263 m against 0.0181 m; docs/design.md)."""
    seq = SyntheticSequence(n_frames=2)
    config = _config(loop)
    system = System(config.model_copy(update={
        "keyframes": config.keyframes.model_copy(update={"revisit_ratio": revisit_ratio}),
        "backend": config.backend.model_copy(update={"loop_result_keyframes": loop_result_keyframes})}))
    return system, walk_laps(system, seq, LAPS * PERIOD, renders)


@pytest.fixture(scope="module")
def walks(renders):
    """The walk with loop closing on, settled as ``close()`` leaves a run (every update applied, the final
    adjustment done) but with its worker running, for the tests that read and edit its graph; and the ATE
    of the trajectory a run writes, taken here, before any test edits the graph."""
    with pytest.MonkeyPatch.context() as mp:
        _inject_drift(mp)
        on, gt = _walk(True, renders)
    on.mapper.settle(on.config.backend.final_global_ba)
    return on, gt, _ate(on, gt)


@pytest.fixture(scope="module")
def loops_off(renders):
    """The same walk with loop closing off, closed: (ATE of the trajectory it writes, the system)."""
    with pytest.MonkeyPatch.context() as mp:
        _inject_drift(mp)
        system, gt = _walk(False, renders)
        system.close()
    return _ate(system, gt), system


def _ate(system: System, gt: np.ndarray) -> float:
    stamps, poses, tracked = system.trajectory()
    assert tracked.all()
    return ate(stamps, gt, stamps, poses).rmse


@pytest.mark.slow
def test_loop_found_and_ate_at_least_halved(walks, loops_off):
    on, gt, ate_on = walks
    ate_off, off = loops_off
    detected = [e for e in on.loop_closer.loops if e.source == "detected"]
    assert detected and any(e.active for e in detected)
    assert not off.loop_closer.loops
    # The first closure joins the end of lap 1 to its start; every loop agrees with ground truth.
    frame_of = [kf.frame_index for kf in on.mapper.map.keyframes]
    assert PERIOD - 10 <= frame_of[detected[0].query_kf] <= PERIOD + 30
    for e in detected:
        T_true = np.linalg.solve(gt[frame_of[e.match_kf]], gt[frame_of[e.query_kf]])
        E = np.linalg.solve(T_true, e.T_match_query)
        assert np.linalg.norm(E[:3, 3]) < 0.1
    report_figures("room walked twice with drift injected (test_loop_closing.py)",
                   f"ATE {ate_off:.4f} m with loop closing off, {ate_on:.4f} m on ({len(detected)} loops)")
    assert ate_off > 0.025, "the injected drift should be visible with loop closing off"
    assert ate_on <= 0.5 * ate_off, (ate_on, ate_off)


@pytest.mark.slow
def test_a_loop_corrected_keyframes_later_also_halves_the_ate(renders, loops_off):
    """``backend.loop_result_keyframes`` 4: tracking goes on while the worker corrects the loop (the query
    side moved rigidly at once), the correction lands 4 keyframes later: the same loop is found and the
    drift is still at least halved (measured 0.0226 m against the waiting default's 0.0185)."""
    with pytest.MonkeyPatch.context() as mp:
        _inject_drift(mp)
        system, gt = _walk(True, renders, loop_result_keyframes=4)
        assert system.loop_closer.correct_at_once
        system.close()
    detected = [e for e in system.loop_closer.loops if e.source == "detected"]
    frame_of = [kf.frame_index for kf in system.mapper.map.keyframes]
    assert detected and PERIOD - 10 <= frame_of[detected[0].query_kf] <= PERIOD + 30
    assert _ate(system, gt) <= 0.5 * loops_off[0]


@pytest.mark.slow
def test_second_lap_after_the_loop_adds_few_keyframes(renders):
    """Without drift and with the default keyframe policy: once the loop has joined the laps, the camera
    passes its lap-1 keyframes, and keyframes due by time alone are not made there
    (``keyframes.revisit_ratio``), so the map grows with the space, not with the laps (measured: 30
    keyframes on lap 1, 5 on lap 2, against 30 and 30 with the rule off), and the trajectory is as good."""
    system, gt = _walk(True, renders, revisit_ratio=KeyframeConfig().revisit_ratio)
    system.close()
    frames = np.array([kf.frame_index for kf in system.mapper.map.keyframes])
    lap1, lap2 = int((frames < PERIOD).sum()), int((frames >= PERIOD).sum())
    assert lap1 >= 25 and lap2 <= lap1 // 3, (lap1, lap2)
    assert _ate(system, gt) < 0.005   # the room walked without drift: 3.2 mm with the rule or without


@pytest.mark.slow
def test_fused_landmarks_link_both_sides_of_the_loop(walks):
    on, _, _ = walks
    edge = next(e for e in on.loop_closer.loops if e.source == "detected")
    slam_map = on.mapper.map
    assert edge.fused_landmarks >= 30
    query_lms = slam_map.keyframes[edge.query_kf].landmark_of_keypoint
    # The query keyframe now observes landmarks created on the first pass, through graph factors.
    old = query_lms[(query_lms >= 0)]
    old = old[slam_map.landmarks.anchor_kf[old] <= edge.match_kf + 5]
    assert len(old) >= 30
    obs = slam_map.observations
    rows = np.flatnonzero((obs.kf == edge.query_kf) & np.isin(obs.lm, old))
    assert obs.in_graph[rows].all() and (obs.factor[rows] >= 0).all()
    # Duplicates were retired: no keyframe table points at a bad landmark that was merged away.
    for kf in slam_map.keyframes:
        ids = kf.landmark_of_keypoint[kf.landmark_of_keypoint >= 0]
        merged = slam_map.landmarks.bad[ids] & (slam_map.landmarks.n_obs[ids] == 0)
        assert not merged.any()


@pytest.mark.slow
def test_wrong_loop_is_removed_and_moves_nothing(walks):
    on, gt, _ = walks
    before = on.trajectory()[1].copy()
    n_kf = on.mapper.map.num_keyframes
    # A loop between a keyframe of lap 1 and the last one, 0.5 m and 20 degrees off the truth.
    frame_of = [kf.frame_index for kf in on.mapper.map.keyframes]
    a, b = 5, n_kf - 1
    T_true = np.linalg.solve(gt[frame_of[a]], gt[frame_of[b]])
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    wrong[:3, 3] = [0.5, 0.0, 0.0]
    edge = on.loop_closer.add_constraint(a, b, T_true @ wrong)
    after = on.trajectory()[1]
    assert not edge.active, "the contradicted loop should have been removed"
    assert edge.residual_t > on.config.loop.max_residual_t
    moved = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
    assert moved.max() < 0.01, moved.max()


@pytest.mark.slow
def test_loop_edges_are_exported_with_the_graph(walks, tmp_path):
    from backend.graph_export import export_g2o, graph_edges_from_mapper, loop_edges, mapper_keyframes
    import gtsam

    on, _, _ = walks
    edges = graph_edges_from_mapper(on.mapper) + loop_edges(on.loop_closer.loops, 0.02, 1.0)
    ids, _, poses = mapper_keyframes(on.mapper)
    export_g2o(tmp_path / "g.g2o", ids, poses, edges)
    graph, initial = gtsam.readG2o(str(tmp_path / "g.g2o"), True)
    active = [e for e in on.loop_closer.loops if e.active]
    assert sum(e.kind == "loop" for e in edges) == len(active) > 0
    assert graph.size() == len(edges) and initial.size() == len(ids)
