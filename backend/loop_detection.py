"""Loop detection for keyframes: DBoW2 place recognition, ORB-SLAM's consistent groups, PnP verification.

``LoopDetector.process_keyframe(slam_map, kf_id)`` runs ORB-SLAM's ``DetectLoop`` + the geometric half
of ``ComputeSim3`` (RGB-D: scale is known, so an SE(3) PnP against the map replaces Sim3):

1. **Place recognition on static features only.** The keyframe's features with
   ``dynamic_prob < dynamic_threshold`` form its bag of words. A walking person or a moved chair
   describes *when* an image was taken, not *where*; letting them vote would both create false
   loops (the same person seen in two places) and hide true ones. A keyframe with no static
   feature gets an empty vector and can neither find nor be found.
2. **Candidates.** The keyframe index is queried (before the keyframe is added) excluding the keyframe,
   its covisible keyframes (``>= min_covisible_shared`` shared landmarks: they are already connected
   in the graph, a "loop" to them closes nothing) and the ``exclude_recent`` newest keyframes. As in
   DBoW2/ORB-SLAM the acceptance threshold adapts to the scene: ``min_score`` is the *lowest* score
   between the keyframe and its covisible neighbours, i.e. how similar an image of *this* place
   looks from nearby. Candidates must beat it and reach ``min_score_ratio`` x the best candidate.
3. **Temporal consistency.** Each candidate and its covisible neighbourhood form a *group*. A group is
   consistent with a group of the previous keyframe if they share a keyframe; the consistency count
   grows by one per consecutive keyframe. Only candidates whose count reaches ``consistency`` go on
   (one keyframe with a lucky BoW score is not enough; a real revisit keeps matching).
4. **Geometric verification (static features only).** The keyframe's static descriptors are matched
   (``backend.pnp_verification``: Hamming, Lowe ratio 0.75, one keypoint per landmark) to the good landmarks
   observed by the candidate and its covisible neighbours; ``cv2.solvePnPRansac`` (the same
   samples in every run: OpenCV's RANSAC draws from a generator fixed inside the call) on world landmark positions vs. the keyframe's undistorted pixels
   (``camera.K``, no distortion) gives a pose that is refined with ``SOLVEPNP_ITERATIVE`` on the
   inliers. Inliers whose predicted depth disagrees with the measured depth by more than
   ``depth_tolerance`` (relative) are dropped: an RGB-D camera measures that depth, and a repeated
   texture at another distance is a classic false match. At least ``min_inliers`` must remain.
5. The first verified candidate (best BoW score first) is returned as a ``LoopCandidate``: the query's
   pose implied by the map around the match (``T_wc_corrected``), the relative pose
   ``T_match_query = T_w,match^-1 T_wc_corrected`` for ``Graph.add_relative_pose(match_kf, query_kf,
   T_match_query, ...)`` (a BetweenFactorPose3), and the inlier (keypoint, landmark) pairs.

Everything per feature/landmark is numpy or OpenCV; Python loops run only over the handful of
candidates and consistent groups. This module imports nothing from ``frontend``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from backend.map_store import SlamMap
from backend.place_recognition import BowVector, KeyframeIndex, Vocabulary, score
from backend.pnp_verification import PnpParams, solve_pnp
from slam.core.geometry import invert

__all__ = ["LoopCandidate", "LoopDetector"]


@dataclass
class LoopCandidate:
    """A verified loop between ``query_kf`` (the new keyframe) and ``match_kf`` (an old one).

    ``T_wc_corrected``: the query's camera-to-world pose implied by the landmarks around the match.
    ``T_match_query``: pose of the query seen from the match (``T_w,match^-1 @ T_wc_corrected``), the
    measurement of a between factor ``add_relative_pose(match_kf, query_kf, T_match_query, ...)``.
    ``matches``: (M, 2) int64 inlier pairs (query keypoint index, landmark id).
    """

    query_kf: int
    match_kf: int
    T_wc_corrected: np.ndarray
    T_match_query: np.ndarray
    n_inliers: int
    score: float
    matches: np.ndarray = field(repr=False)


class LoopDetector:
    """Keeps its own ``KeyframeIndex`` and consistent groups; feed every new keyframe in order."""

    def __init__(self, vocabulary: Vocabulary, camera, min_covisible_shared: int = 15, consistency: int = 3,
                 min_inliers: int = 30, dynamic_threshold: float = 0.5, min_score_ratio: float = 0.75,
                 exclude_recent: int = 5, max_candidates: int = 10, ratio: float = 0.75,
                 max_descriptor_distance: int = 64, reprojection_error: float = 3.0,
                 ransac_iterations: int = 300, depth_tolerance: Optional[float] = 0.1, seed: int = 0) -> None:
        """``depth_tolerance=None`` disables the depth-consistency check; ``seed`` seeds OpenCV's RNG
        before every RANSAC so results do not depend on what else drew from it."""
        if consistency < 1 or min_inliers < 4:
            raise ValueError("need consistency >= 1 and min_inliers >= 4")
        self.vocabulary = vocabulary
        self.camera = camera
        self.min_covisible_shared = int(min_covisible_shared)
        self.consistency = int(consistency)
        self.min_inliers = int(min_inliers)
        self.pnp = PnpParams(int(min_inliers), float(ratio), int(max_descriptor_distance), float(reprojection_error),
                             int(ransac_iterations), depth_tolerance, int(seed))
        self.dynamic_threshold = float(dynamic_threshold)
        self.min_score_ratio = float(min_score_ratio)
        self.exclude_recent = int(exclude_recent)
        self.max_candidates = int(max_candidates)
        self.index = KeyframeIndex(vocabulary)
        self._groups: list[tuple[np.ndarray, int]] = []  # (sorted keyframe ids, consistency count)
        self.last_candidates: list[tuple[int, float]] = []   # diagnostics of the last call
        self.last_consistent: list[int] = []

    # ------------------------------------------------------------------ public
    def process_keyframe(self, slam_map: SlamMap, kf_id: int) -> Optional[LoopCandidate]:
        """Detect a loop for keyframe ``kf_id`` (then index it). ``None`` when there is none."""
        kf_id = int(kf_id)
        feats = slam_map.keyframes[kf_id].features
        static = self._static_mask(feats)
        desc = feats.descriptors[static]
        covisible = slam_map.covisible_keyframes(kf_id, self.min_covisible_shared, limit=slam_map.num_keyframes)
        bow = self.vocabulary.bow(desc)     # once: scored, queried and indexed alike
        try:
            candidates = self._candidates(slam_map, kf_id, bow, covisible)
            self.last_candidates = candidates
            consistent = self._consistent(slam_map, candidates)
            self.last_consistent = [c for c, _ in consistent]
            for cand, s in consistent:
                loop = self._verify(slam_map, kf_id, static, cand, s)
                if loop is not None:
                    return loop
            return None
        finally:
            self.index.add_bow(kf_id, bow)

    def index_keyframe(self, slam_map: SlamMap, kf_id: int) -> None:
        """Add a keyframe's static words to the index without looking for a loop."""
        feats = slam_map.keyframes[int(kf_id)].features
        self.index.add(int(kf_id), feats.descriptors[self._static_mask(feats)])

    def remove_keyframe(self, kf_id: int) -> None:
        """Forget a culled keyframe (it can no longer be a candidate)."""
        if kf_id in self.index:
            self.index.remove(kf_id)

    def reset_consistency(self) -> None:
        self._groups = []

    # ------------------------------------------------------------------ steps
    def _static_mask(self, feats) -> np.ndarray:
        prob = np.nan_to_num(np.asarray(feats.dynamic_prob, np.float64), nan=1.0)
        return prob < self.dynamic_threshold

    def _candidates(self, slam_map: SlamMap, kf_id: int, q: BowVector,
                    covisible: np.ndarray) -> list[tuple[int, float]]:
        """BoW candidates above the adaptive DBoW2 minimum score, best first."""
        if len(q) == 0 or len(self.index) == 0:
            return []
        indexed = [int(c) for c in covisible if int(c) in self.index]
        min_score = min((score(q, self.index.bow(c)) for c in indexed), default=0.0)
        exclude = {kf_id, *map(int, covisible), *range(max(0, kf_id - self.exclude_recent), kf_id)}
        hits = self.index.query_bow(q, exclude=exclude, top_k=len(self.index))
        if not hits:
            return []
        best = hits[0][1]
        keep = [(k, s) for k, s in hits if s > min_score and s >= self.min_score_ratio * best]
        return keep[: self.max_candidates]

    def _group(self, slam_map: SlamMap, kf: int) -> np.ndarray:
        cov = slam_map.covisible_keyframes(kf, self.min_covisible_shared, limit=slam_map.num_keyframes)
        return np.union1d(cov, [kf]).astype(np.int64)

    def _consistent(self, slam_map: SlamMap, candidates: list[tuple[int, float]]) -> list[tuple[int, float]]:
        """ORB-SLAM's consistent groups: update the groups, return candidates whose count reached
        ``consistency`` (score order). Without candidates the groups are cleared: consistency means
        *consecutive* keyframes."""
        new_groups: list[tuple[np.ndarray, int]] = []
        accepted: list[tuple[int, float]] = []
        for cand, s in candidates:
            group = self._group(slam_map, cand)
            counts = [c + 1 for g, c in self._groups if np.intersect1d(g, group, assume_unique=True).size]
            count = max(counts, default=1)
            new_groups.append((group, count))
            if count >= self.consistency:
                accepted.append((cand, s))
        self._groups = new_groups
        return accepted

    def _verify(self, slam_map: SlamMap, kf_id: int, static: np.ndarray, cand: int,
                bow_score: float) -> Optional[LoopCandidate]:
        """Match static query features to the candidate neighbourhood's landmarks, PnP-RANSAC, refine."""
        feats = slam_map.keyframes[kf_id].features
        kp_idx = np.flatnonzero(static)
        points = slam_map.map_points(slam_map.landmarks_of_keyframes(self._group(slam_map, cand)))
        solution = solve_pnp(feats.descriptors[kp_idx], feats.uv[kp_idx], feats.depths[kp_idx], points,
                             self.camera.K, self.pnp)
        if solution is None:
            return None
        T_wc = invert(solution.T_cw)
        T_match_query = invert(slam_map.kf_T_wc[cand]) @ T_wc
        pairs = np.stack([kp_idx[solution.feature_idx], solution.landmark_ids], axis=1).astype(np.int64)
        return LoopCandidate(kf_id, int(cand), T_wc, T_match_query, len(pairs), float(bow_score), pairs)
