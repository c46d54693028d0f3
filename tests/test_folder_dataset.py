"""ImageFolderDataset: colour/ + depth/ images with an intrinsics.yaml, written here from a synthetic room."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from slam.cli import main, resolve_run_config
from slam.datasets import DatasetError, DatasetWarning, ImageFolderDataset, SyntheticSequence, open_dataset

CAMERA = {"fx": 60.0, "fy": 61.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48, "depth_scale": 1000.0}


def write_folder(root: Path, seq: SyntheticSequence, colour_dir: str = "color", camera: dict | None = None,
                 colour_name=lambda i, t: f"{i:06d}.png", depth_name=lambda i, t: f"{i:06d}.png") -> Path:
    """``seq`` as colour PNGs, millimetre depth PNGs and an intrinsics.yaml (camera defaults to seq's)."""
    (root / colour_dir).mkdir(parents=True)
    (root / "depth").mkdir()
    for i, frame in enumerate(seq):
        cv2.imwrite(str(root / colour_dir / colour_name(i, frame.timestamp)), frame.rgb)
        raw = np.round(frame.depth * 1000).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / depth_name(i, frame.timestamp)), raw)
    fx, fy, cx, cy = seq.intrinsics
    camera = camera or {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": seq.width, "height": seq.height,
                        "depth_scale": 1000.0}
    (root / "intrinsics.yaml").write_text(yaml.safe_dump(camera))
    return root


@pytest.fixture(scope="module")
def seq() -> SyntheticSequence:
    return SyntheticSequence(n_frames=4, width=64, height=48, fx=60.0, fy=61.0, cx=31.5, cy=23.5)


def test_frames_round_trip_with_default_fps(tmp_path, seq):
    ds = ImageFolderDataset(write_folder(tmp_path / "rec", seq))
    assert len(ds) == 4 and ds.pairing == "same file name"
    frames = list(ds)
    for orig, back in zip(seq, frames):
        assert np.array_equal(back.rgb, orig.rgb)
        assert back.depth.dtype == np.float32
        assert np.abs(back.depth - orig.depth).max() <= 0.0005 + 1e-6
    np.testing.assert_allclose([f.timestamp for f in frames], np.arange(4) / 30.0)
    assert ds.intrinsics() == CAMERA and ds.groundtruth() is None and ds.name == "rec"


def test_fps_and_distortion_from_the_yaml_and_rgb_alias(tmp_path, seq):
    camera = {**CAMERA, "fps": 10, "distortion": [0.1, 0, 0, 0]}
    ds = ImageFolderDataset(write_folder(tmp_path / "rec", seq, colour_dir="rgb", camera=camera))
    np.testing.assert_allclose(ds.timestamps, np.arange(4) / 10.0)
    assert ds.intrinsics()["distortion"] == [0.1, 0.0, 0.0, 0.0]


def test_times_in_names_are_associated_like_tum(tmp_path, seq):
    root = write_folder(tmp_path / "rec", seq, colour_name=lambda i, t: f"{100 + t:.6f}.png",
                        depth_name=lambda i, t: f"{100.004 + t:.6f}.png")
    ds = ImageFolderDataset(root)
    assert len(ds) == 4 and ds.pairing.startswith("nearest time")
    np.testing.assert_allclose(ds.timestamps, 100 + np.arange(4) / 30.0, atol=1e-6)


def test_numbered_names_pair_by_number_in_natural_order(tmp_path):
    seq = SyntheticSequence(n_frames=12, width=32, height=24, fx=30, fy=30, cx=16, cy=12)
    root = write_folder(tmp_path / "rec", seq, colour_name=lambda i, t: f"color_{i}.png",
                        depth_name=lambda i, t: f"depth_{i}.png")
    ds = ImageFolderDataset(root)
    assert ds.pairing == "same number in the name"
    for orig, back in zip(seq, ds):  # color_10 comes after color_9, not after color_1
        assert np.array_equal(back.rgb, orig.rgb)


def test_mismatched_counts_warn_and_pair_by_name(tmp_path, seq):
    root = write_folder(tmp_path / "rec", seq)
    (root / "depth" / "000002.png").unlink()
    with pytest.warns(DatasetWarning, match=r"4 colour and 3 depth images.*000002\.png"):
        ds = ImageFolderDataset(root)
    assert len(ds) == 3
    assert [f.index for f in ds] == [0, 1, 2]
    np.testing.assert_allclose(ds.timestamps, np.array([0, 1, 3]) / 30.0)


@pytest.mark.parametrize("change, words", [
    ({"fx": None}, "missing key(s) fx"),
    ({"depth_scale": 0}, "'depth_scale' must be positive"),
    ({"fy": "abc"}, "'fy' must be a finite number"),
    ({"width": 64.5}, "'width' must be a whole number"),
    ({"width": 32}, "width x height 32x48 differs from 000000.png's 64x48"),
    ({"distortion": [0.1, 0.2]}, "'distortion' must be a list of 4 or 5 numbers"),
    ({"focal": 3}, "unknown key(s) focal"),
])
def test_bad_yaml_is_a_clear_error_naming_file_and_key(tmp_path, seq, change, words):
    camera = {k: v for k, v in {**CAMERA, **change}.items() if v is not None}
    root = write_folder(tmp_path / "rec", seq, camera=camera)
    with pytest.raises(DatasetError) as info:
        ImageFolderDataset(root)
    assert words in str(info.value) and "intrinsics.yaml" in str(info.value)


def test_missing_depth_folder_and_unpairable_names_are_clear_errors(tmp_path, seq):
    root = write_folder(tmp_path / "rec", seq, colour_name=lambda i, t: f"img{'abcd'[i]}.png",
                        depth_name=lambda i, t: f"d{'abcd'[i]}.png")
    with pytest.raises(DatasetError, match="cannot pair colour and depth images"):
        ImageFolderDataset(root)
    for p in (root / "depth").iterdir():
        p.unlink()
    (root / "depth").rmdir()
    with pytest.raises(DatasetError, match="depth/ folder"):
        ImageFolderDataset(root)


def test_open_dataset_and_run_config_use_intrinsics_yaml(tmp_path, seq):
    root = write_folder(tmp_path / "rec", seq)
    assert isinstance(open_dataset(root), ImageFolderDataset)
    config = resolve_run_config(root, [], {})
    assert (config.camera.fx, config.camera.fy, config.camera.cx, config.camera.width) == (60.0, 61.0, 31.5, 64)
    assert config.camera.depth_scale == 1000.0


def test_dynslam_run_on_an_image_folder_writes_a_trajectory(tmp_path, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    root = write_folder(tmp_path / "my_room", SyntheticSequence(n_frames=15))
    out = tmp_path / "out"
    assert main(["run", str(root), "-o", str(out), "-q", "-c", "static"]) == 0
    rows = [line.split() for line in (out / "trajectory.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    assert len(rows) == 15
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracked"] == 15 and summary["dataset_path"] == str(root.resolve())
    assert yaml.safe_load((out / "config.yaml").read_text())["camera"]["depth_scale"] == 1000.0
