"""YOLOX on the image's own aspect (frontend/onnx_input_shape.py, ``dynamic.detector.fit_input``): the model
rewritten in memory runs at 416 x 320, finds the same boxes as on the padded square, and a model that cannot
(NanoDet-m, malformed bytes) keeps its square input. An option, off by default (docs/design.md)."""
from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from frontend.detector import OnnxDetector, box_iou, cache_path_for
from frontend.onnx_input_shape import OnnxRewriteError, with_input_size
from slam.core.dynamic_config import DetectorConfig

from conftest import BONN, model_file, real_sequence

PERSON = 0


def _bonn_frames(indices):
    files = sorted(real_sequence(BONN).joinpath("rgb").iterdir())
    return [cv2.imread(str(files[i])) for i in indices]


@pytest.mark.real
def test_rewritten_yolox_runs_on_the_new_size_and_keeps_its_weights():
    import onnxruntime as ort

    raw = model_file("yolox").read_bytes()
    fitted = with_input_size(raw, 320, 416)
    assert 0 < len(raw) - len(fitted) < 0.01 * len(raw)      # only shape records go; the weights stay
    session = ort.InferenceSession(fitted, providers=["CPUExecutionProvider"])
    assert session.get_inputs()[0].shape == [1, 3, 320, 416]
    out = session.run(None, {session.get_inputs()[0].name: np.zeros((1, 3, 320, 416), np.float32)})[0]
    assert out.shape == (1, 40 * 52 + 20 * 26 + 10 * 13, 85)   # strides 8, 16, 32 over 320 x 416
    square = ort.InferenceSession(raw, providers=["CPUExecutionProvider"])
    with pytest.raises(Exception, match="dimensions"):          # why the rewrite is needed at all
        square.run(None, {square.get_inputs()[0].name: np.zeros((1, 3, 320, 416), np.float32)})


@pytest.mark.real
def test_fitted_input_finds_the_square_inputs_people():
    """Bonn crowd frames with people near and far: the same people at the same places (IoU > 0.9 for
    every confident person; 0.99 median over every 4th frame of the 480, the lowest 0.85 for a person
    cut by the bottom edge), and a 640 x 480 image runs on 416 x 320."""
    square = OnnxDetector(model_file("yolox"), kind="yolox_nano", fit_input=False)
    fitted = OnnxDetector(model_file("yolox"), kind="yolox_nano", fit_input=True)
    geometry = fitted.input_geometry(480, 640)
    assert (geometry.height, geometry.width) == (320, 416)
    assert square.input_geometry(480, 640).height == 416
    for image in _bonn_frames([300, 350, 420]):
        a, b = square.detect_arrays(image), fitted.detect_arrays(image)
        people_a, people_b = a[0][(a[2] == PERSON) & (a[1] > 0.5)], b[0][(b[2] == PERSON) & (b[1] > 0.5)]
        assert len(people_a) >= 1 and len(people_a) == len(people_b)
        assert box_iou(people_a, people_b).max(axis=1).min() > 0.9


@pytest.mark.real
def test_a_model_with_fixed_reshapes_keeps_its_square_input():
    nanodet = OnnxDetector(model_file("nanodet"), kind="nanodet", fit_input=True)   # not among the fitting models
    assert not nanodet.fit_input and nanodet.input_geometry(480, 640).height == 320
    yolox = OnnxDetector(model_file("yolox"), kind="yolox_nano", fit_input=True)
    yolox.model_path = model_file("nanodet")        # a "YOLOX" file whose graph cannot change size
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        geometry = yolox.input_geometry(480, 640)
    assert geometry.height == geometry.width == 416
    assert any("does not run on a 416 x 320 input" in str(w.message) for w in caught)


def test_fitting_is_off_by_default_and_cache_names_differ_between_square_and_fitted_boxes(tmp_path):
    assert not DetectorConfig().fit_input
    model = tmp_path / "m.onnx"
    model.write_bytes(b"model")
    names = {cache_path_for(tmp_path, "seq", DetectorConfig(fit_input=fit), model_path=model).name
             for fit in (True, False)}
    assert len(names) == 2


def test_malformed_model_bytes_are_refused_clearly():
    with pytest.raises(OnnxRewriteError):
        with_input_size(b"\x3a\xff", 320, 416)           # a graph field longer than the bytes
    with pytest.raises(OnnxRewriteError, match="not found"):
        with_input_size(b"\x08\x07", 320, 416)           # a model with no graph
    with pytest.raises(ValueError, match="positive"):
        with_input_size(b"", 0, 416)
