"""The keyframe masks: the fused pixel mask of moving surfaces (what ``masks/`` stores), and its
revision once a person seen in a keyframe turns out to have stood still there.

A person counts as moving until ``region_motion.RegionMotion`` has followed them for a whole window
(0.5 s) and seen them stay put: the safe side for tracking, which must decide at once. A mask is an
output and can wait for the evidence. When a person is found still over the window ``[t - w, t]``, they
stood still in every keyframe of that window too, so those keyframes' masks are composed again with the
person standing (``KeyframeMaskLedger``), and the run's outputs rewrite them. A person followed for less
than a window is judged over its own life when the track ends (or the run does): a box that never moved
is not a moving surface, however briefly it was seen. Without this, the first
keyframes of a scene whose person stands were masked on the whole person (generated ``stand_walk``:
precision 0.46, every false alarm on the standing person in the three keyframes before the window ended).
Dense maps leave standing and moving people out alike, so a revision moves pixels between
``masks/<index>.png`` and ``masks/<index>_still.png`` and changes no map.

**Settled.** In a standing person's box only the motion-measuring methods count (the first steps of a walk
show there before the person's centre has left the bound). Once the person is shown still for a whole window
past a keyframe as well (or to the run's end), what those methods flagged on them in it was a false alarm, and
it leaves the keyframe's mask. Both flagged the standing person of composited walk_stand on the keyframes
where their box met the image's edge as the camera turned (29 k false pixels, seed 0), and nowhere else.

**Off the body.** box_depth's fill follows depth continuity, so a desk or floor that touches a person in
depth is filled too, and depth_sdf's fit spans the box: on people composited into fr1/rpy, where they stand
behind the desk, most false pixels of the masks lay in a person's box but far in depth from the person.
A pixel of a person's box more than ``_BODY_REACH_M`` in depth from that box's person layer
(``box_depth_segmentation.person_layer``, the box's most contained depth peak), and from the layer of every
other box that holds it, is not that person: there the masks count only the motion-measuring methods, as
for a person standing still, and what the fusion flagged goes to ``_still`` (dense maps unchanged).
Tracking keeps the methods' own per-feature probabilities; only a frame short of static features refills
from the mask (``frontend/static_refill.py``), and with the default box prior (0.3, above refill's 0.25
bound) not there either, so a default run's trajectory is unchanged; the single-method presets, without
the prior, may refill on those pixels.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np

from frontend.dynamic import RevisedMask
from frontend.dynamic.base import MethodOutput, keypoints_in_mask
from frontend.dynamic.box_depth_segmentation import cached_person_layer, layer_fill
from frontend.dynamic.free_space import Evidence
from frontend.dynamic.fusion import fuse_masks
from frontend.dynamic.region_motion import PersonTrack

Box = tuple[int, int, int, int]          # x0, y0, x1, y1 whole pixels
_MOVED_REGION_PROB = 0.9                 # a region the free-space test saw move, as region_motion's regions
_VACATED_COVER = 0.7
"""A fresh box at least this much inside a held one is taken for its person found again, partly hidden: two
people side by side overlap each other's boxes by an arm's width (~10-30 %). Not told apart: a person the
detector misses *because* a walker passes in front of them, the walker's box inside theirs; the masks then
keep only motion evidence on the hidden person's visible rest for those frames (tracking is unaffected;
on Bonn crowd-480 no box was vacated at all, YOLOX's boxes matching by IoU)."""
_BODY_REACH_M = 0.7
"""How far in depth a person reaches from the middle of their body (their layer): an arm stretched
towards the camera (~0.6 m) plus half a torso. Past it a pixel of their box is something else."""


