"""Depth standard-deviation fitting (CP-SLAM, Li, Dai, Su, Zhu 2024; ``../shared/seeds/003_*.txt``).

The paper's Algorithm 1 (SDF), per person box:

* ``S`` = the keypoints inside the box (with a depth, see below).
* ``K = 20`` iterations: pick two features of ``S`` at random; the model is the mean ``mu`` and the
  (population, Eq. 4) standard deviation ``sigma`` of their two depths; every feature of ``S`` gets the
  Gaussian likelihood of its depth under that model (Eq. 5) and is an inlier when it passes the
  threshold ``th = 0.02 * (1 + nInliers / |S|)`` (Eq. 6); every iteration adds its inliers to the
  dynamic set ``S1`` (``combine="union"``, the default).
* The inliers -- the person's depth layer -- are dynamic (prob 1); everything else in the box
  (background behind, objects in front) stays static (0). Features outside person boxes are 0.

Readings of the paper, chosen so that the method does what it says on real data:

* **What is thresholded.** Algorithm 1 writes ``if likelihood < th: inlier``. Taken as the density of
  Eq. 5 that would make the points *far* from the model inliers. The paper builds on MLESAC (its
  ref. [15]), whose per-point cost is the negative log-likelihood, and "smaller than th" is an inlier
  test on a cost. So the test is ``-ln L(d) < th`` with ``L`` exactly as printed in Eq. 5 (normaliser
  ``1 / (sqrt(2 pi) sigma^2)``). This rejects broad models by itself (a person-plus-background pair
  with sigma = 1 m has no inliers) and admits a depth band of at most about +-0.55 m around ``mu``
  (reached for sigma ~ 0.39 m; +-0.07 m at sigma = 2 cm), i.e. one depth layer, which is what the
  method needs. Reading it as ``L > th`` instead lets any wide model swallow the whole box.
* **nInliers in Eq. 6.** For each model the inliers are counted at the base threshold (0.02) and
  counted again at ``th = 0.02 * (1 + n0 / |S|)``: the threshold relaxes with the inlier density of
  that model, as the paper intends, and the 20 models stay independent, so they are evaluated as one
  (K, |S|) array. The two picked features are scored like the others.
* **Degenerate cases.** Equal picked depths (sigma = 0; Kinect depth is quantised) -> sigma is
  floored at ``min_sigma`` (1 cm). A box with fewer than two depth features is not fitted: its
  features abstain (NaN). Features without depth inside a box cannot be placed in a depth layer: they
  abstain (NaN) -- alone the method then leaves them static, as the paper's depth test would, and in
  a fusion the other methods decide. Depth 0 never enters ``S``.
* **One S per box.** The paper's pseudo-code collects the features of all boxes into one set, but
  its Eq. 6 speaks of "the feature points within the detection box"; in a crowd people stand at
  different depths, so each box is fitted on its own. A feature in several boxes is dynamic when it
  is an inlier of any of them.
* **Randomness.** A ``numpy`` Generator seeded with ``cfg.seed + frame.index`` every frame: results
  do not depend on what ran before.
* **Union or best model (``combine``).** ``"union"`` (every preset) is the paper's. ``"best"``, the
  inliers of the model with the most of them (RANSAC's usual choice), classifies features more
  precisely on generated scenes (fused precision 0.944 vs 0.915) but SLAM did worse with it (Bonn
  crowd-480 ATE 0.0129 vs 0.0124 m; the three-close-people scene 16.3 vs 12.3 mm): the table is in
  docs/dynamic.md.
* **Mask** (diagnostics): the pixels of each fitted box whose depth passes the test of a kept model.
* ``detections=None`` (no detector ran) -> abstain on every keypoint; an empty list -> all 0.

On Bonn crowd the winning band covers the person in most boxes; the parts of a body outside the
+-0.55 m band (an arm stretched towards the camera) and features without depth at the silhouettes
(~100 per frame with three people) are not flagged, while the floor and furniture at the person's
depth inside the box are (a property of any depth-layer test).
"""
from __future__ import annotations

from typing import Optional

import numba
import numpy as np

