"""Every limit of the typed config, rules between keys, layers merged before validation, error messages
(file + dotted key, suggestions for unknown keys) and the JSON schema of ``dynslam config --schema``."""
from __future__ import annotations

import json
import typing
from pathlib import Path
from typing import Any, Iterator

import pytest
import yaml
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from slam.cli import main, resolve_run_config
from slam.core.config import (CONFIG_DIR, ConfigError, SlamConfig, build_config, config_schema, load_config,
                              overrides_layer, yaml_layer)

# Lists whose items need no range: distortion coefficients may take any finite value (NaN/inf are refused).
UNBOUNDED = {"camera.distortion"}


def fields(model: type[BaseModel] = SlamConfig, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, pydantic FieldInfo) of every parameter."""
    for name, info in model.model_fields.items():
        if isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel):
            yield from fields(info.annotation, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", info


def bounds(info) -> dict[str, float]:
    found = {}
    for limit in info.metadata:
        for name in ("gt", "ge", "lt", "le"):
            if getattr(limit, name, None) is not None:
                found[name] = getattr(limit, name)
    return found


NUMERIC = [(key, info) for key, info in fields() if info.annotation in (int, float)]


def bad_values(key: str, info) -> Iterator[Any]:
    """Values just outside each limit of a field."""
    step = 1 if info.annotation is int else 0.01
    for name, limit in bounds(info).items():
        yield {"gt": limit, "ge": limit - step, "lt": limit, "le": limit + step}[name]


RANGE_CASES = [pytest.param(key, value, id=f"{key}={value}") for key, info in NUMERIC for value in bad_values(key, info)]


def nested(dotted: str, value: Any) -> dict:
    *parents, leaf = dotted.split(".")
    out: dict = {leaf: value}
    for part in reversed(parents):
        out = {part: out}
    return out


def write(tmp_path: Path, data: Any, name: str = "user.yaml") -> Path:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def error_of(*paths: Path, **kwargs) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(*paths, **kwargs)
    return str(info.value)


# --- every limit ------------------------------------------------------------------------------------


def test_every_numeric_parameter_has_a_range():
    assert len(NUMERIC) > 150
    unbounded = [key for key, info in NUMERIC if not bounds(info)]
    assert not unbounded, f"parameters without a range: {unbounded}"
    lists = {key: info for key, info in fields() if typing.get_origin(info.annotation) is list}
    assert set(lists) >= UNBOUNDED | {"dynamic.methods", "dynamic.classes.dynamic"}
    for key, info in lists.items():   # class ids are bounded, names chosen from a Literal
        (item,) = typing.get_args(info.annotation)
        if key not in UNBOUNDED:
            assert typing.get_origin(item) is typing.Literal or bounds(FieldInfo.from_annotation(item)), key


@pytest.mark.parametrize("key, value", RANGE_CASES)
def test_value_outside_its_range_names_file_and_key(tmp_path, key, value):
    path = write(tmp_path, nested(key, value))
    message = error_of(path)
    assert message.startswith(f"{path}: '{key}' must be"), message
    assert repr(value) in message


@pytest.mark.parametrize("key, value", [pytest.param(k, v, id=k) for k, v in [
    ("dynamic.cpr.voxel_size", 0.0), ("loop.min_inliers", 3), ("dynamic.flow_epipolar.prob_clamp", 0.5),
    ("tracking.match_ratio", 1.5), ("orb.scale_factor", 1.0)]])
def test_the_same_limits_hold_for_set_overrides_and_assignments(key, value):
    with pytest.raises(ConfigError, match=f"--set: '{key}' must be"):
        build_config([overrides_layer({key: value}, "--set")])
    config = SlamConfig()
    *parents, leaf = key.split(".")
    section = config
    for part in parents:
        section = getattr(section, part)
    before = getattr(section, leaf)
    with pytest.raises(ConfigError, match=f"'{leaf}' must be"):
        setattr(section, leaf, value)
    assert getattr(section, leaf) == before


def test_the_brief_example_message(tmp_path):
    path = write(tmp_path, "dynamic:\n  cpr:\n    voxel_size: -1\n", "x.yaml")
    assert error_of(path) == f"{path}: 'dynamic.cpr.voxel_size' must be > 0, got -1"


def test_two_sided_ranges_are_given_whole(tmp_path):
    message = error_of(write(tmp_path, "tracking:\n  match_ratio: 1.5\n"))
    assert "'tracking.match_ratio' must be within (0, 1], got 1.5" in message


@pytest.mark.parametrize("text, expected", [
    ("dynamic:\n  methods: [cpr, yolo]\n", "'dynamic.methods' item [1] must be one of 'cpr', 'box_depth'"),
    ("dynamic:\n  fusion: mean\n", "'dynamic.fusion' must be one of 'single', 'max' or 'noisy_or', got 'mean'"),
    ("dynamic:\n  detector:\n    model: yolov8\n", "'dynamic.detector.model' must be one of 'yolox_nano' or 'nanodet'"),
    ("dynamic:\n  depth_sdf:\n    combine: all\n", "'dynamic.depth_sdf.combine' must be one of 'union' or 'best'"),
    ("loop:\n  kernel: tukey\n", "'loop.kernel' must be one of 'cauchy', 'huber' or 'none', got 'tukey'"),
    ("dynamic:\n  classes:\n    dynamic: [0, 80]\n", "'dynamic.classes.dynamic' item [1] must be <= 79, got 80"),
])
def test_choices_name_the_valid_ones(tmp_path, text, expected):
    path = write(tmp_path, text)
    assert f"{path}: {expected}" in error_of(path)


# --- rules between keys -------------------------------------------------------------------------------


@pytest.mark.parametrize("overrides, expected", [
    ({"camera.min_depth": 9.0}, "'camera.min_depth' (9.0) must be below 'camera.max_depth' (8.0)"),
    ({"camera.cx": 700.0}, "the principal point ('camera.cx' 700.0, 'camera.cy' 239.5) must lie inside the image"),
    ({"camera.distortion": [0.1, 0.2, 0.0]}, "'camera.distortion' needs 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got 3"),
    ({"tracking.strict_descriptor_distance": 120}, "'tracking.strict_descriptor_distance' (120) must not exceed "
                                                   "'tracking.max_descriptor_distance' (100)"),
    ({"keyframes.min_new_landmarks": 700}, "'keyframes.min_new_landmarks' (700) must not exceed"),
    ({"export.truncation": 0.04}, "'export.truncation' (0.04) must be at least twice 'export.voxel_size' (0.025): "
                                  "thinner bands leave holes"),
    ({"dynamic.classes.high_passive": [0]}, "class id(s) [0] are in both 'dynamic.classes.dynamic' and "
                                            "'dynamic.classes.high_passive'"),
    ({"dynamic.classes.low_passive_prob": 0.9}, "'dynamic.classes.low_passive_prob' (0.9) must not exceed"),
    ({"dynamic.cpr.icp_intensity_iterations": 7}, "'dynamic.cpr.icp_intensity_iterations' (7) must not exceed "
                                                  "'dynamic.cpr.icp_iterations' (6)"),
    ({"dynamic.flow_epipolar.likelihood_static": 0.95}, "'dynamic.flow_epipolar.likelihood_static' (0.95) must not"),
    ({"dynamic.methods": ["cpr", "cpr"]}, "'dynamic.methods' lists a method twice"),
    ({"dynamic.methods": ["cpr", "box_depth"], "dynamic.fusion": "single"},
     "'dynamic.fusion' is 'single' but 2 methods are enabled in 'dynamic.methods'"),
    ({"dynamic.methods": ["box_depth"], "dynamic.box_depth.k_passive": 3.0},
     "'dynamic.box_depth.k_passive' (3.0) times 'dynamic.classes.low_passive_prob' (0.25) must exceed 1"),
])
def test_rules_between_keys_say_why(overrides, expected):
    with pytest.raises(ConfigError) as info:
        build_config([overrides_layer(overrides, "--set")])
    assert str(info.value) == f"--set: {expected}" or str(info.value).startswith(f"--set: {expected}"), info.value


def test_k_passive_is_only_checked_when_box_depth_runs():
    config = load_config(overrides={"dynamic.box_depth.k_passive": 3.0, "dynamic.methods": ["cpr"]})
    assert config.dynamic.box_depth.k_passive == 3.0


# --- layers merged first, validated once ----------------------------------------------------------------


def test_rule_satisfied_only_after_the_second_layer_passes(tmp_path):
    coarse = write(tmp_path, "export:\n  voxel_size: 0.1\n", "coarse.yaml")     # truncation 0.1 < 2 * 0.1
    wide = write(tmp_path, "export:\n  truncation: 0.3\n", "wide.yaml")
    config = load_config(coarse, wide)
    assert (config.export.voxel_size, config.export.truncation) == (0.1, 0.3)
    assert error_of(coarse).startswith(f"{coarse}: 'export.truncation' (0.1) must be at least twice")
    # ... and the same through the command line, each file with -c.
    assert main(["config", "-c", str(coarse), "-c", str(wide), "-q"]) == 0


def test_a_rule_broken_by_a_later_layer_names_that_layer(tmp_path):
    first = write(tmp_path, "export:\n  truncation: 0.3\n", "first.yaml")
    second = write(tmp_path, "export:\n  voxel_size: 0.2\n", "second.yaml")
    assert error_of(first, second).startswith(f"{second}: 'export.truncation' (0.3) must be at least twice")
    message = error_of(first, overrides={"export.voxel_size": 0.2})
    assert message.startswith("<overrides>: 'export.truncation'")


def test_each_error_names_the_layer_that_set_its_key(tmp_path):
    preset = write(tmp_path, "orb:\n  n_levels: 0\n", "preset.yaml")
    user = write(tmp_path, "tracking:\n  chi2_mono: -1.0\n", "user.yaml")
    lines = error_of(preset, user, overrides={"seed": -3}).splitlines()
    assert lines == [f"{preset}: 'orb.n_levels' must be >= 1, got 0",
                     f"{user}: 'tracking.chi2_mono' must be > 0, got -1.0",
                     "<overrides>: 'seed' must be within [0, 4294967295], got -3"]


def test_dataset_camera_file_is_a_layer_under_the_users_files(tmp_path):
    """A camera.yaml with a principal point outside the default 640 px width is fine once the user's
    file gives the real width, and a bad value in it is reported as the camera file's."""
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "camera.yaml").write_text("fx: 600.0\nfy: 600.0\ncx: 700.0\ncy: 360.0\n")
    with pytest.raises(ConfigError, match=rf"^{seq / 'camera.yaml'}: the principal point"):
        resolve_run_config(seq, [], {})
    wide = write(tmp_path, "camera:\n  width: 1280\n  height: 720\n", "wide.yaml")
    config = resolve_run_config(seq, [str(wide)], {})
    assert (config.camera.cx, config.camera.width) == (700.0, 1280)
    (seq / "camera.yaml").write_text("fx: -600.0\nfy: 600.0\ncx: 300.0\ncy: 200.0\n")
    with pytest.raises(ConfigError, match=rf"^{seq / 'camera.yaml'}: 'camera.fx' must be > 0, got -600.0$"):
        resolve_run_config(seq, [], {"tracking.match_ratio": 0.7})


