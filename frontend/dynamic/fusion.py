"""Fusing the enabled methods' per-keypoint probabilities into one.

- ``single``: the one enabled method's probability.
- ``max``: the most alarmed method wins (any method can veto a feature).
- ``noisy_or``: 1 - prod(1 - w_m p_m): independent evidence accumulates, and a weight w_m in
  [0, 1] says how much a method is trusted; two methods at 0.5 give 0.75.
Abstentions (NaN) are ignored; a keypoint on which every method abstains is static (0).
"""
from __future__ import annotations

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
