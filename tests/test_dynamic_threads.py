"""The dynamic rejector's threads (frontend/dynamic/rejector.py): the detector and the methods' image-only
work (``DynamicMethod.prepare``, cpr's registration) start in ``begin_frame`` and run while the features
are extracted. Threading must change nothing but the time: the same probabilities and masks as running
everything in line, failures reported for their own frame, and a frame begun but never processed harmless.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from frontend.dynamic.base import DetectorDefaults, DynamicContext
from frontend.dynamic.cpr import CprMethod
from frontend.dynamic.oracle import synthetic_oracle
from frontend.dynamic_filter import build_dynamic_filter
from frontend.orb_extractor import OrbExtractor
from slam.core.camera import PinholeCamera
from conftest import synthetic_config, synthetic_sequence

FRAMES = 8


@pytest.fixture(scope="module")
def scene():
    seq = synthetic_sequence(FRAMES, movers="people")
    config = synthetic_config(seq, preset=None)     # the product's default: all four methods
    camera = PinholeCamera.from_config(config.camera)
    extractor = OrbExtractor(config.orb, camera)
    frames = []
    for i in range(FRAMES):
        f = seq.frame(i)
        gray = cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY)
        frames.append((f, gray, extractor.extract(gray, f.depth, i, f.timestamp)))
    return seq, config, camera, frames


class RecordingDetector(DetectorDefaults):
    """The ground-truth boxes, remembering which frames were asked for."""

    def __init__(self, seq):
        self.oracle, self.asked = synthetic_oracle(seq), []

    def detect(self, bgr, timestamp: float = 0.0):
        self.asked.append(timestamp)
        return self.oracle.detect(bgr, timestamp)


def _rejector(scene, detector=None):
    seq, config, camera, _ = scene
    return build_dynamic_filter(config, camera, detector=detector or synthetic_oracle(seq))


def _pose(i: int) -> np.ndarray:
    return np.eye(4)   # the same (identity) prediction for both ways of running: only threading differs


def _run(scene, threaded: bool, skip_process: frozenset = frozenset()) -> list:
    _, _, _, frames = scene
    rejector = _rejector(scene)
    out = []
    try:
        for i, (f, gray, feat) in enumerate(frames):
            if threaded:
                rejector.begin_frame(f.rgb, gray, f.depth, f.timestamp, _pose(i), _pose(i))
            if i in skip_process:
                continue   # e.g. the frame's extraction failed: begun, never processed
            fused = rejector.process(feat, f.rgb, gray, f.depth, _pose(i), _pose(i))
            masks = {name: o.mask for name, o in rejector.last_outputs.items()}
            out.append((i, fused, masks))
            rejector.end_frame(np.eye(4), is_keyframe=(i % 3 == 0))
    finally:
        rejector.close()
    return out


def test_threaded_prepare_gives_the_same_bits_as_in_line(scene):
    threaded, in_line = _run(scene, True), _run(scene, False)
    assert [i for i, *_ in threaded] == list(range(FRAMES))
    flagged = 0
    for (_, fa, ma), (_, fb, mb) in zip(threaded, in_line):
        assert np.array_equal(fa, fb)
        assert ma.keys() == mb.keys() and "cpr" in ma
        for name in ma:
            assert (ma[name] is None) == (mb[name] is None)
            if ma[name] is not None:
                assert np.array_equal(ma[name], mb[name]), name
        flagged += int(np.sum(fa >= 0.5))
    assert flagged > 0   # people walk through the scene: the comparison is not between empty outputs


def test_a_frame_begun_but_never_processed_does_not_disturb_the_next(scene):
    """The next frame is processed normally, its features get a probability each, and cpr, whose
    registration ran for the dropped frame too, still abstains only while it has no reference."""
    out = _run(scene, True, skip_process=frozenset({3}))
    assert [i for i, *_ in out] == [0, 1, 2, 4, 5, 6, 7]
    _, _, _, frames = scene
    for i, fused, _ in out:
        assert fused.shape == (len(frames[i][2]),) and np.all((fused >= 0) & (fused <= 1))


def test_a_frame_processed_without_its_own_begin_is_computed_in_line(scene):
    """begin_frame ran for frame 3, then frame 4 arrives at process without one: frame 4 gets its own
    detections (not frame 3's) and its own cpr mask, the one a lone cpr computes that saw frame 3's
    registration only (as the threaded rejector did)."""
    seq, config, camera, frames = scene
    detector = RecordingDetector(seq)
    rejector, lone = _rejector(scene, detector), CprMethod(config.dynamic.cpr)
    try:
        for i, (f, gray, feat) in enumerate(frames[:5]):
            ctx = DynamicContext(feat, f.rgb, gray, f.depth, camera, None, _pose(i), _pose(i))
            if i == 3:
                rejector.begin_frame(f.rgb, gray, f.depth, f.timestamp, _pose(i), _pose(i))
                lone.prepare(ctx)
                continue
            rejector.process(feat, f.rgb, gray, f.depth, _pose(i), _pose(i))
            expected = lone.process(ctx)
            assert np.array_equal(rejector.last_outputs["cpr"].prob, expected.prob, equal_nan=True)
            rejector.end_frame(np.eye(4), False)
            lone.end_frame(ctx, expected, np.eye(4), False)
        assert rejector.last_outputs["cpr"].mask is not None      # frame 4 has a reference: a real mask
        assert detector.asked == [f.timestamp for f, _, _ in frames[:5]]   # frame 3 on the thread, 4 in line
    finally:
        rejector.close()


def test_a_prepare_failure_is_reported_for_its_own_frame(scene):
    _, _, _, frames = scene
    rejector = _rejector(scene)
    cpr = next(m for m in rejector.methods if m.name == "cpr")
    original = cpr.prepare

    def failing(ctx):
        if ctx.depth is frames[2][0].depth:
            raise RuntimeError("cpr broke on frame 2")
        original(ctx)

    cpr.prepare = failing
    try:
        for i, (f, gray, feat) in enumerate(frames[:4]):
            rejector.begin_frame(f.rgb, gray, f.depth, f.timestamp, _pose(i), _pose(i))
            if i == 2:
                with pytest.raises(RuntimeError, match="frame 2"):
                    rejector.process(feat, f.rgb, gray, f.depth, _pose(i), _pose(i))
                continue
            rejector.process(feat, f.rgb, gray, f.depth, _pose(i), _pose(i))
            rejector.end_frame(np.eye(4), False)
    finally:
        rejector.close()
