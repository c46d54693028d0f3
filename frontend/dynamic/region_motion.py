"""Region-level decisions on motion (issue 11, items 1 and 3; in none of the four papers).

Two rules, both about whole regions rather than single features: which detected people stand still
(``RegionMotion``, below), and which regions move where the detector sees nobody
(``confirmed_regions``: cpr's dynamic sub-clouds that flow_epipolar's epipolar test confirms;
``RegionCarry`` follows a confirmed region through the frames where that evidence is too thin).

**Standing still.** box_depth and depth_sdf segment people, not motion: they flag a person who stands still as surely as
one who walks. cpr and flow_epipolar measure motion. Each person box's 3-D centre (the median of the
middle third of the box: the torso) is followed in world coordinates from frame to frame, and a person
whose centre stayed within ``max_move_m`` of every position it had over the last ``window_s`` seconds
stands still. In a standing person's box the keyframe masks (``DynamicRejector.last_mask``, a mask of
moving surfaces) then count only the motion-measuring methods, and the person's pixels go to
``last_still_people`` instead, which dense maps leave out as well. Tracking keeps them out, standing or
not: used for tracking (the issue allows it), the man on Bonn crowd who stands at a desk pulled it as he
started to walk (five keyframes in a row, frames 415-419, and the dense map's ghost share among people
0.0030 -> 0.0039), since the rule needs ~5 frames to see a walk begin. Algorithm 3 of the box + depth
paper (Fang et al.) reuses single features that moved like the static scene between two frames; this is the
same idea for a whole person over half a second.

Why the defaults: ``window_s`` 0.5 s and ``max_move_m`` 0.15 m mean an average speed of 0.3 m/s, half
the slowest deliberate walking pace (~0.5-0.6 m/s; typical 1.2-1.4 m/s), while the sway of a standing
person (1-3 cm) and the jitter of a torso's median depth stay well below 0.15 m. A person who starts
walking at 1 m/s counts as moving again after ~0.15 s (5 frames at 30 Hz).

**A second witness: the surface** (``surface_drift``). Behind a monitor the torso centre is the monitor
on some frames and the person on others, so it jumps and the person is never found still. With the
frame's point tracks (flow_epipolar's) a person whose centre jumped continues the track their surface's
tracks came from, and a person whose surface (the median step of the tracks on them, summed) stayed
within ``max_move_m`` over *twice* the window, with few of those tracks moving, stands still too. Twice,
because a box's person layer also holds what stands at their depth beside them, which can outvote a
walker's own tracks while little of the walker shows (see ``surface_window_s``). A stillness covers the
span it was shown over (``PersonTrack.still_since``), the keyframes the ledger revises.

The safe side everywhere: a person is *moving* unless shown still -- a new box, one not matched to last
frame's (the detector missed them, a second person stepped in front), a frame without a predicted pose,
or after a lost frame. Everything is a function of the frames and poses only: deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from frontend.dynamic.base import keypoints_in_mask
from frontend.dynamic.surface_drift import MIN_TRACKS, FrameTracks, PersonView, SurfaceTracker, surface_still
from slam.core.camera import PinholeCamera

_MATCH_M = 0.5
"""A person continues last frame's track whose centre is nearest and less than this far (world, m):
half a person's shoulder width plus a frame of fast walking (~5 cm), so two people side by side keep
their own tracks."""
_MAX_FRAME_OUTLIERS = 0.05
"""Beyond this share of a frame's tracks off their epipolar lines the test itself is unreliable (motion
blur, rolling shutter: fr1/rpy's fast turns reach 0.2-0.35, its median frame 0.001; a walker seen whole
gives 0.01-0.02 on the generated scenes), and no region is confirmed by it."""
_MIN_LIFE_S = 0.15
"""A person followed for less than a window is judged over its own life once it lasted this long (see
``RegionMotion.ended_still``): over 0.15 s the speed bound (``max_move_m / window_s``, 0.3 m/s) allows
0.045 m, 1.5x the 1-3 cm jitter of a standing torso's median, while a walker at 0.5 m/s moves 0.075 m."""
_BODY_BAND_M = 0.5
"""A confirmed region keeps the pixels within this of its moving tracks' median depth: a body's extent in
depth about its middle, an arm stretched forward included."""
_PIXEL_STEP = 2
"""Every 2nd pixel in each direction enters the median (a 200 x 400 px person: ~2 000 pixels)."""


