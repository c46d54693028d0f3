"""The record every dataset yields, and the protocol a dataset follows."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Protocol

import numpy as np


@dataclass
class RGBDFrame:
    """One colour + depth pair as read from disk or generated.

    rgb is HxWx3 uint8 in BGR order (OpenCV's), depth is HxW float32 in metres with 0 = invalid,
    registered to the colour image. ``dynamic_mask`` (HxW bool, True where a moving object is the visible
    surface) is ground truth only synthetic sequences provide; None when unknown.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    rgb_path: Optional[Path] = None
    depth_path: Optional[Path] = None
    dynamic_mask: Optional[np.ndarray] = None


class RGBDDataset(Protocol):
    """What the pipeline needs from a sequence."""

    name: str

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[RGBDFrame]: ...

    def groundtruth(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(timestamps (N,), poses (N,4,4) camera-to-world) or None when the sequence has none."""
        ...
