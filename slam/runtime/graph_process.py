"""The back end's solver in its own process, so tracking does not wait for it.

GTSAM's Python bindings hold the GIL while they solve (a Python thread runs at ~2 % of its speed during
an LM solve in another thread), so a thread would not take the solve off the tracking path; a process
does. ``GraphProcess`` is a ``backend.graph_protocol.GraphBackend``: local mapping and loop closing call
it exactly as they call the graph itself. Each call is recorded as a compact command; ``update()`` sends
the batch to the worker and returns at once.

Determinism by construction: the result of update *n* is applied when update *n + 1* is called (the
next keyframe), waiting there only if the worker is not done yet, and at ``sync()``. Which estimates the
tracker sees therefore depends on the frame sequence only, never on how the OS schedules the two
processes: the same input and config give the same trajectory byte for byte. Until a result arrives,
new keyframes and landmarks keep the poses tracking gave them, as they would in ORB-SLAM while its local
bundle adjustment runs.

A loop's update (``relinearize``) may be given longer (``backend.loop_result_keyframes`` k >= 1): its
result is applied at the k-th update after it, and the updates between are folded here into the one sent
then (the worker solves one batch at a time, and a window behind the loop's correction would wait anyway);
``holding_back`` says so, and the loop's residual is unknown until then. Still a fixed point of the frame
sequence, so still deterministic. With 0 (the default) the caller waits for the loop's result at once.

Realtime mode (``realtime=True``, ``runtime.realtime``): nothing ever waits for the worker except
``sync()`` / ``optimize_all()``. ``update()`` hands the batch over only if the worker is free; otherwise
the commands stay here and the update is folded into the next one (one update with every command since,
``relinearize`` if any asked for it), which goes out as soon as the worker is free. So the worker holds
at most one batch, and the commands waiting here are those of the keyframes made while it was busy.
Results are applied whenever they have arrived (``poll()``: at each update, and at each frame by the
System). The window back end adjusts every keyframe added since its last update, so a folded update
loses no keyframe; which results tracking sees now depends on timing, so runs are not deterministic.

Factor handles are counted here the way the graph counts them (one per factor, priors included) and the
worker checks that they agree, so removal by handle needs no round trip. A loop factor the worker has not
solved yet has no residual to report: ``relative_pose_error`` says (0, 0) until its first result comes back.

Failures: an exception in the worker comes back as a ``BackendError`` naming the command that failed; a
worker that dies is reported with its exit code. Starting and stopping (forkserver, Ctrl-C, no orphans):
slam/core/worker_process.py.
"""
from __future__ import annotations

import traceback
from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

from backend.factors import BackendError, BackendParams, StereoCalibration
from backend.graph_protocol import GraphBackend
from backend.local_mapping import build_graph
from slam.core.config import BackendConfig
from slam.core.geometry import relative_pose_residual
from slam.core.timing import thread_cpu_ms
from slam.core.worker_process import start_worker, stop_worker, worker_started

_WORKER_NAME = "dynslam-mapping"


@dataclass(frozen=True)
class GraphSpec:
    """Everything the worker needs to build the graph the main process would have built."""

    config: BackendConfig
    calibration: StereoCalibration

    def build(self) -> GraphBackend:
        return build_graph(self.config, self.calibration)


def _serve(spec: GraphSpec, conn) -> None:
    """The worker: apply command batches in order, answer each with the estimates it produced."""
    worker_started(_WORKER_NAME)
    graph = spec.build()
    while True:
        try:
            batch = conn.recv()
        except (EOFError, OSError):   # the main process is gone or closed the pipe: stop
            return
        if batch is None:
            return
        step = "?"
        cpu_ms: list[float] = []    # the batch's CPU (its factors built, its update solved): cost per keyframe
        try:
            with thread_cpu_ms(cpu_ms):
                for command in batch:
                    step = command[0]
                    expected = _apply(graph, command)
                    if expected is not None and expected[0] != expected[1]:
                        raise BackendError(f"factor handle {expected[0]} where the main process counted {expected[1]}")
            conn.send(("ok", graph.keyframe_poses(), graph.landmark_positions(), cpu_ms[0]))
        except Exception as exc:   # noqa: BLE001 - every failure goes back to the main process, named
            conn.send(("error", step, f"{type(exc).__name__}: {exc}", traceback.format_exc()))


