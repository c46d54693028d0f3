"""Optical flow + epipolar geometry + region probability propagation (PPS-SLAM, seed 002).

Algorithm 1 (precise dynamic region search), per frame:

1. The previous frame's ORB keypoints (raw pixel coordinates) are tracked into the current grey image
   with pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``).
2. A fundamental matrix is fitted to the tracked pairs with RANSAC (``cv2.findFundamentalMat``,
   ``FM_RANSAC``, which draws from a generator fixed inside the call: the same samples every run and
   whatever ``cfg.seed``, see ``fundamental``) and refitted by the normalised 8-point
   method on the RANSAC inliers ("RANSAC removes the flow vectors that deviate from the motion model
   ... for the subsequent calculation of a more precise fundamental matrix").
3. A tracked point is dynamic when its distance to the epipolar line of its previous position is
   > ``epipolar_px`` (2 px, the paper's ``Distancethreshold``).
4. Every box of a potential dynamic object (``ClassGroups.dynamic``, score >= ``detector_score`` = 0.6,
   the paper's YOLOv8 confidence) is split into ``sub_box_rows`` x ``sub_box_cols`` sub-boxes (Eq. 1).
   A sub-box is a dynamic region when DP = (dynamic tracked points) / (tracked points) inside it is
   > theta = ``region_ratio`` = 0.5 (Eqs. 2-6). Current-frame keypoints in dynamic sub-boxes are
   dynamic (prob 1); the static sub-boxes of a box keep their features (a still person stays usable).

Frames without any dynamic box skip steps 1-3 (their result would not be used).

Algorithm 2 (dynamic region probability propagation): the image is divided into ``grid`` x ``grid``
(10 x 10) cells. A cell's likelihood is ``likelihood_dynamic`` (0.9) when the dynamic sub-boxes of
Algorithm 1 cover > ``cover_ratio`` (0.65) of its area, else ``likelihood_static`` (0.1). The prior is
the mean of the cell's posteriors over the last ``history`` (10) frames and the posterior is
``L P / (L P + (1 - L)(1 - P))`` (Eqs. 8-10). Features in cells whose posterior is >
``remove_threshold`` are removed. This keeps a region dynamic through frames where detection fails.

Output: per keypoint, ``prob`` = 1 inside a dynamic sub-box, else the posterior of its grid cell mapped
piecewise-linearly so that "posterior > remove_threshold" is exactly "prob >= 0.5" (identity for the
default threshold 0.5, except that a posterior of exactly the threshold, which is *not* removed in the
paper, maps just below 0.5). The mask (float32) is 1 on the dynamic sub-boxes and the mapped cell
posterior elsewhere, so that ``mask >= 0.5`` is the union of dynamic sub-boxes and removed cells and
``keypoints_in_mask(mask, uv_raw)`` reproduces ``prob`` up to pixel rounding.

Choices where the paper is silent or vague (all in ``FlowEpipolarConfig``):

* Sub-box split: the paper does not state it; 3 x 3 by default (finer than CDS-SLAM's halves, which
  the paper criticises, while keeping enough tracked points per sub-box for a ratio).
* Algorithm 1's listing prints "Dynamic possibility(rect) <= 0.5" (a typesetting garble); Eq. 6
  (DP > theta) is followed. A sub-box without tracked points has no evidence and stays static.
* LK: window ``lk_window`` = 21, ``lk_levels`` = 3, 30 iterations / 0.01 px (OpenCV's defaults, as
  DS-SLAM), at full resolution. ``lk_start_level`` = 1 with ``lk_window`` = 11 runs the same on the
  half-resolution image (the window covers the same 22 px of the full image, the pyramid reaches one level
  further): 5.0 instead of 18.3 ms of CPU per frame (1000 ORB corners, fr1/rpy, one thread), positions
  0.11 px from the full-resolution flow (median; 95 % within 0.5 px, 0.2 % beyond 2 px, far below
  ``epipolar_px``). Measured 2026-11-27 (``tools/sweep.py``, seeds 0-2, ATE median): Bonn crowd-480 0.0103
  -> 0.0104 m, fr1/rpy-400 0.0227 -> 0.0232 m; ``tools/benchmark.py``: CPU per frame 136.6 -> 132.6 ms on
  fr1/rpy, 160.3 -> 143.9 on Bonn, but the whole run did not get faster on fr1/rpy (89.4 / 89.2 ms per
  frame: tracking then waits for cpr instead, 7.0 -> 15.8 ms). Not the default: the generated three_close
  scene (``tools/hard_scenes.py three_close``) went 1.49x -> 2.02x the ATE without people, over the
  issue's 1.5x; it is that fragile to any change of the flow (full resolution with windows 19 / 23:
  1.90x / 1.80x), its tracking drifting 8-22 mm while people cover 73-81 % of the view (frames 107-110).
  A forward-backward check is available (``fb_max_px`` > 0 drops tracks that do not come
  back within that many pixels) but off by default: on Bonn crowd (frames 225-284) a 1 px check
  discarded 18 % of the tracks inside person boxes (about half of them dynamic) and only 1.3 % outside,
  lowering the outside false-dynamic rate from 0.7 % to 0.5 % while missing more moving sub-boxes, and
  it doubles the LK time.
* F is estimated from the tracks *outside* the dynamic boxes when at least ``min_tracks`` of them exist
  (``f_outside_boxes``), else from all tracks. The paper feeds all tracks to RANSAC; on Bonn crowd
  people cover a large part of the image and F then absorbs part of their motion: over frames 225-284
  all-track F found 3298 dynamic tracks and 133 dynamic sub-boxes, outside-box F 7962 and 302, with
  the same 0.5-0.7 % false-dynamic rate outside the boxes. RANSAC threshold ``ransac_px`` = 1 px. The
  epipolar test runs on undistorted coordinates (``camera.undistort_points``).
* Frames without motion evidence (the first frame; fewer than ``min_tracks`` tracks; F degenerate) use
  the detections only: every sub-box of a dynamic box counts as dynamic. The first frame initialises
  the map, where the conservative choice is safest; one frame later Algorithm 1 releases a still
  person again (a 0.9 prior meeting a 0.1 likelihood gives a posterior of 0.5, not removed). Such an
  output says ``motion_measured=False``: the keyframe masks of moving surfaces leave it out (it shows
  where the detector saw people, not that they move), tracking keeps its probabilities.
* Algorithm 2's prior without history and its clamp: ``frontend/dynamic/grid_propagation.py``.
* Only ``ClassGroups.dynamic`` boxes are examined: the paper considers people, animals and vehicles
  potential dynamic objects and has no passive-object class.

Known limits of the method (not fixed here, they are the paper's): motion along an epipolar line is
invisible (a person walking parallel to a sideways-moving camera keeps most features), and with the
small inter-frame baseline of a handheld camera at 30 Hz (2-5 px background flow on Bonn crowd) F is
poorly constrained away from the background points, so the epipole jumps from frame to frame and
Algorithm 1 flickers on some frames; Algorithm 2 only bridges such gaps for regions that were dynamic
for the whole history window.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from frontend.dynamic.base import Detection, DynamicContext, MethodOutput
from frontend.dynamic.grid_propagation import GridPropagation, above_threshold, point_cells
from slam.core.dynamic_config import ClassGroups, FlowEpipolarConfig


def epipolar_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Distance (px) of each x1 (N,2) to the epipolar line F [x0; 1] in the second image."""
    lines = x0 @ F[:, :2].T + F[:, 2]                      # (N,3): a, b, c
    num = np.abs(np.sum(lines[:, :2] * x1, axis=1) + lines[:, 2])
    den = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        d = num / den
    return np.where(den > 0, d, np.inf)


