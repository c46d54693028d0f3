"""Something nearer than the depth sensor measures (issue 11, item 1; in none of the four papers).

A structured-light RGB-D camera (TUM's Kinect, Bonn's Xtion) returns no depth nearer than about 0.5 m, so
a person who walks past within arm's length is a hole in the depth image: cpr, box_depth and depth_sdf
see nothing there, and when the detector misses the person too (blur, a torso without a head), their
features are unflagged and count as static. This is the map's prediction against the depth image: a hole
where the previous frame, moved by the predicted pose, had a surface well within range is something in
front of that surface, nearer than the sensor measures -- if the image there no longer shows that surface.

Per frame, at a quarter of the resolution (a region-level decision, not per feature):

1. The previous frame's valid depth is warped into this frame with the predicted pose (a z-buffered
   forward splat); each hole component of this frame's depth (after a 3x3 opening: edge dropouts are a
   pixel or two wide) is *seen* where the warp put a surface (nearer than ``_MAX_SEEN_M``).
2. A component counts as *newly near* when at least ``_MIN_SEEN_SHARE`` of it was seen, and either that
   surface was already at the edge of the range (median nearer than ``_NEAR_EDGE_M``: a person walking up
   to the camera is measured at 0.5-0.6 m on the frame before they vanish) and the image still shows it
   (had it gone, the image would show what lies behind it), or it was farther and the image there differs
   from the warped previous image by more than ``_MIN_CHANGE`` (median absolute grey difference):
   something arrived in front of it, where a specular surface (a monitor, glass) that merely stops
   returning depth at this angle still shows itself.
3. A flagged hole is followed cell for cell: last frame's flags stay on this frame's holes (grown to the
   whole component when at least ``_MIN_FOLLOWED_SHARE`` of it was flagged, or to its fresh cells when they
   show an arrival), for at most ``_MAX_CARRY_FRAMES`` frames after the last frame that renewed it; a
   flagged component that uncovers another 1 % of the image of arriving surface is renewed (a person who
   moves keeps uncovering what was behind them).
4. Cells that had no depth in most of the last ~50 frames (``_MEASURED_RATE``: the border band the depth
   camera never covers, a window beyond range) are no holes at all.

Everything is a function of the frames and the poses given: deterministic. Exact synthetic depth has no
holes (the generated rooms are closed), so there nothing changes.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numba
import numpy as np

from slam.core.camera import PinholeCamera

_SCALE = 4
"""Quarter resolution: 160 x 120 cells at 640 x 480; a person within a metre covers thousands of them."""
_MIN_AREA_SHARE = 0.01
"""A component smaller than this share of the image is a dropout (an edge, a dark patch), not a person
within a metre (who covers a tenth of the view or more)."""
_NEAR_EDGE_M = 0.8
"""A surface measured nearer than this a frame ago is at the edge of the sensors' ~0.5 m range: a hole
there now is that surface come nearer still (a person walking up to the lens). The nearest valid depth of
fr1/rpy-400 is 0.58 m and of Bonn crowd-480 0.75 m, with nothing of the static scenes vanishing there."""
_MAX_SEEN_M = 4.0
"""Farther surfaces drop out of a Kinect's depth on their own (range noise, low reflectance)."""
_MIN_SEEN_SHARE = 0.5
"""At least half of a hole component had a surface in range a frame ago: a person arriving; a static hole
(beyond range, glass) had no depth in the frame before either."""
_MIN_CHANGE = 25.0
"""Grey levels (of 255): the image over the hole no longer shows the surface the warp predicts there (a
person in front of a wall differs by far more; the same surface seen a frame later by far less, blur
included, at the 8-bit noise of a few levels)."""
_MIN_FOLLOWED_SHARE = 0.5
"""A hole component at least this much flagged a frame ago is the followed hole, grown (a person walking
nearer covers more of the view each frame); less, and a static hole has joined it: only its fresh cells."""
_MAX_CARRY_FRAMES = 30
"""One second at 30 Hz: a flag that no frame re-confirms (a person standing still within half a metre, or
a static hole flagged by mistake) lapses."""
_MEASURED_RATE = 0.02
"""The running share of frames in which a cell has valid depth moves by this per frame (a time constant of
50 frames): a cell without depth for more than ~35 frames in a row (the depth camera's unseen border, a
window beyond range) no longer counts as a hole -- about when a flag no frame renews lapses anyway."""
_NO_FLAG = np.uint8(255)


