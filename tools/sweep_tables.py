"""The tables of ``tools/sweep.py``: a CSV row per run, a Markdown row per sequence × configuration.

Rows are the sweep's per-run dicts (``sweep.csv`` columns; failed runs have ``status`` "failed" and
their ``error``). Statistics are over the successful repeats: ATE RMSE median and min – max, the
medians of the per-frame RPE (translation, rotation) and of the runs' median ms/frame, the worst
tracked count, and the baseline configuration's ATE median divided by each configuration's.
"""
from __future__ import annotations

import csv
import io
from typing import Optional

import numpy as np

RUN_COLUMNS = ["sequence", "config", "repeat", "seed", "status", "error", "ate_rmse_m", "max_error_m", "rpe_trans_m",
               "rpe_rot_deg", "tracked", "frames", "keyframes", "median_ms", "mean_ms", "wall_s", "run_dir"]


def group_stats(rows: list[dict], spec) -> list[dict]:
    """One entry per sequence × configuration, in sweep order: medians and spread over the repeats."""
    groups = []
    for sequence in dict.fromkeys(r["sequence"] for r in rows):
        for config in spec.configs:
            runs = [r for r in rows if r["sequence"] == sequence and r["config"] == config.label]
            if not runs:
                continue
            ok = [r for r in runs if r["status"] == "ok"]
            ates = [r["ate_rmse_m"] for r in ok if r.get("ate_rmse_m") is not None]
            groups.append({
                "sequence": sequence, "config": config, "runs": len(runs), "failed": len(runs) - len(ok),
                "errors": [r["error"] for r in runs if r["status"] != "ok"],
                "ate_median": _median(ates), "ate_min": min(ates, default=None), "ate_max": max(ates, default=None),
                "rpe_trans": _median([r["rpe_trans_m"] for r in ok if r.get("rpe_trans_m") is not None]),
                "rpe_rot": _median([r["rpe_rot_deg"] for r in ok if r.get("rpe_rot_deg") is not None]),
                "tracked": min(((r["tracked"], r["frames"]) for r in ok), default=None),
                "median_ms": _median([r["median_ms"] for r in ok if r.get("median_ms") is not None])})
    return groups


def _median(values: list[float]) -> Optional[float]:
    return float(np.median(values)) if values else None


def markdown_table(rows: list[dict], spec) -> str:
    """A row per sequence × configuration (the sequence column only when there are several); ``spec``
    gives the configurations (``label``, ``description``) in table order and the ``baseline`` label."""
    groups = group_stats(rows, spec)
    several = len({g["sequence"] for g in groups}) > 1
    header = ["configuration", "ATE RMSE median (m)", "min – max", "RPE median (m, ° per frame)",
              "frames tracked (worst)", "ms/frame (median)", f"vs. {spec.baseline}", "runs"]
    header = ["sequence"] * several + header
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    base = {g["sequence"]: g["ate_median"] for g in groups if g["config"].label == spec.baseline}
    for g in groups:
        runs = str(g["runs"]) if not g["failed"] else f"{g['runs']} ({g['failed']} failed: {_short(g['errors'][0])})"
        cells = [g["config"].description or f"`{g['config'].label}`", _num(g["ate_median"], 4),
                 "–" if g["ate_min"] is None else f"{g['ate_min']:.4f} – {g['ate_max']:.4f}",
                 "–" if g["rpe_trans"] is None else f"{g['rpe_trans']:.4f}, {g['rpe_rot']:.3f}",
                 "–" if g["tracked"] is None else f"{g['tracked'][0]}/{g['tracked'][1]}",
                 _num(g["median_ms"], 1), _ratio(base.get(g["sequence"]), g["ate_median"]), runs.replace("|", "\\|")]
        lines.append("| " + " | ".join([g["sequence"]] * several + cells) + " |")
    return "\n".join(lines) + "\n"


def _short(text: str, limit: int = 80) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _num(value: Optional[float], digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _ratio(baseline: Optional[float], value: Optional[float]) -> str:
    """How many times smaller this ATE is than the baseline's (README style: 21×, 3.8×)."""
    if baseline is None or not value:
        return "–"
    ratio = baseline / value
    return f"{ratio:.0f}×" if ratio >= 10 else f"{ratio:.1f}×"


def csv_text(rows: list[dict]) -> str:
    """RUN_COLUMNS, then the per-module median milliseconds (``ms_<module>``) any run reported."""
    modules = sorted({key for row in rows for key in row if key.startswith("ms_")})
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=RUN_COLUMNS + modules, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()
