"""Free-space evidence for the keyframe masks: a surface seen now where another frame saw through to
something farther away was not there then: it moves (issue 11, item 1: depth consistency against what the
map's frames saw; in none of the four papers).

The keyframe masks (``masks/``) are a mask of *moving* surfaces. The methods that segment people
(box_depth, depth_sdf) flag whatever their box or fit holds: a desk or monitor in front of a person, the
floor around them, a person standing still. On people composited into real fr1/rpy frames the masks'
precision was 0.11-0.51 (generated rooms, where people stand in the open: 0.82-0.94). The test here is
geometric and needs no detector: each pixel of the keyframe, placed in the world with the keyframe's
tracked pose, is projected into the frames ``lags_s`` before it and, as they arrive, ``lags_s`` after it
(with their tracked poses); if such a frame saw a surface clearly *behind* that point, the space the point
occupies was empty then: the surface there moves. A static surface projects onto itself (consistent), one
hidden from the other frame projects behind a nearer surface (no evidence either way), and so does any
pixel outside the other frame's view or without depth (unknown). The later frames matter on a turning
camera: they see the parts of the view the earlier ones had not, and they give evidence at a run's start.

Where a pixel is known and consistent with every frame that knows it, the masks leave it out of the moving
surfaces (``keyframe_masks.compose_mask``) and keep it among the pixels never to be mapped (``_still``),
so a dense map leaves out what it left out before. A keyframe's mask is composed again once the last of its
later frames has been compared, if any of them added evidence (a ``RevisedMask``, as for a person found
standing still; the run's outputs rewrite the files), or at the run's end (``flush``). Tracking and the
sparse map are unchanged: this only sharpens the output masks, which can afford the tracked poses the
features could not wait for.

Why the numbers:

- ``lags_s`` 0.5 and 1.0 s: a walker at the slowest deliberate pace (0.5 m/s) has moved 0.25 / 0.5 m, one
  body width at 1 s, so most of their pixels in the keyframe land where the other frame saw past them; the
  second lag catches the parts where the body overlapped itself at the first.
- ``margin`` ``0.1 m + 3 sigma_z`` (sigma_z = 0.004 z^2, the back end's fitted depth noise): a violation
  must exceed the sensor's noise at the earlier surface's depth (1 m: 0.11 m; 4 m: 0.29 m) plus the
  relative pose error of tracked frames half a second apart (millimetres to ~2 cm).
- The earlier depth is min-filtered over ``window_px`` (20 px, 2 degrees at 525 px focal length): a rotation
  error, rolling shutter or lens distortion that shifts a depth edge by that much does not make the near
  side of an edge look as if it stood in front of the far side.
- A *region* of moving evidence, wider than that window everywhere (a morphological opening) and covering
  at least 1 % of the image, is flagged as moving even where no method flagged it: a person the detector
  misses while they fill the view (composited `border` on fr1/rpy: mask recall 0.12 -> 0.47). A depth edge
  misplaced by a pose error, rolling shutter or the 20 ms between fr1's colour and depth images looks moved
  only along a band narrower than the window; with the motion-capture poses on fr1/rpy-400 without people
  one keyframe in 67 had such a region (5,500 px).
- ``region_lags_s`` 0.25 s (``dynamic.mask_region_lags_s``): on a fast turn the long lags no longer see the
  part of the view a person has just walked into (fr1/rpy turns 14 degrees of its 62 in 0.25 s at the median
  rate, 56 in 1 s). A frame 0.25 s back does, and a walker at 1.2 m/s has moved 0.3 m since (the margin at
  2 m: 0.15 m). It adds to the regions only: inside a walker it may see the body where it is now, which
  must not count as "known unmoved" (``known`` and ``moving`` stay the long lags'). Composited ``border``
  on fr1/rpy: keyframe-mask recall 0.47 -> 0.59, the person walking in past the left border while the
  detector misses them (frames 252-255: 0.44 / 0.65 / 0.56 -> 0.76 / 0.88 / 0.71).
- Regions only from frame pairs that both turn slowly enough (``_steady``): a depth image is taken up to
  20 ms from its colour (TUM pairs them within 0.02 s), so at angular speed w a surface lies ``w * 0.02 *
  f`` px off where the pose puts it; above the 20 px window (1.9 rad/s at 525 px; 3 % of fr1/rpy's frames,
  none of Bonn crowd's) whole surfaces look moved, wider than the opening removes (a 30 x 70 px region on
  the person behind the monitor of composited ``stand_walk``, keyframe 121).
- The moving evidence is grown by ``_GROW_CELLS`` (the band the min filter leaves blind, and a cell), each
  step only into a neighbour whose depth is within the margin: the blind band lies on the surface that
  moved, not on the wall or desk beside it, which stay testable (grown in every direction, the evidence
  held 162 k of composited ``walk_stand``'s 355 k false pixels: background beside a person or an edge).
- Only evidence at least ``_SEED_CELLS`` (3 cells, 12 px) wide counts as moving, before it is grown: a depth
  edge that a pose error, rolling shutter or the colour/depth delay shifts past the min filter's window
  leaves evidence along the edge only one or two cells wide (the shift beyond the window's 10-px reach),
  and growing such a line by 24 px over its surface protected the false flags around it; a body part that
  moves is wider (an arm at 2 m: ~20 px). On people composited into fr1/rpy-400 (seed 0) the opening removed
  a quarter of the raw evidence's cells (walk_stand 4,797 of 19,084), 29 of them on a person; the masks'
  precision rose by 0.01-0.04 on every composite and seed, recall stayed within 0.01 (docs/dynamic.md, "Thin
  evidence").
- ``clear_lags_s`` 2 and 3 s (``dynamic.mask_clear_lags_s``), before and after: on fr1/rpy's turns the long
  lags often see nothing of part of a keyframe's view (out of their view, or hidden then): of composited
  walk_stand's false pixels (seed 0) 27.2 k of 67.9 k were unknown to them. Frames further away see much of
  it again, but their poses have drifted apart, so their "moved" made more false evidence than it found
  (the lags 1.5 and 2 s as full lags lowered precision: docs/dynamic.md, "Thin evidence"). Here they may
  only *clear*: a flagged cell the long lags knew nothing of is unmoved where every far frame that can tell
  saw it consistent; their "moved" counts for nothing. By 2 s a walker at 0.5 m/s has moved 1 m, clear of
  where they stood, so their far frames see past them, not them. Cells the long lags know are left as they
  were, so this can only take pixels out of a mask.
- Evidence on every 4th pixel in each direction (a 160 x 120 grid at VGA): ~19 k points per comparison,
  nine per keyframe with the default lags (0.5 / 1 / 2 / 3 s before and after, 0.25 s before): about a
  millisecond of numpy each; the growth ~1 ms per keyframe.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple, Optional

import cv2
import numba
import numpy as np

from slam.core.camera import PinholeCamera
from slam.core.geometry import rotation_angle_deg

_STEP = 4            # evidence on every 4th pixel in each direction
_GROW_CELLS = 6      # moving evidence grown by 6 cells (24 px): the min filter's blind band and a cell
_SEED_CELLS = 3      # moving evidence narrower than 3 cells (12 px) is a shifted depth edge, not grown
_NOISE_COEFF = 0.004  # sigma_z = 0.004 z^2 (backend.depth_noise_coeff, fitted on fr1/rpy)
_FAR = np.float32(1e6)  # invalid depth in the min filter
_OPEN_CELLS = 5      # a moving region is wider than 5 cells (20 px, the min filter's window) everywhere
_MIN_REGION = 0.01   # ... and covers 1 % of the image (3,000 px at VGA; a person whole at 4 m: ~12,000)
_DEPTH_COLOUR_S = 0.02  # a depth image is taken up to this long from its colour image (TUM's pairing bound)
_TURN_GAP_S = 0.1    # a turn rate needs the frame before within this (3 frames at 30 Hz)


class Evidence(NamedTuple):
    """A keyframe's free-space evidence, HxW bool each."""
    moving: np.ndarray     # some frame saw past the pixel's point (_SEED_CELLS wide, grown over its surface)
    known: np.ndarray      # some frame could tell
    region: np.ndarray     # moving as a whole region (_OPEN_CELLS wide, _MIN_REGION of the image), ungrown