def _quarter(image: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(image[_SCALE // 2::_SCALE, _SCALE // 2::_SCALE])


class NearOccluder:
    """Hole regions of the depth image that hide a surface seen a frame ago (see the module docstring)."""

    def __init__(self, camera: PinholeCamera):
        self.camera = camera
        self._prev: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]] = None   # depth, grey (quarter), T_cw
        self._age: Optional[np.ndarray] = None      # per cell: frames since the flag was renewed (255: none)
        self._pending: Optional[tuple[np.ndarray, np.ndarray]] = None    # this frame's quarter depth and grey
        self._measured: Optional[np.ndarray] = None   # per cell: a running share of frames with valid depth

    def update(self, depth: np.ndarray, gray: np.ndarray, predicted_T_cw: Optional[np.ndarray]
               ) -> Optional[np.ndarray]:
        """HxW bool of this frame's near occluders, or None when there are none."""
        depth_q, gray_q = _quarter(depth), _quarter(gray)
        self._pending = (depth_q, gray_q)
        holes = self._holes(depth_q)
        if holes is None or self._prev is None or predicted_T_cw is None or depth_q.shape != self._prev[0].shape:
            self._age = None
            return None
        labels, big = holes
        # only what lands on or beside (2 cells: the gap closing's reach) a big hole is ever read
        near_big = cv2.dilate(big[labels].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        seen_depth, seen_gray = self._warp_previous(predicted_T_cw, near_big)
        self._age = self._flag(labels, big, seen_depth, seen_gray, gray_q)
        cells = self._age != _NO_FLAG
        if not cells.any():
            return None
        full = cv2.resize(cells.astype(np.uint8), (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_NEAREST)
        return full.astype(bool)

    def _holes(self, depth_q: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(component labels, per label: big enough) of this frame's holes, None without a big one; counts
        the frame in the running share of valid depth."""
        valid = (depth_q > 0).astype(np.float32)
        if self._measured is None or self._measured.shape != valid.shape:
            self._measured = valid
        else:
            self._measured = (1 - _MEASURED_RATE) * self._measured + _MEASURED_RATE * valid
        # holes where the sensor usually measures: not the band along the border that the depth camera's
        # narrower view never covers (a turn warps surfaces into it) nor what lies beyond its range
        hole = cv2.morphologyEx(((valid == 0) & (self._measured >= 0.5)).astype(np.uint8), cv2.MORPH_OPEN,
                                np.ones((3, 3), np.uint8))
        if not hole.any():
            return None
        _, labels, stats, _ = cv2.connectedComponentsWithStats(hole, connectivity=8)
        big = stats[:, cv2.CC_STAT_AREA] >= _MIN_AREA_SHARE * hole.size
        big[0] = False                                       # label 0: the valid depth around the holes
        return (labels, big) if big.any() else None

    def _flag(self, labels: np.ndarray, big: np.ndarray, seen_depth: np.ndarray, seen_gray: np.ndarray,
              gray_q: np.ndarray) -> np.ndarray:
        """Per cell, the age of its flag (``_NO_FLAG``: none): new arrivals, and last frame's flags followed."""
        n = len(big)
        seen = (seen_depth > 0) & (seen_depth < _MAX_SEEN_M) & (labels > 0)
        # last frame's flags on this frame's holes, cell for cell: the person's hole overlaps itself from
        # frame to frame, and its new cells were a surface a frame ago (seen). Not grown: a flag grown by a
        # cell a frame creeps over a static hole that touches the person's (fr1's black monitor)
        before = self._age_before(labels.shape)
        carried = (before != _NO_FLAG) & (labels > 0)
        flat = labels.ravel()
        area = np.bincount(flat, minlength=n)
        n_seen = np.bincount(flat, weights=seen.ravel(), minlength=n)
        n_carried = np.bincount(flat, weights=carried.ravel(), minlength=n)
        # New: most of the component was a surface a frame ago (all of it is the arrival), or a flagged
        # component uncovered a person's worth of such cells again (still moving: the flag is renewed).
        whole = big & (n_seen >= _MIN_SEEN_SHARE * area)
        renewed = big & (n_carried > 0) & (n_seen >= _MIN_AREA_SHARE * labels.size)
        age = np.full(labels.shape, _NO_FLAG, np.uint8)
        for label in np.flatnonzero(big & (whole | (n_carried > 0))):   # a handful of components at most
            comp = labels == label
            fresh = comp & seen
            arrived = self._newly_near(fresh, seen_depth, seen_gray, gray_q)
            if arrived and (whole[label] or renewed[label]):
                # mostly arrival, or a flagged hole that keeps uncovering a person's worth of surface: all of
                # it (a hole's first frame may be too small to count, and its cells are unseen after)
                age[comp] = 0
                continue
            part = comp & carried
            if not part.any():
                continue
            older = before[part] + np.uint8(1)                # below _MAX_CARRY_FRAMES: no overflow
            age[part] = older
            if n_carried[label] >= _MIN_FOLLOWED_SHARE * area[label]:
                age[comp & ~part] = older.min()       # mostly the followed hole: it grew (a person nearing)
            elif arrived:
                age[fresh & ~part] = older.min()      # grown over what was a surface a frame ago
        age[age > _MAX_CARRY_FRAMES] = _NO_FLAG
        return age

    def _age_before(self, shape: tuple[int, int]) -> np.ndarray:
        """Last frame's flag ages that may still be carried (``_NO_FLAG`` elsewhere)."""
        if self._age is None or self._age.shape != shape:
            return np.full(shape, _NO_FLAG, np.uint8)
        return np.where(self._age < _MAX_CARRY_FRAMES, self._age, _NO_FLAG)

    @staticmethod
    def _newly_near(cells: np.ndarray, seen_depth: np.ndarray, seen_gray: np.ndarray, gray: np.ndarray) -> bool:
        """The surface seen a frame ago over ``cells`` was at the edge of the range and the image still shows
        it (it came nearer; had it gone, the image would show what lies behind), or it was well within range
        and the image no longer shows it (something came in front)."""
        if not cells.any():
            return False
        changed = float(np.median(np.abs(gray[cells].astype(np.float32) - seen_gray[cells]))) > _MIN_CHANGE
        return not changed if np.median(seen_depth[cells]) < _NEAR_EDGE_M else changed

    def _warp_previous(self, T_cw: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The previous frame's valid depth and grey, forward-splatted into this frame's quarter grid with
        the nearest surface winning; 0 depth where nothing lands. Only cells under ``keep`` (quarter grid,
        bool) are filled: elsewhere 0. The back-projection and the splat are compiled loops (``_cell_points``,
        ``_splat``: ~19 k points a frame, where a dozen whole-array steps cost ~1 ms on fr1/rpy); the rotation
        stays numpy's product, so the points are the same bits as before."""
        prev_depth, prev_gray, prev_T_cw = self._prev
        cam = self.camera
        xyz, cells = _cell_points(prev_depth, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), _SCALE)
        rel = T_cw @ np.linalg.inv(prev_T_cw)
        p = xyz @ rel[:3, :3].T + rel[:3, 3]
        h, w = keep.shape
        depth_img, gray_img = _splat(p, cells, prev_gray.ravel(), keep, float(cam.fx), float(cam.fy), float(cam.cx),
                                     float(cam.cy), _SCALE)
        landed = (depth_img > 0).astype(np.uint8)
        if not landed.any():
            return depth_img, gray_img
        # a splat leaves one-cell gaps where the view stretches: a 3x3 closing finds them, a 3x3 maximum fills
        # them (depth only decides *whether* a surface was there; its grey comes along); the closing does not
        # grow the splat's outline into the holes around it
        kernel = np.ones((3, 3), np.uint8)
        gaps = (cv2.morphologyEx(landed, cv2.MORPH_CLOSE, kernel) > 0) & (landed == 0)
        filled = cv2.dilate(depth_img, kernel)
        gray_img[gaps] = cv2.dilate(gray_img, kernel)[gaps]
        depth_img[gaps] = filled[gaps]
        return depth_img, gray_img

    def end_frame(self, T_cw: Optional[np.ndarray]) -> None:
        """This frame becomes the previous one, with its final pose (None: lost, no prediction next)."""
        if self._pending is None or T_cw is None:
            self._prev = None
        else:
            self._prev = (*self._pending, np.asarray(T_cw, float))
        self._pending = None


@numba.njit(nogil=True, cache=True)
def _cell_points(depth_q, fx, fy, cx, cy, scale):
    """The quarter grid's cells with depth as camera points (N, 3) (each cell at its full-resolution pixel),
    and their flat cell indices, in row-major order."""
    h, w = depth_q.shape
    n = 0
    for r in range(h):
        for c in range(w):
            if depth_q[r, c] > 0:
                n += 1
    xyz = np.empty((n, 3))
    cells = np.empty(n, np.int64)
    k = 0
    for r in range(h):
        for c in range(w):
            d = depth_q[r, c]
            if d > 0:
                z = np.float64(d)
                u = np.float64(c * scale + scale // 2)
                v = np.float64(r * scale + scale // 2)
                xyz[k, 0] = (u - cx) / fx * z
                xyz[k, 1] = (v - cy) / fy * z
                xyz[k, 2] = z
                cells[k] = r * w + c
                k += 1
    return xyz, cells


@numba.njit(nogil=True, cache=True)
def _splat(p, cells, gray, keep, fx, fy, cx, cy, scale):
    """Points ``p`` (this frame's camera) more than 0.1 m in front, projected onto the quarter grid: per cell
    under ``keep`` the nearest one's depth and its grey (``gray`` read at its source cell); the first point
    in order wins a tie in depth, as a stable sort by (cell, depth) keeps it."""
    h, w = keep.shape
    depth_out = np.zeros((h, w), np.float32)
    gray_out = np.zeros((h, w), np.float32)
    best = np.full(h * w, np.inf)
    for t in range(len(p)):
        z = p[t, 2]
        if not z > 0.1:
            continue
        u = np.int64(np.floor((fx * p[t, 0] / z + cx) / scale))
        v = np.int64(np.floor((fy * p[t, 1] / z + cy) / scale))
        if u < 0 or u >= w or v < 0 or v >= h or not keep[v, u]:
            continue
        if z < best[v * w + u]:
            best[v * w + u] = z
            depth_out[v, u] = np.float32(z)
            gray_out[v, u] = np.float32(gray[cells[t]])
    return depth_out, gray_out
