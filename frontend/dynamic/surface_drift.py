"""A person's surface followed by the point tracks on it: the standing test's second witness (issue 11, item 3).

``region_motion.RegionMotion`` follows a person's torso centre (the median of the box's middle third) in
the world. That centre is a position of the *visible* part: behind a monitor it is the monitor on some
frames and the person on others, and the visible part of the person changes as the camera turns (head and
shoulders above the monitor, legs beside it). On the fr1/rpy composites the standing person's centre moved
by more than the 0.15 m bound over half a second on ~80 % of the windows (``walk_stand``, ``stand_walk``),
with the motion-capture poses.

What the surface does is measured instead of where its visible part lies. flow_epipolar's LK tracks go from
the previous frame to this one; those that start on the person in the previous frame and end on them in
this one (inside the box, within ``_BAND_M`` of the box's person layer at both ends) are back-projected
with each frame's depth and tracked pose, and the median of their world displacements is the person's
step. Summed over half a second, a standing person's steps stay within centimetres whichever part shows;
a walker's add up to their path. Probe on the composites (motion-capture poses, ground-truth boxes): the
standing person's summed steps stayed under 0.15 m on 83 % (``walk_stand``) and 71 % (``stand_walk``) of
the half-second windows measured on two frames in three, against 20-22 % for the centre.

A box's person layer also holds what stands at the person's depth beside them (a wall, a cabinet): the
median then follows the static majority, and a walker can look still (``two_walk``'s far walker: 59 % of
its windows under the bound). The *share* of the tracks that moved more than ``_STEP_NOISE_M`` in the
frame tells the two apart: a walker's own tracks all move (1 m/s is 3.3 cm per frame at 30 Hz), while
depth noise and tracks that slip at an occluding edge move a standing person's by more than 2 cm only now
and then. Measured (same probe), the mean share over a window: standing 0.21-0.26 at the median (90 %
below 0.47), walking 0.53-0.75 (90 % above 0.33); ``MOVING_SHARE`` = 0.3 lies between the standing
median and the walking tail. Both together left 4 of 166 walking windows still, on the three composites.
A track's move is judged across its line of sight only (``SurfaceTracker.step``): along it a step is the
difference of two depth readings, and their noise kept the standing people's shares over the bound on many
windows (in the run, composited ``stand_walk``'s masks: 0.50 / 0.89 with the whole step, 0.64 / 0.89
across it). What that gives up: a walker going straight along the line of sight whose box is mostly
static surface at their depth moves few tracks across it; the median step still shows them while their
own tracks are the majority.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from frontend.dynamic.base import keypoints_in_mask
from slam.core.camera import PinholeCamera
from slam.core.geometry import invert, transform_points

Box = tuple[int, int, int, int]

_BAND_M = 0.3
"""A track is on the person when its depth lies within this of the box's person layer (at both ends): the
layer's own +-0.2 m and a body's depth about its middle, while a monitor in front (~0.8 m nearer on the
composites) or the wall behind stays out."""
MIN_TRACKS = 5
"""Tracks on the person needed for a step (a median of fewer is one or two slipping tracks' say)."""
_MAX_STEP_M = 0.1
"""A median step longer than this in one frame (3 m/s at 30 Hz, faster than anyone moves indoors) is a
wrong association, not a person: the frame counts as unmeasured."""
_STEP_NOISE_M = 0.02
"""A track moved in the frame when its world displacement across its line of sight exceeds this: a walker
at 1 m/s steps 3.3 cm per frame at 30 Hz, a slow one (0.5 m/s) 1.7 cm; a standing person's tracks move by
LK's error (a pixel at 2 m: 0.4 cm) and their sway (1-3 cm over seconds, far less per frame)."""
MOVING_SHARE = 0.3
"""Mean share of a person's moved tracks over the window at and above which they count as moving whatever
the median says (see the module doc for the measured distributions)."""
MIN_MEASURED = 2.0 / 3.0
"""Share of the window's frames that must have a measured step: behind a monitor a person keeps only a
few tracks on some frames; an unmeasured frame adds no step, so too many of them could hide a walk."""


@dataclass(frozen=True)
class PersonView:
    """One person box of a frame (x0, y0, x1, y1 pixels) and its person layer (m; None without one)."""
    box: Box
    layer: Optional[float]


@dataclass(frozen=True)
class FrameTracks:
    """A frame's point tracks from the previous frame (flow_epipolar's LK, raw pixels) and its depth."""
    origins: np.ndarray     # (M, 2) in the previous frame
    tracks: np.ndarray      # (M, 2) in this frame
    depth: np.ndarray       # this frame's depth (H x W, m)


def on_person(points: np.ndarray, depths: np.ndarray, view: PersonView) -> np.ndarray:
    """(M,) bool: the points (raw pixels) inside ``view``'s box whose depth lies within ``_BAND_M`` of its
    layer (none without a layer)."""
    if view.layer is None or not len(points):
        return np.zeros(len(points), bool)
    x0, y0, x1, y1 = view.box
    inside = (points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0) & (points[:, 1] < y1)
    return inside & (depths > 0) & (np.abs(depths - view.layer) < _BAND_M)


@dataclass(frozen=True)
class SurfaceStep:
    """One frame's step of a person's surface: the median world displacement and the share of the tracks
    that moved more than ``_STEP_NOISE_M`` across their line of sight."""
    displacement: np.ndarray
    moved_share: float


class SurfaceTracker:
    """The tracks of one frame against the previous frame's depth: which previous person a person continues
    (``shared``) and the step of their surface (``step``) once the frame's pose is known."""

    def __init__(self, flow: FrameTracks, prev_depth: np.ndarray):
        self.flow = flow
        self._z_prev = keypoints_in_mask(prev_depth, flow.origins).astype(float) if len(flow.origins) else np.zeros(0)
        self._z_cur = keypoints_in_mask(flow.depth, flow.tracks).astype(float) if len(flow.tracks) else np.zeros(0)

    def shared(self, before: PersonView, now: PersonView) -> np.ndarray:
        """(M,) bool: the tracks that start on ``before`` (previous frame) and end on ``now``."""
        return on_person(self.flow.origins, self._z_prev, before) & on_person(self.flow.tracks, self._z_cur, now)

    def step(self, on: np.ndarray, camera: PinholeCamera, prev_T_cw: np.ndarray, T_cw: np.ndarray
             ) -> Optional[SurfaceStep]:
        """The step of the tracks ``on`` (``shared``'s flags) between the two frames' poses (world ->
        camera), or None when fewer than ``MIN_TRACKS`` or the median is longer than ``_MAX_STEP_M``."""
        if int(np.count_nonzero(on)) < MIN_TRACKS:
            return None
        T_wc = invert(T_cw)
        before = transform_points(invert(prev_T_cw), camera.backproject(camera.undistort_points(self.flow.origins[on]),
                                                                         self._z_prev[on]))
        after = transform_points(T_wc, camera.backproject(camera.undistort_points(self.flow.tracks[on]), self._z_cur[on]))
        moves = after - before
        displacement = np.median(moves, axis=0)
        if float(np.linalg.norm(displacement)) > _MAX_STEP_M:
            return None
        # Whether a track moved is judged across its line of sight: along it the step is the difference of
        # two depth readings, whose noise (the sensor's, and a track sliding a pixel over a body's curved
        # side) reaches centimetres, while across it the step comes from LK's sub-pixel positions.
        rays = after - T_wc[:3, 3]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        across = moves - np.sum(moves * rays, axis=1, keepdims=True) * rays
        return SurfaceStep(displacement, float(np.mean(np.linalg.norm(across, axis=1) > _STEP_NOISE_M)))


def surface_still(surface: list[np.ndarray], measured: list[bool], shares: list[float], max_move_m: float) -> bool:
    """Whether a person's surface positions over a window (the first entry where the window begins; each
    later one advanced by its frame's step, ``measured`` False where no step was measured) show them still:
    steps measured on ``MIN_MEASURED`` of the frames, every position within ``max_move_m`` of the last, and
    a mean moved share below ``MOVING_SHARE``."""
    steps = measured[1:]
    if not steps or np.mean(steps) < MIN_MEASURED:
        return False
    moved = np.linalg.norm(np.asarray(surface) - surface[-1], axis=1)
    known = [s for s, m in zip(shares[1:], steps) if m]
    return bool(np.max(moved) < max_move_m and np.mean(known) < MOVING_SHARE)
