"""Free-space evidence for the keyframe masks: a surface seen now where an earlier frame saw through to
something farther away has moved into that space (issue 11, item 1: depth consistency against what the
map's frames saw; in none of the four papers).

The keyframe masks (``masks/``) are a mask of *moving* surfaces. The methods that segment people
(box_depth, depth_sdf) flag whatever their box or fit holds: a desk or monitor in front of a person, the
floor around them, a person standing still. On people composited into real fr1/rpy frames the masks'
precision was 0.11-0.51 (generated rooms, where people stand in the open: 0.82-0.94). The test here is
geometric and needs no detector: each pixel of the keyframe, placed in the world with the keyframe's
tracked pose, is projected into earlier frames (``lags_s`` before, with their tracked poses); if an
earlier frame saw a surface clearly *behind* that point, the space the point occupies was empty then, so
the surface there now moved in. A static surface projects onto itself (consistent), one hidden in the
earlier frame projects behind a nearer surface (no evidence either way), and so does any pixel outside the
earlier frame's view or without depth (unknown).

Where a pixel is known and consistent with every earlier frame, the masks leave it out of the moving
surfaces (``keyframe_masks.compose_mask``) and keep it among the pixels never to be mapped (``_still``),
so a dense map leaves out what it left out before. Tracking and the sparse map are unchanged: this only
sharpens the output masks, which can afford the tracked pose the features could not wait for.

Why the numbers:

- ``lags_s`` 0.5 and 1.0 s: a walker at the slowest deliberate pace (0.5 m/s) has moved 0.25 / 0.5 m, one
  body width at 1 s, so most of their pixels in the keyframe land where an earlier frame saw past them; the
  second lag catches the parts where the body overlapped itself at the first.
- ``margin`` ``0.1 m + 3 sigma_z`` (sigma_z = 0.004 z^2, the back end's fitted depth noise): a violation
  must exceed the sensor's noise at the earlier surface's depth (1 m: 0.11 m; 4 m: 0.29 m) plus the
  relative pose error of tracked frames half a second apart (millimetres to ~2 cm).
- The earlier depth is min-filtered over ``window_px`` (20 px, 2 degrees at 525 px focal length): a rotation
  error, rolling shutter or lens distortion that shifts a depth edge by that much does not make the near
  side of an edge look as if it stood in front of the far side.
- Evidence on every 4th pixel in each direction (a 160 x 120 grid at VGA), grown by ``_GROW_CELLS`` cells:
  ~19 k points per earlier frame, well under a millisecond of numpy at a keyframe.
"""
from __future__ import annotations

from collections import deque
from typing import Optional

import cv2
import numpy as np

from slam.core.camera import PinholeCamera

_STEP = 4            # evidence on every 4th pixel in each direction
_GROW_CELLS = 6      # moving evidence grown by 6 cells (24 px): the min filter's blind band and a cell
_NOISE_COEFF = 0.004  # sigma_z = 0.004 z^2 (backend.depth_noise_coeff, fitted on fr1/rpy)
_FAR = np.float32(1e6)  # invalid depth in the min filter


