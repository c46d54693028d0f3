"""A live Intel RealSense camera as a frame source (``dynslam run realsense`` / ``realsense:SERIAL``).

pyrealsense2 is an optional extra (``pip install "dynslam[realsense]"``), imported only when a camera is
opened. Colour (BGR8) and depth (Z16) streams start together; ``rs.align(rs.stream.color)`` registers each
depth frame to the colour camera inside librealsense, so frames come out like every other source's: BGR
colour and float32 metres on the colour grid. Intrinsics are the colour stream's and the depth scale the
depth sensor's, both read from the device when it starts.

Newest frame wins: a live camera does not wait for SLAM. Before each frame is handed out, every frameset
that arrived meanwhile is drained and only the newest is aligned and returned. ``dropped`` counts the
framesets passed over here plus the jumps of the colour frame counter (frames librealsense dropped
before they reached us); the run's summary reports it.

Stopping: the source is a context manager and ``close()`` stops the device; leaving an iteration early
(Ctrl-C: the run stops after the current frame, see ``slam.run.interrupts``, or ``--max-frames``) stops it
as well. No frame within ``timeout_s`` (a camera unplugged) is a ``RuntimeFailure``.
"""
from __future__ import annotations

import logging
from types import ModuleType
from typing import Iterator, Optional

import numpy as np

from slam.core.errors import DynslamError, RuntimeFailure

from .base import DatasetDefaults, RGBDFrame

log = logging.getLogger("dynslam")

INSTALL_HINT = 'pip install "dynslam[realsense]"'
SOURCE_PREFIX = "realsense"


class RealSenseUnavailable(DynslamError):
    """pyrealsense2 is not installed, or no (matching) camera could be started: exit status 2."""


def is_live_source(spec: str) -> bool:
    """Whether a ``dynslam run`` argument names a live camera: "realsense" or "realsense:SERIAL"."""
    return spec == SOURCE_PREFIX or spec.startswith(SOURCE_PREFIX + ":")


def parse_serial(spec: str) -> Optional[str]:
    """The serial number in "realsense:SERIAL" (None for "realsense": the first camera found)."""
    serial = spec[len(SOURCE_PREFIX) + 1:] if spec.startswith(SOURCE_PREFIX + ":") else ""
    return serial.strip() or None


def import_pyrealsense2() -> ModuleType:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise RealSenseUnavailable(f"a live RealSense camera needs pyrealsense2, which is not installed ({exc}); "
                                   f"install it with: {INSTALL_HINT}") from None
    return rs


def opencv_distortion(model, coeffs, where: str) -> list[float]:
    """librealsense (model, coeffs) as OpenCV's k1 k2 p1 p2 k3: zero coefficients need no model; the
    Brown-Conrady family is taken as OpenCV's model, as the realsense-ros wrapper publishes it."""
    values = [float(c) for c in coeffs][:5]
    if any(values) and "brown" not in str(model).lower():
        raise RealSenseUnavailable(f"{where}: distortion model {model} with coefficients {values} is not supported")
    return (values + [0.0] * 5)[:5]


class RealSenseCamera(DatasetDefaults):
    """Frames of a live RealSense camera; follows ``RGBDDataset`` except that it has no length.

    ``serial`` picks a camera (None: the first); ``width`` x ``height`` at ``fps`` is requested for both
    streams. The device starts here, so ``intrinsics()`` is known before the first frame.
    """

    live = True   # paced by the camera: runs in realtime mode unless runtime.realtime says false

    def __init__(self, serial: Optional[str] = None, width: int = 640, height: int = 480, fps: int = 30,
                 timeout_s: float = 5.0) -> None:
        rs = import_pyrealsense2()
        self._rs = rs
        self.dropped = 0            # (no root, the default: the run keeps copies of its keyframe images)
        self._last_number: Optional[int] = None
        self.timeout_ms = int(round(timeout_s * 1000))
        self._pipeline = rs.pipeline()
        config = rs.config()
        if serial:
            config.enable_device(serial)
        config.enable_stream(rs.stream.color, int(width), int(height), rs.format.bgr8, int(fps))
        config.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
        which = f"RealSense {serial}" if serial else "a RealSense camera"
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as exc:
            raise RealSenseUnavailable(f"could not start {which} with colour and depth at {width}x{height} "
                                       f"{fps} fps ({exc}); is it connected, and free?") from None
        self._running = True
        try:
            self.serial = serial or str(profile.get_device().get_info(rs.camera_info.serial_number))
            self.name = f"realsense_{self.serial}"
            self.depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            self._camera = {"name": "realsense", "fx": float(intr.fx), "fy": float(intr.fy),
                            "cx": float(intr.ppx), "cy": float(intr.ppy), "width": int(intr.width),
                            "height": int(intr.height), "fps": float(fps),
                            "distortion": opencv_distortion(intr.model, intr.coeffs, f"{which} colour stream"),
                            "depth_scale": float(f"{1.0 / self.depth_scale:.7g}")}
        except BaseException:
            self.close()
            raise
        self._align = rs.align(rs.stream.color)
        log.info("%s: colour %dx%d at %d fps, depth scale %g m", self.name, intr.width, intr.height, fps,
                 self.depth_scale)

    def intrinsics(self) -> dict:
        """Camera keys (fx fy cx cy width height distortion depth_scale fps) of the colour stream."""
        return dict(self._camera)

    def groundtruth(self) -> None:
        return None

    def __enter__(self) -> "RealSenseCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the device (once; later calls do nothing)."""
        if self._running:
            self._running = False
            self._pipeline.stop()
            if self.dropped:
                log.info("%s: %d frames dropped (processing was slower than the camera)", self.name, self.dropped)

    def _newest_frameset(self):
        """Wait for a frameset, then drain whatever else has arrived: the newest one wins, and every
        frameset passed over (or missing from the colour frame counter) counts as dropped."""
        try:
            frames = self._pipeline.wait_for_frames(self.timeout_ms)
        except RuntimeError as exc:
            raise RuntimeFailure(f"{self.name}: no frame within {self.timeout_ms / 1000:g} s ({exc}); "
                                 "was the camera unplugged?") from None
        self._count_gap(frames)
        while True:
            newer = self._pipeline.poll_for_frames()
            if not newer:
                return frames
            self.dropped += 1
            self._count_gap(newer)
            frames = newer

    def _count_gap(self, frames) -> None:
        """Frames librealsense itself dropped before we saw them: jumps of the colour frame counter."""
        colour = frames.get_color_frame()
        if not colour:
            return
        number = int(colour.get_frame_number())
        if self._last_number is not None and number > self._last_number + 1:
            self.dropped += number - self._last_number - 1
        self._last_number = number

    def __iter__(self) -> Iterator[RGBDFrame]:
        """Frames until the device is closed; stops the device when the caller leaves the loop."""
        index = 0
        try:
            while self._running:
                aligned = self._align.process(self._newest_frameset())
                colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
                if not colour or not depth:   # a frameset missing one stream (at start-up): not a frame
                    continue
                rgb = np.array(np.asanyarray(colour.get_data()), dtype=np.uint8)    # copies: librealsense
                raw = np.asanyarray(depth.get_data())                               # recycles its buffers
                metres = raw.astype(np.float32) * np.float32(self.depth_scale)
                yield RGBDFrame(index=index, timestamp=float(colour.get_timestamp()) / 1000.0, rgb=rgb, depth=metres)
                index += 1
        finally:
            self.close()

    def __repr__(self) -> str:
        return f"RealSenseCamera({self.name!r}, dropped={self.dropped})"
