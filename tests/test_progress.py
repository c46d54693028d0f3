"""The run progress display (slam.run.progress) on a terminal and in a log, with a fake stream and clock."""
from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np

from frontend.tracker import TrackingState
from slam.run.progress import ProgressPrinter, format_bar


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class FakeClock:
    def __init__(self, step: float):
        self.now, self.step = 100.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def frame_output(i: int) -> SimpleNamespace:
    """Frame i: lost when i % 10 == 3, a keyframe when i % 5 == 0."""
    lost = i % 10 == 3
    return SimpleNamespace(index=i, T_wc=None if lost else np.eye(4), is_keyframe=i % 5 == 0 and not lost,
                           state=TrackingState.LOST if lost else TrackingState.OK)


def feed(printer: ProgressPrinter, frames: int, seconds: float = 0.1) -> None:
    for i in range(frames):
        printer(frame_output(i), seconds)


def test_plain_lines_every_50_frames_and_at_the_end():
    stream = io.StringIO()
    feed(ProgressPrinter(120, stream, clock=FakeClock(0.1)), 120)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in stream.getvalue()
    assert lines[0] == "  frame 50/120   10.0 fps  state ok  lost 5  keyframes 10"
    assert lines[1].startswith("  frame 100/120 ") and lines[2].startswith("  frame 120/120 ")
    assert lines[2].endswith("lost 12  keyframes 24")


def test_terminal_line_is_redrawn_in_place_and_ended_once():
    stream = FakeTerminal()
    feed(ProgressPrinter(20, stream, clock=FakeClock(0.2)), 20, seconds=0.2)   # 5 frames per second
    text = stream.getvalue()
    assert text.count("\r") == 20 and text.count("\n") == 1 and text.endswith("\n")
    last = text.rsplit("\r", 1)[1]
    assert last.startswith("[" + "#" * 24 + "]  20/20   ")
    assert "5.0 fps" in last and "ok " in last and "lost 2  kf 4" in last
    first = text.split("\r")[1]
    assert first.startswith("[" + "#" + "-" * 23 + "]   1/20")


def test_terminal_redraws_are_throttled_but_the_last_frame_is_shown():
    stream = FakeTerminal()
    feed(ProgressPrinter(100, stream, clock=FakeClock(0.01), min_interval_s=0.1), 100, seconds=0.01)
    text = stream.getvalue()
    assert 9 <= text.count("\r") <= 12
    assert "100/100" in text and text.endswith("\n")


def test_lost_state_is_shown_and_finish_ends_an_open_line():
    stream = FakeTerminal()
    printer = ProgressPrinter(50, stream, clock=FakeClock(0.2))
    feed(printer, 4)                      # frame 3 is lost: the run "stops" there
    assert "lost " in stream.getvalue().rsplit("\r", 1)[1] and "\n" not in stream.getvalue()
    assert stream.getvalue().rsplit("\r", 1)[1].split("fps  ")[1].startswith("lost   ")   # the state column
    printer.finish()
    assert stream.getvalue().endswith("\n")
    printer.finish()
    assert stream.getvalue().count("\n") == 1


def test_quiet_writes_nothing_and_unknown_total_has_no_bar():
    stream = FakeTerminal()
    feed(ProgressPrinter(10, stream, quiet=True, clock=FakeClock(0.2)), 10)
    assert stream.getvalue() == ""
    stream = FakeTerminal()
    feed(ProgressPrinter(None, stream, clock=FakeClock(0.2)), 3)
    assert "#" not in stream.getvalue() and "-]" not in stream.getvalue() and "frame 3 " in stream.getvalue()


def test_bar_clamps():
    assert format_bar(0, 10, 10) == "[----------]"
    assert format_bar(5, 10, 10) == "[#####-----]"
    assert format_bar(15, 10, 10) == "[##########]"
    assert format_bar(3, 0, 4) == "[----]"
