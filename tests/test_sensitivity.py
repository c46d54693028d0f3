"""tools/sensitivity.py: the ±50 % grid (bases read from the default configuration, schema clamping,
labels), the sweep it hands to tools/sweep.py, and its table from fabricated runs; one small real sweep
(slow)."""
from __future__ import annotations

import contextlib
import io
import json

import pytest

from conftest import load_tool
from slam.core.config import apply_overrides, apply_yaml

sensitivity = load_tool("sensitivity")


def by_label(grid) -> dict:
    return {v.label: v for v in grid}


def test_bases_are_read_from_the_default_configuration():
    config = sensitivity.default_config()
    grid = sensitivity.variations(config)
    assert len(grid) == 2 * len(sensitivity.PARAMETERS)
    for variation in grid:
        section = config
        for part in variation.key.split("."):
            section = getattr(section, part)
        assert variation.base == section
    # A different default moves the grid with it: nothing is hard-coded.
    apply_overrides(config, {"dynamic.box_prior": 0.4, "tracking.dynamic_threshold": 0.6})
    grid = by_label(sensitivity.variations(config))
    assert (grid["dynamic.box_prior-50pct"].value, grid["dynamic.box_prior+50pct"].value) == (0.2, 0.6)
    assert grid["tracking.dynamic_threshold+50pct"].value == 0.9


def test_each_parameter_has_a_reason_and_the_camera_presets_leave_them_alone():
    assert all(len(p.reason) > 20 for p in sensitivity.PARAMETERS)
    assert len({p.key for p in sensitivity.PARAMETERS}) == len(sensitivity.PARAMETERS)
    default = sensitivity.variations()
    for preset in ("bonn", "tum_fr1"):   # the presets the real sequences' names select
        assert sensitivity.variations(apply_yaml(sensitivity.default_config(), preset)) == default


def test_values_outside_the_schema_range_are_clamped_and_at_bound_cells_not_run():
    config = sensitivity.default_config()
    grid = by_label(sensitivity.variations(config))
    full = grid["dynamic.box_depth.weight+50pct"]   # 1.0 * 1.5 -> 1.0, the default again
    assert (full.value, full.clamped, full.at_bound) == (1.0, True, True)
    assert not grid["dynamic.box_depth.weight-50pct"].clamped
    apply_overrides(config, {"dynamic.cpr.weight": 0.8})
    clamped = by_label(sensitivity.variations(config))["dynamic.cpr.weight+50pct"]
    assert (clamped.value, clamped.clamped, clamped.at_bound) == (1.0, True, False)   # run at the bound
    # An open bound (mad_scale > 0) cannot be reached: the value stays at the default, not run.
    mad = sensitivity.Parameter("dynamic.cpr.mad_scale", "test")
    (zero,) = sensitivity.variations(config, (mad,), (0.0,))
    assert zero.at_bound and zero.clamped


def test_labels_directions_and_the_sweep_spec():
    grid = sensitivity.variations()
    labels = by_label(grid)
    assert labels["dynamic.box_prior-50pct"].direction == "−50 %"
    assert labels["dynamic.box_prior+50pct"].direction == "+50 %"
    assert labels["dynamic.box_prior+50pct"].value == 0.45   # rounded: no 0.44999999999999996 in a config
    spec = sensitivity.sweep_spec(grid, ("synthetic:people",), repeats=2, max_frames=30, detection_cache=None)
    assert spec.configs[0].label == "default" and spec.baseline == "default" and spec.presets == ["dynamic_all"]
    assert len(spec.configs) == 1 + len(grid) - 1   # box_depth.weight +50 % is at bound
    assert "dynamic.box_depth.weight+50pct" not in [c.label for c in spec.configs]
    assert dict(spec.configs[1].overrides) == {"dynamic.box_prior": 0.15}
    assert (spec.repeats, spec.max_frames) == (2, 30)


def fake_row(sequence: str, config: str, ate, repeat: int = 0, max_error=0.01, tracked=100, **extra) -> dict:
    row = {"sequence": sequence, "config": config, "repeat": repeat, "status": "ok", "error": "",
           "ate_rmse_m": ate, "max_error_m": max_error, "tracked": tracked, "frames": 100}
    row.update(extra)
    return row


