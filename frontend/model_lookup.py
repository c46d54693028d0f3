"""Where the detector model of a config is found, and whether there is one at all.

Order: ``dynamic.detector.path``, else ``$DYNSLAM_DETECTOR_MODEL`` (both *explicit*: a missing file
there is an input error naming the path), else ``<cache>/models/<file>`` (what ``dynslam download
model`` writes), else the development folder ``../shared/models`` beside the checkout. When neither
of the last two holds the file, the error gives the exact download command.

``locate_model`` never raises: the dynamic filter asks it whether a detector can be built and, when
the model was not given explicitly and none is found, runs the methods that need no detector.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from slam.core.dynamic_config import DetectorConfig
from slam.core.errors import DynslamError
from slam.core.model_files import MODELS, model_cache_dir, spec_for_config

ENV_MODEL = "DYNSLAM_DETECTOR_MODEL"
# dynamic.detector.model -> file name in the cache and the development folder
MODEL_FILES = {spec.config_model: spec.file_name for spec in MODELS.values()}


class DetectorError(DynslamError, RuntimeError):
    """The detector model cannot be loaded or run (missing/corrupt file, wrong model kind)."""


class ModelNotFoundError(DetectorError):
    """No model given explicitly and none in the cache or the development folder (exit status 2)."""


@dataclass(frozen=True)
class ModelLocation:
    """The outcome of a lookup: ``path`` is None when nothing was found."""

    path: Optional[Path]
    explicit: bool                 # from dynamic.detector.path or $DYNSLAM_DETECTOR_MODEL
    source: str                    # "config", "environment", "cache", "development folder" or ""
    searched: tuple[Path, ...]     # the implicit places looked in (empty for an explicit path)


def default_model_dir() -> Path:
    """The development folder: ``<checkout>/../shared/models``."""
    return Path(__file__).resolve().parents[1].parent / "shared" / "models"


def download_command(model: str) -> str:
    """``dynslam download model <name>`` for a ``dynamic.detector.model`` value."""
    spec = spec_for_config(model)
    return spec.download_command if spec else "dynslam download model"


def locate_model(cfg: DetectorConfig) -> ModelLocation:
    """Where the model for ``cfg`` is; never raises. An explicit path is returned whether or not it
    exists (loading it reports a missing file with its path); implicit places only when the file is there."""
    if cfg.path:
        return ModelLocation(Path(cfg.path).expanduser(), True, "config", ())
    env = os.environ.get(ENV_MODEL, "").strip()
    if env:
        return ModelLocation(Path(env).expanduser(), True, "environment", ())
    file_name = MODEL_FILES.get(cfg.model)
    if file_name is None:
        return ModelLocation(None, False, "", ())
    searched = (model_cache_dir() / file_name, default_model_dir() / file_name)
    for path, source in zip(searched, ("cache", "development folder")):
        if path.is_file():
            return ModelLocation(path, False, source, searched)
    return ModelLocation(None, False, "", searched)


def model_available(cfg: DetectorConfig) -> bool:
    """Whether a detector model file exists for ``cfg`` (explicit path or found in the usual places)."""
    location = locate_model(cfg)
    return location.path is not None and location.path.is_file()


def resolve_model_path(cfg: DetectorConfig) -> Path:
    """The model file for ``cfg``. An explicit path is returned unchecked (``OnnxDetector`` reports a
    missing one with its path); otherwise ModelNotFoundError names the places searched and the command."""
    if cfg.model not in MODEL_FILES:
        raise DetectorError(f"unknown detector model '{cfg.model}' (expected one of {', '.join(MODEL_FILES)})")
    location = locate_model(cfg)
    if location.path is None:
        raise ModelNotFoundError(missing_model_message(cfg.model, location.searched))
    return location.path


def missing_model_message(model: str, searched: tuple[Path, ...]) -> str:
    """One line: which model is missing, where it was looked for, and the command that fetches it."""
    places = " or ".join(str(p) for p in searched)
    return (f"detector model '{model}' not found (looked for {places}); download it with: "
            f"{download_command(model)}  (or set dynamic.detector.path / ${ENV_MODEL} to an ONNX file)")


def howto(kind: str) -> str:
    """What to do about a missing or wrong model file, for the detector's error messages."""
    return (f"set 'dynamic.detector.path' in the config or the environment variable {ENV_MODEL} to the "
            f"{MODEL_FILES.get(kind, 'ONNX model')} file, run '{download_command(kind)}', or disable the "
            f"methods that need a detector")