def sub_box_index(box: Detection, xy: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Flat sub-box index (row-major) of points known to lie inside ``box``."""
    c = np.floor((xy[:, 0] - box.x0) / max(box.width, 1e-9) * cols).astype(int)
    r = np.floor((xy[:, 1] - box.y0) / max(box.height, 1e-9) * rows).astype(int)
    return np.clip(r, 0, rows - 1) * cols + np.clip(c, 0, cols - 1)


class FlowEpipolarMethod:
    """PPS-SLAM's Algorithms 1 and 2 (see the module docstring)."""

    name = "flow_epipolar"
    needs_detector = True
    prepares = True       # the optical flow needs only this image and the frame before's keypoints
    measures_motion = True

    def __init__(self, cfg: FlowEpipolarConfig, classes: ClassGroups):
        self.cfg = cfg
        self.classes = classes
        self._dynamic_ids = set(int(c) for c in classes.dynamic)
        self._prev_gray: Optional[np.ndarray] = None     # at lk_start_level
        self._prev_shape: Optional[tuple[int, ...]] = None   # the full image's
        self._last_level: Optional[tuple[np.ndarray, np.ndarray]] = None   # (image, at lk_start_level) of track
        self._prev_raw: Optional[np.ndarray] = None       # (M,2) float32 raw pixel coordinates
        self._prev_und: Optional[np.ndarray] = None       # (M,2) undistorted
        self._tracked: Optional[tuple[np.ndarray, tuple]] = None   # (the image, track()'s result) of prepare
        self.grid = GridPropagation(cfg)

    # ----------------------------------------------------------------------------------------------
    def reset(self) -> None:
        self._prev_gray = self._prev_raw = self._prev_und = self._prev_shape = self._last_level = None
        self._tracked = None
        self.grid.reset()

    def _boxes(self, detections: Optional[list[Detection]]) -> list[Detection]:
        if not detections:
            return []
        return [d for d in detections
                if int(d.class_id) in self._dynamic_ids and d.score >= self.cfg.detector_score
                and d.width > 0 and d.height > 0]

    # ----------------------------------------------------------------------------------------------
    def track(self, gray: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """LK-track the previous keypoints into ``gray``.

        Returns (prev_und, cur_raw, cur_und, ok) for all previous keypoints; ``ok`` marks good tracks.
        """
        cfg = self.cfg
        p0 = self._prev_raw
        n = 0 if p0 is None else len(p0)
        if n == 0 or self._prev_gray is None or self._prev_shape != gray.shape:
            empty = np.zeros((0, 2))
            return empty, empty, empty, np.zeros(0, bool)
        win = (int(cfg.lk_window), int(cfg.lk_window))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
        level_gray = self._flow_image(gray)
        self._last_level = (gray, level_gray)   # end_frame keeps it as the next frame's previous image
        # pyrDown's pixel j sits on the full image's pixel 2j: coordinates scale without an offset
        scale = np.float32(2 ** int(cfg.lk_start_level))
        p0c = (p0 / scale).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self._prev_gray, level_gray, p0c, None, winSize=win,
                                             maxLevel=int(cfg.lk_levels), criteria=crit)
        ok = st.reshape(-1).astype(bool)
        if cfg.fb_max_px > 0:
            p0r, st_b, _ = cv2.calcOpticalFlowPyrLK(level_gray, self._prev_gray, p1, None, winSize=win,
                                                    maxLevel=int(cfg.lk_levels), criteria=crit)
            fb = np.linalg.norm(p0r.reshape(-1, 2) * scale - p0, axis=1)
            ok &= st_b.reshape(-1).astype(bool) & (fb <= cfg.fb_max_px)
        cur_raw = p1.reshape(-1, 2).astype(float) * float(scale)
        h, w = gray.shape[:2]
        ok &= np.isfinite(cur_raw).all(axis=1)
        ok &= (cur_raw[:, 0] >= 0) & (cur_raw[:, 0] <= w - 1) & (cur_raw[:, 1] >= 0) & (cur_raw[:, 1] <= h - 1)
        cur_und = np.zeros_like(cur_raw)
        if ok.any():
            cur_und[ok] = camera.undistort_points(cur_raw[ok])
        return self._prev_und, cur_raw, cur_und, ok

    def _flow_image(self, gray: np.ndarray) -> np.ndarray:
        """``gray`` at ``lk_start_level`` of its pyramid (the flow's image)."""
        image = np.ascontiguousarray(gray)
        for _ in range(int(self.cfg.lk_start_level)):
            image = cv2.pyrDown(image)
        return image

    def fundamental(self, x0: np.ndarray, x1: np.ndarray) -> Optional[np.ndarray]:
        """RANSAC F, refitted by the normalised 8-point method on its inliers; None if degenerate. OpenCV's RANSAC
        does not read the generator ``cv2.setRNGSeed`` sets (its own has a fixed state), so ``cfg.seed`` does not
        change the fit; it is set anyway for any OpenCV version whose RANSAC would draw from it."""
        if len(x0) < max(int(self.cfg.min_tracks), 8):
            return None
        cv2.setRNGSeed(int(self.cfg.seed))
        F, inl = cv2.findFundamentalMat(x0.astype(np.float64), x1.astype(np.float64), cv2.FM_RANSAC,
                                        float(self.cfg.ransac_px), 0.999, 2000)
        if F is None or F.shape != (3, 3):
            return None
        inl = inl.reshape(-1).astype(bool)
        if inl.sum() >= max(int(self.cfg.min_tracks), 8):
            F8, _ = cv2.findFundamentalMat(x0[inl].astype(np.float64), x1[inl].astype(np.float64), cv2.FM_8POINT)
            if F8 is not None and F8.shape == (3, 3):
                # Keep the refit only if it explains the RANSAC inliers at least as well.
                if (np.median(epipolar_distance(F8, x0[inl], x1[inl]))
                        <= np.median(epipolar_distance(F, x0[inl], x1[inl])) + 1e-9):
                    F = F8
        return F / np.linalg.norm(F)

    # ----------------------------------------------------------------------------------------------
    def prepare(self, ctx: DynamicContext) -> None:
        """The LK flow of the frame before's keypoints into this image (Algorithm 1, line 1): it needs neither
        this frame's features nor its detections, so the rejector runs it on a thread of its own while they
        are made (``DynamicMethod.prepare``); ``process`` does the rest."""
        self._tracked = (ctx.gray, self.track(ctx.gray, ctx.camera))

    def process(self, ctx: DynamicContext) -> MethodOutput:
        cfg = self.cfg
        frame = ctx.frame
        n = len(frame)
        h, w = ctx.gray.shape[:2]
        boxes = self._boxes(ctx.detections)
        kp = np.asarray(frame.uv_raw, float).reshape(-1, 2)
        cur_raw, ok, dyn_track, evidence = self._dynamic_tracks(ctx, boxes)
        region_mask, kp_dynamic, n_sub = self._dynamic_sub_boxes(boxes, cur_raw, ok, dyn_track, evidence,
                                                                 kp, n, (h, w))
        posterior, cell_prob, re, ce = self.grid.update(region_mask)

        prob = np.zeros(n)
        if n:
            r_idx, c_idx = point_cells(kp, re, ce)
            prob = cell_prob[r_idx, c_idx]
            prob[kp_dynamic] = 1.0
        mask = np.repeat(np.repeat(cell_prob.astype(np.float32), np.diff(re), axis=0), np.diff(ce), axis=1)
        mask[region_mask] = 1.0

        info = {
            "tracked": int(ok.sum()),
            "dynamic_tracks": int(dyn_track.sum()),
            "boxes": len(boxes),
            "dynamic_sub_boxes": n_sub,
            "cells_removed": int(np.sum(above_threshold(posterior, cfg.remove_threshold))),
            "sub_box_features": int(kp_dynamic.sum()),
            "grid_features": int(np.sum((prob >= 0.5) & ~kp_dynamic)),
        }
        origins = np.zeros((0, 2)) if self._prev_raw is None or len(self._prev_raw) != len(ok) else self._prev_raw[ok]
        return MethodOutput(prob, mask, info, cur_raw[ok], dyn_track[ok], origins, motion_measured=evidence)

    def _dynamic_tracks(self, ctx: DynamicContext,
                        boxes: list[Detection]) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Algorithm 1, lines 1-7: LK flow, RANSAC F, epipolar distance. Returns the tracked positions
        (raw pixels), the good-track flags, the tracks far from their epipolar line, and whether there is
        motion evidence (an F, or no boxes to judge)."""
        cfg = self.cfg
        # Tracked with or without boxes: the tracks that move against F are detector-free evidence too.
        tracked, self._tracked = self._tracked, None
        x0, cur_raw, x1, ok = tracked[1] if tracked is not None and tracked[0] is ctx.gray else \
            self.track(ctx.gray, ctx.camera)
        in_any_box = np.zeros(len(cur_raw), bool)
        for b in boxes:
            in_any_box |= b.contains(cur_raw)
        sel = ok & ~in_any_box if cfg.f_outside_boxes else ok
        if sel.sum() < cfg.min_tracks:
            sel = ok
        F = self.fundamental(x0[sel], x1[sel]) if sel.any() else None
        dyn_track = np.zeros(len(cur_raw), bool)
        if F is not None:
            dist = np.full(len(cur_raw), np.inf)
            dist[ok] = epipolar_distance(F, x0[ok], x1[ok])
            dyn_track = ok & (dist > cfg.epipolar_px)
        return cur_raw, ok, dyn_track, F is not None or not boxes

    def _dynamic_sub_boxes(self, boxes: list[Detection], cur_raw: np.ndarray, ok: np.ndarray,
                           dyn_track: np.ndarray, evidence: bool, kp: np.ndarray, n: int,
                           shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, int]:
        """Algorithm 1, lines 8-14 and Eqs. 1-6: the pixels of the dynamic sub-boxes (HxW bool), the ``n``
        keypoints ``kp`` inside them, and how many sub-boxes are dynamic. Without motion evidence every
        sub-box of a box is (detections only)."""
        rows, cols = max(int(self.cfg.sub_box_rows), 1), max(int(self.cfg.sub_box_cols), 1)
        region_mask = np.zeros(shape, bool)
        kp_dynamic = np.zeros(n, bool)
        n_sub = 0
        for b in boxes:
            if evidence:
                dynamic_sub = self._moving_sub_boxes(b, cur_raw, ok, dyn_track, rows, cols)
            else:
                dynamic_sub = np.ones(rows * cols, bool)    # no motion evidence: detections only
            if not dynamic_sub.any():
                continue
            n_sub += int(dynamic_sub.sum())
            kin = b.contains(kp)
            if kin.any():
                kp_dynamic[np.flatnonzero(kin)[dynamic_sub[sub_box_index(b, kp[kin], rows, cols)]]] = True
            _fill_sub_boxes(region_mask, b, dynamic_sub, rows, cols)
        return region_mask, kp_dynamic, n_sub

    def _moving_sub_boxes(self, b: Detection, cur_raw: np.ndarray, ok: np.ndarray, dyn_track: np.ndarray,
                          rows: int, cols: int) -> np.ndarray:
        """Eqs. 1-6: per sub-box (row-major), whether its share of dynamic tracks exceeds ``region_ratio``."""
        inside = ok & b.contains(cur_raw)
        idx = sub_box_index(b, cur_raw[inside], rows, cols)
        k = np.bincount(idx, minlength=rows * cols)
        m = np.bincount(idx, weights=dyn_track[inside].astype(float), minlength=rows * cols)
        dp = np.divide(m, k, out=np.zeros(rows * cols), where=k > 0)
        return dp > self.cfg.region_ratio

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        """Keep this frame's grey image and keypoints for the flow, and its grid posterior."""
        last = self._last_level
        self._prev_gray = last[1] if last is not None and last[0] is ctx.gray else self._flow_image(ctx.gray)
        self._last_level = None
        self._prev_shape = ctx.gray.shape
        self._prev_raw = np.asarray(ctx.frame.uv_raw, np.float32).reshape(-1, 2)
        self._prev_und = np.asarray(ctx.frame.uv, float).reshape(-1, 2)
        self.grid.commit()


def _fill_sub_boxes(region_mask: np.ndarray, b: Detection, dynamic_sub: np.ndarray, rows: int, cols: int) -> None:
    """Set the pixels of box ``b``'s dynamic sub-boxes (flags row-major) in ``region_mask``."""
    h, w = region_mask.shape
    xs = b.x0 + b.width * np.arange(cols + 1) / cols
    ys = b.y0 + b.height * np.arange(rows + 1) / rows
    for s in np.flatnonzero(dynamic_sub):
        r, c = divmod(int(s), cols)
        # Pixel p is inside when x0 <= p < x1, as Detection.contains for integer points.
        c0, c1 = np.clip(np.ceil([xs[c], xs[c + 1]]).astype(int), 0, w)
        r0, r1 = np.clip(np.ceil([ys[r], ys[r + 1]]).astype(int), 0, h)
        region_mask[r0:r1, c0:c1] = True
