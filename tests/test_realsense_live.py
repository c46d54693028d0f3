"""The live RealSense source (slam.datasets.realsense_live) and ``dynslam run realsense[:SERIAL]``, wired to a
fake ``pyrealsense2`` module put into ``sys.modules``: no camera and no pyrealsense2 needed.

The fake camera serves colour/depth framesets of a generated room; it "runs faster than SLAM" by
delivering ``per_wait`` framesets each time the source waits, so newest-frame-wins has frames to drop.
"""
from __future__ import annotations

import json
import os
import signal
import sys
import types
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from slam.cli import main
from slam.core.errors import RuntimeFailure
from slam.datasets import SyntheticSequence
from slam.datasets.realsense_live import RealSenseCamera, RealSenseUnavailable, is_live_source, parse_serial

DEPTH_SCALE = 0.00025   # a non-default scale (D400 with 0.25 mm units): must come from the device


class FakeFrame:
    def __init__(self, data: np.ndarray, number: int, timestamp_ms: float):
        self.data, self.number, self.timestamp_ms = data, number, timestamp_ms

    def get_data(self):
        return self.data

    def get_frame_number(self) -> int:
        return self.number

    def get_timestamp(self) -> float:
        return self.timestamp_ms


class FakeFrameset:
    def __init__(self, colour=None, depth=None):
        self.colour, self.depth = colour, depth

    def __bool__(self) -> bool:   # pyrealsense2's poll_for_frames gives an empty (falsy) frameset
        return self.colour is not None

    def get_color_frame(self):
        return self.colour

    def get_depth_frame(self):
        return self.depth


class FakeCamera:
    """State shared by the fake module's objects, and the record the tests check."""

    def __init__(self, seq: SyntheticSequence, per_wait: int = 1, interrupt_at_wait: int = -1,
                 unplug_at_wait: int = -1):
        self.seq, self.per_wait = seq, per_wait
        self.interrupt_at_wait, self.unplug_at_wait = interrupt_at_wait, unplug_at_wait
        self.queue: list[FakeFrameset] = []
        self.produced = self.waits = self.stopped = self.aligned = 0
        self.streams: list[tuple] = []
        self.serial = None

    def produce(self) -> None:
        """The camera delivers its next frameset (frame number = index + 1, timestamps in ms)."""
        i = self.produced % self.seq.n_frames
        frame = self.seq.frame(i, cache=False)
        raw = np.round(frame.depth / DEPTH_SCALE).astype(np.uint16)
        t_ms = 1000.0 * (1_700_000_000.0 + self.produced / self.seq.fps)
        self.produced += 1
        self.queue.append(FakeFrameset(FakeFrame(frame.rgb.copy(), self.produced, t_ms),
                                       FakeFrame(raw, self.produced, t_ms + 1.0)))

    def module(self) -> types.ModuleType:
        cam = self
        rs = types.ModuleType("pyrealsense2")
        rs.stream = SimpleNamespace(color="stream.color", depth="stream.depth")
        rs.format = SimpleNamespace(bgr8="format.bgr8", z16="format.z16")
        rs.camera_info = SimpleNamespace(serial_number="camera_info.serial_number")
        fx, fy, cx, cy = cam.seq.intrinsics

        class Config:
            def enable_device(self, serial):
                cam.serial = serial

            def enable_stream(self, stream, width, height, fmt, fps):
                cam.streams.append((stream, width, height, fmt, fps))

        intrinsics = SimpleNamespace(fx=fx, fy=fy, ppx=cx, ppy=cy, width=cam.seq.width, height=cam.seq.height,
                                     coeffs=[0.0] * 5, model="distortion.inverse_brown_conrady")
        profile = SimpleNamespace(
            get_device=lambda: SimpleNamespace(
                get_info=lambda what: "f1230456" if what == rs.camera_info.serial_number else "?",
                first_depth_sensor=lambda: SimpleNamespace(get_depth_scale=lambda: DEPTH_SCALE)),
            get_stream=lambda stream: SimpleNamespace(
                as_video_stream_profile=lambda: SimpleNamespace(get_intrinsics=lambda: intrinsics)))

        class Pipeline:
            def start(self, config):
                return profile

            def wait_for_frames(self, timeout_ms=5000):
                cam.waits += 1
                if cam.waits == cam.unplug_at_wait:
                    raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
                if cam.waits == cam.interrupt_at_wait:
                    os.kill(os.getpid(), signal.SIGINT)   # the user presses Ctrl-C while the camera runs
                for _ in range(cam.per_wait):
                    cam.produce()
                return cam.queue.pop(0)

            def poll_for_frames(self):
                return cam.queue.pop(0) if cam.queue else FakeFrameset()

            def stop(self):
                cam.stopped += 1

        class Align:
            def __init__(self, to):
                assert to == rs.stream.color, "depth must be aligned to the colour stream"

            def process(self, frames):
                cam.aligned += 1
                return frames

        rs.pipeline, rs.config, rs.align = Pipeline, Config, Align
        return rs


@pytest.fixture
def small_seq() -> SyntheticSequence:
    return SyntheticSequence(n_frames=12, width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)


def install(monkeypatch, camera: FakeCamera) -> FakeCamera:
    monkeypatch.setitem(sys.modules, "pyrealsense2", camera.module())
    return camera


