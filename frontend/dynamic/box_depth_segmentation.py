"""Depth-continuity segmentation inside detector boxes for ``box_depth`` (Fang, Han, Wang, Yuan 2021):
the flood fill, seeds and Eq. 8 filter of Algorithm 1, and the box overlap test of Algorithm 2.

Pure functions of a depth crop and a config, kept apart so they are tested on their own; the mapping
to the paper and the choices where it is vague are in ``frontend.dynamic.box_depth``'s docstring,
which module re-exports the public names here.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from frontend.dynamic.base import Detection
from frontend.dynamic.box_depth_kernels import band_counts, eq8_keep, fill_inputs, histogram_counts, positive_samples
from slam.core.dynamic_config import BoxDepthConfig

_SEED_SEARCH_PX = 4          # a seed on invalid depth moves to the nearest valid pixel this close
_LAYER_BIN_M = 0.05          # the person's layer is a peak of the box's depth histogram: 5 cm bins, smoothed over 3
_LAYER_HALF_M = 0.2          # a layer: within 0.2 m of its peak (a body's depth about its middle, arms included)
_LAYER_MIN_SHARE = 0.08      # ... holding at least 8 % of the box: a visible part of a person, not an edge's strip
_RING_SHARE = 0.15           # the ring around a box: 15 % of its width (height) each side, past a detector's box error
_LAYER_RING_SLACK_M = 0.1    # a ring pixel counts for a layer 0.1 m past its half width (a floor running on at a slant)
_OCCLUDER_GAP_M = 0.3        # the centre seed is on an occluder when that much nearer than the layer (0.2 m + 0.1)
_LAYER_PIXEL_STEP = 2        # every 2nd pixel in each direction enters the histograms
_MAX_FILL_COMPONENTS = 64    # flood fills per passive box (one per depth-connected piece of seeds)
_FILL_FLAGS = 8 | cv2.FLOODFILL_MASK_ONLY | (255 << 8)   # 8-connectivity, floating range, mask value 255


def box_pixels(det: Detection, width: int, height: int) -> Optional[tuple[int, int, int, int]]:
    """Integer pixel bounds (x0, y0, x1, y1), x1/y1 exclusive, clipped to the image; None if empty."""
    x0 = int(np.clip(np.floor(det.x0), 0, width))
    y0 = int(np.clip(np.floor(det.y0), 0, height))
    x1 = int(np.clip(np.ceil(det.x1), 0, width))
    y1 = int(np.clip(np.ceil(det.y1), 0, height))
    if x1 - x0 < 1 or y1 - y0 < 1:
        return None
    return x0, y0, x1, y1


def seed_points(h: int, w: int) -> list[tuple[int, int]]:
    """The five seeds (row, col) of a h x w box, in the paper's order: centre, then the midpoints of
    the upper, lower, left and right half-axes."""
    rc, cc = h // 2, w // 2
    pts = [(rc, cc), (h // 4, cc), (min(h - 1, (3 * h) // 4), cc), (rc, w // 4), (rc, min(w - 1, (3 * w) // 4))]
    return pts


class DepthFill:
    """One depth crop made ready for ``cv2.floodFill`` once (``box_depth_kernels.fill_inputs``), filled from as
    many seeds as Algorithm 1 tries: each fill starts from the crop's own invalid-depth mask."""

    def __init__(self, depth: np.ndarray):
        self.image, self._invalid = fill_inputs(np.asarray(depth))

    def fill(self, seeds: np.ndarray, omega: float, max_components: int = _MAX_FILL_COMPONENTS) -> np.ndarray:
        """Pixels reached from any of ``seeds`` ((K,2) row, col) by 8-neighbour steps whose depth change
        is strictly below ``omega`` (neighbour-to-neighbour, Algorithm 1). Invalid depth (<= 0 or not
        finite) is never entered; seeds on invalid depth are ignored. Returns a bool mask of the crop's
        shape."""
        h, w = self.image.shape
        mask = self._invalid.copy()
        inner = mask[1:-1, 1:-1]
        seeds = np.asarray(seeds, dtype=np.int64).reshape(-1, 2)
        if len(seeds):
            seeds = seeds[(seeds[:, 0] >= 0) & (seeds[:, 0] < h) & (seeds[:, 1] >= 0) & (seeds[:, 1] < w)]
        # OpenCV accepts |diff| <= bound; the paper's test is strict.
        diff = float(np.nextafter(np.float32(omega), np.float32(0)))
        for _ in range(max_components):
            if not len(seeds):
                break
            seeds = seeds[inner[seeds[:, 0], seeds[:, 1]] == 0]     # not yet filled, not invalid
            if not len(seeds):
                break
            r, c = int(seeds[0, 0]), int(seeds[0, 1])
            cv2.floodFill(self.image, mask, (c, r), 0, diff, diff, _FILL_FLAGS)
        return inner == 255


