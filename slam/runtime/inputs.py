"""What ``System.process`` does to its inputs before any module sees them."""
from __future__ import annotations

import numpy as np


def clean_depth(depth: np.ndarray) -> np.ndarray:
    """``depth`` with NaN / inf / negative values set to 0, the invalid value everything downstream
    expects (a float depth image's "no measurement" is NaN or inf); a copy only when there are any."""
    valid = (depth >= 0) & (depth < np.inf)   # False for NaN (every comparison is), -inf, negatives, +inf
    if valid.all():
        return depth
    return np.where(valid, depth, 0).astype(np.float32)
