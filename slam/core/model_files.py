"""The detector model files dynslam can fetch, and where fetched ones are kept.

``MODELS`` is the registry behind ``dynslam download model``: per model its CLI name, the value of
``dynamic.detector.model`` it serves, the file name used in the cache and in the development folder,
the URL it is fetched from, the pinned sha256 and size, and its licence. ``model_cache_dir()`` is
``<cache>/models`` with ``<cache>`` = ``$DYNSLAM_CACHE_DIR``, else the platform's user cache folder.
Both the front end (model lookup) and ``slam.run`` (download) read this, so it lives in the core.

Provenance of the pins (no network where they were taken; see ``../shared/models/README.md``):
the pins are the sha256 and size of the team's development copies in ``../shared/models``, the files
the detector's pre- and post-processing were verified against. Those copies are third-party ONNX
exports, not the upstream projects' own files, so each entry downloads from the repository the copy
came from and names the upstream source in ``upstream``.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional

from slam.core.errors import DynslamError

CACHE_ENV = "DYNSLAM_CACHE_DIR"


class UnknownModelError(DynslamError, ValueError):
    """A model name that is not in the registry (exit status 2)."""


@dataclass(frozen=True)
class ModelSpec:
    """One downloadable detector model."""

    name: str           # CLI name: dynslam download model <name>
    config_model: str   # the dynamic.detector.model value it serves
    file_name: str      # its name in <cache>/models and in ../shared/models
    url: str            # where the pinned bytes are served
    sha256: str         # pinned digest of the file at ``url``
    size: int           # pinned size in bytes
    licence: str
    upstream: str       # the upstream project's own release of the model, for reference
    caveat: str = ""    # shown when the served file does not match the pin

    @property
    def download_command(self) -> str:
        """The exact command that fetches this model into the cache."""
        return f"dynslam download model {self.name}"


MODELS: dict[str, ModelSpec] = {
    # The pin was taken from the team's copy ../shared/models/yolox_nano_416.onnx, as there is no
    # network here to hash the download itself. That copy is not the Megvii release asset
    # (``upstream``): the models README gives its origin as Kazuhito00/YOLOX-ONNX-TFLite-Sample
    # model/yolox_nano.onnx @ 3d4f111, whose notebook exports the official yolox_nano.pth itself, and
    # the file names PyTorch 1.10 as its producer, released after the 0.1.1rc0 assets. The release
    # asset would therefore most likely fail this pin, so the URL is the repository the copy came
    # from, at that commit; switching to ``upstream`` needs that file's own sha256 and size.
    "yolox-nano": ModelSpec(
        name="yolox-nano", config_model="yolox_nano", file_name="yolox_nano_416.onnx",
        url="https://github.com/Kazuhito00/YOLOX-ONNX-TFLite-Sample/raw/"
            "3d4f1119d0694200671c08069ecb847aa0d8495a/model/yolox_nano.onnx",
        sha256="695e750a5d5754bb5a8d5325643b59282191a7e7a564e435a415fd3c578eab14", size=3_660_092,
        licence="Apache-2.0 (YOLOX weights: Megvii; ONNX export: Kazuhito00/YOLOX-ONNX-TFLite-Sample)",
        upstream="https://github.com/Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx"),
    # NanoDet publishes NanoDet-m weights only as a PyTorch checkpoint (Google Drive) and an ncnn zip
    # (release v0.0.1); the ONNX file comes from Kazuhito00/MOT-Tracking-by-Detection-Pipeline @
    # e50a76b. The team's copy is MODIFIED (the initializers listed in graph.input were removed, see
    # the models README), and the digest of the unmodified file could not be established offline, so
    # the pin is the team copy's: the file at ``url`` is expected to be refused until a mirror serving
    # the team's file is used (--base-url keeps the path) or the pin is replaced by the upstream digest.
    "nanodet-m": ModelSpec(
        name="nanodet-m", config_model="nanodet", file_name="nanodet_m_320.onnx",
        url="https://github.com/Kazuhito00/MOT-Tracking-by-Detection-Pipeline/raw/e50a76b/"
            "Detector/nanodet/model/nanodet_m_320.onnx",
        sha256="01ef5cfe9b644607ba69f4e06614d873a9c90614cb0b34f1d62e1e3558da514e", size=3_798_011,
        licence="Apache-2.0 (NanoDet: RangiLyu; ONNX export: Kazuhito00/MOT-Tracking-by-Detection-Pipeline)",
        upstream="https://github.com/RangiLyu/nanodet (NanoDet-m 320 checkpoint)",
        caveat="the pin is the team's modified copy (initializers removed from graph.input); the unmodified "
               "file served upstream differs. Use a mirror of the team's file with --base-url"),
}
DEFAULT_MODEL = "yolox-nano"


def model_spec(name: str) -> ModelSpec:
    """The registry entry for a CLI name (``yolox-nano``) or a config value (``yolox_nano``)."""
    key = name.strip().lower()
    for spec in MODELS.values():
        if key in (spec.name, spec.config_model):
            return spec
    raise UnknownModelError(f"unknown detector model '{name}' (expected one of: {', '.join(MODELS)})")


def spec_for_config(config_model: str) -> Optional[ModelSpec]:
    """The entry serving ``dynamic.detector.model`` = ``config_model``, or None."""
    return next((s for s in MODELS.values() if s.config_model == config_model), None)


def cache_root(environ: Optional[Mapping[str, str]] = None, platform: Optional[str] = None,
               home: Optional[Path] = None) -> Path:
    """dynslam's cache folder: ``$DYNSLAM_CACHE_DIR``, else the platform's user cache convention
    (Linux and other POSIX: ``$XDG_CACHE_HOME/dynslam`` or ``~/.cache/dynslam``; macOS
    ``~/Library/Caches/dynslam``; Windows ``%LOCALAPPDATA%\\dynslam\\Cache``). Arguments are for tests."""
    env = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    home = Path.home() if home is None else home
    explicit = env.get(CACHE_ENV, "").strip()
    if explicit:
        return Path(explicit).expanduser()
    if platform == "darwin":
        return home / "Library" / "Caches" / "dynslam"
    if platform.startswith("win"):
        local = env.get("LOCALAPPDATA", "").strip()
        return (Path(local) if local else home / "AppData" / "Local") / "dynslam" / "Cache"
    xdg = env.get("XDG_CACHE_HOME", "").strip()
    # The XDG spec says a relative XDG_CACHE_HOME is invalid and must be ignored.
    return (Path(xdg) if xdg and os.path.isabs(xdg) else home / ".cache") / "dynslam"


def model_cache_dir() -> Path:
    """``<cache_root()>/models``: where ``dynslam download model`` puts models and runs look for them."""
    return cache_root() / "models"
