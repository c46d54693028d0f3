"""``dynamic.dump_masks_dir``: one debug image per frame (frontend/dynamic/overlay.py), the frame with the
methods' masks tinted and its keypoints drawn."""
from __future__ import annotations

import cv2
import numpy as np

from frontend.dynamic.oracle import synthetic_oracle
from slam.runtime.system import System
from conftest import synthetic_config, synthetic_sequence


def test_dump_masks_dir_writes_a_tinted_frame_per_frame(tmp_path):
    seq = synthetic_sequence(4, movers="people")
    config = synthetic_config(seq, preset=None, **{"dynamic.dump_masks_dir": str(tmp_path / "dump")})
    system = System(config, detector=synthetic_oracle(seq), sequence_name=seq.name)
    frames = [seq.frame(i) for i in range(4)]
    for f in frames:
        system.process(f.rgb, f.depth, f.timestamp, f.index)
    system.close()
    written = sorted((tmp_path / "dump").glob("*.png"))
    assert [p.name for p in written] == [f"{i:06d}.png" for i in range(4)]
    last = cv2.imread(str(written[-1]))
    assert last.shape == frames[-1].rgb.shape
    person = frames[-1].dynamic_mask
    assert person.any()
    # the people are tinted (a method flags them), the rest of the frame mostly left as it was
    assert np.mean(np.abs(last[person].astype(int) - frames[-1].rgb[person].astype(int))) > 10