def test_table_cells_ratios_markers_and_bounds():
    prior = sensitivity.Parameter("dynamic.box_prior", "reason one")
    weight = sensitivity.Parameter("dynamic.box_depth.weight", "reason two")
    grid = sensitivity.variations(None, (prior, weight))
    rows = [fake_row("a", "default", 0.01), fake_row("b", "default", 0.02),
            fake_row("a", "dynamic.box_prior-50pct", 0.02, max_error=0.07, tracked=97),
            fake_row("a", "dynamic.box_prior-50pct", 0.04, repeat=1),
            fake_row("b", "dynamic.box_prior-50pct", None, status="failed", error="boom"),
            fake_row("a", "dynamic.box_prior+50pct", 0.005),
            fake_row("a", "dynamic.box_depth.weight-50pct", 0.01)]
    records = sensitivity.sensitivity_rows(rows, grid, ["a", "b"])
    cells = {(r["parameter"], r["direction"], r["sequence"]): r for r in records}
    minus = cells[("dynamic.box_prior", "−50 %", "a")]
    assert minus["ate_rmse_m"] == pytest.approx(0.03) and minus["ratio_to_default"] == pytest.approx(3.0)
    assert minus["cell"] == "0.0300 (3.00×) ⚠7 cm L3"   # median of the repeats, worst frame, most frames lost
    assert cells[("dynamic.box_prior", "−50 %", "b")]["cell"] == "failed"
    assert cells[("dynamic.box_prior", "+50 %", "b")]["cell"] == "…"   # not run yet
    assert cells[("default", "", "a")]["cell"] == "0.0100"
    assert cells[("dynamic.box_depth.weight", "+50 %", "a")]["cell"] == "at bound"
    table = sensitivity.markdown(records, grid, ["a", "b"]).splitlines()
    assert table[0] == "| parameter | value | a | b | worst ratio |"   # unknown labels stay as they are
    assert table[2] == "| **default** | — | 0.0100 | 0.0200 | — |"
    assert table[3] == "| `dynamic.box_prior` −50 % | 0.3 → 0.15 | 0.0300 (3.00×) ⚠7 cm L3 | failed | 3.00× |"
    assert table[4] == "| `dynamic.box_prior` +50 % | 0.3 → 0.45 | 0.0050 (0.50×) | … | 0.50× |"
    assert table[6] == "| `dynamic.box_depth.weight` +50 % | 1 → 1 (clamped) | at bound | at bound | — |"
    assert "- `dynamic.box_prior`: reason one" in table and "- `dynamic.box_depth.weight`: reason two" in table


@pytest.mark.slow
def test_a_small_real_sweep_writes_the_tables(tmp_path):
    """The default and one variation, 20 frames of walking people and of a hard scene."""
    prior = sensitivity.Parameter("dynamic.box_prior", "reason")
    grid = sensitivity.variations(None, (prior,), (0.5,))
    sequences = ("synthetic:people", "hard:border")
    spec = sensitivity.sweep_spec(grid, sequences, repeats=1, max_frames=20, detection_cache=None)
    with contextlib.redirect_stderr(io.StringIO()):
        rows = sensitivity.sweep.run_sweep(spec, tmp_path, jobs=2, configs_first=True)
    assert [r["status"] for r in rows] == ["ok"] * 4
    labels = [sensitivity.sweep.sequence_label(s) for s in sequences]
    sensitivity.write_outputs(tmp_path, rows, grid, labels, "python tools/sensitivity.py test")
    cells = json.loads((tmp_path / "sensitivity.json").read_text())["cells"]
    assert [(c["parameter"], c["sequence"]) for c in cells] == [
        ("default", "synthetic_people"), ("default", "hard_border"),
        ("dynamic.box_prior", "synthetic_people"), ("dynamic.box_prior", "hard_border")]
    assert all(c["ate_rmse_m"] > 0 and c["max_error_m"] >= c["ate_rmse_m"] for c in cells)
    assert cells[2]["ratio_to_default"] == pytest.approx(cells[2]["ate_rmse_m"] / cells[0]["ate_rmse_m"])
    table = (tmp_path / "sensitivity.md").read_text()
    assert table.startswith("`python tools/sensitivity.py test`")
    assert "| parameter | value | synthetic people | border | worst ratio |" in table
