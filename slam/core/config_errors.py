"""pydantic's validation errors as one line per problem: the file that set the value and its dotted key.

``configs/x.yaml: 'dynamic.cpr.voxel_size' must be > 0, got -1``. The loader merges every layer (defaults,
camera and preset files, ``--set``) before it validates once, so each line looks up which layer last
set the key (its *provenance*) to name the right file. An unknown key gets the closest valid one.
"""
from __future__ import annotations

import difflib
from typing import Any, Iterator, Mapping, Optional

from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticCustomError

RULE_ERROR = "config_rule"   # pydantic error type of the rules between fields (rule_error)

# dotted key -> (index of the layer that set it, the layer's name); later layers have larger indices.
Provenance = Mapping[str, tuple[int, str]]

_TYPE_NAMES = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false",
               "list": "a list", "dict": "a mapping", "NoneType": "nothing (an empty value)"}
_EXPECTED = {"int_type": "an integer", "int_from_float": "an integer", "int_parsing": "an integer",
             "float_type": "a number", "float_parsing": "a number", "string_type": "a string",
             "bool_type": "true or false", "bool_parsing": "true or false", "list_type": "a list",
             "model_type": "a mapping of keys (a config section)", "dict_type": "a mapping",
             "model_attributes_type": "a mapping of keys (a config section)"}
_BOUNDS = {"greater_than": (">", "gt"), "greater_than_equal": (">=", "ge"), "less_than": ("<", "lt"),
           "less_than_equal": ("<=", "le")}
MAX_LINES = 10   # a file with many mistakes: the first ones are enough to start fixing it


def rule_error(message: str, *keys: str) -> PydanticCustomError:
    """The error of a rule between fields. ``message`` quotes the keys relative to the section
    (``'truncation'``); the loader prefixes them with the section's path and names the file that set
    the last of ``keys``."""
    return PydanticCustomError(RULE_ERROR, message, {"keys": ",".join(keys)})


def format_validation_error(exc: ValidationError, default_source: str, provenance: Optional[Provenance] = None,
                            root: Optional[type[BaseModel]] = None) -> str:
    """One line per error (at most MAX_LINES), each naming its source and dotted key. ``root`` is the
    model validated (for suggestions); ``provenance`` says which layer set which key."""
    lines = [_line(err, default_source, provenance or {}, root) for err in exc.errors()]
    if len(lines) > MAX_LINES:
        lines = lines[:MAX_LINES] + [f"... and {len(lines) - MAX_LINES} more problem(s)"]
    return "\n".join(lines)


def source_of(keys: list[str], provenance: Provenance, default: str) -> str:
    """The layer that set the last of ``keys`` (a key set as part of a whole section counts too)."""
    best: Optional[tuple[int, str]] = None
    for key in keys:
        parts = key.split(".")
        for n in range(len(parts), 0, -1):
            hit = provenance.get(".".join(parts[:n]))
            if hit is not None:
                best = hit if best is None or hit[0] > best[0] else best
                break
    return best[1] if best else default


def _line(err: dict, default_source: str, provenance: Provenance, root: Optional[type[BaseModel]]) -> str:
    loc = err["loc"]
    keys = [str(p) for p in loc if not isinstance(p, int)]
    dotted = ".".join(keys)
    item = "".join(f"[{p}]" for p in loc if isinstance(p, int))
    kind, ctx, value = err["type"], err.get("ctx") or {}, err.get("input")
    if kind == RULE_ERROR and ctx.get("keys"):
        prefix = f"{dotted}." if dotted else ""
        involved = [prefix + k for k in ctx["keys"].split(",")]
        message = err["msg"]
        for key in ctx["keys"].split(","):
            message = message.replace(f"'{key}'", f"'{prefix}{key}'")
        return f"{source_of(involved, provenance, default_source)}: {message}"
    source = source_of([dotted], provenance, default_source)
    if kind == "extra_forbidden":
        return f"{source}: unknown key '{dotted}'{_suggestion(root, keys)}"
    where = f"'{dotted or 'top level'}'" + (f" item {item}" if item else "")
    interval = _interval(root, keys) if kind in _BOUNDS and not item else None
    if interval:
        return f"{source}: {where} must be within {interval}, got {value!r}"
    return f"{source}: {where} {_describe(kind, ctx, value, err['msg'])}"