@dataclass
class PersonTrack:
    """One person's centre in the world over the last window (``RegionMotion``; the keyframe-mask ledger
    reads its span). The same object while the person is followed. Beside the centres, the person's surface
    followed by the point tracks on it (``surface_drift``): a position per frame (world), advanced by each
    frame's measured step (``measured``; the share of moved tracks in ``shares``, NaN where unmeasured)."""
    times: list[float] = field(default_factory=list)
    centres: list[np.ndarray] = field(default_factory=list)   # world coordinates
    surface: list[np.ndarray] = field(default_factory=list)
    measured: list[bool] = field(default_factory=list)
    shares: list[float] = field(default_factory=list)
    view: Optional[PersonView] = None                         # the box and layer of its last frame
    # The start of the span over which the person was last shown still (None: not yet): the keyframes from
    # then on hold them standing (keyframe_masks).
    still_since: Optional[float] = None

    def start(self, now: float, span_s: float) -> Optional[int]:
        """Index of the newest entry at least ``span_s`` before ``now`` (where a span that long begins);
        None when the track is younger. Within 1 ns counts as at least: an entry exactly a span back
        must count whatever the rounding of the float timestamps' difference."""
        old = [i for i, t in enumerate(self.times) if t <= now - span_s + 1e-9]
        return old[-1] if old else None


