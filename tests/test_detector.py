"""Object detector: decoding on real frames (needs ../shared), NMS, letterbox maths, errors, cache."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from frontend import detector as det_mod
from frontend.detector import (CachedDetector, DetectorError, OnnxDetector, box_iou, boxes_from_input,
                               boxes_to_input, build_detector, cache_path_for, class_filter_of,
                               letterbox_params, nms_numpy, nms_per_class, resolve_model_path)
from frontend.dynamic.base import Detection, DetectorDefaults
from slam.core.dynamic_config import ClassGroups, DetectorConfig

from conftest import BONN, DATA, XYZ, model_file, real_sequence

BONN_RGB = DATA / BONN / "rgb"
XYZ_RGB = DATA / XYZ / "rgb"
PERSON, CHAIR, KEYBOARD = 0, 56, 66


def _model(kind: str) -> Path:
    return model_file("yolox" if kind == "yolox_nano" else kind)


def _frame(folder: Path, index: int) -> np.ndarray:
    import cv2

    files = sorted(real_sequence(folder.parent.name).joinpath(folder.name).iterdir())
    image = cv2.imread(str(files[index]))
    assert image is not None, files[index]
    return image


@pytest.fixture(scope="module")
def yolox():
    return OnnxDetector(_model("yolox_nano"), kind="yolox_nano")


@pytest.fixture(scope="module")
def nanodet():
    return OnnxDetector(_model("nanodet"), kind="nanodet")


def _as_box(d: Detection) -> np.ndarray:
    return np.array([[d.x0, d.y0, d.x1, d.y1]])


# ----------------------------------------------------------------------------------- real frames


@pytest.mark.real
@pytest.mark.parametrize("index", [300, 350])
def test_people_found_on_bonn_crowd(yolox, nanodet, index):
    image = _frame(BONN_RGB, index)
    h, w = image.shape[:2]
    people = [d for d in yolox.detect(image) if d.class_id == PERSON and d.score > 0.5]
    assert people, "YOLOX found no person on a frame with people walking through"
    for d in people:
        assert 0 <= d.x0 < d.x1 <= w and 0 <= d.y0 < d.y1 <= h
        assert d.height > 100, d
    # Two people are in view on both frames, standing upright (taller than wide).
    assert len(people) >= 2
    assert all(d.height > d.width for d in people)
    nano_people = [d for d in nanodet.detect(image) if d.class_id == PERSON and d.score > 0.5]
    assert nano_people
    # Every confident NanoDet person overlaps a YOLOX person; the two models, with their different
    # letterboxes, strides and box parametrisations, agree closely on the boxes (IoU > 0.8 observed
    # 0.92-0.98): a decoding offset of half a cell or a wrong scale would break this.
    for nano in nano_people:
        ious = [box_iou(_as_box(nano), _as_box(d))[0, 0] for d in people]
        assert max(ious) > 0.5, (nano, people)
    best = max(people, key=lambda d: d.score)
    assert max(box_iou(_as_box(best), _as_box(d))[0, 0] for d in nano_people) > 0.8


@pytest.mark.real
def test_no_people_before_they_enter(yolox):
    image = _frame(BONN_RGB, 0)
    dets = yolox.detect(image)
    assert not [d for d in dets if d.class_id == PERSON and d.score > 0.5]
    assert any(d.class_id == CHAIR and d.score > 0.5 for d in dets)   # the office chair right of centre


@pytest.mark.real
def test_office_desk_scene(yolox, nanodet):
    # fr1/xyz frame 0: keyboard bottom right; the only person sits behind the monitor at the top edge.
    image = _frame(XYZ_RGB, 0)
    for detector in (yolox, nanodet):
        dets = detector.detect(image)
        keyboards = [d for d in dets if d.class_id == KEYBOARD and d.score > 0.5]
        assert keyboards, detector
        kb = keyboards[0]
        assert (kb.x0 + kb.x1) / 2 > 320 and (kb.y0 + kb.y1) / 2 > 300
        people = [d for d in dets if d.class_id == PERSON and d.score > 0.5]
        assert people and all(d.y1 < 160 and 200 < (d.x0 + d.x1) / 2 < 380 for d in people), people


@pytest.mark.real
def test_output_contract(yolox):
    image = _frame(BONN_RGB, 300)
    dets = yolox.detect(image, timestamp=1.0)
    scores = [d.score for d in dets]
    assert scores == sorted(scores, reverse=True)
    assert all(d.score >= yolox.score_threshold for d in dets)
    assert all(isinstance(d.class_id, int) and isinstance(d.x0, float) for d in dets)
    only_people = OnnxDetector(_model("yolox_nano"), kind="yolox_nano", class_filter=[PERSON])
    filtered = only_people.detect(image)
    assert filtered and all(d.class_id == PERSON for d in filtered)
    assert len(filtered) == sum(d.class_id == PERSON for d in dets)


@pytest.mark.real
def test_build_detector_with_cache(tmp_path):
    _model("yolox_nano")
    image = _frame(BONN_RGB, 300)
    cfg = DetectorConfig(model="yolox_nano", cache_dir=str(tmp_path))
    detector = build_detector(cfg, ClassGroups(), sequence_name="bonn crowd")
    assert isinstance(detector, CachedDetector)
    first = detector.detect(image, 12.5)
    detector.close()
    assert detector.cache_file.is_file() and "yolox_nano" in detector.cache_file.name
    again = build_detector(cfg, ClassGroups(), sequence_name="bonn crowd")
    assert len(again) == 1
    assert again.detect(np.zeros_like(image), 12.5) == first   # served from the cache, not the image
    plain = build_detector(DetectorConfig(model="nanodet"), ClassGroups())
    assert isinstance(plain, OnnxDetector) and plain.kind == "nanodet"
    allowed = set(class_filter_of(ClassGroups()))
    assert all(d.class_id in allowed for d in plain.detect(image))


# ----------------------------------------------------------------------------------- no model needed


def test_nms_same_class_duplicate_removed_other_class_kept():
    boxes = np.array([[10, 10, 110, 210], [14, 12, 112, 215], [12, 10, 108, 205], [300, 300, 350, 360]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    classes = np.array([0, 0, 56, 0])
    for nms in (nms_numpy, nms_per_class):
        keep = nms(boxes, scores, classes, 0.45)
        assert sorted(keep.tolist()) == [0, 2, 3], nms
        assert keep.tolist() == [0, 2, 3]   # sorted by score
    assert nms_per_class(boxes[:0], scores[:0], classes[:0], 0.45).size == 0


def test_nms_numpy_matches_opencv_on_random_boxes():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 500, (300, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(10, 150, (300, 2))], axis=1)
    scores = rng.uniform(0.3, 1.0, 300)
    classes = rng.integers(0, 3, 300)
    ours = nms_numpy(boxes, scores, classes, 0.45)
    assert sorted(ours.tolist()) == sorted(nms_per_class(boxes, scores, classes, 0.45).tolist())
    kept = boxes[ours]
    iou = box_iou(kept, kept)
    same = classes[ours][:, None] == classes[ours][None, :]
    np.fill_diagonal(same, False)
    assert np.all(iou[same] <= 0.45)


@pytest.mark.parametrize("size,centred", [(416, False), (320, True)])
def test_letterbox_round_trip(size, centred):
    r, nw, nh, left, top = letterbox_params(480, 640, size, centred)
    assert r == pytest.approx(size / 640) and nw == size and nh == round(480 * size / 640)
    assert left == 0 and top == ((size - nh) // 2 if centred else 0)
    box = np.array([[37.5, 12.0, 600.25, 479.0]])
    inp = boxes_to_input(box, r, left, top)
    assert np.all(inp >= 0) and np.all(inp <= size)
    np.testing.assert_allclose(boxes_from_input(inp, r, left, top), box, atol=1e-9)
    if centred:   # the image occupies the middle rows: its corners map to (0, top) and (size, top + nh)
        np.testing.assert_allclose(boxes_to_input(np.array([[0, 0, 640, 480]]), r, left, top),
                                   [[0, top, size, top + nh]], atol=1e-6)


def test_nanodet_distribution_decoding():
    # Bins peaked at 2 (left), 0 (top), 7 (right), 3 (bottom) for an anchor at cell (1, 2), stride 16.
    logits = np.full((1, 4, 8), -50.0, dtype=np.float32)
    for side, b in enumerate((2, 0, 7, 3)):
        logits[0, side, b] = 50.0
    prior = np.array([[(1 + 0.5) * 16, (2 + 0.5) * 16, 16]], dtype=np.float32)
    box = OnnxDetector._nanodet_boxes(logits.reshape(1, 32), prior)
    np.testing.assert_allclose(box, [[24 - 32, 40 - 0, 24 + 112, 40 + 48]], atol=1e-4)


def test_missing_model_error_names_path(tmp_path):
    missing = tmp_path / "nope" / "yolox_nano_416.onnx"
    with pytest.raises(DetectorError) as err:
        OnnxDetector(missing, kind="yolox_nano")
    assert str(missing) in str(err.value) and "DYNSLAM_DETECTOR_MODEL" in str(err.value)
    assert "dynamic.detector.path" in str(err.value)
    with pytest.raises(DetectorError, match=str(missing).replace("\\", "\\\\")):
        build_detector(DetectorConfig(path=str(missing)), ClassGroups())


def test_corrupt_model_error_names_path(tmp_path):
    bad = tmp_path / "garbage.onnx"
    bad.write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(DetectorError) as err:
        OnnxDetector(bad, kind="nanodet")
    assert str(bad) in str(err.value) and "DYNSLAM_DETECTOR_MODEL" in str(err.value)
    assert isinstance(err.value, RuntimeError)


@pytest.mark.real
def test_resolve_model_path(monkeypatch, tmp_path):
    monkeypatch.delenv("DYNSLAM_DETECTOR_MODEL", raising=False)
    monkeypatch.setenv("DYNSLAM_CACHE_DIR", str(tmp_path / "empty_cache"))   # the development copies count
    model_file("yolox"), model_file("nanodet")   # (the full lookup order: tests/test_model_lookup.py)
    repo = Path(det_mod.__file__).resolve().parents[1]
    assert resolve_model_path(DetectorConfig()) == repo.parent / "shared" / "models" / "yolox_nano_416.onnx"
    assert resolve_model_path(DetectorConfig(model="nanodet")).name == "nanodet_m_320.onnx"
    monkeypatch.setenv("DYNSLAM_DETECTOR_MODEL", str(tmp_path / "env.onnx"))
    assert resolve_model_path(DetectorConfig()) == tmp_path / "env.onnx"
    assert resolve_model_path(DetectorConfig(path=str(tmp_path / "cfg.onnx"))) == tmp_path / "cfg.onnx"


def test_cache_path_depends_on_settings(tmp_path):
    model = tmp_path / "model.onnx"   # the name holds the file's content hash: any file will do here
    model.write_bytes(b"model bytes")
    a = cache_path_for(tmp_path, "rgbd_bonn_crowd", DetectorConfig(), model_path=model)
    b = cache_path_for(tmp_path, "rgbd_bonn_crowd", DetectorConfig(score_threshold=0.5), model_path=model)
    c = cache_path_for(tmp_path, "rgbd_bonn_crowd", DetectorConfig(model="nanodet"), model_path=model)
    d = cache_path_for(tmp_path, "rgbd_bonn_crowd", DetectorConfig(), class_filter=[0, 56], model_path=model)
    e = cache_path_for(tmp_path, "other/seq", DetectorConfig(), model_path=model)
    assert len({a, b, c, d, e}) == 5
    assert all(p.parent == tmp_path and p.suffix == ".npz" for p in (a, b, c, d, e))
    assert "yolox_nano" in a.name and "0.300" in a.name


class CountingDetector(DetectorDefaults):
    def __init__(self):
        self.calls = 0

    def detect(self, bgr, timestamp=0.0):
        self.calls += 1
        return [Detection(1.0, 2.0, 30.5, 40.25, 0, 0.875), Detection(5.0, 6.0, 7.0, 8.0, 56, 0.5)] \
            if timestamp < 2 else []


def test_cached_detector_serves_from_cache(tmp_path):
    image = np.zeros((4, 4, 3), np.uint8)
    path = tmp_path / "cache.npz"
    inner = CountingDetector()
    cached = CachedDetector(inner, path)
    first = cached.detect(image, 1.0)
    assert cached.detect(image, 1.0) == first and inner.calls == 1
    assert cached.detect(image, 3.0) == [] and inner.calls == 2
    cached.save()
    inner2 = CountingDetector()
    reloaded = CachedDetector(inner2, path)
    assert len(reloaded) == 2
    assert reloaded.detect(image, 1.0000001) == first     # keyed by '%.6f'
    assert reloaded.detect(image, 3.0) == []
    assert inner2.calls == 0
    mtime = path.stat().st_mtime_ns
    reloaded.save()   # nothing new: no rewrite
    assert path.stat().st_mtime_ns == mtime


def test_cached_detector_survives_corrupt_cache(tmp_path):
    path = tmp_path / "cache.npz"
    path.write_bytes(b"not a zip file at all")
    inner = CountingDetector()
    with pytest.warns(RuntimeWarning, match="cache"):
        cached = CachedDetector(inner, path)
    assert len(cached) == 0
    assert len(cached.detect(np.zeros((2, 2, 3), np.uint8), 1.0)) == 2 and inner.calls == 1
    cached.save()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(CachedDetector(CountingDetector(), path)) == 1


def test_cached_detector_writes_atomically(tmp_path, monkeypatch):
    path = tmp_path / "sub" / "cache.npz"
    cached = CachedDetector(CountingDetector(), path)
    cached.detect(np.zeros((2, 2, 3), np.uint8), 1.0)
    replaced = []
    real_replace = os.replace

    def spy(src, dst):
        replaced.append((Path(src), Path(dst)))
        assert not Path(dst).exists() and Path(src).stat().st_size > 0
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)   # the os module the cache writer (atomic_io) uses
    cached.save()
    assert len(replaced) == 1 and replaced[0][1] == path and replaced[0][0].parent == path.parent
    good = path.read_bytes()

    # A failure while writing leaves the previous file untouched and no temporary file behind.
    cached.detect(np.zeros((2, 2, 3), np.uint8), 5.0)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(det_mod.np, "savez_compressed", boom)
    with pytest.raises(OSError):
        cached.save()
    assert path.read_bytes() == good
    assert sorted(p.name for p in path.parent.iterdir()) == ["cache.npz"]