def flood_fill(depth: np.ndarray, seeds: np.ndarray, omega: float,
               max_components: int = _MAX_FILL_COMPONENTS) -> np.ndarray:
    """``DepthFill(depth).fill(seeds, omega, max_components)``: one fill of one crop."""
    return DepthFill(depth).fill(seeds, omega, max_components)


def nearest_valid(depth: np.ndarray, row: int, col: int, radius: int = _SEED_SEARCH_PX) -> Optional[tuple[int, int]]:
    """``(row, col)`` if its depth is valid, else the nearest valid pixel within ``radius``, else None."""
    if depth[row, col] > 0:
        return row, col
    h, w = depth.shape
    r0, r1, c0, c1 = max(0, row - radius), min(h, row + radius + 1), max(0, col - radius), min(w, col + radius + 1)
    rr, cc = np.nonzero(depth[r0:r1, c0:c1] > 0)
    if not len(rr):
        return None
    k = int(np.argmin((rr + r0 - row) ** 2 + (cc + c0 - col) ** 2))
    return int(rr[k] + r0), int(cc[k] + c0)


Sides = tuple[bool, bool, bool, bool]   # per box side (left, top, right, bottom): whether it counts
ALL_SIDES: Sides = (True, True, True, True)


def side_distance(h: int, w: int, sides: Sides = ALL_SIDES) -> np.ndarray:
    """G_i (Eqs. 5-7): each pixel centre's distance (px) to the nearest side of an h x w box, of the
    ``sides`` that count (none counting: infinite)."""
    left, top, right, bottom = sides
    rows, cols = np.arange(h) + 0.5, np.arange(w) + 0.5
    gy = np.minimum(np.where(top, rows, np.inf), np.where(bottom, h - rows, np.inf))
    gx = np.minimum(np.where(left, cols, np.inf), np.where(right, w - cols, np.inf))
    return np.minimum(gy[:, None], gx[None, :])


def image_sides(box: tuple[int, int, int, int], width: int, height: int) -> Sides:
    """Which sides of ``box`` (x0, y0, x1, y1 pixels) lie inside the image: a side on the image border is
    where the view ends, and the person may go on beyond it."""
    x0, y0, x1, y1 = box
    return x0 > 0, y0 > 0, x1 < width, y1 < height


def eq8_filter(region: np.ndarray, depth: np.ndarray, alpha: float, omega: float,
               sides: Sides = ALL_SIDES, layer: Optional[float] = None) -> np.ndarray:
    """Remove the pixels of ``region`` (bool, box crop) with ``alpha * d_ave - d_i + omega * G_i < 0``.
    With ``layer`` (the person's depth) and a side of ``sides`` not counting, a pixel within
    ``_LAYER_HALF_M`` of the layer is measured to the counting sides only. The mean is numpy's (Eq. 3); the
    per-pixel test (Eqs. 4-8) one compiled pass (``box_depth_kernels.eq8_keep``) in the precisions numpy used
    for it: alpha * d_ave and the layer's band in the depth's own (a Python float against the image, NEP 50),
    the sum with omega * G_i in float64."""
    if not region.any():
        return region
    d_ave = float(depth[region].mean())                                         # Eq. 3
    kind = depth.dtype.type
    return eq8_keep(region, depth, kind(alpha * d_ave), float(omega), tuple(bool(s) for s in sides),
                    layer is not None, kind(np.float32(layer if layer is not None else 0.0)), kind(_LAYER_HALF_M))


