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
    if not probs:
        return np.zeros(n)
    P = np.vstack([np.asarray(p, float).reshape(1, -1) for p in probs])
    voted = ~np.isnan(P)
    P = np.clip(np.nan_to_num(P, nan=0.0), 0.0, 1.0)
    if mode == "single":
        if len(probs) != 1:
            raise ValueError(f"fusion 'single' needs exactly one method, got {len(probs)}")
        return P[0]
    if mode == "max":
        return P.max(axis=0)
    if mode == "noisy_or":
        w = np.clip(np.asarray(weights, float), 0.0, 1.0)[:, None]
        return 1.0 - np.prod(np.where(voted, 1.0 - w * P, 1.0), axis=0)
    raise ValueError(f"unknown fusion mode '{mode}' (single, max, noisy_or)")
