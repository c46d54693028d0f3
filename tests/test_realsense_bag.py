"""RealSense Viewer (librealsense) .bag recordings: layout detection, intrinsics, depth units, and depth
registered from the depth camera to the colour camera (slam.datasets.realsense_bag, depth_registration).

The bags are written here with rosbags from a generated room: colour from the sequence's camera, depth
ray-cast from a second camera with other intrinsics, 15 mm to the side and turned 0.5 degrees, so the
registration has real work to do and the generator's own colour-frame depth is the exact answer.
"""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from slam.cli import main, resolve_run_config
from slam.datasets import DatasetError, RealSenseBagDataset, RosbagDataset, SyntheticSequence, open_dataset
from slam.datasets.depth_registration import DepthRegistration, StreamIntrinsics
from slam.datasets.realsense_bag import is_realsense_bag

from conftest import (RS_COLOUR, RS_DEPTH, RS_UNITS_TOPIC, START_S, render_depth_camera, rs_extrinsic,  # noqa: E402
                      write_bag, write_realsense_bag)


@pytest.fixture(scope="module")
def seq() -> SyntheticSequence:
    return SyntheticSequence(n_frames=3, width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5)


@pytest.fixture(scope="module")
def rs_bag(tmp_path_factory, seq):
    return write_realsense_bag(tmp_path_factory.mktemp("rs") / "d435.bag", seq)


def test_layout_is_detected_and_routed(tmp_path, rs_bag, seq):
    other = write_bag(tmp_path / "wrapper.bag", seq, 1)   # realsense-ros /camera/... layout: the ROS reader
    assert is_realsense_bag(rs_bag) and not is_realsense_bag(other)
    assert type(open_dataset(rs_bag)) is RealSenseBagDataset
    assert type(open_dataset(other)) is RosbagDataset


def test_intrinsics_extrinsic_and_units_come_from_the_bag(rs_bag, seq):
    ds = RealSenseBagDataset(rs_bag)
    assert ds.intrinsics() == {"name": "realsense", "fx": 150.0, "fy": 150.0, "cx": 79.5, "cy": 59.5,
                               "width": 160, "height": 120, "distortion": [0.0] * 5, "depth_scale": 1000.0}
    depth = ds.static.depth
    assert (depth.fx, depth.fy, depth.cx, depth.cy) == pytest.approx((150 * 6 / 7, 150 * 6 / 7, 81.5, 58.0))
    assert np.allclose(ds.static.T_colour_depth, rs_extrinsic(), atol=1e-9)
    assert ds.static.depth_units == pytest.approx(0.001)
    assert ds.registration is not None and len(ds) == 3
    config = resolve_run_config(rs_bag, [], {})
    assert (config.camera.name, config.camera.fx, config.camera.width) == ("realsense", 150.0, 160)


def test_registered_depth_agrees_with_the_colour_cameras_true_depth(rs_bag, seq):
    """Median |error| under 3 mm. Why that bound: a colour pixel takes the depth of the depth pixel whose
    footprint covers it, whose centre is up to half a depth pixel away along the surface; on a wall seen at
    angle a from z metres that is up to z*tan(a)/(2*fx_depth) (about 2 cm at 3 m and 60 degrees here,
    fx_depth 129), less than a millimetre on the median pixel, plus 0.5 mm of Z16 rounding. Edges (a
    near box over a far wall) give a few large errors: under 1 % of pixels are off by more than 5 cm."""
    naive_errors = []
    for truth, frame in zip(seq, RealSenseBagDataset(rs_bag)):
        assert np.array_equal(frame.rgb, truth.rgb), "rgb8 arrives as BGR"
        assert frame.depth.dtype == np.float32 and frame.depth.shape == truth.depth.shape
        both = (truth.depth > 0) & (frame.depth > 0)
        assert both.mean() > 0.98, "the wider depth camera covers nearly every colour pixel"
        error = np.abs(frame.depth - truth.depth)[both]
        assert np.median(error) < 0.003
        assert (error > 0.05).mean() < 0.01
        raw = render_depth_camera(seq, frame.index, (150 * 6 / 7, 150 * 6 / 7, 81.5, 58.0, 160, 120),
                                  rs_extrinsic(), {})
        naive_errors.append(np.median(np.abs(raw - truth.depth)[both]))
    assert min(naive_errors) > 0.01, "the unregistered depth image is centimetres off: registration matters"


def test_depth_units_are_honoured(tmp_path, seq):
    """A 0.1 mm unit (D400 high-accuracy setting): metres = raw x units, to 0.05 mm rounding."""
    aligned = write_realsense_bag(tmp_path / "fine.bag", seq, depth_camera=(150.0, 150.0, 79.5, 59.5, 160, 120),
                                  T_colour_depth=np.eye(4), depth_units=0.0001)
    ds = RealSenseBagDataset(aligned)
    assert ds.registration is None, "same intrinsics, identity extrinsic: the depth is used as it is"
    assert ds.intrinsics()["depth_scale"] == 10000.0
    for truth, frame in zip(seq, ds):
        assert np.abs(frame.depth - truth.depth).max() <= 0.00005 + 1e-6


def test_missing_units_topic_means_millimetres(tmp_path, seq):
    ds = RealSenseBagDataset(write_realsense_bag(tmp_path / "nounits.bag", seq, depth_units=None))
    assert ds.static.depth_units == 0.001


