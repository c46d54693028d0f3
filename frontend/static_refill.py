"""More features from the static rest of the image when moving objects hold most of them.

The extractor's feature budget is spread over the whole image; when people fill most of the view,
most features land on them and tracking starves. Then features are extracted again, only where the
dynamic mask says a new landmark could be made (outside person boxes and masks), and appended.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from frontend.dynamic.base import keypoints_in_mask
from frontend.orb_extractor import OrbExtractor
from slam.core.frame import FeatureFrame

REDETECTION_PX = 2.0   # an extra feature this close to an existing one is the same corner again


def refill_static(frame: FeatureFrame, gray: np.ndarray, depth: np.ndarray, mask: Optional[np.ndarray],
                  extractor: OrbExtractor, dynamic_threshold: float, min_static: int,
                  admissible: float) -> FeatureFrame:
    """``frame`` plus features where ``mask`` < ``admissible`` when it has fewer than ``min_static``
    features below ``dynamic_threshold``; unchanged otherwise (or without a mask)."""
    if np.sum(frame.dynamic_prob < dynamic_threshold) >= min_static or mask is None:
        return frame
    allowed = (mask < admissible).astype(np.uint8) * 255
    extra = extractor.extract(gray, depth, frame.index, frame.timestamp, mask=allowed)
    if len(extra) == 0:
        return frame
    if len(frame):
        distance, _ = cKDTree(frame.uv_raw).query(extra.uv_raw)
        extra = extra.subset(distance > REDETECTION_PX)
    extra.dynamic_prob = keypoints_in_mask(mask, extra.uv_raw).astype(float)
    return frame.append(extra)
