"""The ``System`` facade: feed RGB-D frames, get poses. No file I/O here (that is the pipeline's).

    system = System(load_config("tum_fr1"))
    for frame in dataset:
        out = system.process(frame.rgb, frame.depth, frame.timestamp)   # out.T_wc is None when lost
    timestamps, poses, tracked = system.trajectory()                     # follows optimised keyframes

Wiring: extractor → dynamic filter → ``TrackingLoop`` (tracker, keyframe policy, relocalisation, loop
triggering; slam/runtime/tracking_loop.py) → local mapper (iSAM2 windows in the worker process). The
``frontend`` and ``backend`` packages never see each other; the runtime adapts one to the other.
"""
from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np

from backend.factors import StereoCalibration
from backend.local_mapping import LocalMapper
from backend.loop_closing import LoopCloser
from backend.map_store import SlamMap
from backend.place_recognition import Vocabulary, load_vocabulary
from backend.pnp_verification import PnpParams
from backend.relocalization import Relocalizer
from frontend.dynamic import DynamicFilter, RevisedMask
from frontend.dynamic.base import Detector
from frontend.dynamic_filter import build_dynamic_filter
from frontend.orb_extractor import OrbExtractor
from frontend.static_refill import refill_static
from slam.core.camera import PinholeCamera
from slam.core.config import SlamConfig
from slam.core.frame import FeatureFrame
from slam.core.geometry import invert
from slam.core.kernel_compile import watch_kernel_compilation
from slam.core.timing import ModuleTimer
from slam.runtime.graph_process import GraphProcess, GraphSpec
from slam.runtime.inputs import InputError, check_inputs, clean_depth, to_gray
from slam.runtime.lookahead import FrameLookahead, UpcomingFrame
from slam.runtime.tracking_loop import FrameOutput, TrackingLoop

__all__ = ["FrameOutput", "System", "UpcomingFrame"]


