"""Local bundle adjustment over a window of covisible keyframes: a back end whose cost per keyframe
stays flat as the map grows (ORB-SLAM's LocalBundleAdjustment + essential-graph loop correction, on GTSAM).

``LocalWindowBackend`` takes the same calls as ``FactorGraphBackend`` (``backend.graph_protocol.GraphBackend``)
and builds the same factors (``backend.factors``), but never solves the whole map:

* ``update()``: Levenberg-Marquardt on the newest keyframe, its ``window_keyframes - 1`` most covisible
  keyframes and every graph landmark they observe. Keyframes outside the window that observe those
  landmarks (or share a relative-pose factor with the window) enter as fixed poses (tight priors):
  they hold the window in place the way ORB-SLAM's fixed keyframes do. The cost depends on the window,
  not on the map: measured with tools/memory.py (README, "Tests", "Long runs and memory").
* ``update(relinearize=True)`` (after a loop is added or removed): first a pose graph over the loop's
  span (the keyframes from the oldest one a changed relative factor touches on) — the graph's own
  relative-pose factors plus an essential graph built from the current estimate (each keyframe to the
  previous one, and pairs sharing ``essential_min_shared`` landmarks); landmarks move rigidly with their
  reference keyframe (the first that observed it). Then a bundle adjustment of the span (its two ends
  where it is longer than ``loop_max_keyframes``) with every observation: the landmarks the loop fused
  carry a right loop, and the rest of the map resists a wrong one, so the loop check sees a wrong loop's
  residual as the iSAM2 graph would. Removing a loop takes back exactly the correction its update applied
  (a pose graph built on the bent estimate could not undo it). Then the local window is adjusted.
* ``optimize_all()``: one batch bundle adjustment of everything (for the end of a run, where nobody waits).

Why not iSAM2 over everything: on a generated 1,500-frame orbit with 24 loops the iSAM2 back end grew
from 74 ms to 2 s per keyframe and 4 GB of memory (loops make the Bayes tree's top clique dense).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import gtsam
import numpy as np

from slam.core.config import BackendConfig
from slam.core.geometry import relative_pose_residual
from slam.core.timing import thread_cpu_ms
from backend.factors import BackendError, BackendParams, FactorBuilder, StereoCalibration
from backend.window_index import GrowingRows, ObservationIndex
from backend.window_adjust import WindowAdjustment
from backend.window_loops import LoopCorrection
from backend.window_solver import ObservationArrays


@dataclass(frozen=True)
class WindowParams:
    """The window's size and effort; defaults mirror ``backend`` in the run config (BackendConfig)."""

    window_keyframes: int = 6
    iterations: int = 10
    relative_tol: float = 1e-2    # a window or loop adjustment stops when an iteration improves its cost by less
    pose_graph_iterations: int = 30
    loop_iterations: int = 5      # the bundle adjustment over a loop's span after its pose graph (0: none)
    # A loop's bundle adjustment: 60 keyframes cover the loops of the TUM/Bonn sequences whole (~2 s, the
    # one wait of a loop keyframe); with 24 the drift room of tests/test_loop_closing.py kept a wrong
    # loop (0.24 m ATE before the final adjustment).
    loop_max_keyframes: int = 60
    # The pose graph of a loop reaches back at most this many keyframes (the loops of the TUM/Bonn
    # sequences span <= 100 and are corrected whole). Unbounded, a loop to a place seen laps ago cost
    # O(map): on the generated orbit the loop keyframes' wait grew from 0.5 s to 2.8 s over 2,500 frames.
    loop_max_span: int = 150
    max_undoable_loops: int = 16   # newest loops whose correction removal can take back exactly
    final_iterations: int = 20   # optimize_all: from windows that each stopped early, to convergence
    # optimize_all stops when an iteration improves the whole map's cost by less than this. At 1e-5 fr1/rpy-400's
    # adjustment ran all 20 iterations (3.0 s; the last 14 lowered its cost by 0.23 % in all), at 1e-3 it
    # stopped after 6 (1.0 s): no camera of the final trajectory moved by more than 0.13 mm (Bonn-480:
    # 0.24 mm, 1.2 -> 1.0 s), ATE 0.02174 / 0.01040 m either way. 1e-2 moved Bonn's cameras by up to 2.1 mm.
    final_relative_tol: float = 1e-3
    final_max_keyframes: int = 300
    essential_min_shared: int = 100
    essential_sigma_t: float = 0.02
    essential_sigma_r_deg: float = 1.0
    max_fixed_keyframes: int = 10
    fixed_sigma: float = 1e-6   # rad / m: a fixed keyframe's prior; far below any measurement's noise
    solver: str = "schur"       # backend/window_solver.py, or "gtsam" (BackendConfig.window_solver)

    @classmethod
    def from_config(cls, cfg: BackendConfig) -> "WindowParams":
        return cls(window_keyframes=cfg.window_keyframes, iterations=cfg.window_iterations,
                   relative_tol=cfg.window_relative_tol,
                   final_max_keyframes=cfg.final_global_ba_max_keyframes,
                   essential_min_shared=cfg.essential_min_shared, max_fixed_keyframes=cfg.window_fixed_keyframes,
                   solver=cfg.window_solver)


