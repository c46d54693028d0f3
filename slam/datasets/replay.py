"""A recording replayed at its recorded rate, as a live camera would deliver it (``runtime.realtime``).

    dataset = RealtimeReplay(TumDataset(path))   # frame i is offered at t_i - t_0 after the first

Frames are offered on the wall clock at their timestamps relative to the first. When the system asks for
the next frame, a frame whose successor's time has already come is passed over (counted in ``dropped``,
reported as ``dropped_frames`` like a live camera's): the newest due frame wins, and a system slower
than the recording falls behind by at most one frame instead of without bound. A system that is faster
waits for each frame's time. The last frame is never dropped (nothing comes after it).

Frames are read one ahead of the one offered (to know the successor's time), so a dropped frame was
still read and decoded; the datasets' own reader threads do that while the system works. ``clock`` and
``sleep`` can be replaced (tests pass a simulated clock).
"""
from __future__ import annotations

import time
from typing import Callable, Iterator

from slam.datasets.base import DatasetWrapper, RGBDDataset, RGBDFrame, frames_of


class RealtimeReplay(DatasetWrapper):
    dropped: int = 0     # this replay's own count (not the recording's): set by each pass over the frames

    def __init__(self, dataset: RGBDDataset, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        super().__init__(dataset)
        self.clock, self.sleep = clock, sleep
        self.dropped = 0

    def __iter__(self) -> Iterator[RGBDFrame]:
        self.dropped = 0
        frames = frames_of(self.dataset)
        try:
            current = next(frames, None)
            if current is None:
                return
            start, t0 = self.clock(), current.timestamp
            upcoming = next(frames, None)
            while current is not None:
                # The system is ready: skip every frame whose successor is already due.
                while upcoming is not None and upcoming.timestamp - t0 <= self.clock() - start:
                    self.dropped += 1
                    current, upcoming = upcoming, next(frames, None)
                wait = (current.timestamp - t0) - (self.clock() - start)
                if wait > 0:
                    self.sleep(wait)
                yield current
                current, upcoming = upcoming, (next(frames, None) if upcoming is not None else None)
        finally:   # stopping early (Ctrl-C, --max-frames) stops the wrapped source's reading too
            frames.close()