from frontend.dynamic.base import DynamicContext, MethodOutput
from frontend.dynamic.box_depth_segmentation import box_pixels
from slam.core.dynamic_config import ClassGroups, DepthSdfConfig

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def neg_log_likelihood(d: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """-ln L of Eq. 5 (``L = exp(-(d-mu)^2 / (2 sigma^2)) / (sqrt(2 pi) sigma^2)``), broadcast."""
    return _LOG_SQRT_2PI + 2.0 * np.log(sigma) + (d - mu) ** 2 / (2.0 * sigma ** 2)


def band_half_width(sigma: float, th: float) -> float:
    """Largest |d - mu| with ``-ln L(d) < th``: the inlier depth band of a model (0 if none)."""
    rest = th - _LOG_SQRT_2PI - 2.0 * np.log(sigma)
    return float(sigma * np.sqrt(2.0 * rest)) if rest > 0 else 0.0


def fit_depth_layer(depths: np.ndarray, rng: np.random.Generator, iterations: int = 20,
                    base_threshold: float = 0.02, min_sigma: float = 0.01,
                    combine: str = "union") -> tuple[np.ndarray, list[dict]]:
    """SDF on the depths of one box's features (all > 0, at least two).

    ``combine="union"`` (the paper's Algorithm 1: every iteration adds its inliers to S1): a feature is
    dynamic when it is an inlier of any of the ``iterations`` two-point models, and the models returned
    are all those with inliers. ``"best"``: the inliers of the model with the most of them (RANSAC's
    usual choice), and that model alone. A model is ``{mu, sigma, th, half_width, inliers}``. All models
    are scored at once as a (K, |S|) array.
    """
    d = np.asarray(depths, dtype=float)
    n = len(d)
    k = max(1, int(iterations))
    i = rng.integers(0, n, size=k)
    j = (i + 1 + rng.integers(0, n - 1, size=k)) % n                  # a second, distinct feature
    d1, d2 = d[i], d[j]
    mu = 0.5 * (d1 + d2)                                                # Eq. 3
    sigma = np.maximum(0.5 * np.abs(d1 - d2), min_sigma)               # Eq. 4 (n = 2), floored
    nll = neg_log_likelihood(d[None, :], mu[:, None], sigma[:, None])  # Eq. 5, (K, n)
    n0 = np.count_nonzero(nll < base_threshold, axis=1)
    th = base_threshold * (1.0 + n0 / n)                                # Eq. 6
    inl = nll < th[:, None]
    counts = inl.sum(axis=1)
    if combine == "best":
        keep = [int(np.argmax(counts))]
        dynamic = inl[keep[0]]
    else:
        keep = [int(m) for m in np.flatnonzero(counts)]
        dynamic = inl.any(axis=0)
    models = [dict(mu=float(mu[m]), sigma=float(sigma[m]), th=float(th[m]),
                   half_width=band_half_width(float(sigma[m]), float(th[m])), inliers=int(counts[m]))
              for m in keep]
    return dynamic, models


class DepthSdfMethod:
    """CP-SLAM's standard-deviation fitting: the dominant depth layer of each person box is dynamic."""

    name = "depth_sdf"
    needs_detector = True
    prepares = False
    measures_motion = False

    def __init__(self, cfg: DepthSdfConfig, classes: ClassGroups):
        self.cfg = cfg
        self.classes = classes
        self._person = set(int(c) for c in classes.dynamic)

    def prepare(self, ctx: DynamicContext) -> None:
        """Nothing to do before the features and detections exist (see ``DynamicMethod.prepare``)."""

    def process(self, ctx: DynamicContext) -> MethodOutput:
        frame = ctx.frame
        n = len(frame)
        if ctx.detections is None:
            return MethodOutput.abstain(n)
        h, w = ctx.depth.shape[:2]
        rng = np.random.default_rng(int(self.cfg.seed) + int(frame.index))
        uv = np.asarray(frame.uv_raw, dtype=float).reshape(-1, 2)
        fd = np.nan_to_num(np.asarray(frame.depths, dtype=float), nan=0.0)
        has_depth = fd > 0
        dynamic = np.zeros(n, bool)
        evaluated = np.zeros(n, bool)
        in_box = np.zeros(n, bool)
        mask = np.zeros((h, w), bool)
        boxes = fitted = 0
        for det in ctx.detections:
            if det.class_id not in self._person:
                continue
            boxes += 1
            inside = det.contains(uv) if n else np.zeros(0, bool)
            in_box |= inside
            s = np.flatnonzero(inside & has_depth)
            if len(s) < 2:
                continue
            inl, models = fit_depth_layer(fd[s], rng, self.cfg.iterations, self.cfg.base_threshold,
                                          self.cfg.min_sigma, self.cfg.combine)
            fitted += 1
            evaluated[s] = True
            dynamic[s[inl]] = True
            self._paint(mask, ctx.depth, det, models)
        prob = dynamic.astype(float)
        prob[in_box & ~evaluated] = np.nan
        info = dict(boxes=boxes, fitted=fitted, dynamic=int(dynamic.sum()),
                    abstained=int(np.count_nonzero(in_box & ~evaluated)))
        return MethodOutput(prob, mask.astype(np.float32), info)

    @staticmethod
    def _paint(mask: np.ndarray, depth: np.ndarray, det, models: list[dict]) -> None:
        """Box pixels whose depth lies in any model's inlier band. One compiled pass over the box for all the
        models (the union keeps ~20: a pass per model was ~1 ms a frame on Bonn crowd); each comparison in the
        depth image's own precision, as numpy makes it with a Python float (NEP 50)."""
        models = [m for m in models if m["inliers"] > 0 and m["half_width"] > 0]
        if not models:
            return
        box = box_pixels(det, mask.shape[1], mask.shape[0])
        if box is None:
            return
        x0, y0, x1, y1 = box
        crop = depth[y0:y1, x0:x1]
        mus = np.array([m["mu"] for m in models], dtype=crop.dtype)
        half_widths = np.array([m["half_width"] for m in models], dtype=crop.dtype)
        _paint_bands(mask[y0:y1, x0:x1], crop, mus, half_widths)

    def end_frame(self, ctx: DynamicContext, output: MethodOutput, T_cw: Optional[np.ndarray],
                  is_keyframe: bool) -> None:
        """Stateless between frames."""
        return None


@numba.njit(nogil=True, cache=True)
def _paint_bands(mask, crop, mus, half_widths):
    """``mask |= (crop > 0) & (|crop - mu_m| < half_width_m for some m)``, in ``crop``'s precision."""
    for r in range(crop.shape[0]):
        for c in range(crop.shape[1]):
            d = crop[r, c]
            if mask[r, c] or not d > 0:
                continue
            for m in range(len(mus)):
                if abs(d - mus[m]) < half_widths[m]:
                    mask[r, c] = True
                    break