class LocalWindowBackend(LoopCorrection, WindowAdjustment):
    def __init__(self, params: BackendParams, calibration: StereoCalibration,
                 window: Optional[WindowParams] = None):
        self.params = params
        self.calibration = calibration
        self.window = window or WindowParams()
        self._factors = FactorBuilder(params, calibration)
        self._poses = GrowingRows((4, 4))
        self._points = GrowingRows((3,))
        self._live: dict[int, Optional[gtsam.NonlinearFactor]] = {}   # handle -> factor (None: arrays only)
        self._obs = ObservationIndex()                          # observation handles -> keyframe, landmark
        self._obs_arrays = ObservationArrays()                  # ... and their measurements (window_solver)
        self._prior_xyz = GrowingRows((3,))                     # per landmark slot: its prior's mean
        self._point_ref = GrowingRows(())   # per landmark slot: pose slot of its first observer, -1 none
        self._span_start: Optional[int] = None  # oldest keyframe a relative factor added/removed touches
        self._added_relative: list[int] = []     # relative factors added / removed since the last update
        self._removed_relative: list[int] = []
        # loop handle -> (pose slots, world-frame correction per slot) its update applied: removing a loop
        # that was wrong undoes exactly what it did (a pose graph on the bent estimate could not)
        self._corrections: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._relative: dict[int, tuple[int, int, np.ndarray]] = {}
        self._kf_relative: dict[int, list[int]] = {}
        self._lm_prior: dict[int, int] = {}                     # landmark -> its prior's handle
        self._first: Optional[tuple[int, int]] = None           # (keyframe, prior handle)
        self._next_handle = 0
        self._new_keyframes: list[int] = []
        self._focus: Optional[int] = None
        self._solved = False
        self.last_window: tuple[int, int, int] = (0, 0, 0)     # keyframes, fixed keyframes, landmarks
        self.update_cpu_ms: list[float] = []                    # thread CPU of every update (GraphBackend)

    # --- variables ------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, T_wc_guess: np.ndarray) -> None:
        if kf_id in self._poses.slot:
            raise BackendError(f"keyframe {kf_id} already exists")
        self._poses.add(kf_id, np.asarray(T_wc_guess, float))
        self._obs.add_keyframe(kf_id)
        self._kf_relative[kf_id] = []
        if self._first is None:
            self._first = (kf_id, self._add(self._factors.first_pose_prior(kf_id, T_wc_guess)))
        self._new_keyframes.append(kf_id)

    def add_landmark(self, lm_id: int, xyz_guess: np.ndarray) -> None:
        if lm_id in self._points.slot:
            raise BackendError(f"landmark {lm_id} already exists")
        self._points.add(lm_id, np.asarray(xyz_guess, float))
        self._point_ref.add(lm_id, -1)
        self._prior_xyz.add(lm_id, np.asarray(xyz_guess, float))
        self._obs.add_landmark(lm_id)
        prior = self._factors.landmark_prior(lm_id, xyz_guess)
        if prior is not None:
            self._lm_prior[lm_id] = self._add(prior)

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self._poses.slot

    def has_landmark(self, lm_id: int) -> bool:
        return lm_id in self._points.slot

    # --- factors --------------------------------------------------------------------------------
    def add_observation(self, kf_id: int, lm_id: int, uv, depth: float = 0.0, level_scale: float = 1.0,
                        dynamic_prob: float = 0.0) -> int:
        self._require(kf_id, lm_id)
        # The schur solver reads the observation as arrays only: no GTSAM factor object to build (~8 us each).
        factor = (self._factors.observation(kf_id, lm_id, uv, depth, level_scale, dynamic_prob)
                  if self.window.solver == "gtsam" else None)
        handle = self._add(factor)
        self._obs.add(handle, kf_id, lm_id)
        self._obs_arrays.add(handle, *self._factors.observation_arrays(uv, depth, level_scale, dynamic_prob))
        slot = self._points.slot[lm_id]
        if self._point_ref.values[slot] < 0:
            self._point_ref.values[slot] = self._poses.slot[kf_id]
        return handle

    def add_relative_pose(self, kf_a: int, kf_b: int, T_ab: np.ndarray, sigma_t: float, sigma_r_deg: float,
                          kernel: Optional[str] = "huber", kernel_k: float = 1.0) -> int:
        self._require(kf_a)
        self._require(kf_b)
        handle = self._add(self._factors.relative_pose(kf_a, kf_b, T_ab, sigma_t, sigma_r_deg, kernel, kernel_k))
        self._relative[handle] = (kf_a, kf_b, np.array(T_ab, dtype=float))
        self._kf_relative[kf_a].append(handle)
        self._kf_relative[kf_b].append(handle)
        self._touch_span(kf_a, kf_b)
        self._added_relative.append(handle)
        return handle

    def _touch_span(self, *kf_ids: int) -> None:
        oldest = min(kf_ids)
        self._span_start = oldest if self._span_start is None else min(self._span_start, oldest)

    def relative_pose_error(self, handle: int) -> tuple[float, float]:
        if handle not in self._relative:
            raise BackendError(f"factor handle {handle} is not a live relative-pose factor")
        a, b, T_ab = self._relative[handle]
        return relative_pose_residual(self.keyframe_pose(a), self.keyframe_pose(b), T_ab)

    def remove_factors(self, handles: Iterable[int]) -> None:
        handles = list(handles)
        unknown = [h for h in handles if h not in self._live]
        if unknown:
            raise BackendError(f"unknown factor handle(s) {unknown} (already removed?)")
        self._obs.remove(handles)
        for h in handles:
            del self._live[h]
            if h in self._relative:
                self._touch_span(*self._relative.pop(h)[:2])
                self._removed_relative.append(h)

    # --- solving --------------------------------------------------------------------------------
    def update(self, extra_updates: Optional[int] = None, relinearize: bool = False) -> None:
        """Adjust the window around the newest keyframe; with ``relinearize`` (a loop changed) first
        correct the loop (``window_loops.LoopCorrection``). ``extra_updates`` is iSAM2's and ignored here."""
        with thread_cpu_ms(self.update_cpu_ms):
            self._update(relinearize)

    def _update(self, relinearize: bool) -> None:
        new, self._new_keyframes = self._new_keyframes, []
        span_start, self._span_start = self._span_start, None
        added, self._added_relative = self._added_relative, []
        removed, self._removed_relative = self._removed_relative, []
        if len(self._poses) == 0:
            return
        if new:
            self._focus = max(new)
        elif self._focus is None:
            self._focus = int(self._poses.ids[len(self._poses) - 1])
        if relinearize and len(self._poses) > 1:
            if removed and not added and all(h in self._corrections for h in removed):
                for h in sorted(removed, reverse=True):
                    self._undo_correction(h)
            else:
                self._correct_loop(span_start, added)
            for h in removed:
                self._corrections.pop(h, None)
        window = self._window(self._focus, new)
        self._adjust(window, relative_tol=self.window.relative_tol)
        self._solved = True

    def optimize_all(self, iterations: Optional[int] = None) -> None:
        """Bundle-adjust every keyframe and landmark at once (for the end of a run, never per keyframe).
        Beyond ``final_max_keyframes`` only the newest that many are adjusted, against their fixed
        neighbours: the whole of a 1,000-keyframe map took minutes and 6 GB."""
        if len(self._poses) == 0:
            return
        ids = np.sort(self._poses.ids[: len(self._poses)])
        self._adjust({int(k) for k in ids[-self.window.final_max_keyframes:]},
                     iterations or self.window.final_iterations, self.window.final_relative_tol)
        self._solved = True

    @property
    def holding_back(self) -> bool:
        return False           # solved in process: every update's estimates are there at once

    # --- estimates ------------------------------------------------------------------------------
    def keyframe_pose(self, kf_id: int) -> np.ndarray:
        if not self._solved or kf_id not in self._poses.slot:
            raise BackendError(f"keyframe {kf_id} has no estimate yet (call update())")
        return self._poses.values[self._poses.slot[kf_id]].copy()

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids (K,), poses (K,4,4)) of every keyframe, sorted by id (empty before the first update)."""
        if not self._solved:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return self._poses.sorted()

    def landmark_positions(self) -> tuple[np.ndarray, np.ndarray]:
        if not self._solved:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return self._points.sorted()

    def sync(self) -> None:
        """Solved in this process: every update is already applied."""

    def close(self) -> None:
        """Nothing held open."""

    @property
    def num_factors(self) -> int:
        return len(self._live)

    # --- helpers --------------------------------------------------------------------------------
    def _require(self, kf_id: int, lm_id: Optional[int] = None) -> None:
        if kf_id not in self._poses.slot:
            raise BackendError(f"unknown keyframe {kf_id}: add_keyframe() it first")
        if lm_id is not None and lm_id not in self._points.slot:
            raise BackendError(f"unknown landmark {lm_id}: add_landmark() it first")

    def _add(self, factor: Optional[gtsam.NonlinearFactor]) -> int:
        handle = self._next_handle
        self._next_handle += 1
        self._live[handle] = factor
        return handle
