"""Local mapping on the iSAM2 graph: keyframe insertion, landmark creation and culling.

Replaces ORB-SLAM2's LocalMapping thread with one synchronous call per keyframe:
1. the keyframe becomes a pose variable, tied to the previous keyframe by a loose odometry factor so
   the system stays well-posed whatever the landmarks do;
2. each tracked landmark gains an observation; landmarks seen by a second keyframe are promoted
   into the graph with all their observations (virtual stereo factors, Huber, depth-aware noise,
   noise inflated by the feature's dynamic probability);
3. new anchored landmarks are created from the keyframe's unmatched close depth features;
4. iSAM2 updates, estimates flow back into the map;
5. landmarks that are rarely found when visible, never re-observed, or persistently dynamic are culled.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from backend.factors import BackendParams, StereoCalibration
from backend.graph import FactorGraphBackend
from backend.graph_protocol import GraphBackend
from backend.window_graph import LocalWindowBackend, WindowParams
from backend.map_store import SlamMap
from slam.core.camera import PinholeCamera
from slam.core.config import BackendConfig, KeyframeConfig
from slam.core.frame import FeatureFrame, MapPoints
from slam.core.geometry import invert


@dataclass
class KeyframeInsertion:
    kf_id: int
    new_landmarks: int
    promoted_landmarks: int
    culled_landmarks: int


def build_graph(cfg: BackendConfig, calibration: StereoCalibration) -> GraphBackend:
    """The graph back end the config names (``backend.optimizer``)."""
    params = BackendParams.from_config(cfg)
    if cfg.optimizer == "isam2":
        return FactorGraphBackend(params, calibration)
    return LocalWindowBackend(params, calibration, WindowParams.from_config(cfg))


class LocalMapper:
    def __init__(self, cfg: BackendConfig, kf_cfg: KeyframeConfig, camera: PinholeCamera,
                 dynamic_threshold: float = 0.5, graph: GraphBackend | None = None):
        """``graph``: the graph to drive (default: the one ``cfg.optimizer`` names, in this process)."""
        self.cfg = cfg
        self.kf_cfg = kf_cfg
        self.camera = camera
        self.dynamic_threshold = dynamic_threshold
        self.map = SlamMap()
        calibration = StereoCalibration(camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
        self.graph: GraphBackend = graph if graph is not None else build_graph(cfg, calibration)

    def insert_keyframe(self, frame: FeatureFrame, T_wc: np.ndarray, landmark_of_keypoint: np.ndarray,
                        colors: np.ndarray | None = None, solve: bool = True) -> KeyframeInsertion:
        """``colors``: (N,3) uint8 BGR of each keypoint, stored with the landmarks it creates.
        ``solve=False`` leaves the graph update to a later ``solve()`` (so loop closing can add to the
        same update: one hand-over to a worker process per keyframe); culling then happens there too."""
        lm_of_kp = landmark_of_keypoint.copy()
        kf_id = self.map.add_keyframe(frame, T_wc, lm_of_kp)
        self.graph.add_keyframe(kf_id, T_wc)
        if kf_id > 0:
            T_prev = self.map.kf_T_wc[kf_id - 1]
            self.graph.add_relative_pose(kf_id - 1, kf_id, invert(T_prev) @ T_wc, self.cfg.odometry_sigma_t,
                                         self.cfg.odometry_sigma_r_deg, kernel="huber")
        promoted = self._add_observations(kf_id, frame, lm_of_kp)
        created = self._create_landmarks(kf_id, frame, T_wc, lm_of_kp, colors)
        self.map.keyframes[kf_id].landmark_of_keypoint = lm_of_kp
        self.map.update_covisibility(kf_id)
        culled = self.solve() if solve else 0
        return KeyframeInsertion(kf_id, created, promoted, culled)

    def solve(self, relinearize: bool = False, extra_updates: int | None = None) -> int:
        """Update the graph (``relinearize`` after a loop changed), take its estimates, cull landmarks;
        returns how many were culled."""
        self.graph.update(extra_updates=extra_updates, relinearize=relinearize)
        if not self.graph.holding_back:   # a worker's loop correction not due yet: nothing new to take up
            self._pull_estimates()
        return self._cull_landmarks(self.map.num_keyframes - 1)

    def record_tracking(self, visible_ids: np.ndarray, found_ids: np.ndarray) -> None:
        """Frame statistics for culling: landmarks in view, and landmarks matched as inliers."""
        lm = self.map.landmarks
        np.add.at(lm.visible, visible_ids[(visible_ids >= 0) & (visible_ids < len(lm))], 1)
        np.add.at(lm.found, found_ids[(found_ids >= 0) & (found_ids < len(lm))], 1)

    def record_dynamic_evidence(self, landmark_ids: np.ndarray, probs: np.ndarray) -> None:
        """Landmarks matched to features judged dynamic: the evidence stays with the landmark
        across frames, and a landmark that is persistently dynamic is culled."""
        lm = self.map.landmarks
        ok = (landmark_ids >= 0) & (landmark_ids < len(lm))
        np.add.at(lm.dynamic_sum, landmark_ids[ok], probs[ok])
        np.add.at(lm.dynamic_hits, landmark_ids[ok], 1)

    # --- observations and promotion ----------------------------------------------------------------
    def _add_observations(self, kf_id: int, frame: FeatureFrame, lm_of_kp: np.ndarray) -> int:
        kp = np.flatnonzero(lm_of_kp >= 0)
        lm_ids = lm_of_kp[kp]
        lm = self.map.landmarks
        ok = ~lm.bad[lm_ids]
        kp, lm_ids = kp[ok], lm_ids[ok]
        lm_of_kp[np.flatnonzero(lm_of_kp >= 0)[~ok]] = -1
        rows = self.record_observations(kf_id, frame, kp, lm_ids)
        in_graph = lm.in_graph[lm_ids]
        self.add_factors(rows[in_graph])
        self.promote_landmarks(lm_ids[~in_graph])
        return int((~in_graph).sum())

    def record_observations(self, kf_id: int, frame: FeatureFrame, kp: np.ndarray, lm_ids: np.ndarray) -> np.ndarray:
        depth = np.where(frame.has_depth[kp], frame.depths[kp], 0.0)
        rows = self.map.observations.append(
            kf=np.full(len(kp), kf_id), lm=lm_ids, kp=kp, uv=frame.uv[kp], depth=depth,
            level_scale=frame.level_scale[kp], dynamic_prob=frame.dynamic_prob[kp], in_graph=np.zeros(len(kp), bool),
            factor=np.full(len(kp), -1, np.int64))
        lm = self.map.landmarks
        np.add.at(lm.n_obs, lm_ids, 1)
        np.add.at(lm.dynamic_sum, lm_ids, frame.dynamic_prob[kp])
        return rows

    def add_factors(self, rows: np.ndarray) -> None:
        """Observation rows become graph factors (their landmarks must be graph variables)."""
        obs = self.map.observations
        # The columns once (each attribute is a fresh view) and as Python numbers: ~300 rows per keyframe.
        kf, lm, uv = obs.kf[rows].tolist(), obs.lm[rows].tolist(), obs.uv[rows].tolist()
        depth, scale, dyn = obs.depth[rows].tolist(), obs.level_scale[rows].tolist(), obs.dynamic_prob[rows].tolist()
        add = self.graph.add_observation
        obs.factor[rows] = [add(kf[i], lm[i], uv[i], depth[i], scale[i], dyn[i]) for i in range(len(kf))]
        obs.in_graph[rows] = True

    # --- creation ----------------------------------------------------------------------------------
    def _create_landmarks(self, kf_id: int, frame: FeatureFrame, T_wc: np.ndarray, lm_of_kp: np.ndarray,
                          colors: np.ndarray | None = None) -> int:
        """New anchored landmarks from unmatched static features with depth, closest first."""
        admissible = frame.dynamic_prob < min(self.dynamic_threshold, self.cfg.landmark_max_dynamic_prob)
        candidates = np.flatnonzero((lm_of_kp < 0) & frame.has_depth & admissible)
        candidates = candidates[np.argsort(frame.depths[candidates], kind="stable")]
        close = frame.depths[candidates] < self.camera.close_depth
        n_take = max(int(close.sum()), min(self.kf_cfg.min_new_landmarks, len(candidates)))
        kp = candidates[: min(n_take, self.kf_cfg.max_new_landmarks)]
        if len(kp) == 0:
            return 0
        local = self.camera.backproject(frame.uv[kp], frame.depths[kp])
        n = len(kp)
        ids = self.map.landmarks.append(
            xyz=local @ T_wc[:3, :3].T + T_wc[:3, 3], local_xyz=local, descriptors=frame.descriptors[kp],
            octave=frame.octaves[kp], anchor_kf=np.full(n, kf_id), n_obs=np.zeros(n, np.int32),
            visible=np.ones(n, np.int32), found=np.ones(n, np.int32), dynamic_sum=np.zeros(n),
            dynamic_hits=np.zeros(n, np.int32),
            bad=np.zeros(n, bool), in_graph=np.zeros(n, bool),
            color=np.zeros((n, 3), np.uint8) if colors is None else colors[kp])
        lm_of_kp[kp] = ids
        self.record_observations(kf_id, frame, kp, ids)
        return n

    # --- estimates and culling ---------------------------------------------------------------------
    def promote_landmarks(self, lm_ids: np.ndarray) -> None:
        """Anchored landmarks become graph variables, with all their recorded observations as factors."""
        lm = self.map.landmarks
        to_promote = np.unique(lm_ids[~lm.in_graph[lm_ids]])
        for lm_id in to_promote:
            self.graph.add_landmark(int(lm_id), lm.xyz[lm_id])
        lm.in_graph[to_promote] = True
        obs = self.map.observations
        rows = self.map.observation_rows(to_promote)
        self.add_factors(rows[~obs.in_graph[rows]])

    def move_rigidly(self, kf_ids: np.ndarray, correction: np.ndarray) -> None:
        """Move keyframes and the landmarks created in them by ``correction`` (a 4x4 world-frame move), in
        the map only: the graph keeps its values until its next estimates come. Landmarks created elsewhere
        stay, though these keyframes observe them: an old landmark re-observed is where the old map has it."""
        kf_ids = np.asarray(kf_ids, np.int64)
        self.map.kf_T_wc[kf_ids] = correction @ self.map.kf_T_wc[kf_ids]
        lm = self.map.landmarks
        moved = np.flatnonzero(lm.in_graph & ~lm.bad & np.isin(lm.anchor_kf, kf_ids))
        lm.xyz[moved] = lm.xyz[moved] @ correction[:3, :3].T + correction[:3, 3]
        self.map.refresh_anchored()    # the landmarks not in the graph follow their anchor keyframe

    def refresh_from_graph(self) -> None:
        """Copy the graph's current estimates into the map (after an update outside insert_keyframe)."""
        self._pull_estimates()

    def sync(self) -> None:
        """Every update sent so far applied to the map (a graph solved in another process answers one
        keyframe late in a run; for a caller that inspects or edits the settled graph mid-run)."""
        self.graph.sync()
        self._pull_estimates()

    def settle(self, global_adjustment: bool = False) -> None:
        """Every update applied (and with ``global_adjustment`` one adjustment of the whole map), estimates
        in the map: what ``finish`` leaves, with the graph's worker still running (a caller that reads the
        map a run would end with, then edits the graph on)."""
        self.graph.sync()
        if global_adjustment and self.map.num_keyframes:
            self.graph.optimize_all()
        self._pull_estimates()

    def finish(self, global_adjustment: bool = False) -> None:
        """End of a run: ``settle``, then the graph's worker (if any) stopped."""
        self.settle(global_adjustment)
        self.graph.close()

    def _pull_estimates(self) -> None:
        """The graph's estimates into the map. A graph solved in another process answers for the
        keyframes and landmarks it had when the update was sent; newer ones move rigidly with the newest
        estimated keyframe (a loop correction must carry them too, as ORB-SLAM corrects the current
        keyframe's neighbourhood). In process the graph answers for everything and nothing moves."""
        kf_ids, poses = self.graph.keyframe_poses()
        if len(kf_ids) == 0:
            return
        last = int(kf_ids[-1])
        correction = poses[-1] @ invert(self.map.kf_T_wc[last])
        self.map.kf_T_wc[kf_ids] = poses
        newer = np.arange(last + 1, self.map.num_keyframes)
        if len(newer):
            self.map.kf_T_wc[newer] = correction @ self.map.kf_T_wc[newer]
        lm_ids, xyz = self.graph.landmark_positions()
        lm = self.map.landmarks
        lm.xyz[lm_ids] = xyz
        unsolved = np.flatnonzero(lm.in_graph)
        unsolved = unsolved[~np.isin(unsolved, lm_ids, assume_unique=True)]
        if len(unsolved):
            lm.xyz[unsolved] = lm.xyz[unsolved] @ correction[:3, :3].T + correction[:3, 3]
        self.map.refresh_anchored()

    def _cull_landmarks(self, kf_id: int) -> int:
        """ORB-SLAM's MapPointCulling, plus removal of landmarks whose evidence is mostly dynamic."""
        lm = self.map.landmarks
        cfg = self.cfg
        alive = ~lm.bad
        rarely_found = lm.found < cfg.cull_found_ratio * lm.visible
        age = kf_id - lm.anchor_kf
        unconfirmed = (age >= cfg.cull_after_keyframes) & (lm.n_obs < cfg.cull_min_observations)
        # Mean dynamic probability over keyframe observations and dynamic matches while tracking.
        mean_dynamic = lm.dynamic_sum / np.maximum(lm.n_obs + lm.dynamic_hits, 1)
        dynamic = (mean_dynamic >= cfg.dynamic_removal_threshold) & (lm.n_obs + lm.dynamic_hits >= 2)
        cull = alive & (rarely_found | unconfirmed | dynamic)
        lm.bad[cull] = True
        return int(cull.sum())

    # --- queries for tracking ----------------------------------------------------------------------
    def local_points(self, seed_landmarks: np.ndarray, n_keyframes: int = 20, n_covisible: int = 10) -> MapPoints:
        """Landmarks of the keyframes that see the seeds, widened by their covisible keyframes."""
        if self.map.num_keyframes == 0:
            return MapPoints.empty()
        local_kfs = self.local_keyframes(seed_landmarks, n_keyframes, n_covisible)
        return self.map.map_points(self.map.landmarks_of_keyframes(local_kfs))

    def local_keyframes(self, seed_landmarks: np.ndarray, n_keyframes: int, n_covisible: int) -> np.ndarray:
        kfs, _ = self.map.keyframes_observing(seed_landmarks) if len(seed_landmarks) else (np.zeros(0, int), None)
        if len(kfs) == 0:
            kfs = np.arange(self.map.num_keyframes)[::-1]
        kfs = kfs[:n_keyframes]
        neighbours = [self.map.covisible_keyframes(k, self.cfg.covisibility_min_shared, n_covisible) for k in kfs[:3]]
        return np.unique(np.concatenate([kfs] + neighbours))

    def keyframes_sharing(self, landmark_ids: np.ndarray) -> np.ndarray:
        """Ids of the keyframes that observe any of the given landmarks, the one sharing most first."""
        return self.map.keyframes_observing(landmark_ids)[0]

    def reference_keyframe(self, sharing: np.ndarray) -> int:
        """The first of ``keyframes_sharing``'s answer (the latest keyframe if it is empty)."""
        return int(sharing[0]) if len(sharing) else self.map.num_keyframes - 1
