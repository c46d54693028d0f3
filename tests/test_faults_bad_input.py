"""The fault table (issue 9), rows 3-7 and 12: input that is damaged or wrong. Corrupt images, a
stretch without depth, images of the wrong size, timestamps out of order, invalid float depth in a
bag, and a detector cache read with another model file.

Each test is one row: the fault is injected, the behaviour checked is a clear message naming what is
wrong and where, and nothing already computed lost. Generated sequences stand in for real data
wherever real data is not the point (fast, exact ground truth).
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from _fault_helpers import frame_lines
from conftest import FAULT_TUM_FRAMES as TUM_FRAMES
from conftest import model_file, read_summary, synthetic_config, synthetic_sequence, write_bag
from slam.cli import main, resolve_run_config
from slam.datasets import DatasetDefaults, DatasetWarning, TumDataset
from slam.run.evaluation import ate
from slam.run.pipeline import Pipeline
from slam.runtime.system import System

pytestmark = pytest.mark.usefixtures("restore_warning_format")


def copy_folder(src: Path, dst: Path) -> Path:
    return Path(shutil.copytree(src, dst))


def run_pipeline(root: Path, out: Path, **overrides):
    """Pipeline on a TUM folder as ``dynslam run`` sets it up, recording every warning."""
    config = resolve_run_config(root, [], {"output.report": False, **overrides})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset = TumDataset(root, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
        summary = Pipeline(dataset, config, out).run()
    return dataset, summary, [str(w.message) for w in caught if issubclass(w.category, DatasetWarning)]


# --- 3. corrupt files ----------------------------------------------------------------------------------

def test_truncated_png_and_zero_byte_depth_are_skipped_by_name(tum_folder, tmp_path):
    root = copy_folder(tum_folder, tmp_path / "synthetic_room")
    original = TumDataset(root)
    truncated, empty = original[5].rgb_path, original[11].depth_path
    truncated.write_bytes(truncated.read_bytes()[:2000])
    empty.write_bytes(b"")
    _, summary, messages = run_pipeline(root, tmp_path / "out")
    assert any(str(truncated) in m and "colour image unreadable" in m for m in messages), messages
    assert any(str(empty) in m and "depth image" in m and "unreadable" in m for m in messages), messages
    assert [s.split(": ")[0] for s in summary.skipped_files] == [str(truncated), str(empty)]
    assert summary.frames == summary.tracked == TUM_FRAMES - 2
    skipped_t = original.timestamps[[5, 11]]
    poses, lost = frame_lines(tmp_path / "out" / "trajectory.txt")
    assert len(poses) == TUM_FRAMES - 2 and not lost
    assert not np.isin(np.round(poses, 6), np.round(skipped_t, 6)).any()
    assert read_summary(tmp_path / "out")["skipped_files"] == summary.skipped_files


# --- 4. depth dropout ----------------------------------------------------------------------------------

class DepthDropout(DatasetDefaults):
    """A dataset whose depth is all zero for ``count`` frames from ``start`` (the colour is intact)."""

    def __init__(self, dataset, start: int, count: int):
        self.dataset, self.start, self.count, self.name = dataset, start, count, dataset.name

    def __len__(self) -> int:
        return len(self.dataset)

    def __iter__(self):
        for frame in self.dataset:
            if self.start <= frame.index < self.start + self.count:
                frame = replace(frame, depth=np.zeros_like(frame.depth))
            yield frame

    def groundtruth(self):
        return self.dataset.groundtruth()


@pytest.mark.slow
def test_thirty_frames_without_depth_are_reported_and_tracking_goes_on_in_the_same_map(tmp_path, caplog):
    """No crash, a warning where the stretch starts, honest poses (tracked against the map without
    depth, never far off) or LOST, and depth-based tracking after it in the same map."""
    seq = synthetic_sequence(75)
    start, count = 20, 30
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pipeline = Pipeline(DepthDropout(seq, start, count), synthetic_config(seq, **{"output.report": False}),
                            tmp_path / "out")
        summary = pipeline.run()
    messages = [str(w.message) for w in caught if issubclass(w.category, DatasetWarning)]
    assert len(messages) == 1 and f"frame {start} " in messages[0] and "no valid depth" in messages[0], messages
    assert f"depth is back at frame {start + count} after {count} frame(s) without any" in caplog.text
    assert summary.no_depth_frames == list(range(start, start + count))
    assert read_summary(tmp_path / "out")["no_depth_frames"] == summary.no_depth_frames
    stamps, poses, tracked = pipeline.system.trajectory()
    assert tracked[:start].all() and tracked[start + count:].all(), np.flatnonzero(~tracked)
    gt_t, gt = seq.groundtruth()
    report = ate(gt_t, gt, stamps[tracked], poses[tracked])
    dropout_t = np.round(stamps[start:start + count], 6)
    worst_dropout = report.errors[np.isin(np.round(report.timestamps, 6), dropout_t)].max(initial=0.0)
    assert worst_dropout < 0.03, f"a pose without depth is {worst_dropout:.3f} m off"
    assert report.rmse < 0.015, report.rmse   # one map: the poses after the dropout agree with those before


# --- 5. wrong image sizes ------------------------------------------------------------------------------

def _resize(path: Path, size=(320, 240)) -> None:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), cv2.resize(image, size, interpolation=cv2.INTER_NEAREST))


def test_images_of_the_wrong_size_are_skipped_naming_file_and_sizes(tum_folder, tmp_path):
    root = copy_folder(tum_folder, tmp_path / "synthetic_room")
    original = TumDataset(root)
    both, colour_only, depth_only = original[4], original[9], original[15]
    _resize(both.rgb_path), _resize(both.depth_path)   # consistent, but not the camera's size
    _resize(colour_only.rgb_path)
    _resize(depth_only.depth_path)
    _, summary, messages = run_pipeline(root, tmp_path / "out")
    text = "\n".join(messages)
    assert re.search(rf"{re.escape(str(both.rgb_path))}\): colour image is 320x240 but the camera is 640x480", text)
    assert re.search(rf"{re.escape(str(colour_only.depth_path))}\): depth image is 640x480 but its colour image "
                     rf"{colour_only.rgb_path.name} is 320x240", text), text
    assert re.search(rf"{re.escape(str(depth_only.depth_path))}\): depth image is 320x240 but its colour image "
                     rf"{depth_only.rgb_path.name} is 640x480", text), text
    assert len(summary.skipped_files) == 3
    assert summary.frames == summary.tracked == TUM_FRAMES - 3   # the rest goes on, nothing else is lost


def test_every_frame_of_the_wrong_size_is_a_camera_error(tum_folder, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.warns(DatasetWarning, match="colour image is 640x480 but the camera is 320x240"):
        code = main(["run", str(tum_folder), "-o", str(out), "-q", "-c", "static", "--set", "camera.width=320",
                     "--set", "camera.height=240"])
    err = capsys.readouterr().err
    assert code == 2 and "are all 640x480 but the camera is 320x240: wrong camera configuration" in err, err
    assert "Traceback" not in err


# --- 6. timestamps in the lists ------------------------------------------------------------------------

def test_out_of_order_and_repeated_timestamps_are_fixed_with_warnings_naming_lines(tum_folder, tmp_path):
    root = copy_folder(tum_folder, tmp_path / "synthetic_room")
    (root / "associations.txt").unlink()   # associate from rgb.txt and depth.txt
    rgb = (root / "rgb.txt").read_text().splitlines()       # 2 comment lines, then one line per frame
    depth = (root / "depth.txt").read_text().splitlines()
    rgb[5], rgb[6] = rgb[6], rgb[5]                          # lines 6 and 7 swapped
    stamp_9 = rgb[11].split()[0]
    rgb.insert(12, f"{stamp_9} {rgb[12].split()[1]}")        # line 13: frame 9's time, frame 10's file
    depth.append(depth[8])                                   # the last line repeats line 9
    depth[14], depth[15] = depth[15], depth[14]              # lines 15 and 16 swapped
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")

    with pytest.warns(DatasetWarning) as record:
        dataset = TumDataset(root)
    text = "\n".join(str(w.message) for w in record)
    assert re.search(rf"{re.escape(str(root / 'rgb.txt'))}: 1 line\(s\) out of time order.*line 7 \(", text), text
    assert re.search(rf"{re.escape(str(root / 'rgb.txt'))}: 1 repeated timestamp.*line 13 repeats "
                     rf"{stamp_9} of line 12", text), text
    assert re.search(rf"{re.escape(str(root / 'depth.txt'))}: 2 line\(s\) out of time order.*line 16 \(.*"
                     rf"line {len(depth)} \(", text), text
    assert re.search(rf"{re.escape(str(root / 'depth.txt'))}: 1 repeated timestamp.*line {len(depth)} repeats "
                     rf".* of line 9", text), text
    assert len(dataset) == TUM_FRAMES and np.all(np.diff(dataset.timestamps) > 0)
    for frame in dataset:   # every pair is the right one: colour, depth and time agree
        assert frame.rgb_path.stem == frame.depth_path.stem == f"{frame.timestamp:.6f}"


# --- 7. invalid float depth in a bag -------------------------------------------------------------------

class _PoisonedDepth:
    """A sequence whose depth carries NaN, +inf, -inf and negative values (32FC1's 'no measurement')."""

    def __init__(self, seq):
        self.seq = seq

    def __getattr__(self, name):
        return getattr(self.seq, name)

    def __len__(self) -> int:
        return len(self.seq)

    def __iter__(self):
        for frame in self.seq:
            depth = frame.depth.copy()
            depth[:40, :] = np.nan
            depth[40:60, :200] = np.inf
            depth[40:60, 200:400] = -np.inf
            depth[60:80, :] = -1.5
            yield replace(frame, depth=depth)


def test_nan_inf_and_negative_bag_depth_is_invalid_depth(tmp_path, capsys):
    from slam.datasets import RosbagDataset

    seq = synthetic_sequence(12)
    bag = write_bag(tmp_path / "poisoned.bag", _PoisonedDepth(seq), 1, "32FC1", distortion=(0.0,) * 5,
                    extra_rgb=False)
    frames = list(RosbagDataset(bag))
    assert len(frames) == 12
    for frame, clean in zip(frames, seq):
        assert np.isfinite(frame.depth).all() and (frame.depth >= 0).all()
        poisoned = ~np.isfinite(clean.depth) | (next(iter(_PoisonedDepth([clean]))).depth != clean.depth)
        assert poisoned[:80].mean() > 0.9 and not frame.depth[poisoned].any(), "every invalid value reads as 0"
        assert np.array_equal(frame.depth[~poisoned], clean.depth[~poisoned])
    # The System's own guard, for any source: no NaN reaches the features or the tracker.
    system = System(synthetic_config(seq))
    nan_depth = next(iter(_PoisonedDepth(seq))).depth
    assert system.process(frames[0].rgb, nan_depth, 0.0, 0).T_wc is not None
    assert np.isfinite(system.last_frame.depths).all() and (system.last_frame.depths >= 0).all()
    assert main(["run", str(bag), "-o", str(tmp_path / "out"), "-q", "-c", "static", "--set", "output.report=false"]) == 0
    summary = read_summary(tmp_path / "out")
    assert summary["frames"] == summary["tracked"] == 12


# --- 12. detector cache keyed by the model's content ---------------------------------------------------

def _one_byte_changed(src: Path, dst: Path) -> Path:
    data = bytearray(src.read_bytes())
    data[len(data) // 2] ^= 0x01   # inside the weights: the model still loads, its boxes may differ
    dst.write_bytes(bytes(data))
    return dst


@pytest.mark.real
def test_detection_cache_is_keyed_by_the_model_files_content(tmp_path, monkeypatch):
    import frontend.detector as detector_module
    from frontend.detector import CachedDetector, build_detector, cache_path_for, model_digest
    from slam.core.dynamic_config import ClassGroups, DetectorConfig

    yolox, nanodet = model_file("yolox"), model_file("nanodet")
    copy = Path(shutil.copy(yolox, tmp_path / "yolox_copy.onnx"))
    changed = _one_byte_changed(yolox, tmp_path / "yolox_changed.onnx")
    cache_dir = tmp_path / "cache"
    cfg = DetectorConfig(model="yolox_nano", cache_dir=str(cache_dir))

    def path_for(model: Path) -> Path:
        return cache_path_for(cache_dir, "seq", cfg, model_path=model)

    assert path_for(copy) == path_for(yolox), "same bytes, same cache, wherever the file lies"
    assert len({path_for(yolox), path_for(changed), path_for(nanodet)}) == 3
    assert hashlib.sha256(changed.read_bytes()).hexdigest()[:16] in path_for(changed).name

    # Hashed once per file version: a second lookup reads nothing; a rewritten file is hashed again.
    monkeypatch.setattr(detector_module, "open", lambda *a, **k: pytest.fail("re-hashed"), raising=False)
    assert model_digest(copy) == model_digest(yolox)
    monkeypatch.delattr(detector_module, "open")
    shutil.copy(changed, copy)
    os.utime(copy, ns=(time.time_ns() + 10**9,) * 2)
    assert model_digest(copy) == model_digest(changed)

    image = np.zeros((480, 640, 3), np.uint8)
    first = build_detector(cfg.model_copy(update={"path": str(yolox)}), ClassGroups(), "seq")
    first.detect(image, 1.0)
    first.close()
    assert first.cache_file.is_file()
    other = build_detector(cfg.model_copy(update={"path": str(changed)}), ClassGroups(), "seq")
    assert isinstance(other, CachedDetector) and other.cache_file != first.cache_file and len(other) == 0
    other.detect(image, 1.0)
    assert other.misses == 1 and other.hits == 0, "boxes of another model are never read"
    # A cache file renamed onto the other model's name is recognised by the digest it records.
    shutil.copy(first.cache_file, other.cache_file)
    with pytest.warns(RuntimeWarning, match="another model file"):
        renamed = CachedDetector(other.inner, other.cache_file, model_digest(changed))
    assert len(renamed) == 0