def cached_person_layer(layers: dict, box: tuple[int, int, int, int], depth: np.ndarray) -> Optional[float]:
    """``person_layer`` of ``box`` from the frame's cache ``layers`` (box -> layer,
    ``DynamicContext.person_layers``), computed and added when missing: box_depth, the standing test and
    the keyframe masks all ask for the same boxes' layers."""
    if box not in layers:
        layers[box] = person_layer(box, depth)
    return layers[box]


def layer_fill(box: tuple[int, int, int, int], depth: np.ndarray, layers: Optional[dict]) -> float:
    """Share of ``box``'s pixels within ``_LAYER_HALF_M`` of its person layer (every 2nd pixel each way, as
    the layer's histogram samples it); 1 for a box without a layer (too little depth to tell: all body)."""
    layers = {} if layers is None else layers
    layer = cached_person_layer(layers, box, depth)
    x0, y0, x1, y1 = box
    crop = depth[y0:y1:_LAYER_PIXEL_STEP, x0:x1:_LAYER_PIXEL_STEP]
    if layer is None or crop.size == 0:
        return 1.0
    return float(np.count_nonzero((crop > 0) & (np.abs(crop - np.float32(layer)) <= _LAYER_HALF_M)) / crop.size)


def person_layer(box: tuple[int, int, int, int], depth: np.ndarray) -> Optional[float]:
    """The depth (m) of the person in a box (x0, y0, x1, y1 pixels of ``depth``): of the peaks of the box's
    depth histogram that hold at least ``_LAYER_MIN_SHARE`` of its pixels within ``_LAYER_HALF_M``, the one
    whose layer lies most inside the box, i.e. has the fewest pixels at its depth in a ring around the box
    (counted at the box's size). A detector's box bounds the person, while what stands in front of them or
    behind (a monitor, a desk, the wall) goes on beyond it. None when no layer holds enough of the box.

    Sampled on the fr1/rpy composites (ground-truth boxes 8 px wider), the layer lay within 0.3 m of the
    person's depth in 49 of 56 boxes of ``walk_stand`` (a person behind the monitor), 20 / 25 of
    ``two_walk`` and 23 / 24 of ``stand_walk``; the median of the box's middle third in 25, 17 and 12."""
    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        return None
    inside = positive_samples(depth, y0, y1, x0, x1, _LAYER_PIXEL_STEP)   # every 2nd pixel each way, valid
    if len(inside) < 20:
        return None
    ring = _ring_depths(box, depth)
    edges = np.arange(_LAYER_BIN_M * np.floor(inside.min() / _LAYER_BIN_M) - _LAYER_BIN_M,
                      inside.max() + 2 * _LAYER_BIN_M, _LAYER_BIN_M)
    hist = histogram_counts(inside, edges, _LAYER_BIN_M)     # np.histogram's counts, without sorting the depths
    smooth = np.convolve(hist, np.ones(3) / 3, mode="same")
    peaks = np.flatnonzero((smooth[1:-1] >= smooth[:-2]) & (smooth[1:-1] > smooth[2:]) & (smooth[1:-1] > 0)) + 1
    centres = 0.5 * (edges[peaks] + edges[peaks + 1])
    held = band_counts(inside, centres, _LAYER_HALF_M)
    beyond = band_counts(ring, centres, _LAYER_HALF_M + _LAYER_RING_SLACK_M)
    best, best_score = None, -1.0
    for centre, n_held, n_beyond in zip(centres.tolist(), held.tolist(), beyond.tolist()):
        if n_held < _LAYER_MIN_SHARE * len(inside):
            continue
        score = n_held / (n_held + n_beyond * len(inside) / max(len(ring), 1))   # the ring counted at the box's size
        if score > best_score:
            best, best_score = float(centre), score
    return best


