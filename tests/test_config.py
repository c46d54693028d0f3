"""Tests for slam.core.config: defaults, presets, and error messages that name the file and the dotted key."""
from __future__ import annotations

from pathlib import Path

import pytest

from slam.core.config import (CONFIG_DIR, ConfigError, SlamConfig, apply_overrides, default_config_yaml,
                         load_config, resolve_config_path, validate)

# Published intrinsics (TUM RGB-D benchmark "camera calibration" page; Bonn RGB-D Dynamic Dataset page).
DOCUMENTED = {
    "tum_fr1": dict(fx=517.306408, fy=516.469215, cx=318.643040, cy=255.313989,
                    distortion=[0.262383, -0.953104, -0.005358, 0.002628, 1.163314]),
    "tum_fr2": dict(fx=520.908620, fy=521.007327, cx=325.141442, cy=249.701764,
                    distortion=[0.231222, -0.784899, -0.003257, -0.000105, 0.917205]),
    "tum_fr3": dict(fx=535.4, fy=539.2, cx=320.1, cy=247.6, distortion=[0.0, 0.0, 0.0, 0.0, 0.0]),
    "bonn": dict(fx=542.822841, fy=542.576870, cx=315.593520, cy=237.756098,
                 distortion=[0.039903, -0.099343, -0.000730, -0.000144, 0.0]),
}