class MaskParts:
    """What a frame's fused pixel mask is composed of. The fused masks are computed on first use (fusing
    four full-resolution masks costs ~10 ms) and kept, so a keyframe's record holds its own arrays and no
    reference to the methods' outputs."""

    def __init__(self, outputs: dict[str, MethodOutput], weights: list[float], motion_methods: list[int],
                 fusion: str, shape: tuple[int, int], motion_region: Optional[np.ndarray],
                 prior: Optional[np.ndarray], boxes: Sequence[Box] = (), depth: Optional[np.ndarray] = None,
                 layers: Optional[dict] = None):
        self._outputs = outputs
        self._weights = weights
        self._motion_methods = motion_methods     # indices of the methods that measure motion
        self._fusion = fusion
        self.shape = shape
        self.motion_region = motion_region        # HxW float, detector-free regions (region_motion)
        self.prior = prior                        # HxW float, the person-box prior
        # free_space.FreeSpaceCheck's evidence once the frame's pose is tracked (grown as later frames
        # come), or None
        self.free_space: Optional[Evidence] = None
        # HxW bool: the boxes of the people standing still, as last known (None: nobody)
        self.still_region: Optional[np.ndarray] = None
        # HxW bool: the boxes of those of them shown still for a window after this frame too, where the
        # motion methods' flags were false alarms (None: nobody; KeyframeMaskLedger)
        self.settled_region: Optional[np.ndarray] = None
        # HxW bool: held boxes the person has left for a fresh box inside them (None: none; vacated_region)
        self.vacated: Optional[np.ndarray] = None
        self._fused: Optional[tuple[Optional[np.ndarray]]] = None
        self._motion: Optional[tuple[Optional[np.ndarray]]] = None
        # the person boxes, the frame's depth and the layers known for its boxes (off_body)
        self._boxes, self._depth, self._layers = list(boxes), depth, layers
        self._off_body: Optional[tuple[Optional[np.ndarray]]] = None

    @property
    def fused(self) -> Optional[np.ndarray]:
        """Every method's mask fused (None if no method has a mask)."""
        if self._fused is None:
            self._fused = (fused_pixel_mask(self._outputs, self._fusion, self._weights, self.shape),)
        return self._fused[0]

    @property
    def motion(self) -> Optional[np.ndarray]:
        """The motion-measuring methods' masks fused (None if none has a mask)."""
        if self._motion is None:
            names = list(self._outputs)
            self._motion = (fused_pixel_mask({names[k]: self._outputs[names[k]] for k in self._motion_methods},
                                             self._fusion, [self._weights[k] for k in self._motion_methods],
                                             self.shape),)
        return self._motion[0]

    @property
    def off_body(self) -> Optional[np.ndarray]:
        """HxW bool: the pixels of person boxes that lie off every holding box's body (None: no such pixel)."""
        if self._off_body is None:
            self._off_body = (None if self._depth is None
                              else off_body_region(self._boxes, self._depth, self._layers),)
        return self._off_body[0]

    def keep(self) -> "MaskParts":
        """Compute the masks now and let go of the methods' outputs and the depth (a keyframe's record)."""
        _ = self.fused, self.motion, self.off_body
        self._outputs, self._depth, self._layers = {}, None, None
        return self


def fused_pixel_mask(outputs: dict[str, MethodOutput], mode: str, weights: list[float],
                     shape: tuple[int, int]) -> Optional[np.ndarray]:
    """The methods' pixel masks fused like their keypoint probabilities (None if none has a mask). A
    motion-measuring method's detections-only output (``MethodOutput.motion_measured`` False) is left out:
    it says where people are, which the segmenting methods say better, not that they move (composited
    two_walk, seed 0: on keyframe 0 flow_epipolar's whole box and depth_sdf's segment, 0.45 each, flagged a
    walker who stood at the start of their path for the 9 frames they were in view, 9 k false pixels)."""
    masks, used = [], []
    for weight, out in zip(weights, outputs.values()):
        if out.mask is not None and np.shape(out.mask) == tuple(shape) and out.motion_measured:
            masks.append(np.asarray(out.mask, np.float32).reshape(-1))
            used.append(weight)
    if not masks:
        return None
    mode = "max" if mode == "single" else mode
    return fuse_masks(masks, used, mode).reshape(shape)


