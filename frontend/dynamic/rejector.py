"""Runs the detector (when a method needs it) and the enabled methods, then fuses their outputs.

Keeps per-method diagnostics: how many features each method flagged per frame, the fused count,
and per-method milliseconds (recorded in the System's timer as ``dynamic.<name>``). Optionally
dumps PNG overlays of each method's mask and the fused features, so a person can see what was
rejected.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from frontend.dynamic import DynamicStats, RevisedMask
from frontend.dynamic.base import Detector, DynamicContext, DynamicMethod, MethodOutput, keypoints_in_mask
from frontend.dynamic.box_depth_segmentation import cached_person_layer
from frontend.dynamic.box_memory import BoxMemory
from frontend.dynamic.free_space import FreeSpaceCheck
from frontend.dynamic.fusion import fuse
from frontend.dynamic.keyframe_masks import (KeyframeMaskLedger, MaskParts, compose_mask, features_off_body,
                                             recompose_with_evidence, still_region, vacated_region)
from frontend.dynamic.near_occluder import NearOccluder
from frontend.dynamic.overlay import overlay
from frontend.dynamic.region_motion import RegionCarry, RegionMotion, box_centre, confirmed_regions
from frontend.dynamic.surface_drift import FrameTracks, PersonView
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import DynamicConfig
from slam.core.frame import FeatureFrame
from slam.core.timing import ModuleTimer


_MOTION_REGION_PROB = 0.9


def _raised_in(fused: np.ndarray, region: Optional[np.ndarray], uv: np.ndarray) -> tuple[np.ndarray, int]:
    """``fused`` raised to ``_MOTION_REGION_PROB`` on the features inside ``region`` (HxW, None: none), and
    how many of them only that raise puts at 0.5 or above."""
    if region is None:
        return fused, 0
    raised = np.maximum(fused, _MOTION_REGION_PROB * keypoints_in_mask(region, uv))
    return raised, int(np.sum((raised >= 0.5) & (fused < 0.5)))


@dataclass
class _BegunFrame:
    """A frame whose image-only work (detection, the methods' prepare) runs on the threads."""

    timestamp: float
    gray: np.ndarray               # the frame's image: ``process`` finds its begun work by this object
    detection: Optional[Future]
    prepared: dict[str, Future] = field(default_factory=dict)   # method name -> its prepare on its thread
    ctx: Optional[DynamicContext] = None   # what the methods' prepare got; process completes it


class DynamicRejector:
    def __init__(self, cfg: DynamicConfig, camera: PinholeCamera, methods: list[DynamicMethod],
                 detector: Optional[Detector], timer: Optional[ModuleTimer] = None):
        self.cfg = cfg
        self.camera = camera
        self.methods = methods
        self.detector = detector
        self.timer = timer or ModuleTimer()
        self.name = "+".join(m.name for m in methods)
        self.stats = DynamicStats()
        self._weights = [getattr(cfg, m.name).weight for m in methods]
        self._last: Optional[tuple[DynamicContext, dict[str, MethodOutput]]] = None
        self._dump_dir = Path(cfg.dump_masks_dir) if cfg.dump_masks_dir else None
        self._mask_parts: Optional[MaskParts] = None
        self._fused_mask: Optional[np.ndarray] = None
        # The last frame's per-method outputs and fused probabilities, for diagnostics and evaluation.
        self.last_outputs: dict[str, MethodOutput] = {}
        self.last_fused: np.ndarray = np.zeros(0)
        self.last_keypoints: np.ndarray = np.zeros((0, 2))
        # ONNX Runtime releases the GIL: the detector runs on this thread while the features are
        # extracted. One thread, one frame ahead at most, results used in frame order: deterministic.
        self._detect_thread: Optional[ThreadPoolExecutor] = None
        # The methods' image-only work (``DynamicMethod.prepare``: cpr's whole registration) on a second
        # thread, also while the features are extracted: OpenCV's ORB releases the GIL and numpy's array
        # loops do. Same computation, same order, so the same bits; measured on Bonn crowd (extraction +
        # cpr, 150 frames): 33 -> 23 ms per frame of wall time, the same CPU time.
        # One thread per method with a prepare (cpr's registration, flow_epipolar's optical flow): they run
        # side by side while the features are extracted and the other methods run on the tracking thread.
        self._prepare_threads: dict[str, ThreadPoolExecutor] = {}
        # Begun, not yet processed, oldest first: the frame being processed and, with the System's
        # lookahead, the next one (begun while this one is tracked; each thread takes them in order).
        self._begun: deque[_BegunFrame] = deque()
        self._box_memory = BoxMemory(cfg.detector.hold_frames, set(cfg.classes.dynamic), camera.width, camera.height)
        self._region_motion = RegionMotion(cfg.still_window_s, cfg.still_max_move_m, camera)
        # A confirmed motion region is carried through thin-evidence frames as long as a lost box is held.
        self._region_carry = RegionCarry(cfg.detector.hold_frames)
        self._near_occluder = NearOccluder(camera) if cfg.near_occluders else None
        self._motion_methods = [k for k, m in enumerate(methods) if m.measures_motion]
        self._still_region: Optional[np.ndarray] = None
        self._motion_region: Optional[np.ndarray] = None
        self._still_people_mask: Optional[np.ndarray] = None
        self._people: tuple[list, np.ndarray] = ([], np.zeros(0, bool))   # the frame's person boxes, who stands
        self._keyframe_masks = KeyframeMaskLedger(cfg.still_window_s)
        self._free_space = FreeSpaceCheck(camera, tuple(cfg.mask_free_space_lags_s), cfg.mask_free_space_margin_m,
                                          cfg.mask_free_space_window_px, tuple(cfg.mask_region_lags_s),
                                          tuple(cfg.mask_clear_lags_s))
        self.people_still = 0       # people standing still in the last frame (region_motion)
        # the last frame's people: their tracks and who stood still (the run's end settles them)
        self._last_people: tuple[list, np.ndarray] = ([], np.zeros(0, bool))
        # Earlier keyframes' masks composed again after the last frame: a person in them was found
        # standing still (keyframe_masks); the run's outputs rewrite those keyframes' mask files.
        self.revised_masks: list[RevisedMask] = []
        self._last_time: Optional[float] = None

    def begin_images(self, rgb: np.ndarray, gray: np.ndarray, timestamp: float) -> None:
        """The work that needs only the image (the detector), started early: the System's lookahead calls
        this one frame ahead, while the frame before is tracked. ``begin_frame`` adds the rest."""
        detection = None
        if self.detector is not None:
            if self._detect_thread is None:
                self._detect_thread = ThreadPoolExecutor(1, thread_name_prefix="dynslam-detector")
            detection = self._detect_thread.submit(self.detector.detect, rgb, timestamp)
        self._begun.append(_BegunFrame(timestamp, gray, detection))

    def begin_frame(self, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray, timestamp: float,
                    predicted_T_cw: Optional[np.ndarray], last_T_cw: Optional[np.ndarray]) -> None:
        if not (self._begun and self._begun[-1].timestamp == timestamp and self._begun[-1].gray is gray
                and not self._begun[-1].prepared):
            self.begin_images(rgb, gray, timestamp)
        threaded = [m for m in self.methods if m.prepares]
        if threaded:
            # With the pose prediction of the frame before's tracking, as in line: the same bits.
            ctx = DynamicContext(None, rgb, gray, depth, self.camera, None, predicted_T_cw, last_T_cw)
            self._begun[-1].ctx = ctx
            for method in threaded:
                if method.name not in self._prepare_threads:
                    self._prepare_threads[method.name] = ThreadPoolExecutor(
                        1, thread_name_prefix=f"dynslam-{method.name.replace('_', '-')}")
                self._begun[-1].prepared[method.name] = self._prepare_threads[method.name].submit(
                    self._prepare, method, ctx)

    def _prepare(self, method: DynamicMethod, ctx: DynamicContext) -> None:
        with self.timer.measure(f"dynamic.{method.name}"):
            method.prepare(ctx)

    def _take_begun(self, timestamp: float, gray: np.ndarray) -> Optional[_BegunFrame]:
        """The frame's begun work; frames begun before it but never processed (their extraction failed)
        end first, so no method ever runs on two frames at once; their results are dropped. None (and
        nothing left running) when the frame was not begun."""
        while self._begun:
            begun = self._begun.popleft()
            if begun.timestamp == timestamp and begun.gray is gray:
                return begun
            self._end(begun)
        return None

    @staticmethod
    def _end(begun: _BegunFrame) -> None:
        """Wait for a dropped frame's work; its failure is not the next frame's."""
        for future in (begun.detection, *begun.prepared.values()):
            if future is not None:
                future.exception()

    def process(self, frame: FeatureFrame, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray,
                predicted_T_cw: Optional[np.ndarray], last_T_cw: Optional[np.ndarray]) -> np.ndarray:
        ctx, prepared = self._context(frame, rgb, gray, depth, predicted_T_cw, last_T_cw)
        outputs = self._run_methods(ctx, prepared)
        fused = fuse([o.prob for o in outputs.values()], self._weights, self.cfg.fusion, len(frame))
        with self.timer.measure("dynamic.standing_people"):
            self._still_region = self._standing_people(ctx, outputs.get("flow_epipolar"))
        fused, prior_mask = self._regions_and_prior(fused, outputs, ctx)
        self._last = (ctx, outputs)
        self.last_outputs, self.last_fused, self.last_keypoints = outputs, fused, frame.uv_raw
        motion_region = None if self._motion_region is None else _MOTION_REGION_PROB * self._motion_region
        self._mask_parts = MaskParts(outputs, self._weights, self._motion_methods, self.cfg.fusion, ctx.gray.shape,
                                     motion_region, prior_mask, self._person_boxes(ctx, 0), ctx.depth,
                                     ctx.person_layers)
        self._mask_parts.still_region = self._still_region
        self._mask_parts.vacated = self._vacated_boxes(ctx)
        self._fused_mask = None
        if self._dump_dir is not None:
            self._dump(ctx, outputs, fused)
        return fused

    def _context(self, frame: FeatureFrame, rgb: np.ndarray, gray: np.ndarray, depth: np.ndarray,
                 predicted_T_cw: Optional[np.ndarray],
                 last_T_cw: Optional[np.ndarray]) -> tuple[DynamicContext, dict[str, Future]]:
        """The frame's context (the one its threaded work began with, when it was begun) with its
        detections, and the futures of that threaded work by method (empty when there is none)."""
        begun = self._take_begun(frame.timestamp, gray)
        ctx = DynamicContext(frame, rgb, gray, depth, self.camera, None, predicted_T_cw, last_T_cw)
        prepared: dict[str, Future] = {}
        if begun is not None and begun.ctx is not None:
            ctx, prepared = begun.ctx, begun.prepared     # the context the methods prepared, completed
            ctx.frame = frame
        if self.detector is not None:  # built only when a method or the box prior needs it
            with self.timer.measure("dynamic.detector"):   # with begin_frame: the wait for the thread
                if begun is not None and begun.detection is not None:
                    ctx.detections = begun.detection.result()
                else:
                    ctx.detections = self.detector.detect(rgb, frame.timestamp)
                ctx.detections = self._box_memory.update(ctx.detections)
        return ctx, prepared

    def _run_methods(self, ctx: DynamicContext, prepared: dict[str, Future]) -> dict[str, MethodOutput]:
        """Every method's output, in config order. The methods without threaded work run first, while the
        threaded ones (cpr, flow_epipolar) may still run; the methods are independent, so the order changes
        no output."""
        outputs: dict[str, MethodOutput] = {}
        for method in sorted(self.methods, key=lambda m: m.prepares):
            future = prepared.get(method.name)
            if future is not None:
                with self.timer.measure("dynamic.prepare_wait"):
                    future.result()            # re-raises a method's failure here, in frame order
            with self.timer.measure(f"dynamic.{method.name}"):
                if future is None:             # not begun on its thread (or no thread): prepared in line
                    method.prepare(ctx)
                outputs[method.name] = method.process(ctx)
        outputs = {m.name: outputs[m.name] for m in self.methods}
        for name, out in outputs.items():
            self.stats.add(name, out.flagged)
        return outputs

    def _regions_and_prior(self, fused: np.ndarray, outputs: dict[str, MethodOutput],
                           ctx: DynamicContext) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """The fused probabilities raised by the detector-free motion regions and the person-box prior,
        and the prior's pixel mask; counts the frame in ``stats``."""
        frame = ctx.frame
        self._motion_region = self._confirmed_motion(outputs, frame, ctx)
        fused, found_by_motion = _raised_in(fused, self._motion_region, frame.uv_raw)
        if self._near_occluder is not None:
            # nearer than the sensor measures: a region to the keyframe masks like a confirmed motion region
            near = self._near_occluder.update(ctx.depth, ctx.gray, ctx.predicted_T_cw)
            fused, found_near = _raised_in(fused, near, frame.uv_raw)
            if near is not None:
                self._motion_region = near if self._motion_region is None else np.maximum(self._motion_region, near)
            self.stats.add("near_occluders", found_near)     # features only the near-occluder rule flagged
        prior_mask = self._box_prior_mask(ctx)
        if prior_mask is not None:
            feature_prior = keypoints_in_mask(prior_mask, frame.uv_raw)
            if self.cfg.box_prior_on_body:
                feature_prior[features_off_body(prior_mask > 0, self._person_boxes(ctx, 0), ctx.depth,
                                                ctx.person_layers, frame.uv_raw, self.cfg.box_prior_dilate_px,
                                                self.cfg.box_prior_on_body_max_fill)] = 0.0
            fused = np.maximum(fused, feature_prior)
        self.stats.frames += 1
        self.stats.add("fused", int(np.sum(fused >= 0.5)))
        if self.detector is not None and self._region_motion.enabled:
            self.stats.add("standing_people", self.people_still)   # a column of dynamic.csv
        if self.cfg.motion_region_votes > 0 and {"cpr", "flow_epipolar"} <= set(outputs):
            self.stats.add("motion_regions", found_by_motion)      # features only the region rule flagged
        return fused, prior_mask

    @property
    def last_mask(self) -> Optional[np.ndarray]:
        """The last frame's fused pixel mask of moving surfaces, computed on first use: fusing four
        full-resolution masks costs ~10 ms and is needed only when static features run short, for
        keyframes and for overlays."""
        if self._fused_mask is None and self._mask_parts is not None:
            self._fused_mask, self._still_people_mask = compose_mask(self._mask_parts)
        return self._fused_mask

    def _confirmed_motion(self, outputs: dict[str, MethodOutput], frame: FeatureFrame,
                          ctx: DynamicContext) -> Optional[np.ndarray]:
        """cpr's regions that flow_epipolar's tracks confirm (region_motion.confirmed_regions) where the
        detector sees nobody, carried through a few frames of thin evidence (RegionCarry), or None.
        Inside a (dilated) person box the box methods segment the person better; there a cpr region also
        holds the floor and wall around them, and flagging those costs tracking its static points
        (generated crowds: close_pass 3.8 -> 4.0 mm, three_close 6.0 -> 7.1)."""
        cpr, flow = outputs.get("cpr"), outputs.get("flow_epipolar")
        if self.cfg.motion_region_votes <= 0 or cpr is None or flow is None or cpr.mask is None \
                or flow.tracks is None or not len(frame):
            return None
        allowed = np.ones(ctx.gray.shape, bool)
        for x0, y0, x1, y1 in self._person_boxes(ctx, self.cfg.box_prior_dilate_px):
            allowed[y0:y1, x0:x1] = False
        candidates = (np.asarray(cpr.mask) >= 0.5) & allowed
        confirmed = confirmed_regions(candidates, flow.tracks, flow.track_moving, ctx.depth,
                                      self.cfg.motion_region_votes, self.cfg.motion_region_share)
        return self._region_carry.update(confirmed, flow.track_origins, flow.tracks, flow.track_moving, ctx.depth,
                                        allowed)

    @property
    def last_still_people(self) -> Optional[np.ndarray]:
        """HxW bool: the pixels of the last frame's people standing still that the fusion flags as a
        person (they leave ``last_mask``, a mask of moving surfaces, but must stay out of dense maps);
        None when nobody stands still."""
        _ = self.last_mask                      # computed together
        return self._still_people_mask

    def _standing_people(self, ctx: DynamicContext, flow: Optional[MethodOutput]) -> Optional[np.ndarray]:
        """HxW bool: the boxes of the people who stand still (region_motion), less every moving person's
        box (a walker in front of them keeps all the evidence); None when nobody stands still. ``flow``:
        flow_epipolar's output, whose point tracks follow each person's surface (surface_drift)."""
        self.people_still = 0
        self._people = ([], np.zeros(0, bool))
        if not self._region_motion.enabled or not ctx.detections:
            self._region_motion.classify([], ctx.predicted_T_cw, ctx.frame.timestamp)
            return None
        boxes = self._person_boxes(ctx, 0)
        centres = [box_centre(b, ctx.depth, self.camera) for b in boxes]
        views = [PersonView(b, cached_person_layer(ctx.person_layers, b, ctx.depth)) for b in boxes]
        tracks = None
        if flow is not None and flow.tracks is not None and flow.track_origins is not None \
                and len(flow.tracks) == len(flow.track_origins):
            tracks = FrameTracks(flow.track_origins, flow.tracks, ctx.depth)
        still = self._region_motion.classify(centres, ctx.predicted_T_cw, ctx.frame.timestamp, views, tracks)
        self._people = (boxes, still)
        self.people_still = int(still.sum())
        return still_region(ctx.gray.shape, boxes, still)

    def _person_boxes(self, ctx: DynamicContext, pad: int, detections: Optional[list] = None
                      ) -> list[tuple[int, int, int, int]]:
        """The dynamic-class detections (default: the frame's) as whole-pixel boxes (x0, y0, x1, y1), grown
        by ``pad`` pixels, clipped to the image, empty ones left out: the box prior, the standing-still test
        and the detector-free regions all work on these."""
        h, w = ctx.gray.shape
        boxes = [(max(int(d.x0) - pad, 0), max(int(d.y0) - pad, 0),
                  min(int(np.ceil(d.x1)) + pad, w), min(int(np.ceil(d.y1)) + pad, h))
                 for d in (ctx.detections if detections is None else detections) or ()
                 if d.class_id in self.cfg.classes.dynamic]
        return [b for b in boxes if b[2] > b[0] and b[3] > b[1]]

    def _vacated_boxes(self, ctx: DynamicContext) -> Optional[np.ndarray]:
        """keyframe_masks.vacated_region of this frame's held and fresh dynamic-class boxes."""
        carried = {id(d) for d in self._box_memory.carried}
        if not carried or not ctx.detections:
            return None
        fresh = self._person_boxes(ctx, 0, [d for d in ctx.detections if id(d) not in carried])
        held = self._person_boxes(ctx, 0, [d for d in ctx.detections if id(d) in carried])
        return vacated_region(ctx.gray.shape, fresh, held) if fresh and held else None

    def _box_prior_mask(self, ctx: DynamicContext) -> Optional[np.ndarray]:
        """``box_prior`` inside every dilated dynamic-class box (None when off or no detections)."""
        boxes = self._person_boxes(ctx, self.cfg.box_prior_dilate_px) if self.cfg.box_prior > 0 else []
        if not boxes:
            return None
        mask = np.zeros(ctx.gray.shape, np.float32)
        for x0, y0, x1, y1 in boxes:
            mask[y0:y1, x0:x1] = self.cfg.box_prior
        return mask

    def end_frame(self, T_cw: Optional[np.ndarray], is_keyframe: bool) -> None:
        if self._last is None:
            return
        ctx, outputs = self._last
        tracks = self._region_motion.commit(T_cw)
        if self._near_occluder is not None:
            self._near_occluder.end_frame(T_cw)
        grown = []
        if T_cw is not None and self._free_space.enabled:
            if is_keyframe and self._mask_parts is not None:
                key = (ctx.frame.index, ctx.frame.timestamp, self._mask_parts.keep())
                self._mask_parts.free_space = self._free_space.keyframe(key, ctx.frame.timestamp, ctx.depth, T_cw)
                self._fused_mask = None        # composed again, with the evidence, on the next read
            grown = self._free_space.remember(ctx.frame.timestamp, ctx.depth, T_cw)
        boxes, still = self._people
        keyframe = (ctx.frame.index, self._mask_parts, boxes) if is_keyframe and self._mask_parts is not None else None
        self.revised_masks = self._keyframe_masks.advance(ctx.frame.timestamp, tracks, still, keyframe,
                                                          self._region_motion.ended_still)
        self._last_people = (tracks, still)
        # Earlier keyframes that later frames showed (un)moved: composed again (keyframe_masks).
        self.revised_masks.extend(recompose_with_evidence(grown))
        self._last_time = ctx.frame.timestamp
        for method in self.methods:
            with self.timer.measure(f"dynamic.{method.name}"):
                method.end_frame(ctx, outputs[method.name], T_cw, is_keyframe)
        self._last = None

    def finish_masks(self) -> list[RevisedMask]:
        """At the end of a run: the keyframes whose masks change because a person still followed, for less
        than a window, never moved (the run's end ends their track), or because the people standing on the
        last frame stood through the keyframes of its last window too (``KeyframeMaskLedger``: settled)."""
        if self._last_time is None:
            return []
        # The keyframes whose later frames are not all in yet, with the evidence those that came added; then
        # the ledger's last word (composing with that evidence), as the frames before handed them in that order.
        revised = recompose_with_evidence(self._free_space.flush())
        tracks, still = self._last_people
        return revised + self._keyframe_masks.advance(self._last_time, tracks, still, None,
                                                      self._region_motion.finish(), final=True)

    def close(self) -> None:
        """Stop the threads and persist what is worth keeping (the detection cache)."""
        while self._begun:                 # frames begun, never processed: their work ends first
            self._end(self._begun.popleft())
        for pool in (self._detect_thread, *self._prepare_threads.values()):
            if pool is not None:
                pool.shutdown(wait=True)
        self._detect_thread = None
        self._prepare_threads = {}
        if self.detector is not None:
            self.detector.save()

    def _dump(self, ctx: DynamicContext, outputs: dict[str, MethodOutput], fused: np.ndarray) -> None:
        self._dump_dir.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(self._dump_dir / f"{ctx.frame.index:06d}.png"), overlay(ctx, outputs, fused))