class FreeSpaceCheck:
    """Remembers the last second of tracked frames (depth on the evidence grid and pose) and tests a
    keyframe's pixels against them (see the module doc)."""

    def __init__(self, camera: PinholeCamera, lags_s: tuple[float, ...], margin_m: float, window_px: int):
        self.camera = camera
        self.lags_s = tuple(float(v) for v in lags_s)
        self.margin_m = float(margin_m)
        radius = max(1, int(np.ceil(window_px / (2 * _STEP))))
        self._kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        # (t, depth on the grid, its min-filtered copy, T_cw)
        self._frames: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._rays: Optional[np.ndarray] = None

    @property
    def enabled(self) -> bool:
        return bool(self.lags_s)

    def reset(self) -> None:
        self._frames.clear()

    def remember(self, timestamp: float, depth: np.ndarray, T_cw: np.ndarray) -> None:
        """A tracked frame, kept while it may serve as the earlier frame of a later keyframe."""
        if not self.enabled:
            return
        grid = np.asarray(depth, np.float32)[::_STEP, ::_STEP]
        grid = np.where(np.isfinite(grid) & (grid > 0), grid, _FAR)
        self._frames.append((float(timestamp), grid, cv2.erode(grid, self._kernel), np.asarray(T_cw, float)))
        horizon = timestamp - max(self.lags_s) * 1.5
        while self._frames and self._frames[0][0] < horizon:
            self._frames.popleft()

    def evidence(self, timestamp: float, depth: np.ndarray, T_cw: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(moving, known), HxW bool, for a frame at ``timestamp`` with pose ``T_cw``: ``moving`` where a
        pixel stands in space an earlier frame saw empty, ``known`` where some earlier frame could tell.
        None when no earlier frame is far enough back (the run's first half second)."""
        references = self._references(timestamp)
        if not references:
            return None
        h, w = depth.shape
        z = np.asarray(depth, np.float32)[::_STEP, ::_STEP]
        valid = np.isfinite(z) & (z > 0)
        rays = self._grid_rays(z.shape)
        points = rays[valid] * z[valid, None].astype(float)          # camera frame, (N, 3)
        T_wc = np.linalg.inv(T_cw)
        world = points @ T_wc[:3, :3].T + T_wc[:3, 3]
        moving_cells = np.zeros(len(points), bool)
        known_cells = np.zeros(len(points), bool)
        gh, gw = z.shape
        cam = self.camera
        for ref_depth, ref_nearest, ref_T_cw in references:
            p = world @ ref_T_cw[:3, :3].T + ref_T_cw[:3, 3]
            front = p[:, 2] > 1e-6
            zr = np.where(front, p[:, 2], 1.0)
            col = np.rint((cam.fx * p[:, 0] / zr + cam.cx) / _STEP).astype(np.int64)
            row = np.rint((cam.fy * p[:, 1] / zr + cam.cy) / _STEP).astype(np.int64)
            inside = front & (col >= 0) & (col < gw) & (row >= 0) & (row < gh)
            seen = np.full(len(p), _FAR, np.float32)
            nearest = np.full(len(p), _FAR, np.float32)
            seen[inside] = ref_depth[row[inside], col[inside]]
            nearest[inside] = ref_nearest[row[inside], col[inside]]
            margin = self.margin_m + 3.0 * _NOISE_COEFF * seen.astype(float) ** 2
            # Behind the earlier surface: hidden then, no evidence. In front of the nearest surface near
            # where it lands: moving.
            known = inside & (seen < _FAR) & (p[:, 2] <= seen + margin)
            moving_cells |= known & (p[:, 2] < nearest - margin)
            known_cells |= known
        moving = np.zeros(z.shape, np.uint8)
        known = np.zeros(z.shape, np.uint8)
        moving[valid] = moving_cells
        known[valid] = known_cells
        grow = np.ones((2 * _GROW_CELLS + 1,) * 2, np.uint8)
        moving = cv2.dilate(moving, grow)
        full = (w, h)
        moving_px = cv2.resize(moving, full, interpolation=cv2.INTER_NEAREST).astype(bool)
        known_px = cv2.resize(known, full, interpolation=cv2.INTER_NEAREST).astype(bool)
        return moving_px, known_px

    def _references(self, timestamp: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per lag, the remembered frame nearest ``timestamp - lag``, at least half the lag back."""
        chosen, seen_ids = [], set()
        for lag in self.lags_s:
            candidates = [(abs(f[0] - (timestamp - lag)), k) for k, f in enumerate(self._frames)
                          if f[0] <= timestamp - lag / 2]
            if not candidates:
                continue
            k = min(candidates)[1]
            if k not in seen_ids:
                seen_ids.add(k)
                chosen.append(self._frames[k][1:])
        return chosen

    def _grid_rays(self, shape: tuple[int, int]) -> np.ndarray:
        if self._rays is None or self._rays.shape[:2] != shape:
            rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float) * _STEP
            cam = self.camera
            self._rays = np.dstack([(cols - cam.cx) / cam.fx, (rows - cam.cy) / cam.fy, np.ones(shape)])
        return self._rays