@dataclass
class _Reference:
    """A tracked frame as the test reads it: its depth on the grid, the grid min-filtered, its pose."""
    timestamp: float
    depth: np.ndarray
    nearest: np.ndarray
    T_cw: np.ndarray
    steady: bool = True     # turning slowly enough that its depth lies where its pose puts it (_steady)


@dataclass
class _Keyframe:
    """A keyframe whose evidence is still growing: its grid cells with depth, in the world, and what the
    frames compared so far said about each."""
    key: Any
    timestamp: float
    shape: tuple[int, int]                  # full-resolution image shape
    valid: np.ndarray                       # grid cells with depth (bool, grid shape)
    depth: np.ndarray                       # the keyframe's depth on the grid (grid shape; NaN: none)
    world: np.ndarray                       # (N, 3) world points of those cells
    moving: np.ndarray                      # (N,) bool
    known: np.ndarray                       # (N,) bool
    due: list[tuple[float, bool]]           # later lags not yet compared (lag, clear-only), ascending
    far_known: np.ndarray                   # (N,) bool: some clear-only frame could tell
    far_moving: np.ndarray                  # (N,) bool: some clear-only frame saw the cell's space empty
    moved_before: Optional[np.ndarray] = None   # (N,) bool: what the earlier frames alone saw move
    changed: bool = False                   # a later frame added evidence not yet handed back