def write(tmp_path: Path, text: str, name: str = "user.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def load_error(tmp_path: Path, text: str, name: str = "user.yaml") -> tuple[str, Path]:
    path = write(tmp_path, text, name)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    return str(info.value), path


# --- defaults and presets ------------------------------------------------------------------------


def test_defaults_validate_and_are_consistent():
    config = SlamConfig()
    assert validate(config) is config
    assert load_config() == SlamConfig()
    cam = config.camera
    assert cam.min_depth < cam.max_depth
    assert len(cam.distortion) == 5
    assert config.orb.scale_factor > 1.0
    assert 0.0 < config.tracking.match_ratio <= 1.0


def test_default_instances_do_not_share_mutable_state():
    a, b = SlamConfig(), SlamConfig()
    a.camera.distortion[0] = 0.5
    a.tracking.match_ratio = 0.1
    assert b.camera.distortion[0] == 0.0
    assert b.tracking.match_ratio == SlamConfig().tracking.match_ratio


@pytest.mark.parametrize("preset", sorted(DOCUMENTED))
def test_presets_load_with_documented_intrinsics(preset):
    config = load_config(preset)
    cam = config.camera
    expected = DOCUMENTED[preset]
    assert cam.name == preset
    for key in ("fx", "fy", "cx", "cy"):
        assert getattr(cam, key) == pytest.approx(expected[key], abs=1e-9), key
    assert cam.distortion == pytest.approx(expected["distortion"], abs=1e-9)
    assert (cam.width, cam.height) == (640, 480)
    assert cam.depth_scale == 5000.0
    # Presets are partial: every other section keeps its defaults.
    defaults = SlamConfig()
    assert config.orb == defaults.orb
    assert config.tracking == defaults.tracking
    assert config.keyframes == defaults.keyframes
    # Only the sensor's depth noise differs between camera presets (Bonn's Xtion is noisier).
    expected_backend = defaults.backend.model_copy(update={"depth_noise_coeff": 0.05 if preset == "bonn"
                                                           else defaults.backend.depth_noise_coeff})
    assert config.backend == expected_backend


def test_every_preset_file_is_covered_and_loads_by_path():
    found = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
    assert set(DOCUMENTED) <= set(found)
    for stem in found:
        by_path = load_config(CONFIG_DIR / f"{stem}.yaml")
        assert by_path == load_config(stem)
        assert resolve_config_path(stem) == CONFIG_DIR / f"{stem}.yaml"


def test_later_files_and_overrides_win(tmp_path):
    user = write(tmp_path, "camera:\n  fx: 600.0\ntracking:\n  match_ratio: 0.7\n")
    config = load_config("tum_fr1", user, overrides={"tracking.match_ratio": 0.9})
    assert config.camera.fx == 600.0
    assert config.camera.fy == pytest.approx(DOCUMENTED["tum_fr1"]["fy"])  # from the preset
    assert config.tracking.match_ratio == 0.9


# --- unknown keys, types ------------------------------------------------------------------------


def test_unknown_key_names_file_and_dotted_key(tmp_path):
    message, path = load_error(tmp_path, "tracking:\n  match_ratoi: 0.7\n", "typo.yaml")
    assert str(path) in message
    assert "tracking.match_ratoi" in message


def test_unknown_top_level_section_names_file_and_key(tmp_path):
    message, path = load_error(tmp_path, "trackin:\n  match_ratio: 0.7\n")
    assert str(path) in message
    assert "'trackin'" in message


def test_unknown_nested_key_does_not_partially_fall_back(tmp_path):
    message, _ = load_error(tmp_path, "camera:\n  fx: 500.0\n  focal: 500.0\n")
    assert "camera.focal" in message


@pytest.mark.parametrize("text, key", [
    ("camera:\n  fx: fast\n", "camera.fx"),                     # string for a float
    ("camera:\n  fx: '525.0'\n", "camera.fx"),                  # quoted number is a string
    ("orb:\n  n_features: 1000.5\n", "orb.n_features"),         # float for an int
    ("orb:\n  n_levels: 8.0\n", "orb.n_levels"),                # even an integral float
    ("tracking:\n  match_ratio: true\n", "tracking.match_ratio"),  # bool for a float
    ("orb:\n  n_features: yes\n", "orb.n_features"),            # YAML 1.1 bool for an int
    ("camera:\n  name: 5\n", "camera.name"),                    # int for a string
    ("output:\n  online_trajectory: 1\n", "output.online_trajectory"),  # int for a bool
    ("camera:\n  distortion: 0.1\n", "camera.distortion"),      # scalar for a list
    ("camera:\n  distortion: [0.1, x, 0, 0, 0]\n", "camera.distortion"),
    ("camera: 5\n", "camera"),                                  # scalar for a section
])
def test_wrong_type_names_key_and_file(tmp_path, text, key):
    message, path = load_error(tmp_path, text)
    assert str(path) in message
    assert f"'{key}'" in message


def test_bad_list_item_names_its_index(tmp_path):
    message, path = load_error(tmp_path, "camera:\n  distortion: [0.1, x, 0, 0, 0]\n")
    assert str(path) in message
    assert "camera.distortion" in message and "[1]" in message


def test_ints_are_accepted_for_floats(tmp_path):
    config = load_config(write(tmp_path, "camera:\n  fx: 500\n  distortion: [0, 0, 0, 0, 0]\n"))
    assert config.camera.fx == 500.0 and isinstance(config.camera.fx, float)
    assert all(isinstance(d, float) for d in config.camera.distortion)


def test_top_level_must_be_a_mapping(tmp_path):
    message, path = load_error(tmp_path, "- 1\n- 2\n")
    assert str(path) in message


# --- impossible values --------------------------------------------------------------------------


@pytest.mark.parametrize("text, key", [
    ("camera:\n  fx: -525.0\n", "camera.fx"),
    ("camera:\n  fy: 0.0\n", "camera.fy"),
    ("camera:\n  depth_scale: 0\n", "camera.depth_scale"),
    ("camera:\n  cx: -1.0\n", "camera.cx"),
    ("tracking:\n  match_ratio: 1.5\n", "tracking.match_ratio"),
    ("tracking:\n  dynamic_threshold: -0.1\n", "tracking.dynamic_threshold"),
    ("camera:\n  min_depth: 8.0\n  max_depth: 8.0\n", "camera.min_depth"),
    ("camera:\n  min_depth: 9.0\n", "camera.min_depth"),
    ("camera:\n  distortion: [0.1, 0.2, 0.0]\n", "camera.distortion"),
    ("camera:\n  distortion: [0.1, 0.2, 0.0, 0.0, 0.0, 0.0]\n", "camera.distortion"),
    ("orb:\n  scale_factor: 1.0\n", "orb.scale_factor"),
    ("orb:\n  scale_factor: 0.8\n", "orb.scale_factor"),
    ("orb:\n  n_features: 0\n", "orb.n_features"),
    ("seed: -1\n", "seed"),
])
def test_impossible_values_name_the_key(tmp_path, text, key):
    message, path = load_error(tmp_path, text)
    assert str(path) in message
    assert f"'{key}'" in message


def test_distortion_message_says_how_many(tmp_path):
    message, _ = load_error(tmp_path, "camera:\n  distortion: [0.1, 0.2, 0.0]\n")
    assert "4 or 5" in message and "3" in message


def test_four_distortion_coefficients_are_accepted(tmp_path):
    config = load_config(write(tmp_path, "camera:\n  distortion: [0.1, -0.2, 0.001, 0.002]\n"))
    assert config.camera.distortion == [0.1, -0.2, 0.001, 0.002]


def test_nan_principal_point_is_rejected(tmp_path):
    message, _ = load_error(tmp_path, "camera:\n  cx: .nan\n")
    assert "camera.cx" in message


def test_nan_focal_length_is_rejected(tmp_path):
    message, _ = load_error(tmp_path, "camera:\n  fx: .nan\n")
    assert "camera.fx" in message


# --- syntax, partial files, overrides -----------------------------------------------------------


def test_invalid_yaml_names_the_file(tmp_path):
    message, path = load_error(tmp_path, "camera:\n  fx: [525.0\n  fy: 525.0\n", "broken.yaml")
    assert str(path) in message
    assert "YAML" in message


def test_empty_file_keeps_defaults(tmp_path):
    assert load_config(write(tmp_path, "# nothing here\n")) == SlamConfig()


def test_partial_file_keeps_other_defaults(tmp_path):
    config = load_config(write(tmp_path, "tracking:\n  match_ratio: 0.6\norb:\n  n_features: 1500\n"))
    expected = SlamConfig()
    expected.tracking.match_ratio = 0.6
    expected.orb.n_features = 1500
    assert config == expected


def test_apply_overrides_with_dotted_keys():
    config = SlamConfig()
    out = apply_overrides(config, {"tracking.match_ratio": 0.6, "camera.fx": 600, "seed": 3,
                                   "keyframes.max_frames": 7})
    assert out is config
    assert config.tracking.match_ratio == 0.6
    assert config.camera.fx == 600.0 and isinstance(config.camera.fx, float)
    assert config.seed == 3
    assert config.keyframes.max_frames == 7
    assert config.camera.fy == SlamConfig().camera.fy


def test_load_config_overrides_argument():
    config = load_config("bonn", overrides={"orb.n_features": 800})
    assert config.orb.n_features == 800
    assert config.camera.fx == pytest.approx(DOCUMENTED["bonn"]["fx"])


@pytest.mark.parametrize("overrides, key", [
    ({"tracking.match_ratoi": 0.7}, "tracking.match_ratoi"),
    ({"tracking.match_ratio": 1.5}, "tracking.match_ratio"),
    ({"orb.n_features": 10.5}, "orb.n_features"),
    ({"camera.fx": "big"}, "camera.fx"),
])
def test_bad_overrides_name_the_key(overrides, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        apply_overrides(SlamConfig(), overrides)


def test_override_of_a_section_with_a_scalar_is_rejected():
    with pytest.raises(ConfigError, match="camera"):
        apply_overrides(SlamConfig(), {"camera": 5})


# --- round trip and resolution ------------------------------------------------------------------


def test_default_yaml_round_trips(tmp_path):
    path = write(tmp_path, default_config_yaml(), "defaults.yaml")
    assert load_config(path) == SlamConfig()


def test_modified_config_round_trips(tmp_path):
    config = load_config("tum_fr1", overrides={"tracking.match_ratio": 0.65, "orb.n_features": 1234})
    path = write(tmp_path, config.to_yaml(), "dump.yaml")
    assert load_config(path) == config
    assert load_config(path).model_dump() == config.to_dict()


def test_unknown_preset_lists_the_presets():
    with pytest.raises(ConfigError) as info:
        resolve_config_path("tum_fr9")
    message = str(info.value)
    assert "tum_fr9" in message
    for preset in DOCUMENTED:
        assert preset in message


def test_missing_yaml_file_is_reported(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="nope.yaml"):
        load_config(missing)


def test_seeded_reaches_every_random_choice_and_nothing_else():
    """Repeats of a run (tools/sweep.py --repeats, tools/hard_scenes.py --repeats, the hard-scene test's
    median) differ only in their seeds: OpenCV's RANSAC and each dynamic method that draws at random."""
    from slam.core.dynamic_config import METHOD_NAMES
    from slam.run.run_config import seeded

    config = seeded(SlamConfig(), 7)
    assert config.seed == 7
    drawing = {m for m in METHOD_NAMES if "seed" in type(getattr(config.dynamic, m)).model_fields}
    assert drawing == {"cpr", "flow_epipolar", "depth_sdf"}
    assert all(getattr(config.dynamic, m).seed == 7 for m in drawing)
    default = SlamConfig().model_dump()
    changed = seeded(SlamConfig(), 7).model_dump()
    for section in ("tracking", "backend", "keyframes", "loop"):
        assert changed[section] == default[section]