def _ring_depths(box: tuple[int, int, int, int], depth: np.ndarray) -> np.ndarray:
    """Valid depths of the ring ``_RING_SHARE`` of the box's size wide around it (sampled every
    ``_LAYER_PIXEL_STEP`` pixels from the ring's outer corner), as the strips above, below, left and right
    of the box: only their count near a depth matters, not their order."""
    x0, y0, x1, y1 = box
    h, w = depth.shape
    dx, dy = int(_RING_SHARE * (x1 - x0)) + 1, int(_RING_SHARE * (y1 - y0)) + 1
    X0, Y0, X1, Y1 = max(x0 - dx, 0), max(y0 - dy, 0), min(x1 + dx, w), min(y1 + dy, h)
    outer = depth[Y0:Y1:_LAYER_PIXEL_STEP, X0:X1:_LAYER_PIXEL_STEP]
    step = _LAYER_PIXEL_STEP
    r0, r1 = -(-max(y0 - Y0, 0) // step), -(-max(y1 - Y0, 0) // step)     # sampled rows inside [y0, y1)
    c0, c1 = -(-max(x0 - X0, 0) // step), -(-max(x1 - X0, 0) // step)
    strips = (outer[:r0], outer[r1:], outer[r0:r1, :c0], outer[r0:r1, c1:])
    ring = np.concatenate([strip.ravel() for strip in strips]).astype(float)
    return ring[ring > 0]


def segment_box(depth: np.ndarray, cfg: BoxDepthConfig, layer: Optional[float] = None,
                sides: Sides = ALL_SIDES) -> tuple[np.ndarray, int]:
    """Algorithm 1 on the depth crop of one PDT box. Returns the segment (bool, crop shape) and the
    index of the accepted seed, or -1 when no seed passed the height test (then the fill with the largest
    vertical span is returned). The seeds are the paper's five, unless the box's centre lies on something
    ``_OCCLUDER_GAP_M`` nearer than the person's ``layer`` (``person_layer``; a monitor in front of them):
    then the layer's pixel nearest the centre is tried first (``cfg.seed_past_occluder``). Eq. 8 measures the
    layer's pixels to the box's ``sides`` inside the image only (``image_sides``; ``cfg.eq8_border_on_body``)."""
    h, w = depth.shape
    best, best_span, accepted = np.zeros((h, w), bool), -1, -1
    seeds = seed_points(h, w)
    centre = nearest_valid(depth, *seeds[0])
    if cfg.seed_past_occluder and layer is not None and centre is not None and depth[centre] < layer - _OCCLUDER_GAP_M:
        on = np.argwhere(np.abs(depth - layer) <= _LAYER_HALF_M)
        if len(on):
            d2 = (on[:, 0] - h / 2) ** 2 + (on[:, 1] - w / 2) ** 2
            seeds = [tuple(on[int(np.argmin(d2))])] + list(seeds)
    fills = DepthFill(depth)
    for k, (r, c) in enumerate(seeds):
        seed = nearest_valid(depth, r, c)
        if seed is None:
            continue
        region = fills.fill(np.array([seed]), cfg.omega_pixel)
        rows = np.flatnonzero(region.any(axis=1))
        span = int(rows[-1] - rows[0]) if len(rows) else -1
        if span > best_span:
            best, best_span = region, span
        if span > cfg.height_ratio * h:
            best, accepted = region, k
            break
    best = eq8_filter(best, depth, cfg.alpha, cfg.omega, sides, layer if cfg.eq8_border_on_body else None)
    return _absorb_invalid(best, depth, cfg.invalid_fill_px), accepted


def _absorb_invalid(region: np.ndarray, depth: np.ndarray, radius: int) -> np.ndarray:
    """Add the invalid-depth pixels within ``radius`` of ``region`` (holes on hair and dark clothes, the
    depth shadow at the silhouette): continuity cannot be tested there, and they most likely belong to it."""
    if radius <= 0 or not region.any():
        return region
    k = 2 * int(radius) + 1
    near = cv2.dilate(region.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    return region | (near & ~(depth > 0))


def overlaps_enough(b: tuple[int, int, int, int], pdt_boxes: list, bound: float) -> bool:
    """Eq. 9 against any PDT box: A_pas / (A_pas ∩ A_act) <= bound."""
    x0, y0, x1, y1 = b
    area = (x1 - x0) * (y1 - y0)
    for a0, b0, a1, b1 in pdt_boxes:
        inter = max(0, min(x1, a1) - max(x0, a0)) * max(0, min(y1, b1) - max(y0, b0))
        if inter > 0 and area / inter <= bound:
            return True
    return False
