"""Loop correction for ``LocalWindowBackend`` (backend/window_graph.py): pose graph over a loop's span,
bundle adjustment of the span, and taking a removed loop's correction back.

``LoopCorrection`` is a mixin: it works on the window back end's own state (poses and points as growing
arrays, observation indexes, relative-pose factors) and is not meant to be used on its own. It lives
apart because loop correction is a job of its own (ORB-SLAM's ``CorrectLoop`` + essential graph);
its bundle adjustments go through ``window_adjust.WindowAdjustment._adjust`` like every window's.
"""
from __future__ import annotations

from typing import Optional

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X
from scipy import sparse

from backend.factors import FactorBuilder, pose3


class LoopCorrection:
    """What ``update(relinearize=True)`` does after a loop factor was added or removed."""

    def _correct_loop(self, span_start: Optional[int], added: list[int]) -> None:
        """A pose graph over the loop's span (fast, brings both ends together), then a bundle adjustment
        of the span with its observations: the fused landmarks carry a right loop, and the landmarks
        resist a wrong one, whose residual then stays large for the loop check (as in the iSAM2 graph).
        Records the loop's whole correction so that removing it can take it back."""
        n = len(self._poses)
        before = self._poses.values[:n].copy()
        span = self._correct_with_pose_graph(span_start)
        if self.window.loop_iterations > 0 and span:
            self._adjust(self._loop_window(span), self.window.loop_iterations, relative_tol=self.window.relative_tol)
        slots = np.fromiter((self._poses.slot[k] for k in span), np.int64, len(span))
        correction = self._poses.values[slots] @ np.linalg.inv(before[slots])
        for h in added:
            self._corrections[h] = (slots, correction)
        while len(self._corrections) > self.window.max_undoable_loops:
            del self._corrections[min(self._corrections)]

    def _undo_correction(self, handle: int) -> None:
        """Take back the world-frame correction a loop's update applied to each keyframe of its span;
        landmarks follow their reference keyframe."""
        slots, correction = self._corrections[handle]
        n = len(self._poses)
        before = self._poses.values[:n].copy()
        self._poses.values[slots] = np.linalg.solve(correction, before[slots])
        moved = np.zeros(n, bool)
        moved[slots] = True
        self._move_landmarks_with_reference(moved, before, self._poses.values[:n])

    def _loop_window(self, span: list[int]) -> set[int]:
        """The keyframes a loop's bundle adjustment moves: the whole span, or where it is longer than
        ``loop_max_keyframes`` its two ends (the loop's match and query sides, where the fused landmarks
        tie them); the middle, already bent by the pose graph, holds them as fixed poses."""
        half = self.window.loop_max_keyframes // 2
        return set(span) if len(span) <= 2 * half else set(span[:half]) | set(span[-half:])

    def _correct_with_pose_graph(self, span_start: Optional[int]) -> list[int]:
        """Loop correction of the keyframes from the oldest one a changed relative factor touches (the
        loop's match keyframe) onwards, that keyframe and older neighbours held fixed: the part of the map
        before the loop already agrees with the match keyframe, and the cost is that of the loop's span,
        not of the map. Landmarks follow their reference keyframe."""
        n = len(self._poses)
        ids, before = self._poses.ids[:n].copy(), self._poses.values[:n].copy()
        start = int(ids.min()) if span_start is None else span_start
        if n > self.window.loop_max_span:   # the older part already agrees with the loops closed before
            start = max(start, int(np.sort(ids)[-self.window.loop_max_span]))
        in_span = ids >= start
        span = {int(k) for k in ids[in_span]}
        handles = {h for k in span for h in self._kf_relative[k] if h in self._relative}
        fixed = {start} | {x for h in handles for x in self._relative[h][:2] if x not in span}
        w = self.window
        edges = [e for e in self._essential_edges(span) if e[0] in span | fixed and e[1] in span | fixed]
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        noise = gtsam.noiseModel.Isotropic.Sigma(6, w.fixed_sigma)
        for k in sorted(span | fixed):
            pose = pose3(before[self._poses.slot[k]])
            values.insert(X(k), pose)
            if k in fixed:
                graph.add(gtsam.PriorFactorPose3(X(k), pose, noise))
        for h in sorted(handles):
            graph.add(self._live[h])
        for a, b in edges:
            T_ab = np.linalg.solve(before[self._poses.slot[a]], before[self._poses.slot[b]])
            graph.add(FactorBuilder.relative_pose(a, b, T_ab, w.essential_sigma_t, w.essential_sigma_r_deg, None))
        result = self._solve(graph, values, w.pose_graph_iterations)
        after = before.copy()
        for k in span - fixed:
            after[self._poses.slot[k]] = result.atPose3(X(k)).matrix()
        self._poses.values[:n] = after
        self._move_landmarks_with_reference(in_span, before, after)
        return sorted(span - {start})

    def _move_landmarks_with_reference(self, in_span: np.ndarray, before: np.ndarray, after: np.ndarray) -> None:
        """Landmarks whose reference keyframe moved (``in_span`` by pose slot) move rigidly with it."""
        m = len(self._points)
        ref = self._point_ref.values[:m].astype(np.int64)
        moved = np.flatnonzero((ref >= 0) & in_span[np.maximum(ref, 0)])
        if len(moved) == 0:
            return
        correction = after[ref[moved]] @ np.linalg.inv(before[ref[moved]])
        xyz = self._points.values[moved]
        self._points.values[moved] = np.einsum("nij,nj->ni", correction[:, :3, :3], xyz) + correction[:, :3, 3]

    def _essential_edges(self, span: set[int]) -> list[tuple[int, int]]:
        """ORB-SLAM's essential graph on the current estimate, among ``span`` and the keyframes they share
        landmarks with: consecutive keyframes, and pairs sharing at least ``essential_min_shared``
        landmarks (a sparse keyframe x landmark product over the span's observations only)."""
        order = sorted(span)
        edges = {(a, b) for a, b in zip(order[:-1], order[1:])}
        obs = self._obs
        handles = obs.of_landmarks(np.unique(obs.lm[obs.of_keyframes(span)]).tolist())
        ends = np.stack([obs.kf[handles], obs.lm[handles]], axis=1)     # (keyframe, landmark) per observation
        if len(ends):
            kf_codes, kf_index = np.unique(ends[:, 0], return_inverse=True)
            lm_codes, lm_index = np.unique(ends[:, 1], return_inverse=True)
            incidence = sparse.csr_matrix((np.ones(len(ends)), (kf_index, lm_index)),
                                          shape=(len(kf_codes), len(lm_codes)))
            incidence.data[:] = 1.0   # duplicates summed: one keyframe observing a landmark twice counts once
            shared = sparse.triu(incidence @ incidence.T, k=1).tocoo()
            strong = shared.data >= self.window.essential_min_shared
            for a, b in zip(kf_codes[shared.row[strong]], kf_codes[shared.col[strong]]):
                if int(a) in span or int(b) in span:
                    edges.add((int(min(a, b)), int(max(a, b))))
        return sorted(edges)