def still_region(shape: tuple[int, int], boxes: list[Box], still) -> Optional[np.ndarray]:
    """HxW bool: the boxes of the people standing still less every other person's box (a walker in
    front of a standing person keeps all the evidence); None when nobody stands still."""
    if not np.any(still):
        return None
    region = np.zeros(shape, bool)
    for (x0, y0, x1, y1), k_still in zip(boxes, still):
        if k_still:
            region[y0:y1, x0:x1] = True
    for (x0, y0, x1, y1), k_still in zip(boxes, still):
        if not k_still:
            region[y0:y1, x0:x1] = False
    return region


def vacated_region(shape: tuple[int, int], fresh: Sequence[Box], held: Sequence[Box]) -> Optional[np.ndarray]:
    """HxW bool: each held box (the detector's memory of a box it did not see again) that holds at least
    ``_VACATED_COVER`` of a fresh box, less every fresh box: the person was found again there, in a box the
    memory did not match (a person half hidden as the camera turns keeps a box inside their last one, whose
    IoU is small), so the rest of the held box holds nobody. None when there is no such box."""
    region = np.zeros(shape, bool)
    for hx0, hy0, hx1, hy1 in held:
        for fx0, fy0, fx1, fy1 in fresh:
            inter = max(0, min(hx1, fx1) - max(hx0, fx0)) * max(0, min(hy1, fy1) - max(hy0, fy0))
            if inter >= _VACATED_COVER * max((fx1 - fx0) * (fy1 - fy0), 1):
                region[hy0:hy1, hx0:hx1] = True
                break
    for fx0, fy0, fx1, fy1 in fresh:
        region[fy0:fy1, fx0:fx1] = False
    return region if region.any() else None


def off_body_region(boxes: Sequence[Box], depth: np.ndarray, layers: Optional[dict] = None) -> Optional[np.ndarray]:
    """HxW bool: pixels with depth inside a person box that lie more than ``_BODY_REACH_M`` from the person
    layer of every box holding them; a box without a layer (too little depth) counts as all body. None when
    no pixel is off the body. ``layers`` (box -> layer) holds those already computed for the frame (box_depth's,
    ``DynamicContext.person_layers``); the rest are computed and added."""
    layers = {} if layers is None else layers
    if not boxes:
        return None
    near = np.full(depth.shape, np.inf, np.float32)      # per pixel: the distance to the nearest holding layer
    for box in boxes:
        x0, y0, x1, y1 = box
        crop = depth[y0:y1, x0:x1]
        layer = cached_person_layer(layers, box, depth)
        gap = np.zeros(crop.shape, np.float32) if layer is None else np.abs(crop - np.float32(layer))
        np.minimum(near[y0:y1, x0:x1], gap, out=near[y0:y1, x0:x1])
    off = np.isfinite(near) & (near > _BODY_REACH_M) & (depth > 0)
    return off if off.any() else None