def test_a_section_replaced_by_a_scalar_is_reported_by_its_layer(tmp_path):
    good = write(tmp_path, "camera:\n  fx: 500.0\n", "good.yaml")
    bad = write(tmp_path, "camera: 5\n", "bad.yaml")
    assert error_of(good, bad) == f"{bad}: 'camera' must be a mapping of keys (a config section), got int 5"


def test_layers_do_not_change_the_defaults_or_each_other(tmp_path):
    user = write(tmp_path, "camera:\n  distortion: [0.1, 0.0, 0.0, 0.0]\n")
    layer = yaml_layer(user)
    load_config(user).camera.distortion.append(0.0)
    assert layer.data == {"camera": {"distortion": [0.1, 0.0, 0.0, 0.0]}}
    assert load_config(user).camera.distortion == [0.1, 0.0, 0.0, 0.0]
    assert SlamConfig().camera.distortion == [0.0] * 5


# --- unknown keys --------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, unknown, suggestion", [
    ("tracking:\n  match_ratoi: 0.7\n", "tracking.match_ratoi", "tracking.match_ratio"),
    ("trackin:\n  match_ratio: 0.7\n", "trackin", "tracking"),
    ("orb:\n  voxel_size: 0.1\n", "orb.voxel_size", "dynamic.cpr.voxel_size"),        # right name, wrong section
    ("flow_epipolar:\n  grid: 8\n", "flow_epipolar", "dynamic.flow_epipolar"),
    ("dynamic:\n  cpr:\n    voxelsize: 0.1\n", "dynamic.cpr.voxelsize", "dynamic.cpr.voxel_size"),
])
def test_unknown_key_suggests_the_closest_valid_one(tmp_path, text, unknown, suggestion):
    path = write(tmp_path, text)
    assert error_of(path) == f"{path}: unknown key '{unknown}' (did you mean '{suggestion}'?)"


