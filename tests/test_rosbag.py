"""RosbagDataset on small ROS 1 and ROS 2 bags written here with rosbags' writers (no ROS needed)."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from slam.cli import main, resolve_run_config
from slam.datasets import DatasetError, RosbagDataset, SyntheticSequence, open_dataset
from slam.datasets.rosbag import is_rosbag

from conftest import DEPTH_DELAY_S, DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC, START_S, write_bag  # noqa: E402  (the shared bag factory)


@pytest.fixture(scope="module")
def small_seq() -> SyntheticSequence:
    return SyntheticSequence(n_frames=4, width=64, height=48, fx=60.0, fy=61.0, cx=31.5, cy=23.5)


def bag_path(tmp_path: Path, ros_version: int, name: str = "recording") -> Path:
    return tmp_path / (f"{name}.bag" if ros_version == 1 else name)


@pytest.mark.parametrize("ros_version", [1, 2])
@pytest.mark.parametrize("depth_encoding, tolerance", [("16UC1", 0.0005 + 1e-6), ("32FC1", 0.0)])
def test_frames_round_trip(tmp_path, small_seq, ros_version, depth_encoding, tolerance):
    path = write_bag(bag_path(tmp_path, ros_version), small_seq, ros_version, depth_encoding)
    assert is_rosbag(path)
    ds = RosbagDataset(path)
    assert (ds.topics.rgb, ds.topics.depth, ds.topics.camera_info) == (RGB_TOPIC, DEPTH_TOPIC, INFO_TOPIC)
    assert len(ds) == 4 and ds.unmatched_rgb == 1
    frames = list(ds)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for orig, back in zip(small_seq, frames):
        assert back.rgb.dtype == np.uint8 and back.rgb.shape == (48, 64, 3)
        assert np.array_equal(back.rgb, orig.rgb), "rgb8 arrives as BGR"
        assert back.depth.dtype == np.float32
        assert np.abs(back.depth - orig.depth).max() <= tolerance
        assert back.timestamp == pytest.approx(START_S + orig.timestamp, abs=1e-6)
    assert ds.groundtruth() is None
    assert ds.root == path and ds.name == "recording"


@pytest.mark.parametrize("ros_version", [1, 2])
def test_intrinsics_come_from_camera_info(tmp_path, small_seq, ros_version):
    path = write_bag(bag_path(tmp_path, ros_version), small_seq, ros_version, "32FC1")
    camera = RosbagDataset(path).intrinsics()
    assert camera == {"fx": 60.0, "fy": 61.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48,
                      "distortion": [0.01, -0.02, 0.0, 0.0, 0.0], "depth_scale": 1.0}


def test_16bit_depth_reports_millimetres_and_handles_padding_and_byte_order(tmp_path, small_seq):
    path = write_bag(tmp_path / "padded.bag", small_seq, 1, "16UC1", rgb_encoding="bgr8", pad=6, bigendian=True)
    ds = RosbagDataset(path)
    assert ds.intrinsics()["depth_scale"] == 1000.0
    for orig, back in zip(small_seq, ds):
        assert np.array_equal(back.rgb, orig.rgb)
        assert np.abs(back.depth - orig.depth).max() <= 0.0005 + 1e-6


def test_unsupported_depth_encoding_is_a_clear_error(tmp_path, small_seq):
    path = write_bag(tmp_path / "bad.bag", small_seq, 1, depth_encoding="64FC1")
    with pytest.raises(DatasetError, match=rf"'{DEPTH_TOPIC}' has unsupported encoding '64FC1'"):
        RosbagDataset(path)


def test_named_topic_with_unsupported_encoding_is_a_clear_error(tmp_path, small_seq):
    path = write_bag(tmp_path / "rec.bag", small_seq, 1)
    with pytest.raises(DatasetError, match=rf"depth topic '{RGB_TOPIC}' has unsupported encoding 'rgb8'"):
        RosbagDataset(path, depth_topic=RGB_TOPIC)
    with pytest.raises(DatasetError, match="no Image topic '/nope'"):
        RosbagDataset(path, rgb_topic="/nope")


def test_bag_without_camera_info_has_no_intrinsics(tmp_path, small_seq):
    path = write_bag(tmp_path / "rec.bag", small_seq, 1, camera_info=False)
    ds = RosbagDataset(path)
    assert ds.intrinsics() is None and len(ds) == 4  # the topic exists but carries no message
    assert resolve_run_config(path, [], {}).camera.fx == 525.0, "defaults, with a warning"


def test_run_on_a_file_that_is_no_bag_exits_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    (tmp_path / "notes.txt").write_text("hello")
    assert main(["run", str(tmp_path / "notes.txt"), "-o", str(tmp_path / "out")]) == 2
    assert "notes.txt is not a dataset" in capsys.readouterr().err


def test_not_a_bag_is_a_clear_error(tmp_path):
    (tmp_path / "broken.bag").write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match="broken.bag"):
        RosbagDataset(tmp_path / "broken.bag")


def test_open_dataset_dispatches_bags(tmp_path, small_seq):
    ros1 = write_bag(tmp_path / "a.bag", small_seq, 1)
    ros2 = write_bag(tmp_path / "b", small_seq, 2)
    assert isinstance(open_dataset(ros1), RosbagDataset)
    assert isinstance(open_dataset(str(ros2)), RosbagDataset)
    config = resolve_run_config(ros2, [], {})
    assert (config.camera.fx, config.camera.cy, config.camera.width) == (60.0, 23.5, 64)
    assert config.camera.depth_scale == 1000.0


def test_dynslam_run_on_a_bag_writes_a_trajectory(tmp_path, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    seq = SyntheticSequence(n_frames=15)
    path = write_bag(tmp_path / "synthetic_room.bag", seq, 1, "16UC1", distortion=(0.0,) * 5, extra_rgb=False)
    out = tmp_path / "out"
    assert main(["run", str(path), "-o", str(out), "-q", "-c", "static"]) == 0
    rows = [line.split() for line in (out / "trajectory.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    assert len(rows) == 15
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracked"] == 15
    assert summary["dataset_path"] == str(path.resolve())
