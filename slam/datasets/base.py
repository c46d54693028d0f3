"""The record every dataset yields, and the protocol a dataset follows."""
from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Generator, Iterator, Optional, Protocol, Sequence, TypeVar

import numpy as np

T = TypeVar("T")

READ_AHEAD_FRAMES = 2   # frames loaded ahead on a reader thread


@dataclass
class RGBDFrame:
    """One colour + depth pair as read from disk or generated.

    rgb is HxWx3 uint8 in BGR order (OpenCV's), depth is HxW float32 in metres with 0 = invalid,
    registered to the colour image. ``dynamic_mask`` (HxW bool, True where a moving object is the visible
    surface) is ground truth only synthetic sequences provide; None when unknown.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    rgb_path: Optional[Path] = None
    depth_path: Optional[Path] = None
    dynamic_mask: Optional[np.ndarray] = None


class RGBDDataset(Protocol):
    """What the pipeline needs from a sequence. A source with nothing to say in the bookkeeping members
    (``root`` ... ``dropped``) inherits ``DatasetDefaults`` for them."""

    name: str
    root: Optional[Path]
    """The folder or file the frames come from (summary.json's ``dataset_path``); None: generated or live."""
    reopenable: bool
    """Whether map export can open ``root`` again as a TUM folder and read any keyframe's images back;
    else the run keeps copies of its keyframe images (``keyframes/``)."""
    live: bool
    """Paced by a camera: the run is in realtime mode unless ``runtime.realtime`` says otherwise."""
    skipped: Sequence[tuple[object, str]]
    """(where, why) of each frame that could not be read, as the frames are read."""
    missing: Sequence[Path]
    """Files the sequence lists that are not there (left out of the frames)."""
    dropped: Optional[int]
    """Frames dropped because processing was slower than the source (live, replay); None: it never drops."""

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[RGBDFrame]: ...

    def groundtruth(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(timestamps (N,), poses (N,4,4) camera-to-world) or None when the sequence has none."""
        ...

    def close(self) -> None:
        """Release what the source holds open (a live camera stops); called on every way out of a run."""
        ...


class DatasetDefaults:
    """``RGBDDataset``'s bookkeeping members for a source that has nothing to report in them: no folder,
    nothing skipped or missing, never drops a frame. A source overrides what it knows."""

    root: Optional[Path] = None
    reopenable: bool = False
    live: bool = False
    skipped: Sequence[tuple[object, str]] = ()
    missing: Sequence[Path] = ()
    dropped: Optional[int] = None

    def close(self) -> None:
        """Nothing held open between runs (a reader thread ends with its frames' iterator)."""


class DatasetWrapper:
    """A dataset around another (a fault injected, a replay's pacing): its name, length, ground truth and
    bookkeeping are the wrapped dataset's unless the wrapper says otherwise; it writes ``__iter__``."""

    def __init__(self, dataset: RGBDDataset):
        self.dataset = dataset
        self.name = dataset.name

    def __len__(self) -> int:
        return len(self.dataset)

    root = property(lambda self: self.dataset.root)
    reopenable = property(lambda self: self.dataset.reopenable)
    live = property(lambda self: self.dataset.live)
    skipped = property(lambda self: self.dataset.skipped)
    missing = property(lambda self: self.dataset.missing)
    dropped = property(lambda self: self.dataset.dropped)

    def groundtruth(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        return self.dataset.groundtruth()

    def close(self) -> None:
        self.dataset.close()


def frames_of(dataset: RGBDDataset) -> Generator[RGBDFrame, None, None]:
    """The dataset's frames as a generator whose ``close()`` also closes the dataset's own iterator when
    that has a ``close`` (PEP 380's ``yield from``): stopping early stops a reader thread or a camera."""
    yield from dataset


def read_ahead(load: Callable[[int], T], count: int) -> Iterator[T]:
    """``load(0) .. load(count - 1)`` in order, each begun ``READ_AHEAD_FRAMES`` ahead on a reader thread
    ("dynslam-reader") while the caller works on the one before: decoding a TUM folder's PNGs and rendering
    a generated frame release the GIL for most of their time. At most that many results wait in memory;
    closing the iterator early waits for those only. ``load``'s exceptions are raised here, in order."""
    with ThreadPoolExecutor(1, thread_name_prefix="dynslam-reader") as reader:
        ahead = deque(reader.submit(load, i) for i in range(min(READ_AHEAD_FRAMES, count)))
        for i in range(count):
            result = ahead.popleft().result()
            if i + READ_AHEAD_FRAMES < count:
                ahead.append(reader.submit(load, i + READ_AHEAD_FRAMES))
            yield result