def test_frames_pair_colour_with_the_nearest_depth(rs_bag, seq):
    ds = RealSenseBagDataset(rs_bag, max_dt=0.02)
    assert np.allclose(ds.timestamps, START_S + seq.timestamps, atol=1e-6), "colour stamps are the master"
    with pytest.raises(DatasetError, match=r"no colour/depth pair within 1 ms"):
        RealSenseBagDataset(rs_bag, max_dt=0.001)   # depth comes 2 ms after colour


@pytest.mark.parametrize("what, kwargs, message", [
    ("depth stream", {"depth_stream": False}, r"no depth stream .*Depth_\*/image/data"),
    ("depth intrinsics", {"depth_info": False}, rf"no intrinsics for {RS_DEPTH} \(topic '{RS_DEPTH}/info/camera_info'"),
    ("extrinsics", {"extrinsics": False}, rf"no extrinsics between {RS_DEPTH} and {RS_COLOUR}"),
])
def test_incomplete_bag_is_a_clear_error(tmp_path, seq, what, kwargs, message):
    path = write_realsense_bag(tmp_path / "broken.bag", seq, **kwargs)
    with pytest.raises(DatasetError, match=message) as info:
        RealSenseBagDataset(path)
    assert str(path) in str(info.value), f"a bag without {what} must be named"


def test_colour_distortion_is_read_as_opencvs_model(tmp_path):
    seq = SyntheticSequence(n_frames=1, width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    coeffs = (0.11, -0.23, 0.001, -0.002, 0.04)
    ds = RealSenseBagDataset(write_realsense_bag(tmp_path / "d455.bag", seq, colour_coeffs=coeffs))
    assert ds.intrinsics()["distortion"] == list(coeffs) and ds.registration.colour.distortion == coeffs
    path = write_realsense_bag(tmp_path / "fisheye.bag", seq, colour_coeffs=coeffs, colour_model="Kannala Brandt4")
    with pytest.raises(DatasetError, match="distortion model 'Kannala Brandt4' .* is not supported"):
        RealSenseBagDataset(path)


def test_bad_depth_units_are_a_clear_error(tmp_path, seq):
    path = write_realsense_bag(tmp_path / "units.bag", seq, depth_units=0.0)
    with pytest.raises(DatasetError, match=rf"'{RS_UNITS_TOPIC}' says 0.0 m per depth unit"):
        RealSenseBagDataset(path)


def test_run_on_an_incomplete_bag_exits_2_naming_the_file(tmp_path, seq, capsys):
    path = write_realsense_bag(tmp_path / "noext.bag", seq, extrinsics=False)
    assert main(["run", str(path), "-q", "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{path}: no extrinsics between" in err and "Traceback" not in err


def test_registration_z_buffer_keeps_the_nearest_surface():
    """A near square in front of a far wall, seen from 5 cm to the side: the square's pixels keep its
    depth where both land (the nearest wins), and the wall strip the depth camera could not see beside
    the square is left without depth rather than given a wrong one."""
    cam = StreamIntrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)
    depth = np.full((60, 80), 3.0, np.float32)
    depth[20:40, 30:50] = 0.5
    T = np.eye(4)
    T[0, 3] = -0.05        # colour camera 5 cm to the right: near points move 10 px left, far ones 1.7 px
    out = DepthRegistration(cam, cam, T)(depth)
    assert np.all(out[22:38, 22:38] == pytest.approx(0.5)), "the square covers wall points landing there too"
    assert np.all(out[22:38, 41:47] == 0.0), "the disoccluded strip has no measurement"
    assert np.all(out[22:38, 49:77] == pytest.approx(3.0)) and np.all(out[5:15, 2:77] == pytest.approx(3.0))


def test_registration_projects_with_the_colour_distortion_like_opencv():
    import cv2

    colour = StreamIntrinsics(300.0, 310.0, 160.0, 118.0, 320, 240, (0.12, -0.25, 0.001, -0.002, 0.05))
    reg = DepthRegistration(StreamIntrinsics(280.0, 280.0, 160.0, 120.0, 320, 240), colour, rs_extrinsic())
    pts = np.random.default_rng(0).uniform([-1, -0.8, 1.0], [1, 0.8, 4.0], (200, 3)).astype(np.float32)
    u, v = reg._project(pts[:, 0], pts[:, 1], pts[:, 2])
    expected = cv2.projectPoints(pts.astype(np.float64), np.zeros(3), np.zeros(3), colour.K,
                                 np.asarray(colour.distortion))[0][:, 0]
    assert np.abs(np.c_[u, v] - expected).max() < 1e-3


def test_dynslam_run_on_a_realsense_bag_follows_the_true_path(tmp_path, monkeypatch):
    """End to end: the run on registered depth follows the generator's path to within a centimetre
    (measured: 2.6 mm ATE; the same 15 frames with the colour camera's exact Z16 depth give 2.5 mm)."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    seq = SyntheticSequence(n_frames=15)
    path = write_realsense_bag(tmp_path / "room.bag", seq)
    out = tmp_path / "out"
    assert main(["run", str(path), "-q", "-c", "static", "-o", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracked"] == 15 and summary["dropped_frames"] is None
    from slam.run.evaluation import evaluate
    from slam.run.trajectory import read_tum

    stamps, poses = read_tum(out / "trajectory.txt")
    gt_t, gt_poses = seq.groundtruth()
    report = evaluate(START_S + gt_t, gt_poses, stamps, poses, 0.005, "groundtruth", "trajectory.txt")
    print(f"ATE {report.ate.rmse * 1000:.2f} mm over {len(report.ate.errors)} frames")
    assert len(report.ate.errors) == 15 and report.ate.rmse < 0.01, f"ATE {report.ate.rmse * 1000:.1f} mm"