class FreeSpaceCheck:
    """Remembers the last frames (depth on the evidence grid and tracked pose) and tests a keyframe's
    pixels against the frames ``lags_s`` before it at once and against the frames ``lags_s`` after it as
    they arrive (see the module doc)."""

    def __init__(self, camera: PinholeCamera, lags_s: tuple[float, ...], margin_m: float, window_px: int,
                 region_lags_s: tuple[float, ...] = (), clear_lags_s: tuple[float, ...] = ()):
        self.camera = camera
        self.lags_s = tuple(sorted(float(v) for v in lags_s))
        self.region_lags_s = tuple(sorted(float(v) for v in region_lags_s)) if self.lags_s else ()
        self.clear_lags_s = tuple(sorted(float(v) for v in clear_lags_s)) if self.lags_s else ()
        self.margin_m = float(margin_m)
        self._window_px = float(window_px)
        radius = max(1, int(np.ceil(window_px / (2 * _STEP))))
        self._kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        self._frames: deque[_Reference] = deque()
        self._pending: list[_Keyframe] = []
        self._rays: Optional[np.ndarray] = None

    @property
    def enabled(self) -> bool:
        return bool(self.lags_s)

    def reset(self) -> None:
        self._frames.clear()
        self._pending = []

    def keyframe(self, key: Any, timestamp: float, depth: np.ndarray, T_cw: np.ndarray
                 ) -> Optional[Evidence]:
        """Test a keyframe against the earlier frames now; ``remember`` compares it with the later ones as
        they come and hands ``key`` back with the grown evidence. Returns the ``Evidence`` (HxW bool each:
        ``moving`` where a pixel stands in space another frame saw empty, ``known`` where some frame could
        tell, ``region`` the whole regions the earlier frames saw move), or None while no earlier frame
        could tell anything (the run's first half second)."""
        z = np.asarray(depth, np.float32)[::_STEP, ::_STEP]
        valid = np.isfinite(z) & (z > 0)
        points = self._grid_rays(z.shape)[valid] * z[valid, None].astype(float)      # camera frame
        T_wc = np.linalg.inv(T_cw)
        n = len(points)
        record = _Keyframe(key, float(timestamp), tuple(depth.shape), valid, np.where(valid, z, np.nan),
                           points @ T_wc[:3, :3].T + T_wc[:3, 3],
                           np.zeros(n, bool), np.zeros(n, bool),
                           sorted([(lag, False) for lag in self.lags_s] + [(lag, True) for lag in self.clear_lags_s]),
                           np.zeros(n, bool), np.zeros(n, bool))
        steady = self._steady(timestamp, T_cw)
        record.moved_before = np.zeros(n, bool)
        for reference in self._earlier(timestamp, self.lags_s):
            known, moving = self._test(record, reference)
            record.known |= known
            record.moving |= moving
            if steady and reference.steady:
                record.moved_before |= moving
        # The short lags add to the moving regions only (see region_lags_s in the module doc): inside a
        # walker they may see the body where it is now, which must not count as "known unmoved".
        for reference in self._earlier(timestamp, self.region_lags_s):
            if steady and reference.steady:
                record.moved_before |= self._test(record, reference)[1]
        for reference in self._earlier(timestamp, self.clear_lags_s):
            self._compare(record, reference, clear_only=True)
        self._pending.append(record)
        return self._pixels(record) if (record.known.any() or record.moved_before.any()
                                        or record.far_known.any()) else None

    def remember(self, timestamp: float, depth: np.ndarray, T_cw: np.ndarray) -> list[tuple[Any, Evidence]]:
        """A tracked frame: kept while it may serve as an earlier frame, and compared with the pending
        keyframes it is the first frame ``lag`` after. Returns (key, ``Evidence``) of the keyframes it was the
        last later frame of, whose evidence a later frame added to. Handed back once, not after every lag: each
        hand-over is a mask composed and its PNGs written again (Bonn crowd-480: 456 of them for 96 keyframes,
        ~5 ms of CPU per frame), and every one but the last was overwritten; the last is the same."""
        if not self.enabled:
            return []
        grid = np.asarray(depth, np.float32)[::_STEP, ::_STEP]
        grid = np.where(np.isfinite(grid) & (grid > 0), grid, _FAR)
        reference = _Reference(float(timestamp), grid, cv2.erode(grid, self._kernel), np.asarray(T_cw, float),
                               self._steady(timestamp, T_cw))
        self._frames.append(reference)
        horizon = timestamp - max(self.lags_s + self.region_lags_s + self.clear_lags_s) * 1.5
        while self._frames and self._frames[0].timestamp < horizon:
            self._frames.popleft()
        changed = []
        for record in self._pending:
            due = [d for d in record.due if timestamp >= record.timestamp + d[0]]
            if not due:
                continue
            record.due = [d for d in record.due if d not in due]
            # one comparison per kind of lag due (several lags falling due on one frame compare it once)
            told = [self._compare(record, reference, clear_only) for clear_only in sorted({c for _, c in due})]
            record.changed |= any(told)
            if not record.due and record.changed:
                changed.append((record.key, self._pixels(record)))
        self._pending = [r for r in self._pending if r.due]
        return changed

    def flush(self) -> list[tuple[Any, Evidence]]:
        """At the end of a run: (key, ``Evidence``) of the keyframes still waiting for a later frame whose
        evidence a later frame already added to (``remember`` hands a keyframe back after its last one)."""
        flushed = [(r.key, self._pixels(r)) for r in self._pending if r.changed]
        for record in self._pending:
            record.changed = False
        return flushed

    def _compare(self, record: _Keyframe, ref: _Reference, clear_only: bool = False) -> bool:
        """Fold one frame's evidence into a keyframe's; True if it knew any cell. A clear-only frame's
        goes to ``far_known`` / ``far_moving``, which can only clear cells the other lags knew nothing of."""
        known, moving = self._test(record, ref)
        if clear_only:
            record.far_moving |= moving
            record.far_known |= known
        else:
            record.moving |= moving
            record.known |= known
        return bool(known.any())

    def _test(self, record: _Keyframe, ref: _Reference) -> tuple[np.ndarray, np.ndarray]:
        """Per keyframe cell: whether ``ref`` can tell, and whether it saw the cell's space empty. The rotation
        is numpy's product (the same points as before); the projection and the comparisons one compiled pass
        (``_project_and_compare``: a dozen whole-array steps over ~19 k cells before, ~0.4 ms a call)."""
        p = record.world @ ref.T_cw[:3, :3].T + ref.T_cw[:3, 3]
        cam = self.camera
        return _project_and_compare(p, ref.depth, ref.nearest, float(cam.fx), float(cam.fy), float(cam.cx),
                                    float(cam.cy), _STEP, self.margin_m, _NOISE_COEFF)

    def _pixels(self, record: _Keyframe) -> Evidence:
        moving = np.zeros(record.valid.shape, np.uint8)
        known = np.zeros(record.valid.shape, np.uint8)
        moving[record.valid] = record.moving
        # The clear-only lags tell only where the others could not, and only "unmoved": a cell every
        # far frame that could tell saw consistent (a far frame's "moved" may be its drifted pose).
        known[record.valid] = record.known | (~record.known & record.far_known & ~record.far_moving)
        # The regions from the earlier frames only: a later frame that sees past a person says they will
        # have left, not that they move now (a person standing, then walking away).
        region = np.zeros(record.valid.shape, np.uint8)
        region[record.valid] = record.moved_before
        region = cv2.morphologyEx(region, cv2.MORPH_OPEN, np.ones((_OPEN_CELLS, _OPEN_CELLS), np.uint8))
        _, labels, stats, _ = cv2.connectedComponentsWithStats(region, connectivity=8)
        big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= _MIN_REGION * region.size)
        region = np.isin(labels, big[big > 0]).astype(np.uint8)
        moving = cv2.morphologyEx(moving, cv2.MORPH_OPEN, np.ones((_SEED_CELLS, _SEED_CELLS), np.uint8))
        moving = self._grow_along_surfaces(moving.astype(bool), record.depth).astype(np.uint8)
        full = (record.shape[1], record.shape[0])

        def up(cells: np.ndarray) -> np.ndarray:
            return cv2.resize(cells, full, interpolation=cv2.INTER_NEAREST).astype(bool)
        return Evidence(up(moving), up(known), up(region))

    def _steady(self, timestamp: float, T_cw: np.ndarray) -> bool:
        """Whether a frame turns slowly enough (against the frame remembered before it) that its depth, taken
        up to ``_DEPTH_COLOUR_S`` from the colour its pose was tracked on, shifts by less than the min
        filter's window: a faster turn misplaces whole surfaces by more than the regions' opening removes.
        Unknown (no frame just before) counts as steady."""
        if not self._frames or not 0 < timestamp - self._frames[-1].timestamp <= _TURN_GAP_S:
            return True
        last = self._frames[-1]
        turn = np.radians(float(rotation_angle_deg(np.asarray(T_cw)[:3, :3] @ last.T_cw[:3, :3].T)))
        shift_px = turn / (timestamp - last.timestamp) * _DEPTH_COLOUR_S * max(self.camera.fx, self.camera.fy)
        return shift_px <= self._window_px

    def _margin(self, z: np.ndarray) -> np.ndarray:
        """How far (m) a surface at depth ``z`` may lie from another before it counts: ``margin_m`` + 3 sigma_z."""
        return self.margin_m + 3.0 * _NOISE_COEFF * z ** 2

    def _grow_along_surfaces(self, moving: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """``moving`` (grid bool) grown by ``_GROW_CELLS`` cells, each step only into a neighbour whose depth
        is within the test's margin of the moving cell's: the band the min filter leaves blind lies on the
        surface that moved, not on the wall or desk beside it. A compiled loop (``_grow``): as whole-array
        steps it was 48 shifted comparisons per step, ~0.6 ms a call."""
        tolerance = self._margin(np.nan_to_num(depth, nan=0.0))
        return _grow(moving, np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(tolerance, np.float64),
                     _GROW_CELLS)

    def _earlier(self, timestamp: float, lags_s: tuple[float, ...]) -> list[_Reference]:
        """Per lag, the remembered frame nearest ``timestamp - lag``, at least half the lag back."""
        chosen: list[_Reference] = []
        for lag in lags_s:
            candidates = [f for f in self._frames if f.timestamp <= timestamp - lag / 2]
            if not candidates:
                continue
            best = min(candidates, key=lambda f: abs(f.timestamp - (timestamp - lag)))
            if all(best is not c for c in chosen):
                chosen.append(best)
        return chosen

    def _grid_rays(self, shape: tuple[int, int]) -> np.ndarray:
        if self._rays is None or self._rays.shape[:2] != shape:
            rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float) * _STEP
            cam = self.camera
            self._rays = np.dstack([(cols - cam.cx) / cam.fx, (rows - cam.cy) / cam.fy, np.ones(shape)])
        return self._rays