def features_off_body(prior_region: np.ndarray, boxes: Sequence[Box], depth: np.ndarray, layers: Optional[dict],
                      uv_raw: np.ndarray, margin_px: float, max_fill: float = 1.0) -> np.ndarray:
    """Per keypoint (raw pixel coordinates): inside ``prior_region`` (the dilated person boxes) but off every
    holding box's body (``off_body_region``) and more than ``margin_px`` from every other pixel of the region
    (the body, the boxes' dilation ring, pixels without depth): a background surface the box merely frames
    (``DynamicConfig.box_prior_on_body``). The margin is the boxes' own silhouette margin
    (``box_prior_dilate_px``); ORB's descriptor patch (15 px at level 0) may still reach the person, and a
    margin that keeps it clear at every pyramid level lost the case the switch is for (docs/dynamic.md).
    With ``max_fill`` < 1 only in boxes whose person layer fills less than that share of them (``layer_fill``)
    and in no other box: a box mostly of what lies behind its person (a walker cut diagonally by a rolled
    camera's box, a person mostly hidden), not an upright person in full view."""
    free = np.zeros(len(uv_raw), bool)
    if not len(uv_raw) or not boxes:
        return free
    layers = {} if layers is None else layers
    sparse = [layer_fill(b, depth, layers) < max_fill for b in boxes] if max_fill < 1.0 else [True] * len(boxes)
    if not any(sparse):          # most frames: upright people in full view; the region is not needed
        return free
    off = off_body_region(boxes, depth, layers)
    if off is None:
        return free
    if not all(sparse):
        in_sparse, in_dense = np.zeros(depth.shape, bool), np.zeros(depth.shape, bool)
        for (x0, y0, x1, y1), is_sparse in zip(boxes, sparse):
            (in_sparse if is_sparse else in_dense)[y0:y1, x0:x1] = True
        off = off & in_sparse & ~in_dense
    near_person = prior_region & ~off
    to_person = cv2.distanceTransform((~near_person).view(np.uint8), cv2.DIST_L2, 5)
    return keypoints_in_mask(off, uv_raw) & (keypoints_in_mask(to_person, uv_raw) > margin_px)


def compose_mask(parts: MaskParts) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """(mask of moving surfaces, pixels never to be mapped though not moving) for a frame whose standing
    people cover ``parts.still_region``: there, and off every person's body (``parts.off_body``), only the
    motion-measuring methods count (none in ``parts.settled_region``), and what the fusion would have flagged
    of them goes to the second mask.
    The free-space test (``parts.free_space``) adds the regions it saw move (not over people shown standing
    still), and flagged pixels it finds consistent with every frame that could tell go to the second mask
    too. Either may be None."""
    mask = None if parts.fused is None else parts.fused.copy()
    still_people = None
    regions = [r for r in (parts.still_region, parts.off_body, parts.vacated) if r is not None]
    region = np.logical_or.reduce(regions) if regions else None
    if mask is not None and region is not None:
        still_people = (mask >= 0.5) & region
        mask[region] = 0.0 if parts.motion is None else parts.motion[region]
        if parts.settled_region is not None:
            mask[parts.settled_region] = 0.0
    if mask is not None and parts.motion_region is not None:
        mask = np.maximum(mask, parts.motion_region)
    if mask is not None and parts.free_space is not None:
        moving, known, moved_region = parts.free_space
        if parts.still_region is not None:
            # Not over people shown standing still: the frames a quarter to a whole second back saw through
            # the space where a walker who has just stopped now stands; that says they arrived, not that
            # they move (composited border, keyframes 284-300, the first second after the walker stopped:
            # 134 k of the 138 k false pixels on them).
            moved_region = moved_region & ~parts.still_region
        if moved_region.any():
            mask[moved_region] = np.maximum(mask[moved_region], _MOVED_REGION_PROB)
        unmoved = (mask >= 0.5) & known & ~moving & ~moved_region   # the short lags' regions: moving too
        if unmoved.any():
            mask[unmoved] = 0.0
            still_people = unmoved if still_people is None else still_people | unmoved
    if parts.prior is not None:
        mask = parts.prior if mask is None else np.maximum(mask, parts.prior)
    return mask, still_people


def recompose_with_evidence(handed_back: list[tuple[tuple[int, float, MaskParts], Evidence]]) -> list[RevisedMask]:
    """Keyframe masks composed again with the free-space evidence ``FreeSpaceCheck`` handed back (its keys: frame
    index, timestamp, the keyframe's mask parts, which keep the evidence for later compositions)."""
    revised = []
    for (index, timestamp, parts), evidence in handed_back:
        parts.free_space = evidence
        mask, unmoved = compose_mask(parts)
        if mask is not None:
            revised.append(RevisedMask(index, timestamp, mask, unmoved))
    return revised


def _motion_flagged(parts: MaskParts, box: Box) -> bool:
    """Whether the motion-measuring methods flag anything in ``box`` (what settling it would take away)."""
    x0, y0, x1, y1 = box
    return parts.motion is not None and bool((parts.motion[y0:y1, x0:x1] >= 0.5).any())


