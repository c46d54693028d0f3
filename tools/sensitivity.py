#!/usr/bin/env python3
"""Sensitivity of the default configuration's main weights and thresholds: each one at -50 % and +50 %
(one at a time, everything else at the default) on every sequence we have, in one table.

    python tools/sensitivity.py --jobs 2 -o /tmp/sens --detection-cache /tmp/detcache
    python tools/sensitivity.py --quick -o /tmp/sens_quick      # 40 frames of synthetic:people and fr1/xyz

Runs go through tools/sweep.py (one process per run; ``runs/``, ``sweep.csv/.md/.json`` in the output
folder), configuration by configuration so that a sweep cut short holds whole rows. ``sensitivity.md``
(+ ``.csv``, ``.json``) is rewritten after every run: a row per parameter × direction, a column per
sequence, each cell the ATE RMSE (median over repeats) and its ratio to the default run on that sequence
(> 1 = worse), marked when a tracked frame is more than 5 cm off or frames are lost. Base values are read
from the default configuration (``configs/dynamic_all.yaml`` on ``SlamConfig``); a value pushed out of
its schema range is clamped to it, and a cell whose clamped value equals the default is not run
("at bound").
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

import sweep

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
DEFAULT_PRESET = "dynamic_all"
DEFAULT_LABEL = "default"
FACTORS = (0.5, 1.5)              # the issue's ±50 %
MAX_FRAME_ERROR_M = 0.05          # the bar: no tracked frame more than 5 cm off
QUICK_FRAMES = 40                 # --quick: enough frames for the methods to have references and a keyframe
SEQUENCES = (str(DATA / "rgbd_bonn_crowd_first480"), str(DATA / "rgbd_dataset_freiburg1_rpy_first400"),
             str(DATA / "rgbd_dataset_freiburg1_xyz_first37"), str(DATA / "rgbd_dataset_freiburg1_desk_9frames"),
             "synthetic:people", "hard:close_pass", "hard:three_close", "hard:stand_walk", "hard:border")
QUICK_SEQUENCES = ("synthetic:people", str(DATA / "rgbd_dataset_freiburg1_xyz_first37"))
COLUMN_NAMES = {"rgbd_bonn_crowd_first480": "Bonn crowd", "rgbd_dataset_freiburg1_rpy_first400": "fr1/rpy",
                "rgbd_dataset_freiburg1_xyz_first37": "fr1/xyz", "rgbd_dataset_freiburg1_desk_9frames": "fr1/desk",
                "synthetic_people": "synthetic people"}   # the table's headers; others keep their run label


@dataclass(frozen=True)
class Parameter:
    key: str      # dotted config path
    reason: str   # why it is a main weight or threshold


PARAMETERS = (
    Parameter("dynamic.box_prior", "floor probability inside person boxes: between the map's and tracking's "
              "thresholds, it keeps people out of the map without removing a still person from tracking"),
    Parameter("dynamic.box_depth.weight", "trust in the method that segments a person on its own"),
    Parameter("dynamic.cpr.weight", "trust in CPR, kept low because its MAD threshold flags static sub-clouds"),
    Parameter("dynamic.flow_epipolar.weight", "trust in flow + epipolar, below 0.5 so a second method must agree"),
    Parameter("dynamic.depth_sdf.weight", "trust in depth-SDF, below 0.5 so a second method must agree"),
    Parameter("tracking.dynamic_threshold", "fused probability from which a feature is left out of tracking"),
    Parameter("backend.landmark_max_dynamic_prob", "fused probability above which a feature never becomes a landmark"),
    Parameter("dynamic.detector.score_threshold", "detector confidence from which a box counts: every method "
              "but CPR starts from the boxes"),
    Parameter("dynamic.box_depth.omega_pixel", "box_depth's threshold: the depth step (m) the flood fill of "
              "Fang et al.'s Algorithm 1 may cross between neighbours (alpha only scales Eq. 8's mean depth)"),
    Parameter("dynamic.flow_epipolar.epipolar_px", "flow_epipolar's threshold: distance (px) to the epipolar line "
              "from which a track is moving"),
    Parameter("dynamic.depth_sdf.base_threshold", "depth_sdf's threshold: the base inlier band (m) of the depth "
              "standard-deviation fit"),
    Parameter("dynamic.cpr.mad_scale", "CPR's MAD threshold multiplier (eps = mean + mad_scale * MAD, Eqs. 14-16; "
              "tau only acts with refine on, off by default)"),
    Parameter("backend.smoothing_sigma_acc", "the final trajectory smoother's acceleration sigma (m/s^2): how far a "
              "loosely tracked frame may leave its neighbours' motion"),
    Parameter("keyframes.revisit_ratio", "a keyframe due by time is not made while an older keyframe is nearer than "
              "this fraction of the way to the last one (bounds the map on revisits)"),
    Parameter("dynamic.still_max_move_m", "how far (m) a person's torso may move in still_window_s and still "
              "stand still (then only motion evidence counts on them; 0.15 m in 0.5 s: 0.3 m/s)"),
    Parameter("dynamic.motion_region_share", "share of a cpr region's flow tracks that must fail the epipolar test "
              "for the whole region to count as moving without a detection"),
)


@dataclass(frozen=True)
class Variation:
    """One parameter moved by one factor; ``value`` is clamped to the schema range."""

    key: str
    factor: float
    base: float
    value: float
    clamped: bool      # factor * base lay outside the range
    reason: str

    @property
    def at_bound(self) -> bool:
        """Clamping brought the value back to the default: nothing to run."""
        return self.value == self.base

    @property
    def direction(self) -> str:
        percent = round((self.factor - 1) * 100)
        return f"{'+' if percent > 0 else '−'}{abs(percent)} %"

    @property
    def label(self) -> str:
        """Configuration label (run folder names): e.g. ``dynamic.box_prior-50pct``."""
        return f"{self.key}{round((self.factor - 1) * 100):+d}pct"


def default_config():
    from slam.core.config import SlamConfig, apply_yaml

    return apply_yaml(SlamConfig(), DEFAULT_PRESET)


def _field(config, key: str) -> tuple[Any, Any]:
    """(section model, pydantic FieldInfo) of a dotted key."""
    *path, name = key.split(".")
    section = config
    for part in path:
        section = getattr(section, part)
    return section, type(section).model_fields[name]


def schema_range(config, key: str) -> tuple[float, float, bool, bool]:
    """(low, high, low_open, high_open) of a field from its ge/gt/le/lt constraints (±inf when none)."""
    low, high, low_open, high_open = -np.inf, np.inf, False, False
    for limit in _field(config, key)[1].metadata:
        for attr, is_low, is_open in (("ge", True, False), ("gt", True, True), ("le", False, False),
                                      ("lt", False, True)):
            bound = getattr(limit, attr, None)
            if bound is not None and is_low:
                low, low_open = float(bound), is_open
            elif bound is not None:
                high, high_open = float(bound), is_open
    return low, high, low_open, high_open


def variations(config=None, parameters: tuple[Parameter, ...] = PARAMETERS,
               factors: tuple[float, ...] = FACTORS) -> list[Variation]:
    """Each parameter × factor, its base read from ``config`` (default: the default configuration). An
    open bound (gt/lt) cannot be reached: a value beyond it stays at the base ("at bound")."""
    config = config if config is not None else default_config()
    grid = []
    for parameter in parameters:
        section, _ = _field(config, parameter.key)
        base = float(getattr(section, parameter.key.rsplit(".", 1)[1]))
        low, high, low_open, high_open = schema_range(config, parameter.key)
        for factor in factors:
            wanted = round(base * factor, 12)   # 0.3 * 1.5 is 0.44999999999999996 in binary
            value = min(max(wanted, low), high)
            if (low_open and value <= low) or (high_open and value >= high):
                value = base
            grid.append(Variation(parameter.key, factor, base, float(value), value != wanted, parameter.reason))
    return grid


def sweep_spec(grid: list[Variation], sequences: tuple[str, ...], repeats: int, max_frames: Optional[int],
               detection_cache: Optional[str]) -> sweep.SweepSpec:
    """The default plus every variation that changes a value (at-bound cells are not run)."""
    configs = [sweep.ConfigSpec(DEFAULT_LABEL, description="default")]
    configs += [sweep.ConfigSpec(v.label, overrides=((v.key, v.value),), description=f"{v.key} {v.direction}")
                for v in grid if not v.at_bound]
    return sweep.SweepSpec(sequences=list(sequences), configs=configs, presets=[DEFAULT_PRESET],
                           baseline=DEFAULT_LABEL, repeats=repeats, max_frames=max_frames,
                           detection_cache=detection_cache)


# ------------------------------------------------------------------------------------------ tables
def cell_stats(rows: list[dict], sequence: str, config: str) -> Optional[dict]:
    """Median ATE over the successful repeats, the worst frame error and the most frames lost; None if
    no run of this cell has finished yet."""
    runs = [r for r in rows if r["sequence"] == sequence and r["config"] == config]
    if not runs:
        return None
    ok = [r for r in runs if r["status"] == "ok" and r.get("ate_rmse_m") is not None]
    if not ok:
        return {"ate": None, "failed": len(runs), "error": runs[0].get("error", "")}
    return {"ate": float(np.median([r["ate_rmse_m"] for r in ok])), "failed": len(runs) - len(ok),
            "max_error": max((r["max_error_m"] for r in ok if r.get("max_error_m") is not None), default=None),
            "lost": max(int(r["frames"]) - int(r["tracked"]) for r in ok)}


def format_cell(stats: Optional[dict], default_ate: Optional[float]) -> str:
    """``0.0128 (1.05×)``, ``⚠7 cm`` when the worst tracked frame is > 5 cm off, ``L<n>`` when n frames were
    lost."""
    if stats is None:
        return "…"   # not run yet
    if stats["ate"] is None:
        return "failed"
    text = f"{stats['ate']:.4f}"
    if default_ate:
        text += f" ({stats['ate'] / default_ate:.2f}×)"
    if stats.get("max_error") is not None and stats["max_error"] > MAX_FRAME_ERROR_M:
        text += f" ⚠{stats['max_error'] * 100:.0f} cm"
    if stats.get("lost"):
        text += f" L{stats['lost']}"
    if stats.get("failed"):
        text += f" ({stats['failed']} failed)"
    return text


def _value(value: float) -> str:
    return f"{value:.4g}"


def sensitivity_rows(rows: list[dict], grid: list[Variation], sequences: list[str]) -> list[dict]:
    """One record per (default or variation) × sequence: the numbers behind each table cell."""
    records = []
    defaults = {s: cell_stats(rows, s, DEFAULT_LABEL) for s in sequences}
    entries: list[Optional[Variation]] = [None, *grid]
    for variation in entries:
        for sequence in sequences:
            label = DEFAULT_LABEL if variation is None else variation.label
            at_bound = variation is not None and variation.at_bound
            stats = None if at_bound else cell_stats(rows, sequence, label)
            default_ate = (defaults[sequence] or {}).get("ate")
            ate = None if stats is None else stats["ate"]
            records.append({
                "parameter": DEFAULT_LABEL if variation is None else variation.key,
                "direction": "" if variation is None else variation.direction,
                "base": None if variation is None else variation.base,
                "value": None if variation is None else variation.value,
                "clamped": bool(variation and variation.clamped), "at_bound": at_bound, "sequence": sequence,
                "ate_rmse_m": ate, "ratio_to_default": ate / default_ate if ate and default_ate else None,
                "max_error_m": None if stats is None else stats.get("max_error"),
                "lost_frames": None if stats is None else stats.get("lost"),
                "cell": "at bound" if at_bound else format_cell(stats, None if variation is None else default_ate)})
    return records


def markdown(records: list[dict], grid: list[Variation], sequences: list[str]) -> str:
    """The table (a row per default / variation, a column per sequence) and the parameters' reasons."""
    header = ["parameter", "value", *[COLUMN_NAMES.get(s, s.removeprefix("hard_")) for s in sequences],
              "worst ratio"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    by_row: dict[tuple[str, str], list[dict]] = {}
    for record in records:
        by_row.setdefault((record["parameter"], record["direction"]), []).append(record)
    for (parameter, direction), cells in by_row.items():
        first = cells[0]
        if parameter == DEFAULT_LABEL:
            name, value = "**default**", "—"
        else:
            name = f"`{parameter}` {direction}"
            value = f"{_value(first['base'])} → {_value(first['value'])}" + (" (clamped)" if first["clamped"] else "")
        ratios = [c["ratio_to_default"] for c in cells if c["ratio_to_default"] is not None]
        worst = f"{max(ratios):.2f}×" if ratios and parameter != DEFAULT_LABEL else "—"
        lines.append("| " + " | ".join([name, value, *[c["cell"] for c in cells], worst]) + " |")
    reasons = dict.fromkeys(f"- `{v.key}`: {v.reason}" for v in grid)
    legend = ("\nCells: ATE RMSE (m, median over repeats) and its ratio to the default run on that sequence "
              f"(> 1 = worse); ⚠ the worst tracked frame's error where it is more than "
              f"{MAX_FRAME_ERROR_M * 100:.0f} cm; L<n> n frames lost; at bound: the schema range clamps the value "
              "back to the default (not run); … not run yet. Worst ratio: the largest ratio over the sequences.\n\n")
    return "\n".join(lines) + "\n" + legend + "\n".join(reasons) + "\n"


def write_outputs(output: Path, rows: list[dict], grid: list[Variation], sequences: list[str],
                  command: str) -> None:
    from slam.core.atomic_io import write_text_atomic

    records = sensitivity_rows(rows, grid, sequences)
    write_text_atomic(output / "sensitivity.md", f"`{command}`\n\n" + markdown(records, grid, sequences))
    write_text_atomic(output / "sensitivity.csv", csv_text_records(records))
    write_text_atomic(output / "sensitivity.json", json.dumps(
        {"command": command, "variations": [asdict(v) for v in grid], "cells": records}, indent=2) + "\n")


def csv_text_records(records: list[dict]) -> str:
    import csv
    import io

    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(records[0]) if records else [], lineterminator="\n")
    writer.writeheader()
    writer.writerows(records)
    return out.getvalue()