@numba.njit(nogil=True, cache=True)
def _grow(moving, depth, tolerance, steps):
    """``steps`` times: every cell with a grown 8-neighbour whose depth lies within the cell's ``tolerance``
    of its own joins (a cell without depth, NaN, never joins nor passes it on); stops early when none does.
    Only the last step's new cells are looked around: an older neighbour that did not take a cell in before
    never will (the depths do not change)."""
    h, w = moving.shape
    grown = moving.copy()
    front_r = np.empty(h * w, np.int64)
    front_c = np.empty(h * w, np.int64)
    n_front = 0
    for r in range(h):
        for c in range(w):
            if grown[r, c]:
                front_r[n_front], front_c[n_front] = r, c
                n_front += 1
    new_r = np.empty(h * w, np.int64)
    new_c = np.empty(h * w, np.int64)
    for _ in range(steps):
        n_new = 0
        for f in range(n_front):
            fr, fc = front_r[f], front_c[f]
            df = depth[fr, fc]
            for dy in range(-1, 2):
                r = fr + dy
                if r < 0 or r >= h:
                    continue
                for dx in range(-1, 2):
                    c = fc + dx
                    if (dy == 0 and dx == 0) or c < 0 or c >= w or grown[r, c]:
                        continue
                    if abs(depth[r, c] - df) <= tolerance[r, c]:     # False for NaN on either side
                        grown[r, c] = True          # joins at the end of this step: no cell looks at it now,
                        new_r[n_new], new_c[n_new] = r, c   # since only the last step's cells are looked around
                        n_new += 1
        if n_new == 0:
            break
        front_r, new_r = new_r, front_r
        front_c, new_c = new_c, front_c
        n_front = n_new
    return grown


@numba.njit(nogil=True, cache=True)
def _project_and_compare(p, depth, nearest, fx, fy, cx, cy, step, margin_m, noise_coeff):
    """``FreeSpaceCheck._test`` per point of ``p`` (the other frame's camera): its grid cell in that frame;
    known where it lies in front of the depth seen there or within the margin behind it (not hidden), moving
    where it also lies in front of the nearest depth around by more than the margin."""
    gh, gw = depth.shape
    n = len(p)
    known = np.zeros(n, np.bool_)
    moving = np.zeros(n, np.bool_)
    far = np.float32(_FAR)
    for t in range(n):
        z = p[t, 2]
        if not z > 1e-6:
            continue
        col = np.int64(np.rint((fx * p[t, 0] / z + cx) / step))
        row = np.int64(np.rint((fy * p[t, 1] / z + cy) / step))
        if col < 0 or col >= gw or row < 0 or row >= gh:
            continue
        seen = depth[row, col]
        if not seen < far:
            continue
        seen64 = np.float64(seen)
        margin = margin_m + 3.0 * noise_coeff * seen64 ** 2
        if z <= seen64 + margin:
            known[t] = True
            moving[t] = z < np.float64(nearest[row, col]) - margin
    return known, moving
