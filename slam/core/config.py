"""Typed configuration: defaults, YAML layers and ``--set`` overrides, merged first and validated once.

A config file holds any subset of the sections below; whatever it leaves out keeps its default.
Presets in ``configs/`` are such partial files. The layers (defaults, then camera and preset files in
order, then dotted overrides) are merged as plain dicts and validated once, so a rule between two keys
holds for the result, not for each file alone; every error still names the layer that set the key and
its dotted name (``configs/x.yaml: 'dynamic.cpr.voxel_size' must be > 0, got -1``), so a typo in a
user's YAML never silently falls back to a default.

The sections are pydantic models (slam.core.config_sections, dynamic_config, loop_config) with each
limit beside its field; ``config_schema()`` is their JSON schema, for editors.
"""
from __future__ import annotations

import copy
import importlib.resources
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence

import yaml
from pydantic import Field, ValidationError

from slam.core.config_base import ConfigError, ConfigSection
from slam.core.config_errors import Provenance, format_validation_error
from slam.core.config_sections import (TRAJECTORY_FORMATS, BackendConfig, CameraConfig, KeyframeConfig,
                                       MapExportConfig, OrbConfig, OutputConfig, RuntimeConfig, TrackingConfig)
from slam.core.dynamic_config import DynamicConfig
from slam.core.loop_config import LoopConfig

__all__ = ["CONFIG_DIR", "TRAJECTORY_FORMATS", "BackendConfig", "CameraConfig", "ConfigError", "DynamicConfig",
           "KeyframeConfig", "Layer", "LoopConfig", "MapExportConfig", "OrbConfig", "OutputConfig", "RuntimeConfig",
           "SlamConfig", "TrackingConfig", "apply_overrides", "apply_yaml", "build_config", "config_schema",
           "default_config_yaml", "load_config", "overrides_layer", "resolve_config_path", "validate", "yaml_layer"]


