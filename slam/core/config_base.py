"""The base of every config section and the error it raises.

Every section is a pydantic model that forbids unknown keys, validates assignments and is strict about
types: a quoted number, a float for a count or ``1`` for a flag is a mistake in a YAML file, not a value
to coerce (only an integer where a float is expected is accepted, as YAML writes ``500`` for ``500.0``).
NaN and infinity are refused everywhere: no parameter is meaningful at either.

Rules between fields raise :func:`slam.core.config_errors.rule_error`, which names the keys involved
so that the loader can say which file set them and print their full dotted names.
"""
from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from slam.core.config_errors import format_validation_error, rule_error
from slam.core.errors import DynslamError

__all__ = ["ConfigError", "ConfigSection", "rule_error"]


class ConfigError(DynslamError, ValueError):
    """A config file or value is wrong; the message names the file and the key."""


class ConfigSection(BaseModel):
    """A config section: typed fields, each limit beside its field, attribute access as a dataclass."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, strict=True, allow_inf_nan=False,
                              use_attribute_docstrings=True)

    def __setattr__(self, name: str, value: Any) -> None:
        # An assignment in Python (``cfg.dynamic.cpr.voxel_size = -1``) fails with the same message as
        # the same value in a YAML file, as a ConfigError.
        try:
            super().__setattr__(name, value)
        except ValidationError as exc:
            raise ConfigError(format_validation_error(exc, type(self).__name__, root=type(self))) from None
