"""PPS-SLAM's Algorithm 2 (seed 002): dynamic region probability propagation on a grid.

``frontend/dynamic/flow_epipolar.py`` (Algorithm 1) finds the dynamic sub-boxes of a frame; this spreads
their evidence over time. The image is divided into ``grid`` x ``grid`` cells; a cell's likelihood is
``likelihood_dynamic`` when the frame's dynamic sub-boxes cover more than ``cover_ratio`` of it, else
``likelihood_static``; its prior is the mean of its posteriors over the last ``history`` frames, and the
posterior is ``L P / (L P + (1 - L)(1 - P))`` (Eqs. 8-10). A region stays dynamic through frames where
the detector misses it, as long as its history holds.

* Prior without history: ``initial_prior`` = 0.5, the uninformative prior for which the posterior
  equals the likelihood (0.9 / 0.1), so the first frames' grid is Algorithm 1's coverage itself.
  With fewer than ``history`` frames the prior is the mean of the posteriors available.
* Posteriors are clamped to [``prob_clamp``, 1 - ``prob_clamp``] (0.05) before they enter the history.
  The literal recursion drives a static cell's posterior geometrically to 0 (or a long-dynamic cell to
  1), after which the 0.9 / 0.1 likelihood can never move it: after the 230 static frames at the start
  of Bonn crowd Algorithm 2 would never mark the people. Note that one static-likelihood frame divides
  the prior odds by 9, so a cell survives a detection miss only when the mean of its last 10
  posteriors is > 0.9. With the 0.05 clamp a newly dynamic cell is removed from its 3rd consecutive
  dynamic frame and, after >= 15 consecutive dynamic frames, stays removed for 1-2 frames without
  evidence. A 0.01 clamp needs 6 frames to rise and leaves trails of up to 5 frames (more removal of
  the static background a person just left, which the paper reports for W/static) while recovering no
  more missed frames in simulation. Removal uses ``posterior > remove_threshold + 1e-9`` so that the
  exact 0.5 of a 0.9 prior meeting a 0.1 likelihood does not flip on rounding.
"""
from __future__ import annotations

from collections import deque
from typing import Optional

import cv2
import numpy as np

from slam.core.dynamic_config import FlowEpipolarConfig


def bayes_posterior(likelihood: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """PPS-SLAM Eqs. 8-10: L P / (L P + (1 - L)(1 - P))."""
    a = likelihood * prior
    b = (1.0 - likelihood) * (1.0 - prior)
    with np.errstate(invalid="ignore", divide="ignore"):
        post = a / (a + b)
    return np.where(a + b > 0, post, 0.5)


REMOVE_EPS = 1e-9   # "posterior > threshold" tolerance against rounding (0.9 * 0.1 vs 0.1 * 0.9)


def above_threshold(p: np.ndarray, threshold: float) -> np.ndarray:
    return p > threshold + REMOVE_EPS


def threshold_to_half(p: np.ndarray, threshold: float) -> np.ndarray:
    """Map probabilities piecewise-linearly so that ``above_threshold(p)`` becomes ``out >= 0.5``."""
    t = float(np.clip(threshold, 1e-6, 1.0 - 1e-6))
    low = 0.5 * p / t
    high = 0.5 + 0.5 * (p - t) / (1.0 - t)
    return np.where(above_threshold(p, t), np.clip(high, 0.5, 1.0),
                    np.clip(low, 0.0, np.nextafter(0.5, 0.0)))


def grid_edges(size: int, n: int) -> np.ndarray:
    """Pixel index edges of n cells over ``size`` pixels (n + 1 values, first 0, last size)."""
    return np.round(np.linspace(0, size, n + 1)).astype(int)


def cell_coverage(mask: np.ndarray, row_edges: np.ndarray, col_edges: np.ndarray) -> np.ndarray:
    """Fraction of each grid cell's pixels set in a boolean mask (integral image, no loops)."""
    # Only the grid's corners are read: they are cast, not the whole integral image (a VGA frame's 2.5 MB).
    image = mask.view(np.uint8) if mask.dtype == bool and mask.flags.c_contiguous else mask.astype(np.uint8)
    s = cv2.integral(image, sdepth=cv2.CV_32S)[np.ix_(row_edges, col_edges)].astype(np.int64)
    sums = s[1:, 1:] - s[:-1, 1:] - s[1:, :-1] + s[:-1, :-1]
    area = np.diff(row_edges)[:, None] * np.diff(col_edges)[None, :]
    return sums / np.maximum(area, 1)


def point_cells(xy: np.ndarray, row_edges: np.ndarray, col_edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grid cell (row, col) of each point's nearest pixel."""
    h, w = row_edges[-1], col_edges[-1]
    cols = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    return (np.searchsorted(row_edges, rows, side="right") - 1,
            np.searchsorted(col_edges, cols, side="right") - 1)


class GridPropagation:
    """The grid's posterior history: ``update`` gives a frame's cell posteriors from its dynamic region,
    ``commit`` (once the frame is done) adds them to the history that makes the next frame's prior."""

    def __init__(self, cfg: FlowEpipolarConfig):
        self.cfg = cfg
        self.history: deque[np.ndarray] = deque(maxlen=max(int(cfg.history), 1))
        self._pending: Optional[np.ndarray] = None

    def reset(self) -> None:
        self.history.clear()
        self._pending = None

    def prior(self) -> np.ndarray:
        """Per-cell prior: mean of the stored posteriors, or ``initial_prior`` without history."""
        g = max(int(self.cfg.grid), 1)
        if not self.history:
            return np.full((g, g), float(self.cfg.initial_prior))
        return np.mean(np.stack(self.history), axis=0)

    def update(self, region_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One frame (``region_mask``: HxW bool, its dynamic sub-boxes). Returns the cell posteriors, the
        cell probabilities mapped so that 0.5 is the removal threshold, and the grid's row and column
        edges; keeps the clamped posterior for ``commit``."""
        cfg = self.cfg
        h, w = region_mask.shape
        g = max(int(cfg.grid), 1)
        re, ce = grid_edges(h, g), grid_edges(w, g)
        coverage = cell_coverage(region_mask, re, ce)
        likelihood = np.where(coverage > cfg.cover_ratio, cfg.likelihood_dynamic, cfg.likelihood_static)
        posterior = bayes_posterior(likelihood, self.prior())
        c = float(np.clip(cfg.prob_clamp, 0.0, 0.5))
        self._pending = np.clip(posterior, c, 1.0 - c)
        return posterior, threshold_to_half(posterior, cfg.remove_threshold), re, ce

    def commit(self) -> None:
        """The last ``update``'s posterior joins the history (nothing if there was none since)."""
        if self._pending is not None:
            self.history.append(self._pending)
            self._pending = None
