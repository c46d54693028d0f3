"""Training a place-recognition vocabulary on the ORB features of a user's images (``dynslam vocabulary``)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from backend.place_recognition import Vocabulary
from frontend.orb_extractor import OrbExtractor
from slam.core.camera import PinholeCamera
from slam.core.config import SlamConfig
from slam.datasets import DatasetError


def train_vocabulary(folders: Sequence[str], step: int, branches: int, levels: int,
                     seed: int) -> tuple[Vocabulary, int, int]:
    """(vocabulary, descriptors used, images used) from every ``step``-th PNG/JPEG under ``folders``
    (unreadable images are skipped with a line on stderr)."""
    paths = sorted(p for folder in folders for p in Path(folder).rglob("*")
                   if p.suffix.lower() in (".png", ".jpg", ".jpeg"))[::step]
    if not paths:
        raise DatasetError(f"no PNG/JPEG images found under {', '.join(folders)}")
    config = SlamConfig()
    extractor = OrbExtractor(config.orb, PinholeCamera.from_config(config.camera))
    descriptors = []
    for path in paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            print(f"dynslam vocabulary: skipping unreadable {path}", file=sys.stderr)
            continue
        descriptors.append(extractor.extract(gray, np.zeros(gray.shape, np.float32)).descriptors)
    vocabulary = Vocabulary.train(descriptors, k=branches, levels=levels, seed=seed)
    return vocabulary, sum(map(len, descriptors)), len(descriptors)