def _preset_dir() -> Path:
    """configs/ of the checkout, shipped in the wheel as the package slam.presets (pyproject.toml);
    a source tree that was never installed has only the folder beside the packages."""
    try:
        return Path(str(importlib.resources.files("slam.presets")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "configs"


CONFIG_DIR = _preset_dir()
DEFAULTS_SOURCE = "<defaults>"


class SlamConfig(ConfigSection):
    """The whole configuration of a run (``dynslam config`` prints it, every run saves it)."""

    camera: CameraConfig = Field(default_factory=CameraConfig)
    orb: OrbConfig = Field(default_factory=OrbConfig)
    tracking: TrackingConfig = Field(default_factory=TrackingConfig)
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    runtime: RuntimeConfig = Field(default_factory=RuntimeConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    dynamic: DynamicConfig = Field(default_factory=DynamicConfig)
    loop: LoopConfig = Field(default_factory=LoopConfig)
    export: MapExportConfig = Field(default_factory=MapExportConfig)
    seed: int = Field(0, ge=0, le=2**32 - 1)   # numpy's and OpenCV's seeds are 32-bit (OpenCV's RANSAC ignores it)
    max_association_dt: float = Field(0.02, gt=0)
    """Largest time difference (s) between an RGB and a depth image paired into one frame."""

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump()

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --- layers ---------------------------------------------------------------------------------------


class Layer(NamedTuple):
    """One source of values: a nested mapping (as in a YAML file) and the name errors give it."""

    source: str
    data: dict


def resolve_config_path(name_or_path: str | Path) -> Path:
    """A path to a YAML file, or the name of a preset in configs/ (``tum_fr1`` → configs/tum_fr1.yaml)."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        return path
    preset = CONFIG_DIR / f"{name_or_path}.yaml"
    if not preset.is_file():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"no config file or preset named '{name_or_path}' (presets: {', '.join(known)})")
    return preset


def yaml_layer(path: str | Path) -> Layer:
    """The layer of a YAML file or preset name; an empty file is an empty layer."""
    path = resolve_config_path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of config sections, got "
                          f"{type(data).__name__}")
    return Layer(str(path), data)


def overrides_layer(overrides: dict[str, Any], source: str = "<overrides>") -> Layer:
    """The layer of dotted-key values ({'tracking.match_ratio': 0.8, ...})."""
    nested: dict[str, Any] = {}
    for dotted, value in overrides.items():
        node = nested
        *parents, leaf = str(dotted).split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{source}: '{dotted}' conflicts with another override")
        if isinstance(node.get(leaf), dict):
            raise ConfigError(f"{source}: '{dotted}' conflicts with another override")
        node[leaf] = value
    return Layer(source, nested)


def _merge(base: dict, data: dict, layer: tuple[int, str], provenance: dict, prefix: str = "") -> None:
    """Overlay ``data`` onto ``base`` in place, recording which layer set each key."""
    for key, value in data.items():
        key = str(key)
        dotted = prefix + key
        current = base.get(key)
        if isinstance(current, dict):
            # A section replaced by a scalar would hide the section's other keys: say so now, naming
            # this layer, rather than after a later layer happens to restore it.
            if not isinstance(value, dict):
                raise ConfigError(f"{layer[1]}: '{dotted}' must be a mapping of keys (a config section), "
                                  f"got {type(value).__name__} {value!r}")
            _merge(current, value, layer, provenance, dotted + ".")
        else:
            base[key] = copy.deepcopy(value)
            provenance[dotted] = layer


def build_config(layers: Sequence[Layer], base: Optional[SlamConfig] = None) -> SlamConfig:
    """``base`` (default: the defaults), then each layer in order, merged as dicts and validated once.
    An error names the layer that last set the offending key (for a rule between keys, the last layer
    that set any of them)."""
    merged = (base or SlamConfig()).to_dict()
    provenance: dict[str, tuple[int, str]] = {}
    for index, layer in enumerate(layers):
        _merge(merged, layer.data, (index, layer.source), provenance)
    default = layers[-1].source if layers else DEFAULTS_SOURCE
    return _validated(merged, default, provenance)


def _validated(data: dict, default_source: str, provenance: Provenance) -> SlamConfig:
    try:
        return SlamConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, default_source, provenance, SlamConfig)) from None


def _update_in_place(config: SlamConfig, new: SlamConfig) -> SlamConfig:
    # The callers of apply_* hold on to their config object; the new values are already validated.
    config.__dict__.update(new.__dict__)
    return config


# --- the public functions ---------------------------------------------------------------------------


def validate(config: SlamConfig, source: str = "<config>") -> SlamConfig:
    """Check a config again (lists edited in place escape assignment checks); errors name ``source``."""
    _validated(config.to_dict(), source, {})
    return config


def apply_yaml(config: SlamConfig, path: str | Path) -> SlamConfig:
    """Overlay one YAML file onto ``config`` in place and validate the result."""
    return _update_in_place(config, build_config([yaml_layer(path)], base=config))


def apply_overrides(config: SlamConfig, overrides: dict[str, Any], source: str = "<overrides>") -> SlamConfig:
    """Overlay dotted-key values ({'tracking.match_ratio': 0.8, ...}) in place and validate."""
    return _update_in_place(config, build_config([overrides_layer(overrides, source)], base=config))


def load_config(*paths: str | Path, overrides: Optional[dict[str, Any]] = None) -> SlamConfig:
    """Defaults, then each file in order, then ``overrides`` ({'tracking.match_ratio': 0.8, ...}),
    validated once."""
    layers = [yaml_layer(path) for path in paths]
    if overrides:
        layers.append(overrides_layer(overrides))
    return build_config(layers)


def default_config_yaml() -> str:
    return SlamConfig().to_yaml()


def config_schema() -> dict[str, Any]:
    """JSON schema of a config file (every key optional), for editors: e.g. the YAML language server
    reads it from a ``# yaml-language-server: $schema=<file>`` line at the top of a YAML file."""
    schema = SlamConfig.model_json_schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema, "title": "dynslam configuration"}
