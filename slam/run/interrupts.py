"""Ctrl-C (SIGINT) during a run: stop after the frame being processed, then write every result.

Python turns SIGINT into ``KeyboardInterrupt`` wherever the interpreter happens to be: halfway
through a keyframe insertion (the map, the graph and the per-frame records then disagree, so the
final trajectory need not cover the frames the online file lists) or halfway through the final
writes (each write is atomic, so the old file stays, but every result after it is never written).
``DeferredInterrupt`` replaces the handler for the length of a run by one that only records the
request; the pipeline checks it between frames. A Ctrl-C while the results are being written is
reported and ignored: they take seconds, and they are what the user wants to keep.

Signal handlers can only be set from the main thread; elsewhere (a worker thread) nothing is
installed and Python's ``KeyboardInterrupt`` behaviour stays as it was. A SIGINT the process was
told to ignore (``SIG_IGN``, e.g. a background job of a non-interactive shell) stays ignored.
"""
from __future__ import annotations

import logging
import signal
import threading
from types import FrameType, TracebackType
from typing import Any, Optional

log = logging.getLogger("dynslam")


class DeferredInterrupt:
    """Context manager: while active, SIGINT sets ``requested`` instead of raising.

    ``finishing()`` marks the start of the final writes, after which a SIGINT only logs that the
    results are still being written.
    """

    def __init__(self) -> None:
        self.requested = False
        self.installed = False
        self._finishing = False
        self._previous: Any = None

    def __enter__(self) -> "DeferredInterrupt":
        if threading.current_thread() is not threading.main_thread():
            return self
        previous = signal.getsignal(signal.SIGINT)
        if previous == signal.SIG_IGN:
            return self
        self._previous = previous
        signal.signal(signal.SIGINT, self._handle)
        self.installed = True
        return self

    def __exit__(self, exc_type: Optional[type[BaseException]], exc: Optional[BaseException],
                 tb: Optional[TracebackType]) -> None:
        if self.installed:
            signal.signal(signal.SIGINT, self._previous)
            self.installed = False

    def finishing(self) -> None:
        """The frames are done; from now on the results are being written."""
        self._finishing = True

    def _handle(self, signum: int, frame: Optional[FrameType]) -> None:
        if self._finishing:
            log.warning("still writing the results (Ctrl-C ignored until they are complete)")
        elif not self.requested:
            log.warning("interrupted: stopping after the current frame, then writing the results")
        self.requested = True
