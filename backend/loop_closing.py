"""Loop closing on the iSAM2 graph: detected loops become robust pose factors; bad ones are removed again.

``LoopCloser.process_keyframe(kf_id)`` runs after each keyframe insertion:

1. ``LoopDetector`` (BoW on static features, consistent groups, PnP verification) proposes a loop
   between the new keyframe and an old one, with the query pose the old landmarks imply;
2. the loop becomes a ``BetweenFactorPose3`` (match → query) under a Cauchy kernel: a correct loop
   pulls, a wrong one that slipped through verification gets almost no weight;
3. the landmarks on both sides are fused (``landmark_fusion``): the query keyframe now observes the
   old landmarks, so the correction is carried by hundreds of observations, not one factor;
4. iSAM2 runs ``extra_updates`` more updates (a loop moves many variables far from their
   linearisation point) and the map takes the new estimates; every frame follows its reference
   keyframe, so the whole per-frame trajectory is corrected;
5. every live loop is re-checked: one the optimised graph disagrees with by more than
   ``max_residual_t`` / ``max_residual_r_deg`` is removed by its factor handle (inconsistent loops can
   also surface later, so the check runs after every keyframe).

The keyframe index the detector keeps is also what relocalization queries. This module never
imports the front end.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from backend.landmark_fusion import fuse_loop_landmarks
from backend.local_mapping import LocalMapper
from backend.loop_detection import LoopCandidate, LoopDetector
from backend.place_recognition import KeyframeIndex, Vocabulary
from slam.core.loop_config import LoopConfig


@dataclass
class LoopEdge:
    """A loop constraint in the graph: ``T_match_query`` is the query pose seen from the match."""

    query_kf: int
    match_kf: int
    T_match_query: np.ndarray
    n_inliers: int
    score: float
    handle: int                   # factor handle in FactorGraphBackend (for removal)
    source: str = "detected"      # "detected" by place recognition, or "injected" through the API
    fused_landmarks: int = 0
    active: bool = True
    residual_t: float = 0.0       # disagreement with the optimised graph at the last check
    residual_r_deg: float = 0.0

    def to_dict(self) -> dict:
        return {"query_kf": self.query_kf, "match_kf": self.match_kf, "n_inliers": self.n_inliers,
                "score": round(self.score, 6), "source": self.source, "fused_landmarks": self.fused_landmarks,
                "active": self.active, "residual_t_m": round(self.residual_t, 6),
                "residual_r_deg": round(self.residual_r_deg, 4),
                "T_match_query": np.round(self.T_match_query, 9).tolist()}


class LoopCloser:
    def __init__(self, cfg: LoopConfig, mapper: LocalMapper, vocabulary: Vocabulary, dynamic_threshold: float = 0.5,
                 seed: int = 0, correct_at_once: bool = False) -> None:
        self.cfg = cfg
        self.mapper = mapper
        # Whether a closed loop's neighbourhood is moved in the map at once (``correct_neighbourhood``): for a
        # graph whose loop correction arrives some keyframes later, while tracking goes on.
        self.correct_at_once = correct_at_once
        self._neighbourhood: Optional[tuple[LoopEdge, np.ndarray]] = None   # the loop closed, its keyframes
        self.detector = LoopDetector(
            vocabulary, mapper.camera, min_covisible_shared=cfg.min_covisible_shared, consistency=cfg.consistency,
            min_inliers=cfg.min_inliers, dynamic_threshold=dynamic_threshold, min_score_ratio=cfg.min_score_ratio,
            exclude_recent=cfg.exclude_recent, max_candidates=cfg.max_candidates,
            reprojection_error=cfg.reprojection_error, depth_tolerance=cfg.depth_tolerance, seed=seed)
        self.loops: list[LoopEdge] = []
        self._optimize_now = True
        self._pending_optimization = False

    @property
    def index(self) -> KeyframeIndex:
        return self.detector.index

    def process_keyframe(self, kf_id: int, optimize: bool = True) -> Optional[LoopEdge]:
        """Detect and close a loop for a newly inserted keyframe (which is indexed either way). With
        ``optimize=False`` a loop added or removed is left in the graph for the caller's next update
        (``take_pending_optimization()`` says whether it must relinearise)."""
        self._optimize_now = optimize
        try:
            return self._process_keyframe(kf_id, optimize)
        finally:
            self._optimize_now = True   # direct calls (add_constraint, check_consistency) solve at once

    def _process_keyframe(self, kf_id: int, optimize: bool) -> Optional[LoopEdge]:
        last = max((e.query_kf for e in self.loops if e.source == "detected"), default=None)
        edge = None
        if not self.cfg.enabled or (last is not None and kf_id < last + self.cfg.min_keyframes_between):
            self.detector.index_keyframe(self.mapper.map, kf_id)
            self.detector.reset_consistency()
        else:
            candidate = self.detector.process_keyframe(self.mapper.map, kf_id)
            edge = self.close(candidate) if candidate is not None else None
        if self.active_loops():
            # A loop whose update is still to come has no residual yet: checked from the next keyframe on.
            self.check_consistency(skip=edge if not optimize else None)
        return edge

    def close(self, candidate: LoopCandidate) -> LoopEdge:
        """Add a verified loop to the graph, fuse its landmarks and re-optimise."""
        edge = self.add_constraint(candidate.match_kf, candidate.query_kf, candidate.T_match_query,
                                   candidate.n_inliers, candidate.score, "detected", optimize=False)
        if self.correct_at_once:     # before the fusion links the two sides in the covisibility
            self._neighbourhood = (edge, self._query_side(candidate.match_kf, candidate.query_kf))
        if self.cfg.fuse_landmarks:
            edge.fused_landmarks = fuse_loop_landmarks(self.mapper, candidate.query_kf, candidate.matches)
        self.optimize()
        return edge

    def _query_side(self, match_kf: int, query_kf: int) -> np.ndarray:
        """The query keyframe and its covisible keyframes, less the match and its covisible ones (sorted)."""
        slam_map = self.mapper.map
        limit = slam_map.num_keyframes
        old_side = set(slam_map.covisible_keyframes(match_kf, limit=limit).tolist()) | {match_kf}
        near = {query_kf, *slam_map.covisible_keyframes(query_kf, limit=limit).tolist()} - old_side
        return np.array(sorted(near), np.int64)

    def correct_neighbourhood(self) -> None:
        """ORB-SLAM's first step of CorrectLoop, for the loop just closed (if ``correct_at_once``): its query
        side moves rigidly to where the loop puts the query keyframe, with the landmarks made there, so that
        tracking meets one consistent map (the fused landmarks are the match side's) until the graph's
        correction arrives, which then spreads the loop's error along it. Called after the keyframe's graph
        update has taken up the estimates due then, which would otherwise move the keyframes back."""
        if self._neighbourhood is None:
            return
        (edge, near), self._neighbourhood = self._neighbourhood, None
        if not edge.active:
            return
        T_wc = self.mapper.map.kf_T_wc
        correction = T_wc[edge.match_kf] @ edge.T_match_query @ np.linalg.inv(T_wc[edge.query_kf])
        self.mapper.move_rigidly(near, correction)

    def add_constraint(self, match_kf: int, query_kf: int, T_match_query: np.ndarray, n_inliers: int = 0,
                       score: float = 0.0, source: str = "injected", optimize: bool = True) -> LoopEdge:
        """A loop factor between two existing keyframes (also how other pipelines inject their own
        loops); with ``optimize`` the graph is updated and the loop checked right away."""
        kernel = None if self.cfg.kernel == "none" else self.cfg.kernel
        handle = self.mapper.graph.add_relative_pose(int(match_kf), int(query_kf), T_match_query, self.cfg.sigma_t,
                                                     self.cfg.sigma_r_deg, kernel=kernel, kernel_k=self.cfg.kernel_k)
        edge = LoopEdge(int(query_kf), int(match_kf), np.array(T_match_query, float), int(n_inliers), float(score),
                        handle, source)
        self.loops.append(edge)
        if optimize:
            self.optimize()
            self.check_consistency()
        return edge

    def optimize(self) -> None:
        if not self._optimize_now:
            self._pending_optimization = True
            return
        self.mapper.graph.update(extra_updates=self.cfg.extra_updates, relinearize=True)
        self.mapper.sync()   # a direct call returns with its update applied, also from a worker process

    def take_pending_optimization(self) -> bool:
        """Whether a loop changed since the last call without the graph being updated for it."""
        pending, self._pending_optimization = self._pending_optimization, False
        return pending

    def check_consistency(self, skip: Optional[LoopEdge] = None) -> list[LoopEdge]:
        """Remove live loops the optimised graph contradicts; returns the ones removed."""
        removed = []
        for edge in self.active_loops():
            if edge is skip:
                continue
            edge.residual_t, edge.residual_r_deg = self.mapper.graph.relative_pose_error(edge.handle)
            if edge.residual_t > self.cfg.max_residual_t or edge.residual_r_deg > self.cfg.max_residual_r_deg:
                removed.append(edge)
        if removed:
            self.mapper.graph.remove_factors([e.handle for e in removed])
            for edge in removed:
                edge.active = False
            self.optimize()
        return removed

    def active_loops(self) -> list[LoopEdge]:
        return [e for e in self.loops if e.active]