def _apply(graph: GraphBackend, command: tuple):
    """One recorded call; returns (handle the graph gave, handle the main process counted) for factors."""
    kind = command[0]
    if kind == "keyframe":
        graph.add_keyframe(command[1], command[2])
    elif kind == "landmark":
        graph.add_landmark(command[1], command[2])
    elif kind == "observation":
        return graph.add_observation(*command[1:-1]), command[-1]
    elif kind == "relative":
        return graph.add_relative_pose(*command[1:-1]), command[-1]
    elif kind == "remove":
        graph.remove_factors(command[1])
    elif kind == "update":
        graph.update(extra_updates=command[1], relinearize=command[2])
    elif kind == "optimize_all":
        graph.optimize_all(command[1])
    else:
        raise BackendError(f"unknown command {kind!r}")
    return None


class GraphProcess:
    """A GraphBackend whose solving runs in a worker process (see the module docstring)."""

    def __init__(self, spec: GraphSpec, realtime: bool = False):
        self.spec = spec
        self.realtime = realtime
        self._landmark_prior = BackendParams.from_config(spec.config).landmark_prior_sigma > 0
        self._process, self._conn = start_worker(_serve, (spec,), _WORKER_NAME)
        self._batch: list[tuple] = []
        self._in_flight = False
        self._update_in_flight = False            # the batch in flight holds an update (not only optimize_all)
        # Dataset mode: a loop's correction is applied loop_result_keyframes updates after the one that sent it;
        # the updates between are folded here (``update``).
        self._loop_result_keyframes = int(spec.config.loop_result_keyframes)
        self._fold_left = 0                       # updates still to fold before the loop's result is due
        self._loop_in_flight = False              # the batch in flight changed a loop (relinearises)
        self.update_cpu_ms: list[float] = []      # the worker's CPU per update batch (GraphBackend)
        self._keyframes: set[int] = set()
        self._landmarks: set[int] = set()
        self._live: set[int] = set()
        self._relative: dict[int, tuple[int, int, np.ndarray]] = {}
        self._solved_relative: set[int] = set()   # relative factors included in an applied result
        self._sent_relative: set[int] = set()     # ... and those in the batch now being solved
        self._next_handle = 0
        self._kf_ids, self._kf_poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        self._lm_ids, self._lm_xyz = np.zeros(0, np.int64), np.zeros((0, 3))
        self.waits = 0          # updates that found the worker still busy (tracking waited)
        self._holding_back = False              # the last update folded (a loop's correction not due yet)
        self.folded = 0         # realtime: updates folded into a later one (the worker was busy)

    # --- variables ------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, T_wc_guess: np.ndarray) -> None:
        if kf_id in self._keyframes:
            raise BackendError(f"keyframe {kf_id} already exists")
        if not self._keyframes:
            self._next_handle += 1   # the first keyframe's prior
            self._live.add(self._next_handle - 1)
        self._keyframes.add(kf_id)
        self._batch.append(("keyframe", int(kf_id), np.asarray(T_wc_guess, float)))

    def add_landmark(self, lm_id: int, xyz_guess: np.ndarray) -> None:
        if lm_id in self._landmarks:
            raise BackendError(f"landmark {lm_id} already exists")
        if self._landmark_prior:
            self._live.add(self._next_handle)
            self._next_handle += 1
        self._landmarks.add(lm_id)
        self._batch.append(("landmark", int(lm_id), np.asarray(xyz_guess, float)))

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self._keyframes

    def has_landmark(self, lm_id: int) -> bool:
        return lm_id in self._landmarks

    # --- factors --------------------------------------------------------------------------------
    def add_observation(self, kf_id: int, lm_id: int, uv, depth: float = 0.0, level_scale: float = 1.0,
                        dynamic_prob: float = 0.0) -> int:
        self._require(kf_id, lm_id)
        handle = self._new_handle()
        self._batch.append(("observation", int(kf_id), int(lm_id), (float(uv[0]), float(uv[1])), float(depth),
                            float(level_scale), float(dynamic_prob), handle))
        return handle

    def add_relative_pose(self, kf_a: int, kf_b: int, T_ab: np.ndarray, sigma_t: float, sigma_r_deg: float,
                          kernel: Optional[str] = "huber", kernel_k: float = 1.0) -> int:
        self._require(kf_a)
        self._require(kf_b)
        if kernel not in ("huber", "cauchy", None):
            raise BackendError(f"unknown kernel '{kernel}' (use 'huber', 'cauchy' or None)")
        handle = self._new_handle()
        T_ab = np.array(T_ab, dtype=float)
        self._relative[handle] = (int(kf_a), int(kf_b), T_ab)
        self._batch.append(("relative", int(kf_a), int(kf_b), T_ab, float(sigma_t), float(sigma_r_deg), kernel,
                            float(kernel_k), handle))
        return handle

    def relative_pose_error(self, handle: int) -> tuple[float, float]:
        """Against the last applied estimate; (0, 0) while the factor's first solve is still out."""
        if handle not in self._relative:
            raise BackendError(f"factor handle {handle} is not a live relative-pose factor")
        if handle not in self._solved_relative and handle in self._sent_relative and self._in_flight:
            if self.realtime:
                self.poll()       # never wait: if its result is not back yet, it has no residual yet
            elif self._fold_left == 0:
                self._collect()   # its update was sent and its result is due: wait for it
            # else its result is not due yet (a loop's correction): no residual until it is applied
        if handle not in self._solved_relative:
            return 0.0, 0.0
        a, b, T_ab = self._relative[handle]
        return relative_pose_residual(self.keyframe_pose(a), self.keyframe_pose(b), T_ab)

    def remove_factors(self, handles: Iterable[int]) -> None:
        handles = [int(h) for h in handles]
        unknown = [h for h in handles if h not in self._live]
        if unknown:
            raise BackendError(f"unknown factor handle(s) {unknown} (already removed?)")
        for h in handles:
            self._live.discard(h)
            self._relative.pop(h, None)
        self._batch.append(("remove", handles))

    # --- solving --------------------------------------------------------------------------------
    def update(self, extra_updates: Optional[int] = None, relinearize: bool = False) -> None:
        """Apply the previous update's result (waiting only if it is not ready), then send this batch.
        Realtime: apply a result only if it has arrived, send the batch only if the worker is free (else
        fold this update into the next one); never waits."""
        command = ("update", extra_updates, relinearize)
        self._holding_back = not self.realtime and self._fold_left > 0
        if not self.realtime:
            if self._fold_left > 0:
                # A loop's correction is being solved: this keyframe's window waits for it, folded into the
                # update that follows the correction (tracking goes on against the uncorrected map).
                self._fold_left -= 1
                self._batch = _fold_updates(self._batch, command)
                return
            self._collect()
            self._batch = _fold_updates(self._batch, command)
            self._send_waiting()
            if self._loop_in_flight and self._loop_result_keyframes > 0:
                self._fold_left = self._loop_result_keyframes - 1
            return
        self.folded += any(c[0] == "update" for c in self._batch)
        self._batch = _fold_updates(self._batch, command)
        self.poll()

    def poll(self) -> bool:
        """Realtime: apply the result in flight if it has arrived, then hand the worker the waiting
        update if it is free; never waits. Returns whether new estimates were applied. In dataset mode a
        no-op (results are applied at fixed points only, see the module docstring)."""
        if not self.realtime:
            return False
        applied = False
        if self._in_flight and self._conn.poll(0):   # a dead worker's closed pipe also polls ready
            self._collect()
            applied = True
        if not self._in_flight:
            self._send_waiting()
        return applied

    def optimize_all(self, iterations: Optional[int] = None) -> None:
        """Synchronous: the whole-map adjustment, for the end of a run."""
        self._fold_left = 0
        self._collect()
        self._send(("optimize_all", iterations))
        self._collect()

    def sync(self) -> None:
        """Wait for the update in flight and apply it (the end of a run, or a test); realtime: also send
        the update still waiting here and wait for its result; dataset mode: also the updates folded while a
        loop's correction was solved."""
        self._fold_left = 0
        self._collect()
        if self._send_waiting():
            self._collect()

    def close(self) -> None:
        """Stop the worker (after ``sync()`` if its last result is wanted); safe to call twice."""
        if self._process is None:
            return
        stop_worker(self._process, self._conn)
        self._process = None

    def __del__(self):
        if getattr(self, "_process", None) is not None and self._process.is_alive():
            self._process.kill()

    # --- estimates ------------------------------------------------------------------------------
    def keyframe_pose(self, kf_id: int) -> np.ndarray:
        i = np.searchsorted(self._kf_ids, kf_id)
        if i >= len(self._kf_ids) or self._kf_ids[i] != kf_id:
            raise BackendError(f"keyframe {kf_id} has no estimate yet (call update())")
        return self._kf_poses[i].copy()

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]:
        return self._kf_ids.copy(), self._kf_poses.copy()

    def landmark_positions(self) -> tuple[np.ndarray, np.ndarray]:
        return self._lm_ids.copy(), self._lm_xyz.copy()

    @property
    def num_factors(self) -> int:
        return len(self._live)

    @property
    def holding_back(self) -> bool:
        return self._holding_back

    # --- helpers --------------------------------------------------------------------------------
    def _send(self, command: tuple) -> None:
        batch, self._batch = self._batch + [command], []
        self._send_batch(batch)

    def _send_waiting(self) -> bool:
        """Realtime: send the commands up to the waiting (folded) update, if there is one; the commands
        recorded after it wait for the next update. Returns whether a batch was sent."""
        ends = [i for i, command in enumerate(self._batch) if command[0] == "update"]
        if not ends:
            return False
        batch, self._batch = self._batch[:ends[-1] + 1], self._batch[ends[-1] + 1:]
        self._send_batch(batch)
        return True

    def _send_batch(self, batch: list[tuple]) -> None:
        # Relative factors recorded after the batch's update (realtime) are not in it: they wait.
        self._sent_relative = set(self._relative) - {c[-1] for c in self._batch if c[0] == "relative"}
        try:
            self._conn.send(batch)
        except (BrokenPipeError, OSError) as exc:
            raise self._died() from exc
        self._in_flight = True
        self._update_in_flight = any(c[0] == "update" for c in batch)
        self._loop_in_flight = any(c[0] == "update" and c[2] for c in batch)

    def _collect(self) -> None:
        if not self._in_flight:
            return
        if not self._conn.poll(0):
            self.waits += 1
        while not self._conn.poll(1.0):
            if self._process is None or not self._process.is_alive():
                raise self._died()
        try:
            reply = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise self._died() from exc
        self._in_flight = False
        if reply[0] == "error":
            _, step, message, trace = reply
            raise BackendError(f"mapping worker failed in '{step}': {message}\n{trace}")
        _, (self._kf_ids, self._kf_poses), (self._lm_ids, self._lm_xyz), cpu_ms = reply
        if self._update_in_flight:
            self.update_cpu_ms.append(cpu_ms)
        self._loop_in_flight = False
        self._solved_relative = self._sent_relative & set(self._relative)

    def _died(self) -> BackendError:
        code = None if self._process is None else self._process.exitcode
        return BackendError(f"the mapping worker process exited unexpectedly (exit code {code})")

    def _require(self, kf_id: int, lm_id: Optional[int] = None) -> None:
        if kf_id not in self._keyframes:
            raise BackendError(f"unknown keyframe {kf_id}: add_keyframe() it first")
        if lm_id is not None and lm_id not in self._landmarks:
            raise BackendError(f"unknown landmark {lm_id}: add_landmark() it first")

    def _new_handle(self) -> int:
        handle = self._next_handle
        self._next_handle += 1
        self._live.add(handle)
        return handle


def _fold_updates(batch: list[tuple], command: tuple) -> list[tuple]:
    """``batch`` + the update ``command``, with the update still waiting in ``batch`` (if any) folded
    into it: one update covers every command since the last one sent (the window back end adjusts every
    keyframe added since; iSAM2 takes the new factors at once). It relinearises if any of them asked,
    with the most ``extra_updates`` asked for (None: the graph's default)."""
    earlier = [c for c in batch if c[0] == "update"]
    if not earlier:
        return batch + [command]
    updates = earlier + [command]
    extra = [c[1] for c in updates if c[1] is not None]
    folded = ("update", max(extra) if extra else None, any(c[2] for c in updates))
    return [c for c in batch if c[0] != "update"] + [folded]
