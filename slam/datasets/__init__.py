"""RGB-D sequence sources: TUM/Bonn folders on disk and a seeded synthetic room."""
from __future__ import annotations

from pathlib import Path
from typing import Union

from .base import RGBDDataset, RGBDFrame
from .synthetic import SyntheticSequence, write_tum_layout
from .tum import (DatasetError, DatasetWarning, TumDataset, associate, guess_camera, load_groundtruth,
                  read_intrinsics)

__all__ = [
    "RGBDDataset", "RGBDFrame", "SyntheticSequence", "write_tum_layout", "DatasetError", "DatasetWarning",
    "TumDataset", "associate", "guess_camera", "load_groundtruth", "read_intrinsics", "open_dataset",
]


def open_dataset(path_or_name: Union[str, Path], **kwargs) -> Union[TumDataset, SyntheticSequence]:
    """The string "synthetic" gives the default SyntheticSequence (kwargs go to its constructor); any
    other string or Path is opened as a TUM-layout folder (write "./synthetic" for a folder of that name)."""
    if isinstance(path_or_name, str) and path_or_name == "synthetic":
        return SyntheticSequence(**kwargs)
    return TumDataset(path_or_name, **kwargs)