def _graph_process(config: SlamConfig, camera: PinholeCamera) -> GraphProcess:
    calibration = StereoCalibration(camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
    return GraphProcess(GraphSpec(config.backend, calibration), realtime=config.runtime.realtime is True)


class System:
    def __init__(self, config: SlamConfig, dynamic_filter: Optional[DynamicFilter] = None, sequence_name: str = "",
                 detector: Optional[Detector] = None, prior_map: Optional[SlamMap] = None,
                 localization_only: bool = False,
                 vocabulary: Optional[Vocabulary] = None, prior_words: Optional[dict] = None):
        """``detector``: boxes from elsewhere instead of the configured ONNX model, anything with
        ``detect(bgr, timestamp) -> list[Detection]``, ``save()`` and ``close()`` (``frontend.Detector``;
        inherit ``frontend.DetectorDefaults`` for the last two when there is nothing to keep).
        ``prior_map`` with ``localization_only=True``: track against a saved map that stays fixed
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
        watch_kernel_compilation()   # the first run after an install compiles the kernels: say so, time it
        self._lookahead = FrameLookahead(config.orb, self.camera, self.timer)
        self.dynamic_filter = dynamic_filter or build_dynamic_filter(config, self.camera, self.timer, sequence_name,
                                                                     detector)
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
        self.last_frame: Optional[FeatureFrame] = None   # features (with dynamic_prob) of the last frame
        self._closed = False
        self._build_place_recognition(vocabulary, prior_words or {})
        self.tracking = TrackingLoop(config, self.camera, self.mapper, self.loop_closer, self.relocalizer, self.timer,
                                     self.realtime, localization_only)
        # This thread's OpenCV generator, for any OpenCV call that draws from it. OpenCV's RANSAC (solvePnPRansac,
        # findFundamentalMat, findHomography) does not: each call draws from a generator of its own with a fixed
        # state, so its choices are the same in every run and on every thread, whatever this seed
        # (tests/test_flow_epipolar.py::test_opencv_ransac_draws_the_same_whatever_the_rng_seed).
        cv2.setRNGSeed(config.seed)

    def _build_place_recognition(self, vocabulary: Optional[Vocabulary], prior_words: dict) -> None:
        """Loop closer (owns the keyframe index) and relocalizer (queries it). A prior map's keyframes
        are indexed up front so a localisation run can relocalise anywhere in it."""
        cfg, threshold = self.config.loop, self.config.tracking.dynamic_threshold
        vocabulary = vocabulary or load_vocabulary(cfg.vocabulary or None)
        backend = self.config.backend
        # A loop's correction that arrives keyframes later (backend.loop_result_keyframes, from the worker
        # process): its query side moves in the map at once, so tracking meets one consistent map meanwhile.
        deferred = (backend.worker_process and backend.loop_result_keyframes > 0
                    and self.config.runtime.realtime is not True)
        self.loop_closer = LoopCloser(cfg, self.mapper, vocabulary, threshold, self.config.seed,
                                      correct_at_once=deferred)
        params = PnpParams(min_inliers=cfg.reloc_min_inliers, reprojection_error=cfg.reprojection_error,
                           depth_tolerance=cfg.depth_tolerance, seed=self.config.seed)
        self.relocalizer = Relocalizer(self.loop_closer.index, self.camera, params, cfg.reloc_candidates, threshold,
                                       cfg.min_covisible_shared)
        for kf in self.mapper.map.keyframes:
            if kf.id in prior_words:
                self.loop_closer.index.add_bow(kf.id, prior_words[kf.id])
            else:
                self.loop_closer.detector.index_keyframe(self.mapper.map, kf.id)

    # --- public -----------------------------------------------------------------------------------
    def process(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float, index: Optional[int] = None,
                upcoming: Optional[UpcomingFrame] = None) -> FrameOutput:
        """Track one frame. ``upcoming``: the frame the next call will get, if known (a dataset); its
        features and detections then run on threads while this frame is tracked
        (slam/runtime/lookahead.py). The result is the same bits as without it."""
        index = len(self.tracking.frames) if index is None else index
        begun = self._lookahead.take(timestamp, index)
        if begun is None or not begun.checked(rgb, depth):   # a frame begun ahead was checked then
            try:
                check_inputs(rgb, depth, timestamp, self.camera.width, self.camera.height)
            except InputError:
                if begun is not None:
                    begun.features.exception()   # its work ends before the error leaves
                raise
        if begun is not None:
            rgb, depth = begun.rgb, begun.depth
        else:
            depth = clean_depth(depth)   # NaN / inf / negative (float depth's "no measurement") -> 0 = invalid
        self._apply_arrived_results()   # before anything uses the predicted pose
        tracker = self.tracking.tracker
        predicted_T_cw, last_T_cw = tracker.predicted_T_cw(), tracker.last_T_cw
        if begun is None:
            with self.timer.measure("extract"):
                gray = to_gray(rgb)
        else:
            gray = begun.gray
        # The image-only dynamic work (detector, cpr) runs on threads while the features are extracted
        # (the detector of a frame begun ahead already runs).
        self.dynamic_filter.begin_frame(rgb, gray, depth, timestamp, predicted_T_cw, last_T_cw)
        if upcoming is not None and not self.realtime:
            # Begun after this frame's own work, so every thread takes the frames in order.
            self._lookahead.begin(upcoming, self.dynamic_filter)
        with self.timer.measure("extract"):
            frame = begun.features.result() if begun is not None else self.extractor.extract(gray, depth, index,
                                                                                               timestamp)
        with self.timer.measure("dynamic"):
            probs = self.dynamic_filter.process(frame, rgb, gray, depth, predicted_T_cw, last_T_cw)
            frame.dynamic_prob = np.clip(np.nan_to_num(probs, nan=0.0), 0.0, 1.0)
            frame = self._refill_static(frame, gray, depth)
        self.last_frame = frame
        output = self.tracking.step(frame, rgb)
        with self.timer.measure("dynamic"):
            self.dynamic_filter.end_frame(None if output.T_wc is None else invert(output.T_wc), output.is_keyframe)
        self.timer.end_frame()
        return output

    def _apply_arrived_results(self) -> None:
        """Realtime: a graph result that arrived since the last frame goes into the map now, and tracking
        continues from the last frame's pose on its (moved) reference keyframe. Costs one pipe poll when
        nothing arrived; a no-op in dataset mode."""
        if self._polled_graph is None or not self._polled_graph.poll():
            return
        with self.timer.measure("backend"):
            self.mapper.refresh_from_graph()
        self.tracking.rebase_on_refreshed_map()

    def _refill_static(self, frame: FeatureFrame, gray: np.ndarray, depth: np.ndarray) -> FeatureFrame:
        """frontend.static_refill, where new features could become landmarks (outside person boxes
        and masks); the fused mask is only computed when static features run short."""
        tracking = self.config.tracking
        if np.sum(frame.dynamic_prob < tracking.dynamic_threshold) >= tracking.min_static_features:
            return frame
        admissible = min(tracking.dynamic_threshold, self.config.backend.landmark_max_dynamic_prob)
        return refill_static(frame, gray, depth, self.dynamic_filter.last_mask, self.extractor,
                             tracking.dynamic_threshold, tracking.min_static_features, admissible)

    @property
    def last_dynamic_mask(self) -> Optional[np.ndarray]:
        """HxW float dynamic probability per pixel of the last frame (None with dynamic handling off)."""
        return self.dynamic_filter.last_mask

    @property
    def last_still_people_mask(self) -> Optional[np.ndarray]:
        """HxW bool: the last frame's people standing still (left out of ``last_dynamic_mask``, a mask of
        moving surfaces, but never to enter a dense map); None when there are none."""
        return self.dynamic_filter.last_still_people

    @property
    def revised_keyframe_masks(self) -> Sequence[RevisedMask]:
        """Earlier keyframes whose masks the last frame changed (a person in them turned out to stand
        still; frontend/dynamic/keyframe_masks.py): outputs rewrite their ``masks/`` files."""
        return self.dynamic_filter.revised_masks

    def finish_keyframe_masks(self) -> Sequence[RevisedMask]:
        """At the end of a run (after ``close`` too): earlier keyframes whose masks change now that the
        run has ended (frontend/dynamic/keyframe_masks.py); outputs rewrite their ``masks/`` files."""
        return self.dynamic_filter.finish_masks()

    def place_recognition_report(self) -> tuple[list[dict], dict]:
        """(loops with their keyframes' timestamps, counts and ms per keyframe / per relocalization)."""
        return self.tracking.place_recognition_report()

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
                self.tracking.refine_trajectory()
        finally:
            self._lookahead.close()
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
        (a live view that asks every frame: the smoothing costs ~20 ms per 1,000 frames); untracked frames hold
        NaN poses.
        """
        sigma_acc = self.config.backend.smoothing_sigma_acc if smoothed else 0.0
        return self.tracking.frames.trajectory(self.mapper.map.kf_T_wc, sigma_acc, self.config.tracking.chi2_stereo)

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        kfs = self.mapper.map.keyframes
        return np.array([k.timestamp for k in kfs]), self.mapper.map.kf_T_wc.copy()
