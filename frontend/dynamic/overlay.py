"""The debug image of ``dynamic.dump_masks_dir``: a frame with each method's mask tinted, the detections' boxes
and the keypoints coloured by their fused dynamic probability (``DynamicRejector`` writes one per frame)."""
from __future__ import annotations

import cv2
import numpy as np

from frontend.dynamic.base import DynamicContext, MethodOutput

_COLOURS = [(0, 0, 255), (0, 200, 255), (255, 0, 255), (255, 128, 0)]


def overlay(ctx: DynamicContext, outputs: dict[str, MethodOutput], fused: np.ndarray) -> np.ndarray:
    """The frame with each method's mask tinted, detection boxes, and features coloured by the
    fused probability (green static, red dynamic)."""
    image = ctx.rgb.copy()
    for colour, (name, out) in zip(_COLOURS, outputs.items()):
        if out.mask is not None and np.any(out.mask):
            tint = np.zeros_like(image)
            tint[np.asarray(out.mask) > 0.5] = colour
            image = cv2.addWeighted(image, 1.0, tint, 0.35, 0)
    for det in ctx.detections or []:
        cv2.rectangle(image, (int(det.x0), int(det.y0)), (int(det.x1), int(det.y1)), (255, 255, 255), 1)
    for (x, y), p in zip(np.rint(ctx.frame.uv_raw).astype(int), fused):
        cv2.circle(image, (int(x), int(y)), 2, (0, int(255 * (1 - p)), int(255 * p)), -1)
    y = 16
    for colour, name in zip(_COLOURS, outputs):
        cv2.putText(image, f"{name}: {outputs[name].flagged}", (8, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
        y += 16
    return image
