"""The ``System`` facade: feed RGB-D frames, get poses. No file I/O here (that is the pipeline's).

    system = System(load_config("tum_fr1"))
    for frame in dataset:
        out = system.process(frame.rgb, frame.depth, frame.timestamp)   # out.T_wc is None when lost
    timestamps, poses, tracked = system.trajectory()                     # follows optimised keyframes

Wiring: extractor → dynamic filter → tracker → keyframe policy → local mapper (iSAM2). The
``frontend`` and ``backend`` packages never see each other; this module adapts one to the other.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from backend.factors import StereoCalibration
from backend.local_mapping import LocalMapper
from backend.loop_closing import LoopCloser
from backend.map_store import SlamMap
from backend.place_recognition import Vocabulary, load_vocabulary
from backend.pnp_verification import PnpParams
from backend.relocalization import Relocalizer
from frontend.dynamic import DynamicFilter
from frontend.dynamic_filter import build_dynamic_filter
from frontend.keyframe_policy import KeyframeEvidence, close_point_counts, need_keyframe
from frontend.orb_extractor import OrbExtractor
from frontend.static_refill import refill_static
from frontend.tracker import Tracker, TrackingResult, TrackingState
from slam.core.camera import PinholeCamera
from slam.core.config import SlamConfig
from slam.core.frame import FeatureFrame, MapPoints
from slam.core.geometry import invert, pose_distance
from slam.runtime.frame_log import FrameLog
from slam.runtime.graph_process import GraphProcess, GraphSpec
from slam.runtime.inputs import check_inputs, clean_depth
from slam.core.timing import ModuleTimer


@dataclass
class FrameOutput:
    index: int
    timestamp: float
    state: TrackingState
    T_wc: Optional[np.ndarray]
    is_keyframe: bool
    n_features: int
    n_tracked: int
    # How far the pose's inliers let its position slide along the weakest direction (1 sigma, metres);
    # NaN where tracking did not estimate one (lost, the first frame). Beyond tracking.max_pose_sigma_m
    # the frame is LOST.
    pose_sigma_m: float = float("nan")


class _MapView:
    """Adapts the back end's map to the tracker's LocalMapSource protocol."""

    def __init__(self, mapper: LocalMapper, n_keyframes: int, n_covisible: int):
        self._mapper, self._n_kf, self._n_cov = mapper, n_keyframes, n_covisible

    def local_points(self, seed_landmarks: np.ndarray) -> MapPoints:
        return self._mapper.local_points(seed_landmarks, self._n_kf, self._n_cov)

    def landmark_points(self, ids: np.ndarray) -> MapPoints:
        return self._mapper.map.map_points(ids)


class _WholeMapView(_MapView):
    """Relocalisation source for localisation-only mode: every good landmark of the map, whatever
    the seeds (brute-force descriptor matching + PnP-RANSAC against the whole map)."""

    def __init__(self, mapper: LocalMapper):
        super().__init__(mapper, 0, 0)

    def local_points(self, seed_landmarks: np.ndarray) -> MapPoints:
        return self._mapper.map.map_points(np.arange(len(self._mapper.map.landmarks)))


def _graph_process(config: SlamConfig, camera: PinholeCamera) -> GraphProcess:
    calibration = StereoCalibration(camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
    return GraphProcess(GraphSpec(config.backend, calibration), realtime=config.runtime.realtime is True)


class System:
    def __init__(self, config: SlamConfig, dynamic_filter: Optional[DynamicFilter] = None, sequence_name: str = "",
                 detector=None, prior_map: Optional[SlamMap] = None, localization_only: bool = False,
                 vocabulary: Optional[Vocabulary] = None, prior_words: Optional[dict] = None):
        """``prior_map`` with ``localization_only=True``: track against a saved map that stays fixed
        (no graph updates, keyframes, landmark creation or culling, no statistics written to it).
        ``vocabulary``: place-recognition words (default: ``loop.vocabulary`` or the shipped one);
        ``prior_words``: {keyframe id: BowVector} of the prior map, as saved with it."""
        if localization_only != (prior_map is not None):
            raise ValueError("prior_map and localization_only go together (extending a loaded map is not supported)")
        self.config = config
        self.localization_only = localization_only
        self.camera = PinholeCamera.from_config(config.camera)
        self.extractor = OrbExtractor(config.orb, self.camera)
        self.timer = ModuleTimer()
        self.dynamic_filter = dynamic_filter or build_dynamic_filter(config, self.camera, self.timer, sequence_name,
                                                                     detector)
        self.tracker = Tracker(config.tracking, self.camera)
        # A worker process only where the graph will be solved: a fixed prior map is only read.
        graph = _graph_process(config, self.camera) if config.backend.worker_process and not localization_only else None
        # Realtime (runtime.realtime; None counts as off here: the pipeline decides it for live sources):
        # the worker's results are taken whenever they arrive, also between keyframes.
        self.realtime = config.runtime.realtime is True
        self._polled_graph = graph if graph is not None and self.realtime else None
        self.mapper = LocalMapper(config.backend, config.keyframes, self.camera, config.tracking.dynamic_threshold,
                                  graph)
        if prior_map is not None:
            self.mapper.map = prior_map
        self._map_view = _MapView(self.mapper, config.tracking.local_keyframes, config.tracking.covisible_per_keyframe)
        self._whole_map_view = _WholeMapView(self.mapper) if localization_only else None
        self._frames = FrameLog()
        self._last_keyframe_frame = -1
        self._reference_kf = -1
        self.last_frame: Optional[FeatureFrame] = None   # features (with dynamic_prob) of the last frame
        self._closed = False
        self._build_place_recognition(vocabulary, prior_words or {})
        cv2.setRNGSeed(config.seed)  # PnP-RANSAC draws from OpenCV's global generator

    def _build_place_recognition(self, vocabulary: Optional[Vocabulary], prior_words: dict) -> None:
        """Loop closer (owns the keyframe index) and relocalizer (queries it). A prior map's keyframes
        are indexed up front so a localisation run can relocalise anywhere in it."""
        cfg, threshold = self.config.loop, self.config.tracking.dynamic_threshold
        vocabulary = vocabulary or load_vocabulary(cfg.vocabulary or None)
        self.loop_closer = LoopCloser(cfg, self.mapper, vocabulary, threshold, self.config.seed)
        params = PnpParams(min_inliers=cfg.reloc_min_inliers, reprojection_error=cfg.reprojection_error,
                           depth_tolerance=cfg.depth_tolerance, seed=self.config.seed)
        self.relocalizer = Relocalizer(self.loop_closer.index, self.camera, params, cfg.reloc_candidates, threshold,
                                       cfg.min_covisible_shared)
        for kf in self.mapper.map.keyframes:
            if kf.id in prior_words:
                self.loop_closer.index.add_bow(kf.id, prior_words[kf.id])
            else:
                self.loop_closer.detector.index_keyframe(self.mapper.map, kf.id)
        self.loop_times_ms: list[float] = []    # per keyframe
        self.reloc_times_ms: list[float] = []   # per relocalization attempt

    # --- public -----------------------------------------------------------------------------------
    def process(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float, index: Optional[int] = None) -> FrameOutput:
        check_inputs(rgb, depth, timestamp, self.camera.width, self.camera.height)
        index = len(self._frames) if index is None else index
        depth = clean_depth(depth)   # NaN / inf / negative (float depth's "no measurement") -> 0 = invalid
        self._apply_arrived_results()   # before anything uses the predicted pose
        with self.timer.measure("extract"):
            gray = rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_BGR2GRAY)
        predicted_T_cw, last_T_cw = self.tracker.predicted_T_cw(), self.tracker.last_T_cw
        # The image-only dynamic work (detector, cpr) runs on threads while the features are extracted.
        self.dynamic_filter.begin_frame(rgb, gray, depth, timestamp, predicted_T_cw, last_T_cw)
        with self.timer.measure("extract"):
            frame = self.extractor.extract(gray, depth, index, timestamp)
        with self.timer.measure("dynamic"):
            probs = self.dynamic_filter.process(frame, rgb, gray, depth, predicted_T_cw, last_T_cw)
            frame.dynamic_prob = np.clip(np.nan_to_num(probs, nan=0.0), 0.0, 1.0)
            frame = self._refill_static(frame, gray, depth)
        self.last_frame = frame
        self._last_rgb = rgb
        if self.localization_only:
            output = self._localize(frame)
        elif self.tracker.state == TrackingState.NOT_INITIALIZED:
            output = self._initialize(frame)
        else:
            output = self._track(frame)
        with self.timer.measure("dynamic"):
            self.dynamic_filter.end_frame(None if output.T_wc is None else invert(output.T_wc), output.is_keyframe)
        self.timer.end_frame()
        return output

    def _apply_arrived_results(self) -> None:
        """Realtime: a graph result that arrived since the last frame goes into the map now, and tracking
        continues from the last frame's pose on its (moved) reference keyframe, as after a keyframe's
        update. Costs one pipe poll when nothing arrived; a no-op in dataset mode."""
        if self._polled_graph is None or not self._polled_graph.poll():
            return
        with self.timer.measure("backend"):
            self.mapper.refresh_from_graph()
        if len(self._frames) and self._reference_kf >= 0 and np.isfinite(self._frames.last_T_kf_c).all():
            self.tracker.rebase(invert(self.mapper.map.kf_T_wc[self._reference_kf] @ self._frames.last_T_kf_c))

    def _refill_static(self, frame: FeatureFrame, gray: np.ndarray, depth: np.ndarray) -> FeatureFrame:
        """frontend.static_refill, where new features could become landmarks (outside person boxes
        and masks); the fused mask is only computed when static features run short."""
        tracking = self.config.tracking
        if np.sum(frame.dynamic_prob < tracking.dynamic_threshold) >= tracking.min_static_features:
            return frame
        admissible = min(tracking.dynamic_threshold, self.config.backend.landmark_max_dynamic_prob)
        return refill_static(frame, gray, depth, self.dynamic_filter.last_mask, self.extractor,
                             tracking.dynamic_threshold, tracking.min_static_features, admissible)

    def _keypoint_colors(self, frame: FeatureFrame) -> np.ndarray:
        """BGR colour under each keypoint (grey images give grey colours), for coloured map exports."""
        rgb = self._last_rgb
        h, w = rgb.shape[:2]
        u = np.clip(np.round(frame.uv_raw[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.round(frame.uv_raw[:, 1]).astype(int), 0, h - 1)
        px = rgb[v, u]
        return (np.repeat(px[:, None], 3, axis=1) if rgb.ndim == 2 else px[:, :3]).astype(np.uint8)

    @property
    def last_dynamic_mask(self) -> Optional[np.ndarray]:
        """HxW float dynamic probability per pixel of the last frame (None with dynamic handling off)."""
        return self.dynamic_filter.last_mask

    def place_recognition_report(self) -> tuple[list[dict], dict]:
        """(loops with their keyframes' timestamps, counts and ms per keyframe / per relocalization)."""
        stamps = [k.timestamp for k in self.mapper.map.keyframes]
        loops = [{**e.to_dict(), "query_t": stamps[e.query_kf], "match_t": stamps[e.match_kf]}
                 for e in self.loop_closer.loops]

        def stats(ms: list[float]) -> dict:
            return {"count": len(ms), "median_ms": float(np.median(ms)) if ms else 0.0,
                    "mean_ms": float(np.mean(ms)) if ms else 0.0, "max_ms": float(np.max(ms)) if ms else 0.0}

        counts = {"loops_added": len(loops), "loops_active": len(self.loop_closer.active_loops()),
                  "loop_per_keyframe": stats(self.loop_times_ms),
                  "relocalization_attempts": self.relocalizer.attempts,
                  "relocalization_successes": self.relocalizer.successes,
                  "relocalization_per_attempt": stats(self.reloc_times_ms)}
        return loops, counts

    def save_map(self, path) -> None:
        """Write the map with its keyframe index, vocabulary and loops (``backend.map_io``), atomically."""
        from backend.map_io import camera_info_from_config, save_map

        save_map(path, self.mapper.map, camera_info_from_config(self.config.camera), self.config.to_yaml(),
                 self.loop_closer.index, self.loop_closer.loops)

    def close(self) -> None:
        """End of the run: the graph's last updates (and the final global adjustment if configured) are
        applied to the map before anything reads it, the mapping worker stops, and the components release
        what they hold open (e.g. save the detection cache). Safe to call twice."""
        try:
            if not self.localization_only and not self._closed:
                self._closed = True
                self.mapper.finish(self.config.backend.final_global_ba)
        finally:
            self.dynamic_filter.close()

    @property
    def num_keyframes(self) -> int:
        return self.mapper.map.num_keyframes

    @property
    def num_landmarks(self) -> int:
        return int((~self.mapper.map.landmarks.bad).sum())

    def trajectory(self, smoothed: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(timestamps (N,), T_wc (N,4,4), tracked (N,) bool) for every processed frame.

        Each tracked frame's pose is its reference keyframe's optimised pose composed with the
        frame's pose relative to it, the positions smoothed with the motion model of
        ``backend.smoothing_sigma_acc`` (slam/runtime/trajectory_smoother.py) unless ``smoothed`` is False
        (a live view that asks every frame: one solve costs ~15 ms per 1,000 frames); untracked frames hold
        NaN poses.
        """
        sigma_acc = self.config.backend.smoothing_sigma_acc if smoothed else 0.0
        return self._frames.trajectory(self.mapper.map.kf_T_wc, sigma_acc)

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        kfs = self.mapper.map.keyframes
        return np.array([k.timestamp for k in kfs]), self.mapper.map.kf_T_wc.copy()

    # --- steps ------------------------------------------------------------------------------------
    def _initialize(self, frame: FeatureFrame) -> FrameOutput:
        static = frame.dynamic_prob < self.config.tracking.dynamic_threshold
        if int((frame.has_depth & static).sum()) < self.config.tracking.min_init_features:
            self._frames.add_lost(frame.timestamp)
            return FrameOutput(frame.index, frame.timestamp, TrackingState.NOT_INITIALIZED, None, False, len(frame), 0)
        T_wc = np.eye(4)
        with self.timer.measure("backend"):
            self.mapper.insert_keyframe(frame, T_wc, np.full(len(frame), -1, np.int64), self._keypoint_colors(frame))
        kf = self.mapper.map.keyframes[0]
        self.tracker.initialize(frame, invert(T_wc), kf.landmark_of_keypoint)
        self._reference_kf, self._last_keyframe_frame = 0, len(self._frames)
        self._frames.add(frame.timestamp, 0, np.eye(4))
        self._close_loops(0)   # indexes the first keyframe
        return FrameOutput(frame.index, frame.timestamp, TrackingState.OK, T_wc, True, len(frame), len(frame))

    def _relocalize(self, frame: FeatureFrame, source) -> Optional[TrackingResult]:
        """BoW relocalization of a lost frame; None when disabled or no candidate verifies."""
        if not self.config.loop.relocalization:
            return None
        with self.timer.measure("relocalization"):
            start = time.perf_counter()
            found = self.relocalizer.relocalize(self.mapper.map, frame)
            result = None
            if found is not None:
                points = self.mapper.map.map_points(found.landmark_ids)
                result = self.tracker.resume(frame, source, invert(found.T_wc), found.feature_idx, points)
            self.reloc_times_ms.append((time.perf_counter() - start) * 1e3)
        return result if result is not None and result.state == TrackingState.OK else None

    def _track(self, frame: FeatureFrame) -> FrameOutput:
        result = self._relocalize(frame, self._map_view) if self.tracker.state == TrackingState.LOST else None
        if result is None:
            with self.timer.measure("tracking"):
                result = self.tracker.track(frame, self._map_view)
        if result.state != TrackingState.OK:
            self._frames.add_lost(frame.timestamp)
            return FrameOutput(frame.index, frame.timestamp, result.state, None, False, len(frame), 0)
        T_wc = invert(result.T_cw)
        tracked_ids = result.landmark_of_keypoint[result.landmark_of_keypoint >= 0]
        with self.timer.measure("mapping"):
            self.mapper.record_tracking(result.visible_landmarks, tracked_ids)
            self.mapper.record_dynamic_evidence(result.dynamic_landmarks, result.dynamic_probs)
            self._reference_kf = self.mapper.reference_keyframe(tracked_ids)
            is_keyframe = self._decide_keyframe(frame, T_wc, result.landmark_of_keypoint, len(tracked_ids))
        if is_keyframe:
            T_wc = self._add_keyframe(frame, T_wc, result.landmark_of_keypoint)
        T_kf_c = invert(self.mapper.map.kf_T_wc[self._reference_kf]) @ T_wc
        self._frames.add(frame.timestamp, self._reference_kf, T_kf_c, result.position_cov_w)
        return FrameOutput(frame.index, frame.timestamp, TrackingState.OK, T_wc, is_keyframe, len(frame), len(tracked_ids),
                           float(result.pose_sigma_t))

    def _add_keyframe(self, frame: FeatureFrame, T_wc: np.ndarray, landmark_of_keypoint: np.ndarray) -> np.ndarray:
        """Insert the keyframe, look for a loop, then one graph update for both (one hand-over to the
        worker per keyframe; tracking waits only when a loop changed). Returns the frame's pose: the
        keyframe's estimate, which a result applied in the update may have moved (a loop correction);
        tracking continues from it."""
        with self.timer.measure("backend"):
            insertion = self.mapper.insert_keyframe(frame, T_wc, landmark_of_keypoint, self._keypoint_colors(frame),
                                                    solve=False)
        kf_id = insertion.kf_id
        self.tracker.adopt_keyframe_landmarks(self.mapper.map.keyframes[kf_id].landmark_of_keypoint)
        self._reference_kf, self._last_keyframe_frame = kf_id, len(self._frames)
        self._close_loops(kf_id, optimize=False)
        loop_changed = self.loop_closer.take_pending_optimization()
        with self.timer.measure("backend"):
            self.mapper.solve(relinearize=loop_changed,
                              extra_updates=self.config.loop.extra_updates if loop_changed else None)
            if loop_changed and not self.realtime:
                # The keyframe that closes (or drops) a loop waits for its correction, as ORB-SLAM's
                # tracking waits on the map-update lock while a loop is corrected: every later pose,
                # landmark and loop check builds on the corrected map (measured on the drift room of
                # tests/test_loop_closing.py: ATE 0.0192 m with the wait, 0.0257 m without). Realtime
                # never waits: the correction reaches tracking when it arrives.
                self.mapper.sync()
        T_wc = self.mapper.map.kf_T_wc[kf_id].copy()
        self.tracker.rebase(invert(T_wc))
        return T_wc

    def _close_loops(self, kf_id: int, optimize: bool = True) -> None:
        """Loop detection/closing for a new keyframe (``optimize=False``: its graph update is left to
        the caller)."""
        with self.timer.measure("loop"):
            start = time.perf_counter()
            self.loop_closer.process_keyframe(kf_id, optimize)
            self.loop_times_ms.append((time.perf_counter() - start) * 1e3)

    def _localize(self, frame: FeatureFrame) -> FrameOutput:
        """Localisation-only: relocalise against the whole map at the start and after LOST, else
        track against the local map; the map is only read. The pose is stored relative to the
        (fixed) reference keyframe, which is the same as storing the absolute pose."""
        relocalize = self.tracker.state != TrackingState.OK
        result = self._relocalize(frame, self._map_view) if relocalize else None
        if result is None:
            source = self._whole_map_view if relocalize else self._map_view
            with self.timer.measure("tracking"):
                result = self.tracker.track(frame, source)
        if result.state != TrackingState.OK:
            self._frames.add_lost(frame.timestamp)
            return FrameOutput(frame.index, frame.timestamp, result.state, None, False, len(frame), 0)
        T_wc = invert(result.T_cw)
        tracked_ids = result.landmark_of_keypoint[result.landmark_of_keypoint >= 0]
        self._reference_kf = self.mapper.reference_keyframe(tracked_ids)
        T_kf_c = invert(self.mapper.map.kf_T_wc[self._reference_kf]) @ T_wc
        self._frames.add(frame.timestamp, self._reference_kf, T_kf_c, result.position_cov_w)
        return FrameOutput(frame.index, frame.timestamp, TrackingState.OK, T_wc, False, len(frame), len(tracked_ids),
                           float(result.pose_sigma_t))

    def _decide_keyframe(self, frame: FeatureFrame, T_wc: np.ndarray, lm_of_kp: np.ndarray, n_tracked: int) -> bool:
        ref = self.mapper.map.keyframes[self._reference_kf]
        ref_ids = ref.landmark_of_keypoint[ref.landmark_of_keypoint >= 0]
        lm = self.mapper.map.landmarks
        # Like ORB-SLAM's TrackedMapPoints(nMinObs): only landmarks confirmed by a second keyframe.
        ref_count = int(((~lm.bad[ref_ids]) & (lm.n_obs[ref_ids] >= 2)).sum())
        tracked_close, untracked_close = close_point_counts(frame, lm_of_kp, self.camera.close_depth,
                                                            self.config.tracking.dynamic_threshold)
        evidence = KeyframeEvidence(len(self._frames) - self._last_keyframe_frame, n_tracked, ref_count,
                                    tracked_close, untracked_close,
                                    *pose_distance(self.mapper.map.kf_T_wc[-1], T_wc))
        return need_keyframe(self.config.keyframes, evidence)
