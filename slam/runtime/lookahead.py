"""One frame of lookahead: the next frame's image-only work runs while this frame is tracked.

``System.process(..., upcoming=UpcomingFrame(...))`` starts, for the frame after the one it processes, the
work that needs only its images: the ORB features (on a thread here, with their own extractor) and the
detector (``DynamicFilter.begin_images``, on the filter's thread). The next ``process`` call takes them
over and starts the pose-dependent image work (cpr's registration) as without lookahead. Without it those
threads ran only while the frame's own features were extracted and stood idle while it was tracked; ORB
and ONNX Runtime release the GIL, so on two cores the tracking of one frame and the image work of the next
overlap.

Nothing that runs ahead depends on the tracking it overlaps: the same bits as without lookahead, whichever
thread finishes first (``tests/test_lookahead.py``). cpr's registration is not run ahead on purpose: its
initial guess is the constant-velocity prediction from the frame before, and the prediction two frames
past the last tracked frame (tried: registration ahead too) made fr1/rpy's first 120 frames 0.0172 ->
0.0292 m ATE (fast rotation: twice the prediction error). A live source in realtime mode has no frame
ahead to wait for; the pipeline gives no ``upcoming`` there.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Optional

import numpy as np

from frontend.dynamic import DynamicFilter
from frontend.orb_extractor import OrbExtractor
from slam.core.camera import PinholeCamera
from slam.core.config import OrbConfig
from slam.core.frame import FeatureFrame
from slam.core.timing import ModuleTimer
from slam.runtime.inputs import InputError, check_inputs, clean_depth, to_gray


@dataclass
class UpcomingFrame:
    """The frame the next ``System.process`` call will get: the same images, timestamp and index (the
    begun work is matched to that call by timestamp and index, and the call's own arrays are not read
    again: the images given here are the ones processed)."""

    rgb: np.ndarray
    depth: np.ndarray
    timestamp: float
    index: int


@dataclass
class BegunFrame:
    """A frame whose image work started one call early."""

    rgb: np.ndarray
    depth: np.ndarray          # cleaned (clean_depth)
    gray: np.ndarray
    timestamp: float
    index: int
    features: Future           # -> FeatureFrame
    source_depth: np.ndarray   # the depth as given (what ``check_inputs`` checked)

    def checked(self, rgb: np.ndarray, depth: np.ndarray) -> bool:
        """Whether ``rgb`` and ``depth`` are the very arrays this frame was begun with (and checked)."""
        return rgb is self.rgb and depth is self.source_depth


class FrameLookahead:
    def __init__(self, orb: OrbConfig, camera: PinholeCamera, timer: ModuleTimer):
        self.camera = camera
        self.timer = timer
        # Its own extractor: OpenCV's ORB object is not shared with the tracking thread's (static refill).
        self._extractor = OrbExtractor(orb, camera)
        self._thread: Optional[ThreadPoolExecutor] = None
        self._begun: Optional[BegunFrame] = None

    def begin(self, upcoming: UpcomingFrame, dynamic_filter: DynamicFilter) -> None:
        """Start ``upcoming``'s features and its detections. A frame that breaks the input contract is left
        alone: its own ``process`` call raises the error, as without lookahead."""
        self.drop()
        try:
            check_inputs(upcoming.rgb, upcoming.depth, upcoming.timestamp, self.camera.width, self.camera.height)
        except InputError:
            return
        rgb = upcoming.rgb
        depth = clean_depth(upcoming.depth)
        gray = to_gray(rgb)
        dynamic_filter.begin_images(rgb, gray, upcoming.timestamp)
        if self._thread is None:
            self._thread = ThreadPoolExecutor(1, thread_name_prefix="dynslam-features")
        features = self._thread.submit(self._extract, gray, depth, upcoming.index, upcoming.timestamp)
        self._begun = BegunFrame(rgb, depth, gray, upcoming.timestamp, upcoming.index, features, upcoming.depth)

    def take(self, timestamp: float, index: int) -> Optional[BegunFrame]:
        """The begun frame if it is this one (the same timestamp and index: the caller announced it with
        its images), else None (and a begun frame that is not this one is dropped)."""
        begun, self._begun = self._begun, None
        if begun is None:
            return None
        if begun.timestamp == timestamp and begun.index == index:
            return begun
        begun.features.exception()     # waits; its failure belongs to no frame that is processed
        return None

    def drop(self) -> None:
        """Forget a begun frame that will not be processed (the run stopped), once its work has ended."""
        begun, self._begun = self._begun, None
        if begun is not None:
            begun.features.exception()

    def close(self) -> None:
        self.drop()
        if self._thread is not None:
            self._thread.shutdown(wait=True)
            self._thread = None

    def _extract(self, gray: np.ndarray, depth: np.ndarray, index: int, timestamp: float) -> FeatureFrame:
        with self.timer.measure("extract.ahead"):      # a part of "extract": not in the frame's latency
            return self._extractor.extract(gray, depth, index, timestamp)