def box_centre(box: tuple[int, int, int, int], depth: np.ndarray, camera: PinholeCamera) -> Optional[np.ndarray]:
    """Median 3-D point (camera frame) of the middle third (width and height) of a person's box (x0, y0,
    x1, y1 pixels): the torso, which a person's box centres on whatever their pose (box_depth seeds its
    fill there too); the median ignores the background seen between arm and body. None without depth."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    rows = np.arange(y0 + h // 3, y1 - h // 3, _PIXEL_STEP)
    cols = np.arange(x0 + w // 3, x1 - w // 3, _PIXEL_STEP)
    if not len(rows) or not len(cols):
        return None
    z = depth[np.ix_(rows, cols)].astype(float)
    r, c = np.nonzero(z > 0)
    if not len(r):
        return None
    z, v, u = z[r, c], rows[r].astype(float), cols[c].astype(float)
    xyz = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1)
    return np.median(xyz, axis=0)


class RegionMotion:
    """Follows people's centres in the world and says who stands still (see the module doc)."""

    def __init__(self, window_s: float, max_move_m: float, camera: Optional[PinholeCamera] = None):
        self.window_s = float(window_s)
        self.max_move_m = float(max_move_m)
        self.camera = camera              # for the surfaces' steps (surface_drift); None: centres only
        # The surface's evidence must hold twice as long as the centre's: a box's person layer also holds
        # what stands at the person's depth beside them, which can outvote a walker's own tracks while the
        # walker shows little of themselves (composited walk_stand, frames 189-193: a strip of legs at the
        # image's top over desk clutter at the same depth, found still 0.5 s after the track began).
        self.surface_window_s = 2.0 * self.window_s
        self._tracks: list[PersonTrack] = []
        # The current frame's people (camera-frame centres, views) and the track each continues, until
        # ``commit`` places them in the world with the frame's tracked pose.
        self._pending: list[tuple[int, np.ndarray, Optional[PersonTrack], Optional[PersonView]]] = []
        self._people = 0
        self._time = 0.0
        self._surface: Optional[SurfaceTracker] = None     # this frame's tracks against the previous depth
        self._flow: Optional[FrameTracks] = None
        self._prev: Optional[tuple[np.ndarray, np.ndarray]] = None   # the last committed (depth, T_cw)
        # Tracks that ended in the last ``commit`` (the box was not seen again) without ever moving faster
        # than the bound over their whole life, though shorter than a window: a detection that came and
        # went on something static (YOLOX-Nano's "person" on fr1/rpy's desk, frame 395, score 0.35) or a
        # person who stood briefly. Tracking has treated them as moving (it must decide at once); the
        # keyframe masks, which can wait, are revised (keyframe_masks).
        self.ended_still: list[PersonTrack] = []

    @property
    def enabled(self) -> bool:
        return self.window_s > 0

    def reset(self) -> None:
        self._tracks, self._pending, self._prev = [], [], None

    def classify(self, centres: list[Optional[np.ndarray]], predicted_T_cw: Optional[np.ndarray],
                 timestamp: float, views: Optional[list[PersonView]] = None,
                 flow: Optional[FrameTracks] = None) -> np.ndarray:
        """Per person (camera-frame centre, None without depth): True for those who stand still. With
        ``views`` (each person's box and layer) and ``flow`` (the frame's point tracks and depth), a person
        whose centre jumped continues the track their surface's tracks came from, and a person whose
        surface stayed still over the window stands still too (``surface_drift``)."""
        still = np.zeros(len(centres), bool)
        self._time, self._pending, self._people = timestamp, [], len(centres)
        self._flow = flow if self.camera is not None and views is not None else None
        self._surface = None if self._flow is None or self._prev is None else SurfaceTracker(self._flow, self._prev[0])
        if not self.enabled:
            return still
        world = None if predicted_T_cw is None else _to_world(predicted_T_cw)
        free = list(self._tracks)
        for k in np.argsort([np.inf if c is None else float(np.linalg.norm(c)) for c in centres], kind="stable"):
            centre = centres[k]
            if centre is None:
                continue
            view = None if views is None else views[k]
            track = None
            if world is not None and free:
                w = world(centre)
                dist = [float(np.linalg.norm(t.centres[-1] - w)) for t in free]
                j = int(np.argmin(dist))
                if dist[j] < _MATCH_M:
                    track = free.pop(j)
                else:
                    track = self._continued_surface(free, view)
                if track is not None:
                    since = [track.times[i] for i in (self._stands_still(track, w, timestamp),
                                                      self._surface_still(track, timestamp)) if i is not None]
                    still[k] = bool(since)
                    if since:
                        track.still_since = min(since)
            self._pending.append((int(k), centre, track, view))
        return still

    def _continued_surface(self, free: list[PersonTrack], view: Optional[PersonView]) -> Optional[PersonTrack]:
        """The free track most of whose last frame's surface tracks end on ``view`` (at least
        ``MIN_TRACKS``), taken from ``free``; None without one."""
        if self._surface is None or view is None:
            return None
        counts = [0 if t.view is None else int(np.count_nonzero(self._surface.shared(t.view, view))) for t in free]
        if not counts or max(counts) < MIN_TRACKS:
            return None
        return free.pop(int(np.argmax(counts)))

    def commit(self, T_cw: Optional[np.ndarray]) -> list[Optional[PersonTrack]]:
        """After tracking: the frame's people join their tracks at the tracked pose; without a pose
        every track ends (no world position to compare with). Returns each person's track, in the order
        ``classify`` got them (None: no depth, or no pose); a track is the same object while it goes on."""
        pending, self._pending = self._pending, []
        per_person: list[Optional[PersonTrack]] = [None] * self._people
        before = self._tracks
        prev, self._prev = self._prev, None if T_cw is None or self._flow is None else (self._flow.depth, T_cw)
        if T_cw is None:
            self._tracks = []
            self.ended_still = self._still_over_lives(before)
            return per_person
        world, tracks = _to_world(T_cw), []
        for k, centre, track, view in pending:
            track = track or PersonTrack()
            position = world(centre)
            step = None
            if track.view is not None and view is not None and self._surface is not None and prev is not None:
                step = self._surface.step(self._surface.shared(track.view, view), self.camera, prev[1], T_cw)
            track.times.append(self._time)
            track.centres.append(position)
            track.surface.append(track.surface[-1] + step.displacement if step is not None
                                 else track.surface[-1] if track.surface else position)
            track.measured.append(step is not None)
            track.shares.append(np.nan if step is None else step.moved_share)
            track.view = view
            # Keep what the tests need: the newest entry at least a surface window old and everything after.
            first = track.start(self._time, self.surface_window_s)
            if first:
                for series in (track.times, track.centres, track.surface, track.measured, track.shares):
                    del series[:first]
            tracks.append(track)
            per_person[k] = track
        self._tracks = tracks
        self.ended_still = self._still_over_lives([t for t in before if not any(t is n for n in tracks)])
        return per_person

    def finish(self) -> list[PersonTrack]:
        """At the end of a run: the tracks still going that are shorter than a window and never moved
        faster than the bound (``ended_still``'s rule: the run ending ends them)."""
        return self._still_over_lives(self._tracks)

    def _still_over_lives(self, tracks: list[PersonTrack]) -> list[PersonTrack]:
        """Those of ``tracks`` still over their whole life (``_still_over_life``), shown still since it began."""
        still = [t for t in tracks if self._still_over_life(t)]
        for track in still:
            track.still_since = track.times[0]
        return still

    def _still_over_life(self, track: PersonTrack) -> bool:
        """A track shorter than a window (longer ones are judged frame by frame) that lasted at least
        ``_MIN_LIFE_S`` and stayed within the speed bound over its life."""
        if not self.enabled or len(track.times) < 2:
            return False
        life = track.times[-1] - track.times[0]
        if life >= self.window_s or life < _MIN_LIFE_S:
            return False
        moved = np.linalg.norm(np.asarray(track.centres) - track.centres[-1], axis=1)
        return bool(np.max(moved) < self.max_move_m * life / self.window_s)

    def _stands_still(self, track: PersonTrack, centre_w: np.ndarray, now: float) -> Optional[int]:
        """Where the window over which the track's centre stayed within the bound begins (index), or None."""
        first = track.start(now, self.window_s)
        if first is None:
            return None                                   # not followed for a whole window yet
        moved = np.linalg.norm(np.asarray(track.centres[first:]) - centre_w, axis=1)
        return first if np.max(moved) < self.max_move_m else None

    def _surface_still(self, track: PersonTrack, now: float) -> Optional[int]:
        """Where the surface window over which the track's surface stayed still begins (index), or None:
        up to the frame before (this frame's step needs its tracked pose: one frame later, which only the
        masks read; ``surface_drift``)."""
        first = track.start(now, self.surface_window_s)
        if first is None or len(track.surface) - first < 2:
            return None
        still = surface_still(track.surface[first:], track.measured[first:], track.shares[first:], self.max_move_m)
        return first if still else None