# ---------------------------------------------------------------------------------------------- CLI
def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--output", "-o", type=Path, default=REPO / "results" / "sensitivity")
    parser.add_argument("--jobs", "-j", type=int, default=1, help="parallel run processes")
    parser.add_argument("--repeats", type=int, default=1, help="runs per cell (seeds 0..N-1)")
    parser.add_argument("--detection-cache", metavar="DIR", help="reuse detections across runs and sweeps")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_FRAMES} frames of {', '.join(Path(s).name for s in QUICK_SEQUENCES)} only")
    parser.add_argument("--timeout", type=float, help="seconds after which a run is killed and recorded as failed")
    parser.add_argument("--resume", action="store_true", help="keep the finished runs of an identical earlier sweep")
    parser.add_argument("--quiet", "-q", action="store_true", help="no per-run progress lines")
    parser.add_argument("--tables-only", action="store_true",
                        help="rewrite sensitivity.* from the runs already in --output (sweep.json), run nothing")
    parser.add_argument("--only", action="append", metavar="KEY",
                        help="vary only this parameter (repeatable; default: all of them)")
    args = parser.parse_args(argv)
    parameters = PARAMETERS
    if args.only:
        unknown = sorted(set(args.only) - {p.key for p in PARAMETERS})
        if unknown:
            parser.error(f"--only: unknown parameter(s) {', '.join(unknown)}; "
                         f"choose from {', '.join(p.key for p in PARAMETERS)}")
        parameters = tuple(p for p in PARAMETERS if p.key in args.only)
    grid = variations(parameters=parameters)
    sequences = QUICK_SEQUENCES if args.quick else SEQUENCES
    cache = str(Path(args.detection_cache).expanduser().resolve()) if args.detection_cache else None
    spec = sweep_spec(grid, sequences, args.repeats, QUICK_FRAMES if args.quick else None, cache)
    labels = [sweep.sequence_label(s) for s in sequences]
    command = "python tools/sensitivity.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.tables_only:   # e.g. after a sweep cut short: the table of the runs that finished
        previous = json.loads((args.output / "sensitivity.json").read_text())["command"]
        write_outputs(args.output, json.loads((args.output / "sweep.json").read_text())["runs"], grid, labels,
                      previous)
        print((args.output / "sensitivity.md").read_text(), end="")
        return 0
    try:
        rows = sweep.run_sweep(spec, args.output, args.jobs, args.timeout, args.quiet, args.resume,
                               configs_first=True,
                               on_rows=lambda done: write_outputs(args.output, done, grid, labels, command))
    except sweep.SweepError as exc:
        print(f"sensitivity: error: {exc}", file=sys.stderr)
        return 2
    write_outputs(args.output, rows, grid, labels, command)
    print((args.output / "sensitivity.md").read_text(), end="")
    print(f"sensitivity: {sum(r['status'] == 'ok' for r in rows)}/{len(rows)} runs ok; tables in {args.output}",
          file=sys.stderr)
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
