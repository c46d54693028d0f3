"""GraphProcess: the graph solved in a worker process, with results applied at fixed points.

Same calls, same numbers as the graph in process (once synced); results lag by exactly one update;
a failure in the worker or a dead worker is a clear BackendError; close() leaves no process behind.
Realtime mode: nothing waits, updates made while the worker is busy are folded into one, and after
sync() every keyframe and landmark is estimated as in dataset mode."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from backend.factors import BackendError
from backend.local_mapping import build_graph
from conftest import REPO, RING_CALIBRATION, run_ring
from slam.core.config import BackendConfig
from slam.runtime.graph_process import GraphProcess, GraphSpec, _fold_updates


def _spec(**fields) -> GraphSpec:
    return GraphSpec(BackendConfig(**fields), RING_CALIBRATION)


@pytest.fixture
def process_graph():
    graph = GraphProcess(_spec(window_keyframes=4))
    yield graph
    graph.close()


def test_same_estimates_as_in_process_once_synced(process_graph):
    inline = build_graph(BackendConfig(window_keyframes=4), RING_CALIBRATION)
    run_ring(inline, 10, drift_deg=0.3)
    run_ring(process_graph, 10, drift_deg=0.3)
    process_graph.sync()
    for a, b in zip(inline.keyframe_poses() + inline.landmark_positions(),
                    process_graph.keyframe_poses() + process_graph.landmark_positions()):
        np.testing.assert_array_equal(a, b)   # the same solver on the same calls: bit for bit
    assert process_graph.num_factors == inline.num_factors


@pytest.mark.parametrize("optimizer", ["window", "isam2"])
def test_every_back_end_reports_its_cpu_per_update_wherever_it_solves(process_graph, optimizer):
    """update_cpu_ms: one entry per keyframe update, in line and from the worker (its own CPU, measured
    there), none for the end-of-run adjustment; the benchmark reports it per keyframe."""
    inline = build_graph(BackendConfig(window_keyframes=4, optimizer=optimizer), RING_CALIBRATION)
    run_ring(inline, 8)
    inline.optimize_all()
    run_ring(process_graph, 8)
    process_graph.sync()
    process_graph.optimize_all()
    for graph in (inline, process_graph):
        assert len(graph.update_cpu_ms) == 8
        assert all(ms > 0 for ms in graph.update_cpu_ms)


def test_results_arrive_one_update_later(process_graph):
    """Update n's result is applied when update n + 1 is called: which estimates tracking sees depends
    on the call sequence only, not on how fast the worker is."""
    process_graph.add_keyframe(0, np.eye(4))
    process_graph.update()
    assert len(process_graph.keyframe_poses()[0]) == 0          # sent, not applied
    T1 = np.eye(4)
    T1[0, 3] = 0.1
    process_graph.add_keyframe(1, T1)
    process_graph.add_relative_pose(0, 1, T1, 0.05, 2.0)
    process_graph.update()
    assert list(process_graph.keyframe_poses()[0]) == [0]       # the first update's result
    process_graph.sync()
    ids, poses = process_graph.keyframe_poses()
    assert list(ids) == [0, 1]
    np.testing.assert_allclose(poses[1], T1, atol=1e-9)


def _solved_pair_with_wrong_loop(graph) -> int:
    """Two keyframes tied by odometry and solved, then a loop 1 m off between them (not solved yet)."""
    graph.add_keyframe(0, np.eye(4))
    graph.add_keyframe(1, np.eye(4))
    graph.add_relative_pose(0, 1, np.eye(4), 0.05, 2.0)
    graph.update()
    graph.sync()
    T_wrong = np.eye(4)
    T_wrong[0, 3] = 1.0
    return graph.add_relative_pose(0, 1, T_wrong, 0.02, 1.0, kernel="cauchy")


def test_unsolved_loop_reports_no_residual_until_its_result_arrives(process_graph):
    loop = _solved_pair_with_wrong_loop(process_graph)
    assert process_graph.relative_pose_error(loop) == (0.0, 0.0)
    process_graph.update(relinearize=True)
    process_graph.sync()
    assert process_graph.relative_pose_error(loop)[0] > 0.5     # the graph keeps disagreeing with it


def test_handles_agree_and_removal_needs_no_round_trip(process_graph):
    inline = build_graph(BackendConfig(window_keyframes=4), RING_CALIBRATION)
    for graph in (inline, process_graph):
        graph.add_keyframe(0, np.eye(4))
        graph.add_keyframe(1, np.eye(4))
        graph.add_landmark(7, np.array([0.0, 0.0, 2.0]))
        handles = [graph.add_observation(0, 7, (319.5, 239.5), 2.0), graph.add_relative_pose(0, 1, np.eye(4), 0.05, 2)]
        graph.remove_factors(handles[1:])
        graph.add_relative_pose(0, 1, np.eye(4), 0.05, 2.0)
        graph.update()
    process_graph.sync()   # the worker checks every handle against the one counted here
    assert handles == [2, 3]
    with pytest.raises(BackendError, match="unknown factor handle"):
        process_graph.remove_factors([3])


def test_a_loops_result_is_applied_at_a_fixed_later_update_and_the_updates_between_fold():
    """``backend.loop_result_keyframes`` 3: after the update that changes a loop (relinearize), the next two
    neither wait nor take anything up (``holding_back``; the loop's residual is not known yet); the third
    applies the loop's result and sends one update for the keyframes of all three, so nothing is lost."""
    graph = GraphProcess(_spec(window_keyframes=4, loop_result_keyframes=3))
    try:
        loop = _solved_pair_with_wrong_loop(graph)
        graph.update(relinearize=True)                 # the loop's update goes out
        assert not graph.holding_back
        before, waits = graph.keyframe_poses(), graph.waits
        for kf in (2, 3):                              # two keyframes while it is solved: folded, nothing waits
            graph.add_keyframe(kf, np.eye(4))
            graph.add_relative_pose(kf - 1, kf, np.eye(4), 0.05, 2.0)
            graph.update()
            assert graph.holding_back and graph.waits == waits
            np.testing.assert_array_equal(graph.keyframe_poses()[1], before[1])
            if kf == 2:     # at the due keyframe (the next) a loop check may wait for the result
                assert graph.relative_pose_error(loop) == (0.0, 0.0)
        graph.add_keyframe(4, np.eye(4))
        graph.add_relative_pose(3, 4, np.eye(4), 0.05, 2.0)
        graph.update()                                 # due: the loop's result is applied here
        assert not graph.holding_back
        assert list(graph.keyframe_poses()[0]) == [0, 1]
        assert graph.relative_pose_error(loop)[0] > 0.5
        graph.sync()                                   # the folded update covered keyframes 2-4
        assert list(graph.keyframe_poses()[0]) == [0, 1, 2, 3, 4]
        assert len(graph.update_cpu_ms) == 3           # first, the loop's, the folded one
    finally:
        graph.close()


def test_by_default_the_update_after_a_loops_waits_for_its_result(process_graph):
    loop = _solved_pair_with_wrong_loop(process_graph)
    process_graph.update(relinearize=True)
    process_graph.add_keyframe(2, np.eye(4))
    process_graph.add_relative_pose(1, 2, np.eye(4), 0.05, 2.0)
    process_graph.update()
    assert not process_graph.holding_back and process_graph.relative_pose_error(loop)[0] > 0.5


def test_a_failure_in_the_worker_names_the_step():
    """A pose of NaNs (a bug upstream) fails in the worker: the error names the command and the cause."""
    graph = GraphProcess(_spec())
    try:
        graph.add_keyframe(0, np.full((4, 4), np.nan))
        graph.update()
        with pytest.raises(BackendError, match=r"mapping worker failed in 'keyframe': LinAlgError"):
            graph.sync()
    finally:
        graph.close()


def test_a_dead_worker_is_reported_with_its_exit_code():
    graph = GraphProcess(_spec())
    try:
        graph.add_keyframe(0, np.eye(4))
        graph.update()
        graph.sync()
        os.kill(graph._process.pid, signal.SIGKILL)
        graph._process.join(timeout=10)
        with pytest.raises(BackendError, match=r"exited unexpectedly \(exit code -9\)"):
            graph.update()
            graph.sync()
    finally:
        graph.close()


def test_close_leaves_no_worker_and_estimates_stay_readable():
    graph = GraphProcess(_spec())
    graph.add_keyframe(0, np.eye(4))
    graph.update()
    graph.sync()
    pid = graph._process.pid
    graph.close()
    graph.close()   # twice is fine
    assert pid not in [p.pid for p in mp.active_children()]
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    assert list(graph.keyframe_poses()[0]) == [0]


def test_worker_ignores_ctrl_c():
    """Ctrl-C at a terminal reaches the whole process group; the main process handles it (and still
    needs the worker to finish the run), so the worker must not die of it."""
    graph = GraphProcess(_spec())
    try:
        graph.add_keyframe(0, np.eye(4))
        graph.update()
        graph.sync()
        os.kill(graph._process.pid, signal.SIGINT)
        graph.add_keyframe(1, np.eye(4))
        graph.add_relative_pose(0, 1, np.eye(4), 0.05, 2.0)
        graph.update()
        graph.sync()
        assert list(graph.keyframe_poses()[0]) == [0, 1]
    finally:
        graph.close()


# --- realtime mode ---------------------------------------------------------------------------------

@pytest.fixture
def realtime_graph():
    graph = GraphProcess(_spec(window_keyframes=4), realtime=True)
    yield graph
    graph.close()


class _BusyWorker:
    """The worker's pipe as seen while the worker is still solving: no result is ready to read unless
    the caller is prepared to wait (sync). Counts the batches sent."""

    def __init__(self, conn):
        self.conn, self.sent = conn, 0

    def poll(self, timeout: float = 0.0) -> bool:
        return self.conn.poll(timeout) if timeout > 0 else False

    def send(self, batch) -> None:
        self.sent += 1
        self.conn.send(batch)

    def __getattr__(self, name):
        return getattr(self.conn, name)


def test_realtime_update_returns_at_once_and_the_result_arrives_by_polling(realtime_graph):
    realtime_graph.add_keyframe(0, np.eye(4))
    realtime_graph.update()
    assert len(realtime_graph.keyframe_poses()[0]) == 0          # sent, not waited for
    deadline = time.monotonic() + 60
    while not realtime_graph.poll():                             # no update() or sync() needed
        assert time.monotonic() < deadline, "the worker's result never arrived"
        time.sleep(0.002)
    assert list(realtime_graph.keyframe_poses()[0]) == [0]
    assert realtime_graph.waits == 0


def test_realtime_folds_updates_while_the_worker_is_busy_and_sync_loses_nothing(realtime_graph):
    """While the worker is busy every update is folded into the one waiting here (the worker never holds
    more than one batch, nothing queues up); sync() sends it and waits: every keyframe and landmark is
    then estimated, every handle agrees with the worker's, and the estimates are those of dataset mode."""
    dataset = GraphProcess(_spec(window_keyframes=4))
    try:
        run_ring(dataset, 12, drift_deg=0.3)
        dataset.sync()
        busy = _BusyWorker(realtime_graph._conn)
        realtime_graph._conn = busy
        waiting_updates = []
        update = realtime_graph.update

        def update_and_count(*args, **kwargs):
            update(*args, **kwargs)
            waiting_updates.append(sum(c[0] == "update" for c in realtime_graph._batch))

        realtime_graph.update = update_and_count
        start = time.perf_counter()
        run_ring(realtime_graph, 12, drift_deg=0.3)
        assert time.perf_counter() - start < 5.0                 # nothing waited for the worker
        assert busy.sent == 1 and realtime_graph.folded == 10    # the first update went; the other 11 wait as one
        assert max(waiting_updates) == 1
        assert realtime_graph.waits == 0
        realtime_graph.sync()                                    # waits: for the first result, then the folded one
        assert busy.sent == 2 and not realtime_graph._batch
        np.testing.assert_array_equal(realtime_graph.keyframe_poses()[0], np.arange(12))
        np.testing.assert_array_equal(realtime_graph.landmark_positions()[0], dataset.landmark_positions()[0])
        # The ring's measurements agree with each other, so one adjustment of all keyframes (folded) and
        # twelve windows (dataset mode) reach the same estimates up to the solver's tolerance.
        np.testing.assert_allclose(realtime_graph.keyframe_poses()[1], dataset.keyframe_poses()[1], atol=1e-6)
        np.testing.assert_allclose(realtime_graph.landmark_positions()[1], dataset.landmark_positions()[1], atol=1e-6)
        assert realtime_graph.num_factors == dataset.num_factors
    finally:
        dataset.close()


def test_folded_update_relinearises_if_any_asked_and_keeps_the_command_order():
    batch = [("keyframe", 1, None), ("update", None, False), ("relative", 0, 1, None, 0.1, 1.0, None, 1.0, 5),
             ("remove", [5])]
    folded = _fold_updates(batch, ("update", 2, True))
    assert [c[0] for c in folded] == ["keyframe", "relative", "remove", "update"]
    assert folded[-1] == ("update", 2, True)
    assert _fold_updates(folded[:-1] + [("update", None, True)], ("update", None, False))[-1] == ("update", None, True)
    assert _fold_updates([("keyframe", 1, None)], ("update", None, False))[-1] == ("update", None, False)


def test_realtime_loop_residual_does_not_wait(realtime_graph):
    """A loop's residual is asked for right after its update: realtime answers (0, 0) rather than wait."""
    loop = _solved_pair_with_wrong_loop(realtime_graph)
    realtime_graph._conn = _BusyWorker(realtime_graph._conn)
    waits = realtime_graph.waits   # the sync() above may have waited
    realtime_graph.update(relinearize=True)
    assert realtime_graph.relative_pose_error(loop) == (0.0, 0.0)
    assert realtime_graph.waits == waits
    realtime_graph.sync()
    assert realtime_graph.relative_pose_error(loop)[0] > 0.5


@pytest.mark.slow
def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """multiprocessing would re-run the user's script in the worker; a script that just builds a System
    at top level (no ``if __name__ == "__main__"``) must run once and track."""
    script = tmp_path / "my_slam.py"
    script.write_text(
        "from slam.datasets import SyntheticSequence\n"
        "from slam.run.dynamic_eval import synthetic_config\n"
        "from slam.runtime.system import System\n"
        "print('script body runs', flush=True)\n"
        "seq = SyntheticSequence(n_frames=12)\n"
        "system = System(synthetic_config(seq, preset='static'))\n"
        "for f in seq:\n"
        "    system.process(f.rgb, f.depth, f.timestamp)\n"
        "system.close()\n"
        "print('keyframes', system.num_keyframes)\n")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=180,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("script body runs") == 1, proc.stdout
    assert "keyframes" in proc.stdout and "keyframes 0" not in proc.stdout