def test_source_names():
    assert is_live_source("realsense") and is_live_source("realsense:f1230456")
    assert not is_live_source("realsense.bag") and not is_live_source("./realsense")
    assert parse_serial("realsense") is None and parse_serial("realsense:f1230456") == "f1230456"


def test_frames_come_in_order_with_the_newest_winning(monkeypatch, small_seq):
    cam = install(monkeypatch, FakeCamera(small_seq))
    source = RealSenseCamera(width=64, height=48, fps=30)
    assert source.intrinsics() == {"name": "realsense", "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5,
                                   "width": 64, "height": 48, "fps": 30.0, "distortion": [0.0] * 5,
                                   "depth_scale": 4000.0}
    assert cam.streams == [("stream.color", 64, 48, "format.bgr8", 30), ("stream.depth", 64, 48, "format.z16", 30)]
    frames = iter(source)
    first = next(frames)                       # nothing waiting: frame 1 itself
    cam.produce(), cam.produce()               # two more arrive while frame 1 is processed
    second = next(frames)                      # frames 2 and 3 are waiting, plus 4 on the wait: 4 wins
    third = next(frames)
    assert [f.index for f in (first, second, third)] == [0, 1, 2]
    stamps = [f.timestamp for f in (first, second, third)]
    assert stamps == pytest.approx([1_700_000_000.0 + k / 30 for k in (0, 3, 4)], abs=1e-6)
    assert source.dropped == 2 and cam.aligned == 3, "only the frames handed out are aligned"
    truth = small_seq.frame(3, cache=False)
    assert np.array_equal(second.rgb, truth.rgb) and second.rgb.dtype == np.uint8
    assert second.depth.dtype == np.float32
    assert np.abs(second.depth - truth.depth).max() <= DEPTH_SCALE / 2 + 1e-6, "raw units x the device's scale"
    frames.close()                             # the caller leaves the loop: the device stops, once
    assert cam.stopped == 1
    source.close()
    assert cam.stopped == 1


def test_unplugged_camera_is_a_runtime_failure(monkeypatch, small_seq):
    cam = install(monkeypatch, FakeCamera(small_seq, unplug_at_wait=2))
    source = RealSenseCamera(width=64, height=48)
    with pytest.raises(RuntimeFailure, match=r"realsense_f1230456: no frame within 5 s .*unplugged"):
        list(source)
    assert cam.stopped == 1


def test_without_pyrealsense2_the_run_exits_2_with_the_install_command(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)   # import fails as when it is not installed
    with pytest.raises(RealSenseUnavailable):
        RealSenseCamera()
    assert main(["run", "realsense", "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert 'pip install "dynslam[realsense]"' in err and "Traceback" not in err


def _room_camera() -> SyntheticSequence:
    return SyntheticSequence(n_frames=40, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)


def test_dynslam_run_realsense_drops_frames_and_stops_the_camera(monkeypatch, tmp_path):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    cam = install(monkeypatch, FakeCamera(_room_camera(), per_wait=2))   # twice as fast as SLAM
    out = tmp_path / "out"
    code = main(["run", "realsense:f1230456", "-q", "-o", str(out), "--max-frames", "8",
                 "--set", "camera.width=320", "--set", "camera.height=240", "--set", "camera.fps=15"])
    assert code == 0
    assert cam.serial == "f1230456" and cam.streams[0] == ("stream.color", 320, 240, "format.bgr8", 15)
    assert cam.stopped == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 8 and summary["tracked"] == 8 and summary["dataset"] == "realsense_f1230456"
    assert summary["dropped_frames"] == 8, "every other frame: the camera is twice as fast"
    config = (out / "config.yaml").read_text()
    assert "fx: 262.5" in config and "depth_scale: 4000.0" in config
    assert summary["realtime"] is True and "realtime: true" in config, "a live camera runs in realtime mode"
    stamps = [float(line.split()[0]) for line in (out / "trajectory.txt").read_text().splitlines()
              if line and not line.startswith("#")]
    assert stamps == pytest.approx([1_700_000_000.0 + k / 30 for k in range(1, 16, 2)], abs=1e-6)


def test_ctrl_c_stops_the_live_run_and_writes_the_results(monkeypatch, tmp_path):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    cam = install(monkeypatch, FakeCamera(_room_camera(), interrupt_at_wait=5))
    out = tmp_path / "out"
    assert main(["run", "realsense", "-q", "-o", str(out),
                 "--set", "camera.width=320", "--set", "camera.height=240"]) == 130
    assert cam.stopped == 1 and cam.waits == 5, "no frame is awaited after the Ctrl-C"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] and summary["frames"] == 5 and summary["dropped_frames"] == 0
    assert len([ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]) == 5


def test_camera_unplugged_mid_run_exits_1_keeping_the_poses(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    cam = install(monkeypatch, FakeCamera(_room_camera(), unplug_at_wait=4))
    out = tmp_path / "out"
    assert main(["run", "realsense", "-q", "-o", str(out),
                 "--set", "camera.width=320", "--set", "camera.height=240"]) == 1
    assert cam.stopped == 1
    assert "no frame within 5 s" in capsys.readouterr().err
    assert len([ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]) == 3
