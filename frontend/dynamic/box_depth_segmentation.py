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
from slam.core.dynamic_config import BoxDepthConfig

_SEED_SEARCH_PX = 4          # a seed on invalid depth moves to the nearest valid pixel this close
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


def flood_fill(depth: np.ndarray, seeds: np.ndarray, omega: float,
               max_components: int = _MAX_FILL_COMPONENTS) -> np.ndarray:
    """Pixels reached from any of ``seeds`` ((K,2) row, col) by 8-neighbour steps whose depth change
    is strictly below ``omega`` (neighbour-to-neighbour, Algorithm 1). Invalid depth (<= 0 or not
    finite) is never entered; seeds on invalid depth are ignored. Returns a bool mask of ``depth``'s
    shape."""
    img = np.ascontiguousarray(depth, dtype=np.float32)
    h, w = img.shape
    mask = np.zeros((h + 2, w + 2), np.uint8)
    inner = mask[1:-1, 1:-1]
    inner[~(np.isfinite(img) & (img > 0))] = 1
    img = np.where(inner == 1, np.float32(0), img)     # floodFill must not see NaN
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
        cv2.floodFill(img, mask, (c, r), 0, diff, diff, _FILL_FLAGS)
    return inner == 255


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


def side_distance(h: int, w: int) -> np.ndarray:
    """G_i (Eqs. 5-7): each pixel centre's distance (px) to the nearest side of an h x w box."""
    gy = np.minimum(np.arange(h) + 0.5, h - np.arange(h) - 0.5)
    gx = np.minimum(np.arange(w) + 0.5, w - np.arange(w) - 0.5)
    return np.minimum(gy[:, None], gx[None, :])


def eq8_filter(region: np.ndarray, depth: np.ndarray, alpha: float, omega: float) -> np.ndarray:
    """Remove the pixels of ``region`` (bool, box crop) with ``alpha * d_ave - d_i + omega * G_i < 0``."""
    if not region.any():
        return region
    d_ave = float(depth[region].mean())                                         # Eq. 3
    keep = (alpha * d_ave - depth) + omega * side_distance(*depth.shape) >= 0.0   # Eqs. 4-8
    return region & keep


def segment_box(depth: np.ndarray, cfg: BoxDepthConfig) -> tuple[np.ndarray, int]:
    """Algorithm 1 on the depth crop of one PDT box. Returns the segment (bool, crop shape) and the
    index of the accepted seed (0-4), or -1 when no seed passed the height test (then the fill with
    the largest vertical span is returned)."""
    h, w = depth.shape
    best, best_span, accepted = np.zeros((h, w), bool), -1, -1
    for k, (r, c) in enumerate(seed_points(h, w)):
        seed = nearest_valid(depth, r, c)
        if seed is None:
            continue
        region = flood_fill(depth, np.array([seed]), cfg.omega_pixel)
        rows = np.flatnonzero(region.any(axis=1))
        span = int(rows[-1] - rows[0]) if len(rows) else -1
        if span > best_span:
            best, best_span = region, span
        if span > cfg.height_ratio * h:
            best, accepted = region, k
            break
    best = eq8_filter(best, depth, cfg.alpha, cfg.omega)
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
