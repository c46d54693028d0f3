"""Finding the detector model (config path, environment, cache, development folder) and running on
without one: a config with detector methods and cpr falls back to cpr with one warning that gives the
download command; a config of detector methods only, or an explicit path that does not exist, is an error."""
from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from conftest import model_file, synthetic_config, synthetic_sequence
from frontend import model_lookup
from frontend.detector import DetectorError
from frontend.dynamic_filter import DetectorModelMissingWarning, build_dynamic_filter, method_names
from frontend.model_lookup import ModelNotFoundError, locate_model, model_available, resolve_model_path
from slam.cli import main
from slam.core.camera import PinholeCamera
from slam.core.dynamic_config import DetectorConfig
from slam.core.model_files import MODELS

COMMAND = "dynslam download model yolox-nano"


@pytest.fixture
def no_model(tmp_path, monkeypatch) -> Path:
    """An empty cache, no $DYNSLAM_DETECTOR_MODEL, and the development folder hidden; returns the
    cache's models folder."""
    monkeypatch.setenv("DYNSLAM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("DYNSLAM_DETECTOR_MODEL", raising=False)
    monkeypatch.setattr(model_lookup, "default_model_dir", lambda: tmp_path / "no_shared" / "models")
    return tmp_path / "cache" / "models"


def put(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"onnx")
    return path


def test_lookup_order_config_environment_cache_development(no_model, tmp_path, monkeypatch):
    dev = put(tmp_path / "no_shared" / "models" / "yolox_nano_416.onnx")
    assert locate_model(DetectorConfig()).source == "development folder"
    cached = put(no_model / "yolox_nano_416.onnx")
    location = locate_model(DetectorConfig())
    assert (location.path, location.source, location.searched) == (cached, "cache", (cached, dev))
    monkeypatch.setenv("DYNSLAM_DETECTOR_MODEL", str(tmp_path / "env.onnx"))
    assert locate_model(DetectorConfig()).path == tmp_path / "env.onnx", "explicit, even when missing"
    location = locate_model(DetectorConfig(path=str(tmp_path / "cfg.onnx")))
    assert (location.path, location.source, location.explicit) == (tmp_path / "cfg.onnx", "config", True)
    assert resolve_model_path(DetectorConfig(model="nanodet", path=str(dev))) == dev


def test_missing_model_error_gives_the_exact_command(no_model):
    assert not model_available(DetectorConfig())
    with pytest.raises(ModelNotFoundError) as info:
        resolve_model_path(DetectorConfig())
    message = str(info.value)
    assert f"download it with: {COMMAND} " in message and str(no_model / "yolox_nano_416.onnx") in message
    assert info.value.exit_code == 2 and isinstance(info.value, DetectorError)
    with pytest.raises(ModelNotFoundError, match="dynslam download model nanodet-m "):
        resolve_model_path(DetectorConfig(model="nanodet"))
    put(no_model / "nanodet_m_320.onnx")
    assert model_available(DetectorConfig(model="nanodet")) and not model_available(DetectorConfig())


def _filter(preset: str, **overrides):
    config = synthetic_config(synthetic_sequence(n_frames=2), preset=preset, **overrides)
    return config, build_dynamic_filter(config, PinholeCamera.from_config(config.camera))


def test_detector_methods_fall_back_to_cpr_with_one_warning(no_model):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        config, dynamic_filter = _filter("dynamic_all")
    assert [str(w.message) for w in caught if w.category is DetectorModelMissingWarning] == \
        [str(caught[0].message)], "exactly one warning"
    message = str(caught[0].message)
    assert message.endswith(f"Get the model with: {COMMAND}")
    assert "continuing with cpr only (box_depth, flow_epipolar, depth_sdf, the person-box prior need" in message
    assert method_names(dynamic_filter) == ["cpr"] and dynamic_filter.detector is None
    assert (dynamic_filter.cfg.fusion, dynamic_filter.cfg.box_prior) == ("single", 0.0), \
        "cpr alone as its own preset runs it (its 0.2 noisy-OR weight never reaches 0.5 alone)"
    assert config.dynamic.methods == ["cpr", "box_depth", "flow_epipolar", "depth_sdf"], "the config is untouched"


@pytest.mark.parametrize("preset", ["dynamic_box_depth", "dynamic_box_prior"])
def test_detector_methods_alone_are_an_error_with_the_command(no_model, preset):
    with pytest.raises(ModelNotFoundError, match=COMMAND):
        _filter(preset)


def test_an_explicit_missing_model_is_an_error_not_a_fallback(no_model, tmp_path, monkeypatch):
    missing = tmp_path / "gone.onnx"
    with pytest.raises(DetectorError, match=str(missing)) as info:
        _filter("dynamic_all", **{"dynamic.detector.path": str(missing)})
    assert info.value.exit_code == 2
    monkeypatch.setenv("DYNSLAM_DETECTOR_MODEL", str(missing))
    with pytest.raises(DetectorError, match=str(missing)):
        _filter("dynamic_all")


def _tum_folder(tmp_path, frames: int):
    """A generated room written as a TUM folder: `dynslam run` looks its detector model up (the demo
    uses the scene's own boxes and needs none)."""
    from slam.datasets import SyntheticSequence, write_tum_layout

    return write_tum_layout(SyntheticSequence(n_frames=frames), tmp_path / "seq")


def test_cli_run_without_a_model_uses_cpr_and_warns_once(no_model, tmp_path, recwarn, monkeypatch):
    """(pytest records the warnings; outside it the CLI prints each as one 'dynslam: warning:' line.)"""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    out = tmp_path / "out"
    assert main(["run", str(_tum_folder(tmp_path, 4)), "-o", str(out), "-q", "-c", "dynamic_all"]) == 0
    missing = [str(w.message) for w in recwarn if w.category is DetectorModelMissingWarning]
    assert len(missing) == 1 and missing[0].endswith(f"Get the model with: {COMMAND}")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dynamic_methods"] == ["cpr"]
    # no detector-based method ran; the near-occluder rule needs only depth and poses
    assert set(summary["dynamic_flagged"]) <= {"cpr", "near_occluders", "fused"}


def test_cli_run_of_detector_methods_without_a_model_is_exit_2(no_model, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    assert main(["run", str(_tum_folder(tmp_path, 3)), "-o", str(tmp_path / "out"), "-q",
                 "-c", "dynamic_box_depth"]) == 2
    err = capsys.readouterr().err
    assert f"download it with: {COMMAND}" in err and "Traceback" not in err


@pytest.mark.real
def test_downloaded_model_is_what_a_run_then_loads(no_model, server, tmp_path, capsys, monkeypatch):
    """The real model, served locally and verified against the unpatched pin, lands in the cache; a
    box_depth run then finds it there and runs the detector on every frame."""
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    body = model_file("yolox").read_bytes()
    assert hashlib.sha256(body).hexdigest() == MODELS["yolox-nano"].sha256
    server.files[urlsplit(MODELS["yolox-nano"].url).path] = body
    assert main(["download", "model", "--base-url", server.base_url]) == 0
    assert (no_model / "yolox_nano_416.onnx").read_bytes() == body
    out = tmp_path / "out"
    assert main(["run", str(_tum_folder(tmp_path, 3)), "-o", str(out), "-q", "-c", "dynamic_box_depth"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dynamic_methods"] == ["box_depth"] and "dynamic.detector" in summary["timing_ms"]
    assert "no detector model" not in capsys.readouterr().err