def test_unknown_key_without_a_close_one_lists_the_section(tmp_path):
    path = write(tmp_path, "loop:\n  frobnicate: 1\n")
    message = error_of(path)
    assert message.startswith(f"{path}: unknown key 'loop.frobnicate' (valid keys in 'loop': enabled, ")


def test_cli_prints_config_errors_without_traceback_and_exits_2(tmp_path, capsys):
    path = write(tmp_path, "dynamic:\n  cpr:\n    voxel_size: -1\n  fusion: mean\n")
    assert main(["config", "-c", str(path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.startswith(f"dynslam config: error: {path}: 'dynamic.fusion' must be one of")
    assert f"{path}: 'dynamic.cpr.voxel_size' must be > 0, got -1" in err
    assert main(["config", "--set", "orb.n_levels=2.5"]) == 2
    assert "--set: 'orb.n_levels' expected an integer, got 2.5 (a number)" in capsys.readouterr().err


# --- presets and schema ------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
def test_every_preset_validates_alone_and_with_each_camera(preset):
    config = load_config(preset)
    assert config == SlamConfig.model_validate(config.to_dict())
    for camera in ("tum_fr1", "bonn"):
        load_config(camera, preset)


def schema_property(schema: dict, dotted: str) -> dict:
    node = schema
    for part in dotted.split("."):
        if "$ref" in node:
            node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
        node = node["properties"][part]
    return node


def test_schema_lists_every_key_with_its_limits(capsys):
    assert main(["config", "--schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema == json.loads(json.dumps(config_schema()))
    voxel = schema_property(schema, "dynamic.cpr.voxel_size")
    assert (voxel["type"], voxel["exclusiveMinimum"], voxel["default"]) == ("number", 0, 0.05)
    match_ratio = schema_property(schema, "tracking.match_ratio")
    assert (match_ratio["exclusiveMinimum"], match_ratio["maximum"]) == (0, 1)
    assert schema_property(schema, "dynamic.fusion")["enum"] == ["single", "max", "noisy_or"]
    assert "virtual stereo baseline" in schema_property(schema, "camera.bf")["description"]
    for key, _info in fields():
        schema_property(schema, key)   # every parameter is there
    assert schema["$defs"]["CprConfig"]["additionalProperties"] is False


def test_schema_accepts_the_presets_and_rejects_what_the_loader_rejects(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(config_schema())
    for path in CONFIG_DIR.glob("*.yaml"):
        assert not list(validator.iter_errors(yaml.safe_load(path.read_text()))), path
    assert not list(validator.iter_errors(SlamConfig().to_dict()))
    for bad in ({"dynamic": {"cpr": {"voxel_size": -1}}}, {"tracking": {"match_ratoi": 0.7}},
                {"dynamic": {"fusion": "mean"}}):
        assert list(validator.iter_errors(bad)), bad


def test_schema_with_config_options_is_a_usage_error(capsys):
    assert main(["config", "--schema", "-c", "tum_fr1"]) == 2
    assert "--schema" in capsys.readouterr().err
