"""Global relocalization: find where a lost frame is in the map through the keyframe index.

ORB-SLAM's Relocalization() for RGB-D: the frame's *static* features are turned into a bag of words,
the keyframe index returns the most similar keyframes, and each candidate (best first) is verified
against the landmarks of the candidate and its covisible keyframes with the same PnP-RANSAC + depth
check as loop verification. The first verified candidate gives the pose; the tracker then refines it
against the local map and resumes in the *same* map. Independent of where the camera was last seen,
so it also finds a camera that was carried somewhere else ("kidnapped") while tracking was lost.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from backend.map_store import SlamMap
from backend.place_recognition import KeyframeIndex
from backend.pnp_verification import PnpParams, solve_pnp
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert


@dataclass
class Relocalization:
    T_wc: np.ndarray
    keyframe: int                 # the verified candidate
    feature_idx: np.ndarray       # (M,) inlier features of the frame
    landmark_ids: np.ndarray      # (M,) their landmarks
    score: float


class Relocalizer:
    def __init__(self, index: KeyframeIndex, camera, params: PnpParams, n_candidates: int = 5,
                 dynamic_threshold: float = 0.5, min_covisible_shared: int = 15) -> None:
        self.index = index
        self.camera = camera
        self.params = params
        self.n_candidates = int(n_candidates)
        self.dynamic_threshold = float(dynamic_threshold)
        self.min_covisible_shared = int(min_covisible_shared)
        self.attempts = 0
        self.successes = 0

    def relocalize(self, slam_map: SlamMap, frame: FeatureFrame) -> Optional[Relocalization]:
        """The frame's camera-to-world pose in ``slam_map``, or None when no candidate verifies."""
        self.attempts += 1
        static = np.flatnonzero(np.nan_to_num(frame.dynamic_prob, nan=1.0) < self.dynamic_threshold)
        if len(static) < self.params.min_inliers or len(self.index) == 0:
            return None
        hits = self.index.query(frame.descriptors[static], top_k=self.n_candidates)
        for kf_id, bow_score in hits:
            group = np.union1d(slam_map.covisible_keyframes(kf_id, self.min_covisible_shared, limit=10), [kf_id])
            points = slam_map.map_points(slam_map.landmarks_of_keyframes(group))
            solution = solve_pnp(frame.descriptors[static], frame.uv[static], frame.depths[static], points,
                                 self.camera.K, self.params)
            if solution is not None:
                self.successes += 1
                return Relocalization(invert(solution.T_cw), int(kf_id), static[solution.feature_idx],
                                      solution.landmark_ids, float(bow_score))
        return None
