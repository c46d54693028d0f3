"""Region-level decisions on motion (issue 11, items 1 and 3; in none of the four papers).

Two rules, both about whole regions rather than single features: which detected people stand still
(``RegionMotion``, below), and which regions move where the detector sees nobody
(``confirmed_regions``: cpr's dynamic sub-clouds that flow_epipolar's epipolar test confirms).

**Standing still.** box_depth and depth_sdf segment people, not motion: they flag a person who stands still as surely as
one who walks. cpr and flow_epipolar measure motion. Each person box's 3-D centre (the median of the
middle third of the box: the torso) is followed in world coordinates from frame to frame, and a person
whose centre stayed within ``max_move_m`` of every position it had over the last ``window_s`` seconds
stands still. In a standing person's box the keyframe masks (``DynamicRejector.last_mask``, a mask of
moving surfaces) then count only the motion-measuring methods, and the person's pixels go to
``last_still_people`` instead, which dense maps leave out as well. Tracking keeps them out, standing or
not: used for tracking (the issue allows it), the man on Bonn crowd who stands at a desk pulled it as he
started to walk (five keyframes in a row, frames 415-419, and the dense map's ghost share among people
0.0030 -> 0.0039), since the rule needs ~5 frames to see a walk begin. Algorithm 3 of the box + depth paper (Fang et al.) reuses single
features that moved like the static scene between two frames; this is the same idea for a whole person
over half a second.

Why the defaults: ``window_s`` 0.5 s and ``max_move_m`` 0.15 m mean an average speed of 0.3 m/s, half
the slowest deliberate walking pace (~0.5-0.6 m/s; typical 1.2-1.4 m/s), while the sway of a standing
person (1-3 cm) and the jitter of a torso's median depth stay well below 0.15 m. A person who starts
walking at 1 m/s counts as moving again after ~0.15 s (5 frames at 30 Hz).

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
from slam.core.camera import PinholeCamera

_MATCH_M = 0.5
"""A person continues last frame's track whose centre is nearest and less than this far (world, m):
half a person's shoulder width plus a frame of fast walking (~5 cm), so two people side by side keep
their own tracks."""
_MAX_FRAME_OUTLIERS = 0.05
"""Beyond this share of a frame's tracks off their epipolar lines the test itself is unreliable (motion
blur, rolling shutter: fr1/rpy's fast turns reach 0.2-0.35, its median frame 0.001; a walker seen whole
gives 0.01-0.02 on the generated scenes), and no region is confirmed by it."""
_BODY_BAND_M = 0.5
"""A confirmed region keeps the pixels within this of its moving tracks' median depth: a body's extent in
depth about its middle, an arm stretched forward included."""
_PIXEL_STEP = 2
"""Every 2nd pixel in each direction enters the median (a 200 x 400 px person: ~2 000 pixels)."""


@dataclass
class _Track:
    times: list[float] = field(default_factory=list)
    centres: list[np.ndarray] = field(default_factory=list)   # world coordinates


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

    def __init__(self, window_s: float, max_move_m: float):
        self.window_s = float(window_s)
        self.max_move_m = float(max_move_m)
        self._tracks: list[_Track] = []
        # The current frame's people (camera-frame centres) and the track each continues, until
        # ``commit`` places them in the world with the frame's tracked pose.
        self._pending: list[tuple[np.ndarray, Optional[_Track]]] = []
        self._time = 0.0

    @property
    def enabled(self) -> bool:
        return self.window_s > 0

    def reset(self) -> None:
        self._tracks, self._pending = [], []

    def classify(self, centres: list[Optional[np.ndarray]], predicted_T_cw: Optional[np.ndarray],
                 timestamp: float) -> np.ndarray:
        """Per person (camera-frame centre, None without depth): True for those who stand still."""
        still = np.zeros(len(centres), bool)
        self._time, self._pending = timestamp, []
        if not self.enabled:
            return still
        world = None if predicted_T_cw is None else _to_world(predicted_T_cw)
        free = list(self._tracks)
        for k in np.argsort([np.inf if c is None else float(np.linalg.norm(c)) for c in centres], kind="stable"):
            centre = centres[k]
            if centre is None:
                continue
            track = None
            if world is not None and free:
                w = world(centre)
                dist = [float(np.linalg.norm(t.centres[-1] - w)) for t in free]
                j = int(np.argmin(dist))
                if dist[j] < _MATCH_M:
                    track = free.pop(j)
                    still[k] = self._stands_still(track, w, timestamp)
            self._pending.append((centre, track))
        return still

    def commit(self, T_cw: Optional[np.ndarray]) -> None:
        """After tracking: the frame's people join their tracks at the tracked pose; without a pose
        every track ends (no world position to compare with)."""
        pending, self._pending = self._pending, []
        if T_cw is None:
            self._tracks = []
            return
        world, tracks = _to_world(T_cw), []
        for centre, track in pending:
            track = track or _Track()
            track.times.append(self._time)
            track.centres.append(world(centre))
            # Keep what the window needs: the newest entry at least window_s old and everything after it.
            old = [i for i, t in enumerate(track.times) if t <= self._time - self.window_s]
            if old:
                del track.times[:old[-1]], track.centres[:old[-1]]
            tracks.append(track)
        self._tracks = tracks

    def _stands_still(self, track: _Track, centre_w: np.ndarray, now: float) -> bool:
        if not track.times or track.times[0] > now - self.window_s:
            return False                                  # not followed for a whole window yet
        moved = np.linalg.norm(np.asarray(track.centres) - centre_w, axis=1)
        return bool(np.max(moved) < self.max_move_m)


def _to_world(T_cw: np.ndarray):
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    return lambda p_c: R.T @ (p_c - t)


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
    votes = np.bincount(label_of_track[moving], minlength=n)
    total = np.bincount(label_of_track, minlength=n)
    confirmed = (votes >= min_votes) & (votes >= min_share * total)
    confirmed[0] = False                                       # label 0: outside every candidate region
    if not confirmed.any():
        return None
    track_depth = keypoints_in_mask(depth, tracks)
    centre = np.full(n, np.nan)
    for k in np.flatnonzero(confirmed):                        # a handful of regions at most
        d = track_depth[moving & (label_of_track == k) & (track_depth > 0)]
        if len(d):
            centre[k] = np.median(d)
    pixel_centre = centre[labels]
    with np.errstate(invalid="ignore"):
        region = np.abs(depth - pixel_centre) < band_m          # NaN centre (no region, no depth): False
    return region.astype(np.float32) if region.any() else None
