"""What ``System.process`` checks and does to its inputs before any module sees them.

The contract (README, "Using dynslam from Python"): ``rgb`` is the colour image as uint8, HxWx3 in
OpenCV's BGR order (HxW grey is accepted too), of the camera's size; ``depth`` is float32/float64 HxW
in metres, 0 (or NaN/inf) where there is no measurement; ``timestamp`` is a finite number of seconds.
A wrong input is an ``InputError`` naming what was expected and what came, never a crash deep inside.
"""
from __future__ import annotations

import cv2
import numpy as np

from slam.core.errors import DynslamError

MAX_PLAUSIBLE_DEPTH_M = 100.0   # an RGB-D sensor's median depth above this is millimetres, not metres


class InputError(DynslamError, ValueError):
    """An input of ``System.process`` is not what the contract says."""


def check_inputs(rgb: np.ndarray, depth: np.ndarray, timestamp: float, width: int, height: int) -> None:
    """Raise ``InputError`` unless the frame follows the contract above."""
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim not in (2, 3) or \
            (rgb.ndim == 3 and rgb.shape[2] != 3):
        raise InputError(f"rgb must be a uint8 HxWx3 BGR (or HxW grey) image, got {_describe(rgb)}")
    if rgb.shape[:2] != (height, width):
        raise InputError(f"rgb is {rgb.shape[1]}x{rgb.shape[0]} but the camera is {width}x{height} "
                         "(camera.width x camera.height)")
    if not isinstance(depth, np.ndarray) or depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        hint = " (raw sensor units? divide by the depth scale, e.g. 1000 or 5000, to get metres)" \
            if isinstance(depth, np.ndarray) and np.issubdtype(depth.dtype, np.integer) else ""
        raise InputError(f"depth must be a float HxW image in metres, got {_describe(depth)}{hint}")
    if depth.shape != rgb.shape[:2]:
        raise InputError(f"depth is {depth.shape[1]}x{depth.shape[0]} but rgb is {rgb.shape[1]}x{rgb.shape[0]}")
    sample = depth[::8, ::8]   # every 64th pixel: the units check costs microseconds, not a full median
    valid = sample[(sample > 0) & np.isfinite(sample)]
    if valid.size and float(np.median(valid)) > MAX_PLAUSIBLE_DEPTH_M:
        raise InputError(f"depth must be in metres, but its median is {float(np.median(valid)):.0f} "
                         "(millimetres? divide by 1000)")
    if not isinstance(timestamp, (int, float, np.integer, np.floating)) or not np.isfinite(timestamp):
        raise InputError(f"timestamp must be a finite number of seconds, got {timestamp!r}")


def _describe(array) -> str:
    if not isinstance(array, np.ndarray):
        return type(array).__name__
    return f"{array.dtype} with shape {array.shape}"


def clean_depth(depth: np.ndarray) -> np.ndarray:
    """``depth`` with NaN / inf / negative values set to 0, the invalid value everything downstream
    expects (a float depth image's "no measurement" is NaN or inf); a copy only when there are any."""
    valid = (depth >= 0) & (depth < np.inf)   # False for NaN (every comparison is), -inf, negatives, +inf
    if valid.all():
        return depth
    return np.where(valid, depth, 0).astype(np.float32)


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """The grey image every module reads (a grey input is used as it is)."""
    return rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_BGR2GRAY)