def _to_world(T_cw: np.ndarray):
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    return lambda p_c: R.T @ (p_c - t)


def front_depth(depths: np.ndarray, min_count: int, band_m: float) -> Optional[float]:
    """Median depth of the front-most group of at least ``min_count`` of ``depths`` (moving tracks')
    within ``band_m`` of each other, or None. Not the plain median: a mover drags the tracks on the
    background just behind its silhouette along (their LK windows hold the occluding edge), so they fail
    the epipolar test too, and a narrow or passing person can have more of those than of their own
    (generated border scene, frame 106: 8 moving tracks in the person's region, 3 on the person). The
    mover is the surface in front."""
    d = np.sort(depths[depths > 0])
    if len(d) < min_count:
        return None
    upto = np.searchsorted(d, d + band_m, side="left")     # d[i:upto[i]] lie within band_m behind d[i]
    groups = np.flatnonzero(upto - np.arange(len(d)) >= min_count)
    if not len(groups):
        return None
    i = groups[0]
    return float(np.median(d[i:upto[i]]))


def confirmed_regions(candidates: np.ndarray, tracks: np.ndarray, moving: np.ndarray, depth: np.ndarray,
                      min_votes: int, min_share: float, band_m: float = _BODY_BAND_M) -> Optional[np.ndarray]:
    """Motion evidence that needs no detector: the connected parts (8-neighbourhood) of the HxW bool
    ``candidates`` (cpr's dynamic sub-clouds) in which at least ``min_votes`` of the point ``tracks``
    ((M,2) raw pixels) are ``moving`` against the scene's own motion (flow_epipolar's epipolar test), and
    at least ``min_share`` of the tracks there; of such a part, the pixels within ``band_m`` of the
    median depth of its moving tracks (a sub-cloud also holds the floor and wall around a person).
    HxW float32 0/1, or None when no part is confirmed or the frame's epipolar test is unreliable.

    Each method alone is not enough: cpr's threshold flags one or two static sub-clouds in most frames,
    and the epipolar test misses most points of a person (recall 0.17-0.33 per pixel on the generated
    scenes). A region both flag is moving: three tracks off their epipolar lines inside one region are
    not a RANSAC outlier or two, and a fifth of a region's tracks is what a walking person gives."""
    if not len(tracks) or not candidates.any() or np.mean(moving) > _MAX_FRAME_OUTLIERS:
        return None
    n, labels = cv2.connectedComponents(candidates.astype(np.uint8), connectivity=8)
    label_of_track = keypoints_in_mask(labels, tracks)
    track_depth = keypoints_in_mask(depth, tracks)
    votes = np.bincount(label_of_track[moving], minlength=n)
    centre = np.full(n, np.nan)
    for k in np.flatnonzero(votes >= min_votes):               # a handful of regions at most
        if k == 0:
            continue                                           # label 0: outside every candidate region
        in_region = label_of_track == k
        mover = front_depth(track_depth[moving & in_region & (track_depth > 0)], min_votes, band_m)
        if mover is None:
            continue
        # The decision is made on the region's part in the mover's depth band: a sub-cloud that joins a
        # person to the wall behind them holds the wall's many still tracks, which would outvote the
        # person's (generated border scene, frames 99-107: 145-358 tracks, 9-15 moving).
        band = in_region & (np.abs(track_depth - mover) < band_m)
        band_votes = int(np.sum(band & moving))
        if band_votes >= min_votes and band_votes >= min_share * int(np.sum(band)):
            centre[k] = mover
    if np.isnan(centre).all():
        return None
    pixel_centre = centre[labels]
    with np.errstate(invalid="ignore"):
        region = np.abs(depth - pixel_centre) < band_m          # NaN centre (no region, no depth): False
    return region.astype(np.float32) if region.any() else None