def _interval(root: Optional[type[BaseModel]], keys: list[str]) -> Optional[str]:
    """'[0, 1]', '[0, 0.5)', ... for a field bounded on both sides (None otherwise): a message that
    gives the whole range saves a second try."""
    section = _section(root, keys[:-1])
    field = section.model_fields.get(keys[-1]) if section is not None else None
    if field is None:
        return None
    low = high = None
    for limit in field.metadata:
        for name, bracket in (("ge", "["), ("gt", "(")):
            if getattr(limit, name, None) is not None:
                low = f"{bracket}{_number(getattr(limit, name))}"
        for name, bracket in (("le", "]"), ("lt", ")")):
            if getattr(limit, name, None) is not None:
                high = f"{_number(getattr(limit, name))}{bracket}"
    return f"{low}, {high}" if low and high else None


def _describe(kind: str, ctx: dict, value: Any, fallback: str) -> str:
    if kind in _BOUNDS:
        op, name = _BOUNDS[kind]
        return f"must be {op} {_number(ctx[name])}, got {value!r}"
    if kind in _EXPECTED:
        return f"expected {_EXPECTED[kind]}, got {value!r} ({_type_name(value)})"
    if kind == "literal_error":
        return f"must be one of {ctx['expected']}, got {value!r}"
    if kind == "finite_number":
        return f"must be a finite number, got {value!r}"
    if kind == RULE_ERROR:
        return fallback
    return f"{fallback[0].lower()}{fallback[1:]}, got {value!r}"


def _number(bound: Any) -> str:
    """A bound as written beside its field: pydantic turns ``gt=0`` of a float field into 0.0."""
    return str(int(bound)) if isinstance(bound, float) and bound.is_integer() else repr(bound)


def _type_name(value: Any) -> str:
    return _TYPE_NAMES.get(type(value).__name__, type(value).__name__)


def _suggestion(root: Optional[type[BaseModel]], keys: list[str]) -> str:
    """' (did you mean ...?)': the same name in another section (put in the wrong one), else a close
    name in the same section, else a close name elsewhere; or the section's valid keys."""
    section = _section(root, keys[:-1])
    if section is None:
        return ""
    leaf, prefix = keys[-1], ".".join(keys[:-1] + [""])
    valid = list(section.model_fields)
    elsewhere: dict[str, str] = {}
    for name, key in _leaves(root):
        elsewhere.setdefault(name, key)
    if leaf in elsewhere:
        return f" (did you mean '{elsewhere[leaf]}'?)"
    close = difflib.get_close_matches(leaf, valid, n=1, cutoff=0.6)
    if close:
        return f" (did you mean '{prefix}{close[0]}'?)"
    close = difflib.get_close_matches(leaf, list(elsewhere), n=1, cutoff=0.8)
    if close:
        return f" (did you mean '{elsewhere[close[0]]}'?)"
    return f" (valid keys{' in ' + repr(prefix[:-1]) if prefix else ''}: {', '.join(valid)})"


def _section(root: Optional[type[BaseModel]], keys: list[str]) -> Optional[type[BaseModel]]:
    model = root
    for key in keys:
        field = model.model_fields.get(key) if model is not None else None
        annotation = field.annotation if field is not None else None
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return None
        model = annotation
    return model


def _leaves(model: type[BaseModel], prefix: str = "") -> Iterator[tuple[str, str]]:
    """(name, dotted key) of every parameter and section under ``model``, outer ones first."""
    for name, field in model.model_fields.items():
        yield name, f"{prefix}{name}"
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            yield from _leaves(annotation, f"{prefix}{name}.")
