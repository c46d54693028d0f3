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

RGB_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
DEPTH_DELAY_S = 0.005  # depth stamped 5 ms after colour: association must pair them anyway
START_S = 1_700_000_000.0


def _image(types, header, pixels: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False):
    """A sensor_msgs/Image of ``pixels`` (HxW or HxWxC) with ``pad`` spare bytes at the end of each row."""
    height, width = pixels.shape[:2]
    if bigendian:
        pixels = pixels.astype(pixels.dtype.newbyteorder(">"))
    rows = pixels.reshape(height, -1).view(np.uint8)
    rows = np.concatenate([rows, np.zeros((height, pad), np.uint8)], axis=1)
    return types["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding=encoding,
                                          is_bigendian=int(bigendian), step=rows.shape[1], data=rows.ravel())


def _camera_info(types, header, seq: SyntheticSequence, ros1: bool, distortion):
    fx, fy, cx, cy = seq.intrinsics
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    matrices = {"D": np.asarray(distortion, np.float64),
                "K": np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64),
                "R": np.eye(3).ravel(), "P": np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], np.float64)}
    fields = {(k if ros1 else k.lower()): v for k, v in matrices.items()}
    return types["sensor_msgs/msg/CameraInfo"](header=header, height=seq.height, width=seq.width,
                                               distortion_model="plumb_bob", binning_x=0, binning_y=0,
                                               roi=roi, **fields)


def write_bag(path: Path, seq: SyntheticSequence, ros_version: int = 1, depth_encoding: str = "16UC1",
              rgb_encoding: str = "rgb8", pad: int = 0, distortion=(0.01, -0.02, 0.0, 0.0, 0.0),
              extra_rgb: bool = True, depth_topic: str = DEPTH_TOPIC, bigendian: bool = False,
              camera_info: bool = True) -> Path:
    """``seq`` as a bag: colour, depth (5 ms later) and camera info, plus an unmatched colour message."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = ros_version == 1
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    if ros1:
        from rosbags.rosbag1 import Writer
        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer
        writer, serialize = Writer(path, version=9), store.serialize_cdr

    def header(t: float):
        stamp = types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        extra = {"seq": 0} if ros1 else {}
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera", **extra)

    with writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype in
                 ((RGB_TOPIC, "sensor_msgs/msg/Image"), (depth_topic, "sensor_msgs/msg/Image"),
                  (INFO_TOPIC, "sensor_msgs/msg/CameraInfo"))}

        def put(topic, msg, t):
            writer.write(conns[topic], int(round(t * 1e9)), serialize(msg, msg.__msgtype__))

        if camera_info:
            put(INFO_TOPIC, _camera_info(types, header(START_S), seq, ros1, distortion), START_S)
        for frame in seq:
            t = START_S + frame.timestamp
            colour = frame.rgb[..., ::-1] if rgb_encoding == "rgb8" else frame.rgb
            put(RGB_TOPIC, _image(types, header(t), np.ascontiguousarray(colour), rgb_encoding, pad), t)
            depth = (np.round(frame.depth * 1000).astype(np.uint16) if depth_encoding in ("16UC1", "mono16")
                     else frame.depth.astype(np.float32) if depth_encoding == "32FC1"
                     else frame.depth.astype(np.float64))
            td = t + DEPTH_DELAY_S
            put(depth_topic, _image(types, header(td), depth, depth_encoding, pad, bigendian), td)
        if extra_rgb:  # a colour frame whose depth never came: left out by the association
            t = START_S + len(seq) / seq.fps + 1.0
            put(RGB_TOPIC, _image(types, header(t), np.ascontiguousarray(frame.rgb), rgb_encoding), t)
    return path


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
    assert main(["run", str(path), "-o", str(out), "-q"]) == 0
    rows = [line.split() for line in (out / "trajectory.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    assert len(rows) == 15
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracked"] == 15
    assert summary["dataset_path"] == str(path.resolve())
