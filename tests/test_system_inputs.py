"""System.process checks its inputs against its contract (slam.runtime.inputs) with clear errors."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import synthetic_config, synthetic_sequence
from slam.runtime.inputs import InputError
from slam.runtime.system import System


@pytest.fixture(scope="module")
def frame_and_system():
    seq = synthetic_sequence(n_frames=2)
    return seq.frame(0), System(synthetic_config(seq))


@pytest.mark.parametrize("make, message", [
    (lambda f: (f.rgb.astype(np.float32), f.depth, 0.0), "rgb must be a uint8 HxWx3 BGR"),
    (lambda f: (f.rgb[:, :, :2].copy(), f.depth, 0.0), "rgb must be a uint8 HxWx3 BGR"),
    (lambda f: (f.rgb[::2, ::2].copy(), f.depth[::2, ::2].copy(), 0.0), "rgb is 320x240 but the camera is 640x480"),
    (lambda f: (f.rgb, (f.depth * 1000).astype(np.uint16), 0.0), "divide by the depth scale"),
    (lambda f: (f.rgb, f.depth * 1000, 0.0), "millimetres? divide by 1000"),
    (lambda f: (f.rgb, f.depth[:-1], 0.0), "depth is 640x479 but rgb is 640x480"),
    (lambda f: (f.rgb, f.depth, float("nan")), "timestamp must be a finite number"),
    (lambda f: (list(f.rgb), f.depth, 0.0), "got list"),
])
def test_bad_inputs_are_clear_errors(frame_and_system, make, message):
    frame, system = frame_and_system
    with pytest.raises(InputError, match=message.replace("?", r"\?")):
        system.process(*make(frame))


def test_the_contract_itself_is_accepted(frame_and_system):
    frame, system = frame_and_system
    grey = frame.rgb[:, :, 1].copy()
    assert system.process(frame.rgb, frame.depth.astype(np.float64), 0.0).T_wc is not None
    assert system.process(grey, frame.depth, np.float64(1 / 30)).n_features > 0
