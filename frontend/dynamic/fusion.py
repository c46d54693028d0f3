"""Fusing the enabled methods' per-keypoint probabilities into one.

- ``single``: the one enabled method's probability.
- ``max``: the most alarmed method wins (any method can veto a feature).
- ``noisy_or``: 1 - prod(1 - w_m p_m): independent evidence accumulates, and a weight w_m in
  [0, 1] says how much a method is trusted; two methods at 0.5 give 0.75.
Abstentions (NaN) are ignored; a keypoint on which every method abstains is static (0).

``fuse_masks`` fuses whole float32 pixel masks (a keyframe's, four full-resolution masks) with noisy-OR in one
compiled pass: ``fuse`` on them made a float64 copy, a NaN mask, a clip and a product per method, ~3.4 ms a
call on fr1/rpy where the pass takes a fraction of it, with the same arithmetic in the same order (the same bits).
"""
from __future__ import annotations

import numba
import numpy as np


def fuse(probs: list[np.ndarray], weights: list[float], mode: str, n: int) -> np.ndarray:
    """Fused probability of ``n`` items (keypoints, or the pixels of whole masks).

    One method at a time, in place: a stacked (methods, n) formulation made ~8 full-size copies of four
    full-resolution masks (~10 ms a frame). The products and maxima are taken in the same order as a
    reduction over the stacked axis, so the result is the same to the bit."""
    if not probs:
        return np.zeros(n)
    if mode == "single" and len(probs) != 1:
        raise ValueError(f"fusion 'single' needs exactly one method, got {len(probs)}")
    if mode not in ("single", "max", "noisy_or"):
        raise ValueError(f"unknown fusion mode '{mode}' (single, max, noisy_or)")
    out = None
    for p, w in zip(probs, weights):
        p = np.array(p, float).reshape(-1)           # a copy: clipped and rewritten in place below
        voted = ~np.isnan(p)
        np.clip(p, 0.0, 1.0, out=p)                  # +-inf -> 0 / 1, NaN stays NaN until replaced
        if mode == "noisy_or":
            term = 1.0 - float(np.clip(w, 0.0, 1.0)) * p
            term[~voted] = 1.0                       # an abstention leaves the product alone
            out = term if out is None else np.multiply(out, term, out=out)
        else:
            p[~voted] = 0.0
            out = p if out is None else np.maximum(out, p, out=out)
    return 1.0 - out if mode == "noisy_or" else out


def fuse_masks(masks: list[np.ndarray], weights: list[float], mode: str) -> np.ndarray:
    """``fuse(masks, weights, mode, n).astype(np.float32)`` for float32 masks of ``n`` pixels each, bit for bit;
    noisy-OR in one compiled pass (the other modes through ``fuse``)."""
    if mode != "noisy_or" or not masks:
        return fuse(masks, weights, mode, len(masks[0]) if masks else 0).astype(np.float32)
    flat = tuple(np.ascontiguousarray(m, np.float32).reshape(-1) for m in masks)
    trust = np.array([float(np.clip(w, 0.0, 1.0)) for w in weights[:len(flat)]], np.float64)
    return _noisy_or_masks(flat, trust)


@numba.njit(nogil=True, cache=True)
def _noisy_or_masks(masks, trust):
    """1 - prod_m (1 - w_m clip(p_m, 0, 1)) per pixel, an abstention (NaN) leaving the product alone; the
    product taken in method order in float64, as ``fuse`` does, then rounded to float32."""
    n = len(masks[0])
    out = np.empty(n, np.float32)
    for i in range(n):
        prod = 1.0
        for k in range(len(masks)):
            p = np.float64(masks[k][i])
            if p != p:                       # NaN: abstains
                term = 1.0
            else:
                if p < 0.0:
                    p = 0.0
                elif p > 1.0:
                    p = 1.0
                term = 1.0 - trust[k] * p
            prod = term if k == 0 else prod * term
        out[i] = np.float32(1.0 - prod)
    return out
