"""One frame of lookahead (slam/runtime/lookahead.py): the next frame's features and detections run on
threads while this frame is tracked. Whichever finishes first, the result must be the same bits as without
lookahead; a frame announced but never processed, or unreadable, must cost nothing else."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from frontend.dynamic.base import DetectorDefaults
from frontend.dynamic.oracle import synthetic_oracle
from slam.runtime.lookahead import FrameLookahead
from slam.runtime.system import System, UpcomingFrame
from slam.runtime.tracking_loop import TrackingLoop
from conftest import synthetic_config, synthetic_sequence

FRAMES = 7
DELAY_S = 0.1   # far longer than a generated frame's tracking or its cpr registration (~20-60 ms)


@pytest.fixture(scope="module")
def people():
    return synthetic_sequence(FRAMES, movers="people")


class SlowOracle(DetectorDefaults):
    """The ground-truth boxes, after a delay (the detector's thread finishes after the tracking)."""

    def __init__(self, seq, delay: float):
        self.oracle, self.delay = synthetic_oracle(seq), delay

    def detect(self, bgr, timestamp: float = 0.0):
        time.sleep(self.delay)
        return self.oracle.detect(bgr, timestamp)


def _run(seq, monkeypatch, slow: str) -> tuple[np.ndarray, list[np.ndarray]]:
    """Track ``seq`` (the product's default methods); ``slow`` delays one side: "tracking" (the frame ahead's
    image work finishes first), "ahead" (the tracking of this frame finishes first), or "none" without
    lookahead."""
    with monkeypatch.context() as patch:
        detector = synthetic_oracle(seq)
        if slow == "tracking":
            step = TrackingLoop.step
            patch.setattr(TrackingLoop, "step", lambda self, *a: (time.sleep(DELAY_S), step(self, *a))[1])
        elif slow == "ahead":
            extract = FrameLookahead._extract
            patch.setattr(FrameLookahead, "_extract", lambda self, *a: (time.sleep(DELAY_S), extract(self, *a))[1])
            detector = SlowOracle(seq, DELAY_S)
        system = System(synthetic_config(seq, preset=None), detector=detector)
        probs = []
        frames = [seq.frame(i) for i in range(FRAMES)]
        try:
            for f, nxt in zip(frames, frames[1:] + [None]):
                upcoming = None if (nxt is None or slow == "none") else UpcomingFrame(nxt.rgb, nxt.depth,
                                                                                      nxt.timestamp, nxt.index)
                system.process(f.rgb, f.depth, f.timestamp, f.index, upcoming)
                probs.append(system.last_frame.dynamic_prob.copy())
        finally:
            system.close()
        return system.trajectory(smoothed=False)[1], probs


def test_the_frame_ahead_gives_the_same_bits_as_none_whichever_thread_finishes_first(people, monkeypatch):
    poses_a, probs_a = _run(people, monkeypatch, slow="tracking")
    assert np.isfinite(poses_a).all()
    assert any((p >= 0.5).any() for p in probs_a)      # the people were found: the dynamic methods ran
    for slow in ("ahead", "none"):
        poses_b, probs_b = _run(people, monkeypatch, slow=slow)
        assert poses_a.tobytes() == poses_b.tobytes(), slow
        assert all(a.tobytes() == b.tobytes() for a, b in zip(probs_a, probs_b)), slow


def test_a_frame_announced_but_not_processed_changes_nothing_after_it(people):
    """The frame announced ahead does not come (the caller skipped it): its work is dropped and the frame
    that does come is computed as without lookahead; closing leaves no thread running."""
    config = synthetic_config(people, preset=None)
    outputs = []
    for announce_wrong in (False, True):
        system = System(config.model_copy(deep=True), detector=synthetic_oracle(people))
        for i in (0, 1, 2, 4, 5):      # frame 3 skipped
            f = people.frame(i)
            j = 3 if (announce_wrong and i == 2) else None
            upcoming = None if j is None else UpcomingFrame(people.frame(j).rgb, people.frame(j).depth,
                                                            people.frame(j).timestamp, j)
            system.process(f.rgb, f.depth, f.timestamp, f.index, upcoming)
        system.close()
        outputs.append(system.trajectory(smoothed=False)[1])
    assert np.isfinite(outputs[0]).all()
    assert outputs[0].tobytes() == outputs[1].tobytes()   # only the detector and ORB ran ahead: dropped
    assert not [t for t in threading.enumerate() if t.name.startswith("dynslam-") and t.is_alive()]


def test_an_unreadable_frame_ahead_is_reported_for_itself(people):
    """An upcoming frame that breaks the input contract is not begun: the call that gets it raises, the
    frame before is tracked as usual."""
    from slam.runtime.inputs import InputError

    system = System(synthetic_config(people, preset=None), detector=synthetic_oracle(people))
    try:
        f0, f1 = people.frame(0), people.frame(1)
        bad = UpcomingFrame(f1.rgb, (f1.depth * 1000).astype(np.uint16), f1.timestamp, 1)
        out = system.process(f0.rgb, f0.depth, f0.timestamp, 0, bad)
        assert out.T_wc is not None
        with pytest.raises(InputError, match="depth"):
            system.process(bad.rgb, bad.depth, bad.timestamp, 1)
    finally:
        system.close()


def test_a_frame_begun_ahead_is_checked_once_and_other_arrays_are_still_checked(people, monkeypatch):
    """The frame ahead was checked when it was begun: its own call does not check the same arrays again. Other
    arrays under its timestamp and index (a caller that announced one frame and passed another) are checked
    and refused, and the begun work ends before the error leaves."""
    import slam.runtime.lookahead as lookahead
    import slam.runtime.system as system_module
    from slam.runtime.inputs import InputError, check_inputs

    calls = []

    def counting(rgb, *args):
        calls.append(rgb)
        return check_inputs(rgb, *args)

    monkeypatch.setattr(lookahead, "check_inputs", counting)
    monkeypatch.setattr(system_module, "check_inputs", counting)
    system = System(synthetic_config(people, preset=None), detector=synthetic_oracle(people))
    try:
        f0, f1, f2 = people.frame(0), people.frame(1), people.frame(2)
        system.process(f0.rgb, f0.depth, f0.timestamp, 0, UpcomingFrame(f1.rgb, f1.depth, f1.timestamp, 1))
        system.process(f1.rgb, f1.depth, f1.timestamp, 1, UpcomingFrame(f2.rgb, f2.depth, f2.timestamp, 2))
        assert [c is f for c, f in zip(calls, (f0.rgb, f1.rgb, f2.rgb))] == [True] * 3 and len(calls) == 3
        with pytest.raises(InputError, match="depth"):
            system.process(f2.rgb, (f2.depth * 1000).astype(np.uint16), f2.timestamp, 2)
    finally:
        system.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("dynslam-features") and t.is_alive()]
