"""Frame-to-map tracking: motion model, reference fallback, local map, and an honest LOST state.

Per frame (ORB-SLAM's Track() split into short steps):
1. predict the pose with the constant-velocity model and match the last frame's points by
   projection (its landmarks plus temporary points back-projected from its depth);
2. if that fails, match the local map by descriptor alone and solve PnP-RANSAC with depth;
3. refine against the local map (covisible keyframes' landmarks) by projection;
4. report LOST when too few landmark inliers remain, or when they fix the position too loosely (a few
   far points left beside a person filling the view), rather than inventing a pose.
Features whose dynamic probability reaches the threshold never take part; the others are weighted
by (1 - p) in the pose optimisation.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Optional, Protocol

import cv2
import numpy as np

from frontend.matching import match_brute_force, search_by_projection
from frontend.pose_optimizer import PoseObservations, PosePrior, optimize_pose
from slam.core.camera import PinholeCamera
from slam.core.config import TrackingConfig
from slam.core.frame import FeatureFrame, MapPoints
from slam.core.geometry import invert, orthonormalize


class TrackingState(Enum):
    NOT_INITIALIZED = "not_initialized"
    OK = "ok"
    LOST = "lost"


class LocalMapSource(Protocol):
    """What the tracker needs from the map, provided by the orchestration (the tracker never sees
    the back end itself)."""

    def local_points(self, seed_landmarks: np.ndarray) -> MapPoints:
        """Landmarks of the keyframes that observe ``seed_landmarks`` and of their covisible ones."""
        ...

    def landmark_points(self, ids: np.ndarray) -> MapPoints:
        """Current estimates of the given landmarks (unknown or culled ids are left out)."""
        ...


def pose_information(frame: FeatureFrame, kp: np.ndarray) -> np.ndarray:
    """The weight of features ``kp`` in the frame's pose optimisation: their level's 1/sigma^2, times how
    sure the front end is that they are static."""
    return frame.inv_sigma2[kp] * (1.0 - frame.dynamic_prob[kp])


@dataclass
class TrackingResult:
    state: TrackingState
    T_cw: Optional[np.ndarray]
    landmark_of_keypoint: np.ndarray          # (N,) landmark id per feature, -1 = none
    n_inliers: int = 0
    visible_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    method: str = ""
    # Landmarks that matched features judged dynamic (kept out of the pose), with those features'
    # probabilities: evidence that the landmark sits on something moving.
    dynamic_landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    dynamic_probs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # How far the inliers alone let the position slide along its weakest direction (1 sigma, metres);
    # beyond tracking.max_pose_sigma_m the frame is LOST.
    pose_sigma_t: float = float("inf")
    # (3,3) covariance of the camera centre in the world frame from the same information (NaN: unknown):
    # what the final trajectory's smoother weighs this frame's position by.
    position_cov_w: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))


@dataclass
class _Correspondences:
    """Matched (feature, point) pairs; point ids of -1 are temporary depth points."""

    kp: np.ndarray
    point_ids: np.ndarray
    xyz: np.ndarray

    @staticmethod
    def from_projection(points: MapPoints, kp_of_point: np.ndarray) -> "_Correspondences":
        m = kp_of_point >= 0
        return _Correspondences(kp_of_point[m], points.ids[m], points.xyz[m])

    def subset(self, mask: np.ndarray) -> "_Correspondences":
        return _Correspondences(self.kp[mask], self.point_ids[mask], self.xyz[mask])

    def __len__(self) -> int:
        return len(self.kp)


class Tracker:
    def __init__(self, cfg: TrackingConfig, camera: PinholeCamera):
        self.cfg = cfg
        self.camera = camera
        self.state = TrackingState.NOT_INITIALIZED
        self._last_frame: Optional[FeatureFrame] = None
        self._last_T_cw: Optional[np.ndarray] = None
        self._last_landmarks = np.zeros(0, np.int64)
        self._velocity: Optional[np.ndarray] = None
        self._prior: Optional[PosePrior] = None   # this frame's motion-model prior (None: none)
        self._pose_sigma_t = float("inf")         # of the last pose optimisation
        self._pose_cov_t = np.full((3, 3), np.nan)  # of the last pose optimisation (twist frame)
        sigmas = np.r_[np.full(3, np.deg2rad(cfg.motion_prior_sigma_deg)), np.full(3, cfg.motion_prior_sigma_m)]
        self._prior_information = 1.0 / sigmas**2 if (sigmas > 0).all() else None

    def initialize(self, frame: FeatureFrame, T_cw: np.ndarray, landmark_of_keypoint: np.ndarray) -> None:
        """Start tracking from a frame that became the first keyframe."""
        self.state = TrackingState.OK
        self._remember(frame, T_cw, landmark_of_keypoint)
        self._velocity = None

    @property
    def last_T_cw(self) -> Optional[np.ndarray]:
        return self._last_T_cw if self.state == TrackingState.OK else None

    def predicted_T_cw(self) -> Optional[np.ndarray]:
        """Constant-velocity prediction of the next frame's pose (None before init / when lost)."""
        if self.state != TrackingState.OK or self._last_T_cw is None:
            return None
        if self._velocity is None:
            return self._last_T_cw.copy()
        return orthonormalize(self._velocity @ self._last_T_cw)

    def adopt_keyframe_landmarks(self, landmark_of_keypoint: np.ndarray) -> None:
        """The last frame became a keyframe and gained new landmarks: track against them too."""
        self._last_landmarks = landmark_of_keypoint.copy()

    def track(self, frame: FeatureFrame, source: LocalMapSource) -> TrackingResult:
        eligible = frame.dynamic_prob < self.cfg.dynamic_threshold
        corr, T_cw, method = None, None, ""
        self._prior = self._motion_prior()
        if self.state == TrackingState.OK:
            T_cw, corr = self._track_motion_model(frame, source, eligible)
            method = "motion"
        if corr is None:
            # The prediction just failed to find the frame: it is no prior for the pose found without it.
            self._prior = None
            T_cw, corr = self._track_by_descriptors(frame, source, eligible)
            method = "descriptors"
        if corr is None:
            return self._lose(frame)
        return self._finish(frame, source, eligible, T_cw, corr, method)

    def resume(self, frame: FeatureFrame, source: LocalMapSource, T_cw: np.ndarray, keypoints: np.ndarray,
               points: MapPoints) -> TrackingResult:
        """Resume from a pose found outside the tracker (relocalization: PnP of ``keypoints`` against
        the landmarks ``points``): refine against the local map, or stay LOST if that fails."""
        eligible = frame.dynamic_prob < self.cfg.dynamic_threshold
        self._prior = None   # no motion model across the gap
        ok = eligible[keypoints]
        corr = _Correspondences(keypoints[ok], points.ids[ok], points.xyz[ok])
        T_cw, corr = self._optimize(frame, T_cw, corr)
        if len(corr) < 15:
            return self._lose(frame)
        self._last_T_cw, self._velocity = None, None   # no motion model across the gap
        return self._finish(frame, source, eligible, T_cw, corr, "relocalization")

    def _motion_prior(self) -> Optional[PosePrior]:
        """The constant-velocity prediction as a prior on the pose (once a velocity is known)."""
        if self._prior_information is None or self.state != TrackingState.OK or self._velocity is None:
            return None
        return PosePrior(self.predicted_T_cw(), self._prior_information)

    def rebase(self, T_cw: np.ndarray) -> None:
        """The map moved under the last frame (a loop correction): continue from its corrected pose."""
        if self.state == TrackingState.OK:
            self._last_T_cw = T_cw.copy()

    def _finish(self, frame, source, eligible, T_cw, corr, method: str) -> TrackingResult:
        T_cw, corr, visible, local = self._track_local_map(frame, source, eligible, T_cw, corr,
                                                           wide=(method != "motion"))
        landmark_inliers = int((corr.point_ids >= 0).sum())
        if landmark_inliers < self.cfg.min_tracked_inliers or self._pose_sigma_t > self.cfg.max_pose_sigma_m:
            return self._lose(frame)
        lm_of_kp = np.full(len(frame), -1, np.int64)
        is_lm = corr.point_ids >= 0
        lm_of_kp[corr.kp[is_lm]] = corr.point_ids[is_lm]
        self._velocity = orthonormalize(T_cw @ invert(self._last_T_cw)) if self._last_T_cw is not None else None
        self.state = TrackingState.OK
        self._remember(frame, T_cw, lm_of_kp)
        dyn_ids, dyn_probs = self._dynamic_evidence(frame, local, T_cw, eligible, corr.point_ids)
        R_cw = T_cw[:3, :3]
        return TrackingResult(TrackingState.OK, T_cw, lm_of_kp, landmark_inliers, visible, method, dyn_ids, dyn_probs,
                              self._pose_sigma_t, R_cw.T @ self._pose_cov_t @ R_cw)

    def _dynamic_evidence(self, frame, local: MapPoints, T_cw, eligible, used_ids):
        """Match local landmarks to the features kept out as dynamic (they never move the pose)."""
        dynamic = ~eligible
        if not dynamic.any() or len(local) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        candidates = local.subset(~np.isin(local.ids, used_ids))
        matches = search_by_projection(frame, candidates, T_cw, self.camera, self.cfg.local_map_search_radius,
                                       self.cfg.strict_descriptor_distance, self.cfg.match_ratio, dynamic)
        hit = matches.keypoint_of_point >= 0
        return candidates.ids[hit], frame.dynamic_prob[matches.keypoint_of_point[hit]]

    def _lose(self, frame: FeatureFrame) -> TrackingResult:
        self.state = TrackingState.LOST
        self._velocity = None
        return TrackingResult(TrackingState.LOST, None, np.full(len(frame), -1, np.int64))

    def _remember(self, frame: FeatureFrame, T_cw: np.ndarray, lm_of_kp: np.ndarray) -> None:
        self._last_frame, self._last_T_cw, self._last_landmarks = frame, T_cw, lm_of_kp

    # --- step 1: constant velocity --------------------------------------------------------------
    def _track_motion_model(self, frame, source, eligible):
        predicted = self.predicted_T_cw()
        points = self._last_frame_points(source)
        corr = None
        for radius in (self.cfg.motion_search_radius, 2 * self.cfg.motion_search_radius):
            # No ratio test against the last frame (as ORB-SLAM): the pose optimisation rejects outliers.
            matches = search_by_projection(frame, points, predicted, self.camera, radius,
                                           self.cfg.max_descriptor_distance, 1.0, eligible)
            corr = _Correspondences.from_projection(points, matches.keypoint_of_point)
            if len(corr) >= self.cfg.min_motion_matches:
                break
        if len(corr) < self.cfg.min_motion_matches:
            return None, None
        T_cw, corr = self._optimize(frame, predicted, corr)
        if (corr.point_ids >= 0).sum() < 10:
            return None, None
        return T_cw, corr

    def _last_frame_points(self, source: LocalMapSource) -> MapPoints:
        """Last frame's landmarks, plus its other close depth features as temporary points: they
        hold the pose between keyframes when few landmarks are in view (ORB-SLAM's UpdateLastFrame)."""
        last = self._last_frame
        landmarks = source.landmark_points(self._last_landmarks[self._last_landmarks >= 0])
        free = (self._last_landmarks < 0) & last.has_depth & (last.depths < self.camera.close_depth)
        free &= last.dynamic_prob < self.cfg.dynamic_threshold
        idx = np.flatnonzero(free)
        xyz_c = self.camera.backproject(last.uv[idx], last.depths[idx])
        T_wc = invert(self._last_T_cw)
        temp = MapPoints(np.full(len(idx), -1, np.int64), xyz_c @ T_wc[:3, :3].T + T_wc[:3, 3],
                         last.descriptors[idx], last.octaves[idx])
        return MapPoints.concat([landmarks, temp])

    # --- step 2: descriptors + PnP --------------------------------------------------------------
    def _track_by_descriptors(self, frame, source, eligible):
        seeds = self._last_landmarks[self._last_landmarks >= 0]
        points = source.local_points(seeds)
        kp_idx = np.flatnonzero(eligible)
        if len(points) < 10 or len(kp_idx) < 10:
            return None, None
        qi, ti = match_brute_force(frame.descriptors[kp_idx], points.descriptors, 0.8,
                                   self.cfg.max_descriptor_distance)
        if len(qi) < 15:
            return None, None
        T_cw = self._solve_pnp(frame.uv[kp_idx[qi]], points.xyz[ti])
        if T_cw is None:
            return None, None
        corr = _Correspondences(kp_idx[qi], points.ids[ti], points.xyz[ti])
        T_cw, corr = self._optimize(frame, T_cw, corr)
        if len(corr) < 15:
            return None, None
        return T_cw, corr

    def _solve_pnp(self, uv: np.ndarray, xyz: np.ndarray) -> Optional[np.ndarray]:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            xyz.astype(np.float64), uv.astype(np.float64), self.camera.K, None, iterationsCount=200,
            reprojectionError=4.0, confidence=0.99, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inliers is None or len(inliers) < 15:
            return None
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        return T

    # --- step 3: local map ----------------------------------------------------------------------
    def _track_local_map(self, frame, source, eligible, T_cw, corr, wide: bool):
        seeds = corr.point_ids[corr.point_ids >= 0]
        local = source.local_points(seeds)
        not_yet = ~np.isin(local.ids, corr.point_ids)
        candidates = local.subset(not_yet)
        free = eligible.copy()
        free[corr.kp] = False
        radius = self.cfg.motion_search_radius if wide else self.cfg.local_map_search_radius
        matches = search_by_projection(frame, candidates, T_cw, self.camera, radius,
                                       self.cfg.max_descriptor_distance, self.cfg.match_ratio, free)
        extra = _Correspondences.from_projection(candidates, matches.keypoint_of_point)
        merged = _Correspondences(np.r_[corr.kp, extra.kp], np.r_[corr.point_ids, extra.point_ids],
                                  np.vstack([corr.xyz, extra.xyz]))
        T_cw, merged = self._optimize(frame, T_cw, merged)
        visible = candidates.ids[matches.visible]
        return T_cw, merged, np.union1d(visible, seeds), local

    def _optimize(self, frame: FeatureFrame, T_cw: np.ndarray, corr: _Correspondences):
        """Pose-only optimisation; returns the pose and the inlier correspondences."""
        kp = corr.kp
        information = pose_information(frame, kp)
        obs = PoseObservations(corr.xyz, frame.uv[kp], frame.u_right[kp], information)
        result = optimize_pose(T_cw, obs, self.camera, self.cfg.pose_iterations, self.cfg.pose_rounds,
                               self.cfg.chi2_mono, self.cfg.chi2_stereo, self._prior)
        self._pose_sigma_t, self._pose_cov_t = result.sigma_t, result.cov_t
        return result.T_cw, corr.subset(result.inliers)