class RegionCarry:
    """Follows the last confirmed motion region (``confirmed_regions``) through frames where the evidence
    is too thin to confirm it again: a person passing the image border gives cpr and flow_epipolar only a
    handful of tracks, and in some frames fewer than ``min_votes`` of them fail the epipolar test
    (generated border scene: 1-2 on frames 105 and 108-110, 4-15 on the frames around them).

    The region is tracked, not guessed: it moves by the median image motion of the point tracks that
    started inside it (flow_epipolar's LK tracks: the person's own points) and keeps the pixels within
    ``band_m`` of those tracks' current median depth. It is carried at most ``hold_frames`` frames after
    its last confirmation, the hold the detector's boxes get for the same kind of gap (box_memory), and
    needs ``min_tracks`` of its own tracks (started inside it, still at its depth), so it cannot drift off
    onto the background on its own, and one of them off its epipolar line: the passing person keeps 1-2
    such tracks per frame, while a static surface that passed the test once (fr1/rpy's blurred turns:
    6 regions in 400 frames) has none the next frame and is not carried."""

    def __init__(self, hold_frames: int, min_tracks: int = 2, band_m: float = _BODY_BAND_M):
        # Two of the region's own tracks: one LK track alone can be a mismatch; a passing person keeps
        # only 2-11 tracks at the border (generated border scene).
        self.hold_frames = int(hold_frames)
        self.min_tracks = int(min_tracks)
        self.band_m = float(band_m)
        self._region: Optional[np.ndarray] = None   # HxW bool, the last frame's region
        self._centre = 0.0                          # its median depth (m)
        self._age = 0                               # frames since it was last confirmed

    def reset(self) -> None:
        self._region, self._age = None, 0

    def update(self, confirmed: Optional[np.ndarray], origins: Optional[np.ndarray], tracks: Optional[np.ndarray],
               moving: Optional[np.ndarray], depth: np.ndarray, allowed: np.ndarray) -> Optional[np.ndarray]:
        """This frame's motion region (HxW float32 0/1, or None): ``confirmed`` when there is one, else
        the last region carried along its tracks (``origins`` -> ``tracks``, raw pixels; ``moving``: those
        off their epipolar lines), within ``allowed`` (outside the person boxes)."""
        if confirmed is not None:
            self._region, self._age = confirmed > 0, 0
            self._centre = float(np.median(depth[self._region]))
            return confirmed
        carried = self._carry(origins, tracks, moving, depth, allowed)
        self._region, self._age = carried, self._age + 1
        return None if carried is None else carried.astype(np.float32)

    def _carry(self, origins, tracks, moving, depth, allowed) -> Optional[np.ndarray]:
        if self._region is None or self._age >= self.hold_frames or origins is None or tracks is None \
                or moving is None or len(origins) != len(tracks) or not len(origins):
            return None
        # The region's own points: tracks that started inside it and are still at its depth (a track on
        # the background at its silhouette would pull the shift and the depth band off the person).
        d = keypoints_in_mask(depth, tracks)
        own = keypoints_in_mask(self._region, origins).astype(bool) & (np.abs(d - self._centre) < self.band_m)
        if own.sum() < self.min_tracks or not np.any(own & moving):
            return None
        shift = np.median(tracks[own] - origins[own], axis=0)
        h, w = self._region.shape
        moved = cv2.warpAffine(self._region.astype(np.uint8), np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]),
                               (w, h), flags=cv2.INTER_NEAREST).astype(bool)
        self._centre = float(np.median(d[own]))
        region = moved & allowed & (np.abs(depth - self._centre) < self.band_m)
        return region if region.any() else None
