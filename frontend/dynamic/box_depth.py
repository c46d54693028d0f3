"""Bounding box + depth continuity (Fang, Han, Wang, Yuan 2021; ``../shared/seeds/001_*.txt``).

Three steps per frame, as in the paper:

1. **PDT segmentation (Algorithm 1, Eqs. 2-8).** For every box of a priority dynamic target
   (``ClassGroups.dynamic``: person, cat, dog, horse) a flood fill on the depth image starts from one
   of five seeds -- the box centre, then the midpoints of the four half-axes (top, bottom, left,
   right; Fig. 3) -- and grows over the 8-neighbourhood while ``|d_seed - d_neighbour| < omega_pixel``
   and the neighbour lies in the box. Step 3 of the paper makes every newly added pixel the next
   ``p_seed``, so the test is *neighbour to neighbour* (a depth gradient limit, not a band around the
   first seed); that is OpenCV's floating-range ``cv2.floodFill`` with 8-connectivity on the float
   depth crop of the box (the box is the crop, so "inside the box" is implicit). A fill is valid when
   its rows span more than ``height_ratio`` (0.75) of the box height; otherwise the next seed is
   tried. The valid fill is then filtered by Eq. 8: with ``d_ave`` the mean fill depth (Eq. 3),
   ``D_i = alpha * d_ave - d_i`` (Eq. 4) and ``G_i`` the pixel's distance to the nearest box side
   (Eqs. 5-7, pixels), pixels with ``D_i + omega * G_i < 0`` are removed -- i.e. pixels deeper than the
   mean, the more so the closer they lie to the box border (the overflow into the background or the
   floor that the seeds' strategy tends to produce).
2. **Passive objects dragged by a PDT (Algorithm 2, Eqs. 9-11).** A box of a high/low-probability
   passive class (p_pas = 0.8 / 0.25) is examined when, for some PDT box,
   ``A_pas / (A_pas ∩ A_act) <= K * p_pas``. The flood fill then starts from all PDT pixels inside the
   passive box with the larger ``omega_pixel_passive``; ``N_pas`` = pixels reached that are not PDT
   pixels ("the pixels belonging to this object"), ``N_box`` = pixels of the passive box. If
   ``N_box / N_pas <= K * p_pas`` the object is dragged: its features become dynamic.
3. **Effective dynamic features (Algorithm 3, Eqs. 12-17).** Static features of the previous and the
   current frame are matched by ORB descriptor (Hamming, cross-check), a homography ``H`` is fitted by
   RANSAC; each dynamic feature matched to a dynamic feature of the previous frame is projected with
   ``H``. If the projection lies within ``reuse_radius_px`` of its current position (Eq. 13) and the
   composite grey and depth values (Eqs. 14-15) at the projection and at the current position agree
   within ``reuse_gray`` / ``reuse_depth`` (Eqs. 16-17), the feature is an *effective* dynamic feature:
   it moved like the static scene (a seated person's still torso) and is reused for tracking with the
   lowered probability ``reuse_prob``.

Choices where the paper is vague (all checked on the Bonn crowd sequence):

* **Parameters.** The paper gives no numbers for ``omega_pixel``, ``alpha``, ``omega``, ``K``, the
  displacement and composite thresholds. ``omega_pixel`` = 5 cm between neighbours separates a person
  from a wall behind them and still follows a body whose depth noise is ~1-2 cm at 2-3 m; 10 cm for
  passive objects ("appropriately increased"). ``alpha`` = 1, ``omega`` = 0.01 m/px (a pixel 10 px
  from the box side is removed when it is 10 cm deeper than the mean). ``K`` must exceed 1/p_pas for
  Eqs. 9 and 11 to ever hold (both ratios are >= 1); ``K`` = 5 means an overlap / a connected object
  covering >= 25 % of a high-probability passive box and >= 80 % of a low-probability one.
* **Invalid depth (0).** Continuity cannot be tested there, so the fill never enters an invalid pixel
  (they are pre-set in the flood-fill mask), and a seed on an invalid pixel moves to the nearest valid
  pixel within ``_SEED_SEARCH_PX``. After Eq. 8, invalid pixels within ``invalid_fill_px`` of the
  segment (holes on hair and dark clothes, the depth shadow at the silhouette where ORB corners
  like to sit) are added to it, since they most likely belong to the person.
* **No valid seed.** If none of the five fills spans 0.75 of the box (person cut by the image border,
  half occluded, depth missing), the fill with the largest vertical span is kept rather than dropping
  the person (counted in ``info['fallback']``).
* **An occluder over the box's middle (a deviation, measured better).** The paper's first seed is the
  box's centre. When a monitor or desk stands in front of the person, the centre lies on it and its fill
  may span the box's height too: the monitor is segmented and the person not (people composited behind
  fr1/rpy's monitor). When the centre seed lies ``_OCCLUDER_GAP_M`` (0.3 m) nearer than the person's
  depth layer -- the peak of the box's depth histogram that lies most inside the box, since a box bounds
  the person while what stands in front or behind goes on beyond it (``person_layer``) -- the layer's
  pixel nearest the centre is tried first; the paper's five seeds follow (``seed_past_occluder``; False
  gives the paper's seeds alone). Nothing changes where the centre is on the person (every generated
  hard scene: the same bits). On the fr1/rpy composites ATE went from 1.21x to 1.12x the untouched frames
  (``walk_stand``), 1.23x -> 1.11x (``stand_walk``), 1.20x -> 1.06x (``close_pass``); docs/dynamic.md has
  the table.
* **Composite values (Eqs. 14-15).** The printed ``G + G_ave / 2`` is read as the mean of the pixel and
  its 8-neighbourhood average, ``(G + G_ave) / 2``; both composites are taken in the current frame,
  as the paper states. Depth averages skip invalid neighbours; an invalid centre fails the test.
* **Matching.** Mutually best Hamming matches (a cross-check) with a distance cap of 50 (ORB-SLAM's
  TH_LOW), searched among keypoints less than 40 px from their previous position (k-d tree pairs and
  a popcount instead of a full brute-force matrix: ~4x cheaper on Bonn frames, and a handheld camera
  at 30 Hz moves far less); at least 8 static matches are needed for ``H`` (RANSAC threshold
  ``reuse_radius_px``). Faster motion finds no ``H`` and nothing is reused (the safe side).
* **Probabilities.** 1 on PDT pixels and on the pixels filled from them in a dragged passive box;
  ``p_pas`` on the rest of a dragged passive box (the paper marks the whole box dynamic; keeping
  ``p_pas`` there flags high-probability objects and only down-weights low-probability ones);
  ``reuse_prob`` for effective dynamic features; 0 elsewhere. With an empty detection list the method
  says 0 for every keypoint (a confident "static": the detector saw nobody); with
  ``detections=None`` (no detector ran) it abstains (NaN).

Behaviour seen on Bonn crowd (frames 230-480, YOLOX-Nano boxes): the segments follow the people
closely (the RGB-depth misregistration of a few pixels shows at the silhouettes); the fill leaks a
little onto the floor in front of the feet, which Eq. 8 keeps (nearer than the mean), and Eq. 8
trims the far end of a strongly leaning body near the box bottom. A chair beside a person can be
"dragged" because the floor connects them within 10 cm steps (9 of 250 frames, none really moved).
Algorithm 3 reuses 1-6 % of the dynamic features, also on slowly walking people whose inter-frame
motion stays within 3 px of the homography; ``reuse_prob`` keeps them down-weighted.

The segmentation helpers of Algorithms 1-2 are in ``frontend.dynamic.box_depth_segmentation`` and
re-exported here.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
from scipy.spatial import cKDTree

from frontend.dynamic.base import Detection, DynamicContext, MethodOutput, keypoints_in_mask
from frontend.dynamic.box_depth_kernels import composite_values, mutual_best
from frontend.dynamic.box_depth_segmentation import (box_pixels, cached_person_layer, flood_fill, image_sides,
                                                     overlaps_enough, segment_box)
from frontend.dynamic.box_depth_segmentation import (eq8_filter, nearest_valid,  # noqa: F401  (re-exported)
                                                     seed_points, side_distance)
from slam.core.descriptors import descriptor_words
from slam.core.dynamic_config import BoxDepthConfig, ClassGroups

_MAX_HAMMING = 50            # descriptor distance cap for frame-to-frame matching (ORB-SLAM TH_LOW)
_MATCH_RADIUS_PX = 40.0      # frame-to-frame matches are searched this close to the previous position
_MIN_STATIC_MATCHES = 8      # static matches needed to fit the homography


# --------------------------------------------------------------------------------------------
# Frame-to-frame matching and composite values (Algorithm 3; public for tests)


def composite(img: np.ndarray, uv: np.ndarray, skip_zero: bool = False) -> np.ndarray:
    """Eqs. 14-15: (value at the pixel + mean of its 8 neighbours) / 2 at each (N,2) point (nearest
    pixel). With ``skip_zero`` (depth) invalid neighbours are left out of the mean and an invalid
    centre gives NaN. One compiled pass (``box_depth_kernels.composite_values``, numpy's sums)."""
    if not len(uv):
        return np.zeros(0)
    return composite_values(np.ascontiguousarray(img), np.asarray(uv, np.float64).reshape(-1, 2), bool(skip_zero))


def match_descriptors(desc_a: np.ndarray, uv_a: np.ndarray, desc_b: np.ndarray, uv_b: np.ndarray,
                      radius: float = _MATCH_RADIUS_PX, max_distance: int = _MAX_HAMMING) -> np.ndarray:
    """Mutually best Hamming matches (M,2) of indices into a and b among the pairs less than
    ``radius`` px apart (a cross-checked brute-force match restricted to frame-to-frame motion); of pairs
    at the same distance the first the k-d tree lists wins (``box_depth_kernels.mutual_best``)."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.zeros((0, 2), int)
    pairs = cKDTree(np.asarray(uv_a, float)).sparse_distance_matrix(
        cKDTree(np.asarray(uv_b, float)), radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), int)
    return mutual_best(descriptor_words(desc_a), descriptor_words(desc_b), pairs["i"].astype(np.int64),
                       pairs["j"].astype(np.int64), int(max_distance))


# --------------------------------------------------------------------------------------------


class BoxDepthMethod:
    """Fang et al. 2021: depth-continuity segmentation inside detector boxes, dragged passive objects
    and reuse of still dynamic features. Keeps the previous frame for Algorithm 3."""

    name = "box_depth"
    needs_detector = True
    prepares = False
    measures_motion = False

    def __init__(self, cfg: BoxDepthConfig, classes: ClassGroups):
        self.cfg = cfg
        self.classes = classes
        self._dynamic = set(int(c) for c in classes.dynamic)
        self._passive_prob = {int(c): float(classes.low_passive_prob) for c in classes.low_passive}
        self._passive_prob.update({int(c): float(classes.high_passive_prob) for c in classes.high_passive})
        self._prev: Optional[dict] = None

    def reset(self) -> None:
        self._prev = None

    # -- per frame ---------------------------------------------------------------------------------

    def prepare(self, ctx: DynamicContext) -> None:
        """Nothing to do before the features and detections exist (see ``DynamicMethod.prepare``)."""

    def process(self, ctx: DynamicContext) -> MethodOutput:
        frame = ctx.frame
        n = len(frame)
        if ctx.detections is None:
            self._prev = None
            return MethodOutput.abstain(n)
        depth = np.asarray(ctx.depth, dtype=np.float32)
        uv = frame.uv_raw
        # Algorithm 1: PDT pixels; Algorithm 2: passive objects connected in depth to a PDT.
        mask, pdt_boxes, fallback = self._segment_targets(ctx.detections, depth, ctx.person_layers)
        prob, passive_mask, dragged = self._dragged_passives(ctx.detections, depth, mask, pdt_boxes, uv, n)
        seg_mask = mask | passive_mask
        if n:
            prob = np.maximum(prob, keypoints_in_mask(seg_mask, uv).astype(float))
        dyn = prob >= 0.5

        # Algorithm 3: effective dynamic features.
        reused, n_static_matches = self._reuse(ctx, dyn, depth)
        if reused.any():
            prob[reused] = np.minimum(prob[reused], self.cfg.reuse_prob)

        # Algorithm 3 compares both composites in the current frame, so only the keypoints are kept.
        self._prev = dict(index=frame.index, uv=np.asarray(uv, float).copy(), desc=frame.descriptors, dyn=dyn)
        info = dict(pdt_boxes=len(pdt_boxes), fallback=int(fallback), dragged=dragged,
                    dynamic=int(dyn.sum()), reused=int(reused.sum()), static_matches=n_static_matches)
        return MethodOutput(prob, seg_mask.astype(np.float32), info)

    def _segment_targets(self, detections: list[Detection], depth: np.ndarray,
                         layers: dict) -> tuple[np.ndarray, list, int]:
        """Algorithm 1: the PDT pixels (HxW bool), the PDT boxes in pixels, and how many boxes had no
        seed whose fill passed the height test (``info['fallback']``)."""
        h, w = depth.shape[:2]
        mask = np.zeros((h, w), bool)
        pdt_boxes, fallback = [], 0
        for det in detections:
            if det.class_id not in self._dynamic:
                continue
            b = box_pixels(det, w, h)
            if b is None:
                continue
            x0, y0, x1, y1 = b
            layer = None
            if self.cfg.seed_past_occluder or self.cfg.eq8_border_on_body:
                layer = cached_person_layer(layers, b, depth)
            seg, accepted = segment_box(depth[y0:y1, x0:x1], self.cfg, layer, image_sides(b, w, h))
            fallback += accepted < 0
            mask[y0:y1, x0:x1] |= seg
            pdt_boxes.append(b)
        return mask, pdt_boxes, fallback

    def _dragged_passives(self, detections: list[Detection], depth: np.ndarray, mask: np.ndarray,
                          pdt_boxes: list, uv: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Algorithm 2: passive objects connected in depth to a PDT. Returns the keypoint probabilities
        (``p_pas`` inside a dragged box, else 0), the dragged object pixels and how many were dragged."""
        h, w = depth.shape[:2]
        prob = np.zeros(n)
        passive_mask = np.zeros((h, w), bool)
        dragged = 0
        for det in detections:
            if det.class_id not in self._passive_prob:
                continue
            b = box_pixels(det, w, h)
            if b is None or not pdt_boxes:
                continue
            p_pas = self._passive_prob[det.class_id]
            obj = self._dragged_pixels(b, p_pas, depth, mask, pdt_boxes)
            if obj is None:
                continue
            dragged += 1
            x0, y0, x1, y1 = b
            passive_mask[y0:y1, x0:x1] |= obj
            inside = (uv[:, 0] >= x0) & (uv[:, 0] < x1) & (uv[:, 1] >= y0) & (uv[:, 1] < y1)
            prob[inside] = np.maximum(prob[inside], p_pas)
        return prob, passive_mask, dragged

    def _dragged_pixels(self, b: tuple[int, int, int, int], p_pas: float, depth: np.ndarray, mask: np.ndarray,
                        pdt_boxes: list) -> Optional[np.ndarray]:
        """The pixels (box crop, bool) of the passive object in box ``b`` that a PDT drags along, or None
        when it overlaps no PDT box enough (Eqs. 9-10) or too little of the box fills from the PDT pixels
        in it (Eq. 11)."""
        bound = self.cfg.k_passive * p_pas
        if not overlaps_enough(b, pdt_boxes, bound):                               # Eqs. 9-10
            return None
        x0, y0, x1, y1 = b
        seeds_in = mask[y0:y1, x0:x1]
        if not seeds_in.any():
            return None
        filled = flood_fill(depth[y0:y1, x0:x1], np.argwhere(seeds_in), self.cfg.omega_pixel_passive)
        obj = filled & ~seeds_in
        n_box, n_pas = (y1 - y0) * (x1 - x0), int(obj.sum())
        if n_pas == 0 or n_box / n_pas > bound:                                    # Eq. 11
            return None
        return obj

    def _reuse(self, ctx: DynamicContext, dyn: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, int]:
        """Algorithm 3: which of the current dynamic features are effective (still) features."""
        frame = ctx.frame
        reused = np.zeros(len(frame), bool)
        prev = self._prev
        if prev is None or prev["index"] >= frame.index or not dyn.any() or not prev["dyn"].any():
            return reused, 0
        sta_cur, sta_last = np.flatnonzero(~dyn), np.flatnonzero(~prev["dyn"])
        m = match_descriptors(frame.descriptors[sta_cur], frame.uv_raw[sta_cur],
                              prev["desc"][sta_last], prev["uv"][sta_last])
        if len(m) < _MIN_STATIC_MATCHES:
            return reused, len(m)
        src = prev["uv"][sta_last[m[:, 1]]].astype(np.float32)
        dst = frame.uv_raw[sta_cur[m[:, 0]]].astype(np.float32)
        H, _ = cv2.findHomography(src, dst, cv2.RANSAC, float(self.cfg.reuse_radius_px))
        if H is None:
            return reused, len(m)
        dyn_cur, dyn_last = np.flatnonzero(dyn), np.flatnonzero(prev["dyn"])
        md = match_descriptors(frame.descriptors[dyn_cur], frame.uv_raw[dyn_cur],
                               prev["desc"][dyn_last], prev["uv"][dyn_last])
        if not len(md):
            return reused, len(m)
        cur_idx = dyn_cur[md[:, 0]]
        p_cur = frame.uv_raw[cur_idx].astype(float)
        p_last = prev["uv"][dyn_last[md[:, 1]]].astype(np.float64)
        p_proj = cv2.perspectiveTransform(p_last.reshape(-1, 1, 2), H).reshape(-1, 2)     # Eq. 12
        ok = np.linalg.norm(p_cur - p_proj, axis=1) < self.cfg.reuse_radius_px              # Eq. 13
        if ok.any():
            gray = ctx.gray
            g_ok = np.abs(composite(gray, p_proj) - composite(gray, p_cur)) < self.cfg.reuse_gray      # Eq. 16
            d_diff = np.abs(composite(depth, p_proj, True) - composite(depth, p_cur, True))
            d_ok = np.nan_to_num(d_diff, nan=np.inf) < self.cfg.reuse_depth                         # Eq. 17
            ok &= g_ok & d_ok
        reused[cur_idx[ok]] = True
        return reused, len(m)

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        """The previous-frame state for Algorithm 3 is kept in ``process``; nothing to do here."""
        return None
