"""Interfaces shared by the dynamic-rejection methods, the detector and the fusion.

A method sees one ``DynamicContext`` per frame (before tracking) and returns a ``MethodOutput``:
one dynamic probability per keypoint in [0, 1] (NaN = abstain for that keypoint) plus an optional
pixel mask for diagnostics. After tracking, ``end_frame`` tells it the frame's pose and whether it
became a keyframe, for methods that keep history (reference frames, keyframe refinement,
Bayesian propagation). Methods keep their own state; they never touch the map or the tracker.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol

import numpy as np

from slam.core.camera import PinholeCamera
from slam.core.frame import FeatureFrame


@dataclass(frozen=True)
class Detection:
    """One detector box in pixel coordinates of the raw image: x0, y0 (top-left), x1, y1 (exclusive)."""

    x0: float
    y0: float
    x1: float
    y1: float
    class_id: int
    score: float

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def height(self) -> float:
        return self.y1 - self.y0

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Which of the points (N,2) lie inside the box."""
        return (xy[:, 0] >= self.x0) & (xy[:, 0] < self.x1) & (xy[:, 1] >= self.y0) & (xy[:, 1] < self.y1)


class Detector(Protocol):
    """Anything that turns a BGR image into boxes (the ONNX models, a cache, a test double). ``save``
    persists what is worth keeping (a cache's entries) when a run ends; ``close`` also lets go of what
    the detector holds."""

    def detect(self, bgr: np.ndarray, timestamp: float = 0.0) -> list[Detection]: ...

    def save(self) -> None: ...

    def close(self) -> None: ...


class DetectorDefaults:
    """``save`` and ``close`` for a detector with nothing to persist or let go of (known boxes, test
    doubles): inherit it and write ``detect``."""

    def save(self) -> None:
        """Nothing to persist."""

    def close(self) -> None:
        """Nothing held."""


@dataclass
class DynamicContext:
    frame: Optional[FeatureFrame]       # keypoints: uv_raw index the images, uv are undistorted (None in prepare)
    rgb: np.ndarray                     # HxWx3 uint8 BGR
    gray: np.ndarray                    # HxW uint8
    depth: np.ndarray                   # HxW float32 metres, 0 = invalid
    camera: PinholeCamera
    detections: Optional[list[Detection]] = None   # None when no enabled method needs a detector
    predicted_T_cw: Optional[np.ndarray] = None    # constant-velocity prediction (world -> camera)
    last_T_cw: Optional[np.ndarray] = None         # pose of the previous tracked frame
    # Person boxes (x0, y0, x1, y1) -> their depth layer (box_depth_segmentation.person_layer), kept for the
    # frame so box_depth's seeding and the keyframe mask's off-body test compute each one once.
    person_layers: dict = field(default_factory=dict)


@dataclass
class MethodOutput:
    prob: np.ndarray                        # (N,) in [0, 1], NaN = abstain
    mask: Optional[np.ndarray] = None       # (H,W) float32 in [0, 1] or bool, for diagnostics
    info: dict = field(default_factory=dict)  # method-specific counters for the run summary
    # Point tracks this frame (raw pixels, (M,2)) and which of them move against the scene's own motion:
    # motion evidence that needs no detector (flow_epipolar), for the rejector's region decision.
    tracks: Optional[np.ndarray] = None
    track_moving: Optional[np.ndarray] = None
    track_origins: Optional[np.ndarray] = None   # (M,2) where each track was in the previous frame
    # False when a motion-measuring method measured nothing this frame and its output stands on the
    # detections alone (flow_epipolar on its first frame, or without a fundamental matrix): ``prob`` keeps
    # tracking on the safe side, but the keyframe masks of moving surfaces leave ``mask`` out
    # (``keyframe_masks.fused_pixel_mask``).
    motion_measured: bool = True

    @property
    def flagged(self) -> int:
        return int(np.sum(np.nan_to_num(self.prob, nan=0.0) >= 0.5))

    @staticmethod
    def abstain(n: int) -> "MethodOutput":
        return MethodOutput(np.full(n, np.nan))


class DynamicMethod(Protocol):
    name: str
    needs_detector: bool
    prepares: bool    # whether ``prepare`` does work worth a thread (else the rejector calls it in line)
    # Whether the method measures motion itself (cpr, flow_epipolar) rather than finding a class that
    # usually moves (box_depth, depth_sdf): only motion evidence counts on a person standing still.
    measures_motion: bool

    def prepare(self, ctx: DynamicContext) -> None:
        """The part of the frame's work that needs only the images and the poses (``ctx.frame`` and
        ``ctx.detections`` are None): the rejector runs it on a thread while the features are extracted,
        then calls ``process`` with the same context, completed. ``process`` must also work unprepared."""
        ...

    def process(self, ctx: DynamicContext) -> MethodOutput: ...

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        """After tracking: the frame's pose (None if lost) and whether it became a keyframe."""
        ...


def keypoints_in_mask(mask: np.ndarray, uv_raw: np.ndarray) -> np.ndarray:
    """Value of a pixel mask at each keypoint's nearest pixel (raw image coordinates)."""
    h, w = mask.shape[:2]
    cols = np.clip(np.rint(uv_raw[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.rint(uv_raw[:, 1]).astype(int), 0, h - 1)
    return mask[rows, cols]
