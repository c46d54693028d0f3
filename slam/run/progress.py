"""Progress display for ``dynslam run`` / ``demo``: frame i/N, frames per second, tracking state,
lost frames and keyframes.

On a terminal it is one line redrawn in place (``\\r``, at most every ``min_interval_s`` so the
display never costs the run noticeable time); when stderr goes to a file or a pipe (CI logs) it
prints a plain line every ``every`` frames instead, because ``\\r`` would leave one garbled line
per redraw there. No dependency: a bar of ``#`` and ``-`` is all a progress display needs.
"""
from __future__ import annotations

import sys
import time
from typing import Any, Callable, Optional, TextIO

_STATE_WIDTH = len("not_initialized")
_CLEAR_TO_EOL = "\x1b[K"   # erase what a longer previous line left behind


def _is_tty(stream: TextIO) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # closed stream
        return False


def format_bar(done: int, total: int, width: int = 24) -> str:
    """``[#####-------]``: the done fraction of ``total`` (clamped to [0, 1])."""
    filled = round(width * min(max(done / total, 0.0), 1.0)) if total > 0 else 0
    return "[" + "#" * filled + "-" * (width - filled) + "]"


class ProgressPrinter:
    """Callable as the Pipeline's ``progress(out, seconds)`` hook (``out`` a FrameOutput)."""

    def __init__(self, total: Optional[int], stream: Optional[TextIO] = None, quiet: bool = False,
                 every: int = 50, min_interval_s: float = 0.1, clock: Callable[[], float] = time.perf_counter):
        self.total = total or 0
        self.stream = sys.stderr if stream is None else stream
        self.quiet, self.every, self.min_interval_s, self.clock = quiet, every, min_interval_s, clock
        self.tty = _is_tty(self.stream)
        self.done = self.lost = self.keyframes = 0
        self._start: Optional[float] = None
        self._last_draw = -float("inf")
        self._line_open = False   # a TTY line is shown without its newline yet

    def __call__(self, out: Any, seconds: float) -> None:
        now = self.clock()
        if self._start is None:   # from the start of the first frame: setup time is not frame time
            self._start = now - max(seconds, 0.0)
        self.done += 1
        self.lost += out.T_wc is None
        self.keyframes += bool(out.is_keyframe)
        if self.quiet:
            return
        last = self.total > 0 and self.done >= self.total
        if self.tty and (last or now - self._last_draw >= self.min_interval_s):
            self._write("\r" + self.format_tty(out.state.value, now) + _CLEAR_TO_EOL + ("\n" if last else ""))
            self._line_open, self._last_draw = not last, now
        elif not self.tty and (self.done % self.every == 0 or last):
            self._write(self.format_plain(out.state.value, now) + "\n")

    def fps(self, now: float) -> float:
        return self.done / max(now - (self._start if self._start is not None else now), 1e-9)

    def format_tty(self, state: str, now: float) -> str:
        """``[####----]  120/480  25.3 fps  ok               lost 0  kf 12`` (no bar without a total)."""
        count = f"{self.done:>{len(str(self.total))}}/{self.total}" if self.total else f"frame {self.done}"
        bar = format_bar(self.done, self.total) + "  " if self.total else ""
        return (f"{bar}{count}  {self.fps(now):5.1f} fps  {state:<{_STATE_WIDTH}}  "
                f"lost {self.lost}  kf {self.keyframes}")

    def format_plain(self, state: str, now: float) -> str:
        """``  frame 50/480   25.3 fps  state ok  lost 0  keyframes 9`` (the non-TTY log line)."""
        total = f"/{self.total}" if self.total else ""
        return (f"  frame {self.done}{total}  {self.fps(now):5.1f} fps  state {state}  "
                f"lost {self.lost}  keyframes {self.keyframes}")

    def finish(self) -> None:
        """End a TTY line left open (a run stopped before its last frame), so later output starts
        on a line of its own."""
        if self._line_open:
            self._write("\n")
            self._line_open = False

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()
