"""The bundle adjustment of one window for ``LocalWindowBackend`` (backend/window_graph.py): which keyframes a
keyframe's window holds, which fixed keyframes, landmarks and factors hold it in place, and its solve, by the
window solver (``backend.window_solver``, ``backend.window_solver: schur``) or by GTSAM's Levenberg-Marquardt
(``gtsam``).

``WindowAdjustment`` is a mixin like ``window_loops.LoopCorrection``: it works on the window back end's own state
(poses and points as growing arrays, the observation index and arrays, the live factors) and is not meant to be
used on its own. The per-keyframe window, a loop's span and the final adjustment all come through ``_adjust``.
"""
from __future__ import annotations

from typing import Optional

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from backend.factors import BackendError, pose3
from backend.window_index import ranked_by_count
from backend.window_solver import WindowProblem
from backend.window_solver import solve as solve_window


class WindowAdjustment:
    """Window selection, problem assembly and solving (``_adjust``)."""

    def _window(self, focus: int, new: list[int]) -> set[int]:
        """The focus keyframe and its most covisible keyframes (shared graph landmarks), plus any other
        keyframe added since the last update."""
        obs = self._obs
        landmarks = np.unique(obs.lm[obs.of_keyframes([focus])]).tolist()
        seen = self._recent_observations(landmarks)
        pairs = np.unique(np.stack([obs.lm[seen], obs.kf[seen]], axis=1), axis=0)   # each landmark's observers
        observers = pairs[:, 1]
        ranked = ranked_by_count(observers[observers != focus], self.window.window_keyframes - 1)
        window = {focus, *ranked.tolist(), *new}
        for h in self._kf_relative[focus]:     # the previous keyframe, even with no shared landmark yet
            if h in self._relative and len(window) < self.window.window_keyframes:
                a, b, _ = self._relative[h]
                window.add(a if b == focus else b)
        return window

    def _recent_observations(self, landmarks: list[int]) -> np.ndarray:
        """The landmarks' live observations by their latest observers only (``ObservationIndex.recent``)."""
        return self._obs.recent(landmarks, 2 * (self.window.window_keyframes + self.window.max_fixed_keyframes))

    def _adjust(self, window: set[int], iterations: Optional[int] = None, relative_tol: float = 1e-5) -> None:
        """Bundle-adjust the keyframes of ``window`` and the landmarks they see, held by the keyframes
        around it (fixed), and write the estimates back."""
        window, fixed, landmarks, handles = self._window_problem(window)
        if self.window.solver == "schur":
            self._adjust_schur(window, fixed, landmarks, handles, iterations or self.window.iterations, relative_tol)
            return
        graph, values, ordering = self._window_graph(window, fixed, landmarks, handles)
        result = self._solve(graph, values, iterations or self.window.iterations, ordering, relative_tol)
        for k in window:
            self._poses.values[self._poses.slot[k]] = result.atPose3(X(k)).matrix()
        if landmarks:
            slots = np.fromiter((self._points.slot[lm] for lm in landmarks), np.int64, len(landmarks))
            self._points.values[slots] = gtsam.utilities.extractPoint3(result).reshape(-1, 3)
        self.last_window = (len(window), len(fixed), len(landmarks))

    def _adjust_schur(self, window: set[int], fixed: set[int], landmarks: list[int], handles: set[int],
                      iterations: int, relative_tol: float) -> None:
        """``_adjust`` by ``backend.window_solver``: the same factors as arrays (observations, landmark priors)
        and GTSAM's own pose factors."""
        pose_ids = sorted(window) + sorted(fixed)
        pose_slots = np.fromiter((self._poses.slot[k] for k in pose_ids), np.int64, len(pose_ids))
        point_slots = np.fromiter((self._points.slot[lm] for lm in landmarks), np.int64, len(landmarks))
        obs = self._obs
        hs = np.fromiter(sorted(handles), np.int64, len(handles))
        observed = hs[(hs < len(obs.kf))]
        observed = observed[obs.kf[observed] >= 0]
        row_of_kf = np.full(int(max(pose_ids)) + 1, -1, np.int64)
        row_of_kf[np.asarray(pose_ids, np.int64)] = np.arange(len(pose_ids))
        lm_ids = np.asarray(landmarks, np.int64)
        o_pt = np.searchsorted(lm_ids, obs.lm[observed])
        observation_set = set(observed.tolist())
        prior_handles = {self._lm_prior[lm] for lm in landmarks if lm in self._lm_prior}
        pose_factors = [self._live[h] for h in sorted(handles) if h not in observation_set and h not in prior_handles]
        arrays = self._obs_arrays
        problem = WindowProblem(
            poses=self._poses.values[pose_slots], n_adj=len(window), pose_ids=pose_ids,
            points=self._points.values[point_slots], o_pose=row_of_kf[obs.kf[observed]], o_pt=o_pt,
            meas=arrays.meas[observed], sqrt_info=arrays.sqrt_info[observed], huber_k=arrays.huber_k[observed],
            prior_xyz=self._prior_xyz.values[point_slots],
            prior_w2=(1.0 / self.params.landmark_prior_sigma ** 2) if self.params.landmark_prior_sigma > 0 else 0.0,
            pose_factors=pose_factors)
        poses, points, _ = solve_window(problem, self.calibration, iterations, relative_tol)
        self._poses.values[pose_slots[:len(window)]] = poses[:len(window)]
        if landmarks:
            self._points.values[point_slots] = points
        self.last_window = (len(window), len(fixed), len(landmarks))

    def _window_problem(self, window: set[int]) -> tuple[set[int], set[int], list[int], set[int]]:
        """(the keyframes to adjust, the fixed keyframes that hold them, the landmarks, the factor handles)."""
        obs = self._obs
        own = obs.of_keyframes(window)
        landmarks = np.unique(obs.lm[own]).tolist()
        seen = self._recent_observations(landmarks)
        outside = seen[~np.isin(obs.kf[seen], np.fromiter(window, np.int64))]   # by keyframes outside the window
        # The fixed keyframes that see most of the window's landmarks hold it; a cap keeps the cost
        # flat where a place is revisited many times (its landmarks are seen by ever more keyframes).
        outside_kf = obs.kf[outside]
        ranked = ranked_by_count(outside_kf, self.window.max_fixed_keyframes)
        fixed: set[int] = set(ranked.tolist())
        handles = set(own.tolist())
        handles.update(outside[np.isin(outside_kf, ranked)].tolist())
        handles.update(self._lm_prior[lm] for lm in landmarks if lm in self._lm_prior)
        for k in window:
            for h in self._kf_relative[k]:
                if h in self._relative:
                    handles.add(h)
                    a, b, _ = self._relative[h]
                    fixed.update(x for x in (a, b) if x not in window)
        first_kf, first_handle = self._first
        if first_kf in window or first_kf in fixed:
            handles.add(first_handle)
        elif not fixed:
            fixed.add(min(window))   # gauge: a window that touches nothing else keeps its oldest pose
            window = window - fixed
        return window, fixed, landmarks, handles

    def _window_graph(self, window: set[int], fixed: set[int], landmarks: list[int], handles: set[int]
                      ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, gtsam.Ordering]:
        """The factors of ``handles``, a tight prior on every fixed keyframe, the current estimates as the
        starting point, and the elimination order."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        add, live = graph.add, self._live
        for h in sorted(handles):
            add(live[h])
        noise = gtsam.noiseModel.Isotropic.Sigma(6, self.window.fixed_sigma)
        for k in sorted(window | fixed):
            pose = pose3(self._poses.values[self._poses.slot[k]])
            values.insert(X(k), pose)
            if k in fixed:
                graph.add(gtsam.PriorFactorPose3(X(k), pose, noise))
        keys = [L(lm) for lm in landmarks]
        slot = self._points.slot
        points = self._points.values[np.fromiter((slot[lm] for lm in landmarks), np.int64, len(landmarks))]
        insert = values.insert
        for key, xyz in zip(keys, points):
            insert(key, xyz)
        # Landmarks first, then poses: the Schur-complement order of bundle adjustment (measured 30 ms
        # against COLAMD's 52 ms for the linear solve of 12 keyframes and 2,500 landmarks).
        ordering = gtsam.Ordering()
        push = ordering.push_back
        for key in keys:
            push(key)
        for k in sorted(window | fixed):
            ordering.push_back(X(k))
        return graph, values, ordering

    @staticmethod
    def _solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, iterations: int,
               ordering: Optional[gtsam.Ordering] = None, relative_tol: float = 1e-5) -> gtsam.Values:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        params.setRelativeErrorTol(relative_tol)
        # Landmarks-first ordering makes every clique but the last a single landmark: the sequential
        # solver skips the Bayes tree's bookkeeping (same cost values on captured Bonn windows, ~8 % less time).
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        if ordering is not None:
            params.setOrdering(ordering)
        try:
            return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        except RuntimeError as exc:
            raise BackendError(f"local bundle adjustment failed: {exc}") from exc