@dataclass
class _KeyframeRecord:
    frame_index: int
    timestamp: float
    parts: MaskParts
    boxes: list[Box]
    tracks: list[Optional[PersonTrack]]   # per box: the RegionMotion track it belongs to (None: not followed)
    still: np.ndarray          # per box: standing still, as known so far
    settled: np.ndarray        # per box: standing still from the keyframe on for a window too


class KeyframeMaskLedger:
    """The keyframes of the last window whose people may still turn out to have stood still."""

    def __init__(self, window_s: float):
        self.window_s = float(window_s)
        self._records: list[_KeyframeRecord] = []

    def reset(self) -> None:
        self._records = []

    def advance(self, timestamp: float, tracks: list[Optional[PersonTrack]], still: np.ndarray,
                keyframe: Optional[tuple[int, MaskParts, list[Box]]],
                also_still: Sequence[PersonTrack] = (), final: bool = False) -> list[RevisedMask]:
        """After a frame: ``tracks`` and ``still`` per person of this frame (in box order); ``keyframe``
        (frame index, mask parts, the people's boxes) when the frame is a keyframe; ``also_still``: tracks
        found still over their whole (short) life as they ended (``RegionMotion.ended_still``); ``final``:
        the run ends here (no later frame can show anyone move). Returns the earlier keyframes whose masks
        change because a person in them is now found standing still."""
        confirmed = [t for t, s in zip(tracks, still) if s and t is not None] + list(also_still)
        # A stillness found now covers the span the confirming track was shown still over (``still_since``:
        # the newest entry at least a window old, or a surface window for the surface's test) to now; a
        # keyframe older than every live track's stored span is final. Dropping by the window alone lost a
        # keyframe exactly at the span's start (composited two_walk, keyframe 39: 0.500012 s before the
        # frame that found its person still).
        spans = [t.times[0] for t in [*tracks, *also_still] if t is not None and t.times]
        horizon = min([timestamp - self.window_s, *spans])
        self._records = [r for r in self._records if r.timestamp >= horizon]
        revised = []
        for record in self._records:
            covered = [k for k, t in enumerate(record.tracks)
                       if t is not None and t.still_since is not None and record.timestamp >= t.still_since
                       and any(t is c for c in confirmed)]
            newly = [k for k in covered if not record.still[k]]
            # Settled: the span reaches a window past the keyframe (or the run's end), so what the motion
            # methods flagged on the person there was not the first steps of a walk (those take the person
            # past the bound within the window) but their false alarms (composited walk_stand, seed 0: 29 k
            # false pixels on the standing person, on keyframes where their box meets the image's edge as
            # the camera turns). Until then the flags stay: on generated stand_walk's keyframe 75 the person
            # has begun to walk but is still within the bound, and keeps them (mask recall 0.93; 0.88 if not).
            due = final or timestamp - record.timestamp >= self.window_s - 1e-9
            settle = [k for k in covered if not record.settled[k]
                      and _motion_flagged(record.parts, record.boxes[k])] if due else []
            if not newly and not settle:
                continue
            record.still[newly] = True
            record.settled[settle] = True
            record.parts.still_region = still_region(record.parts.shape, record.boxes, record.still)
            record.parts.settled_region = still_region(record.parts.shape, record.boxes, record.settled)
            mask, still_people = compose_mask(record.parts)
            if mask is not None:
                revised.append(RevisedMask(record.frame_index, record.timestamp, mask, still_people))
        if keyframe is not None and self.window_s > 0:
            frame_index, parts, boxes = keyframe
            if any(t is not None for t in tracks):   # someone may yet turn out still, or settle
                self._records.append(_KeyframeRecord(frame_index, timestamp, parts.keep(), list(boxes), list(tracks),
                                                     np.array(still, bool), np.zeros(len(boxes), bool)))
        return revised
