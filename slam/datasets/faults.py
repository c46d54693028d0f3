"""Fault injection for robustness tests: a dataset wrapper that blanks a run of frames.

    dataset = Blackout(TumDataset(path), start=185, count=30)   # frames 185..214 black, no depth

The frames keep their timestamps, so the trajectory shows exactly which frames could not be
tracked, and how soon tracking resumed in the same map afterwards.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Iterator

import numpy as np

from slam.datasets.base import DatasetWrapper, RGBDDataset, RGBDFrame


class Blackout(DatasetWrapper):
    def __init__(self, dataset: RGBDDataset, start: int, count: int):
        if start < 0 or count < 0:
            raise ValueError(f"blackout needs start >= 0 and count >= 0, got {start}:{count}")
        super().__init__(dataset)
        self.start, self.count = start, count
        self.name = f"{dataset.name}_blackout{start}-{start + count - 1}"

    def __iter__(self) -> Iterator[RGBDFrame]:
        for position, frame in enumerate(self.dataset):
            if self.start <= position < self.start + self.count:
                frame = replace(frame, rgb=np.zeros_like(frame.rgb), depth=np.zeros_like(frame.depth))
            yield frame
