#!/usr/bin/env python3
"""Ablation of the dynamic front end: sequences × configurations × repeats, in parallel processes.

    python tools/ablation.py                                  # Bonn crowd: off, each method alone, fused
    python tools/ablation.py SEQ_DIR --configs none dynamic_all --repeats 3 --jobs 2

Each configuration is a preset name or YAML file (``none`` = dynamic handling off). Writes
``ablation.md`` and ``ablation.csv`` to ``--output`` with ATE RMSE (median, min, max over repeats)
and median / mean milliseconds per frame, and prints the Markdown table.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
DEFAULT_CONFIGS = ["none", "dynamic_cpr", "dynamic_box_depth", "dynamic_flow_epipolar", "dynamic_depth_sdf",
                   "dynamic_all"]


def run_one(job: tuple[str, str, int, str, list[str]]) -> dict:
    """One SLAM run in a worker process; returns its numbers (never raises: errors are recorded)."""
    sequence, config_name, repeat, output, overrides = job
    from slam.cli import _parse_overrides, resolve_run_config
    from slam.datasets import TumDataset
    from slam.pipeline import Pipeline

    seq = Path(sequence)
    files = [] if config_name == "none" else [config_name]
    try:
        config = resolve_run_config(seq, files, _parse_overrides(overrides))
        # Repeats differ only in their seeds: RANSAC's and every method's random choices.
        config.seed = repeat
        for method in ("cpr", "flow_epipolar", "depth_sdf"):
            getattr(config.dynamic, method).seed = repeat
        dataset = TumDataset(seq, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
        summary = Pipeline(dataset, config, Path(output) / f"{seq.name}__{Path(config_name).stem}__{repeat}").run()
    except Exception as exc:  # a failed run is a row in the table, not a crashed sweep
        return {"sequence": seq.name, "config": config_name, "repeat": repeat, "error": f"{type(exc).__name__}: {exc}"}
    timing = summary.timing_ms
    return {"sequence": seq.name, "config": config_name, "repeat": repeat, "ate": summary.ate_rmse_m,
            "tracked": summary.tracked, "frames": summary.frames,
            "median_ms": timing.get("total", {}).get("median_ms"), "mean_ms": timing.get("total", {}).get("mean_ms"),
            "dynamic_ms": timing.get("dynamic", {}).get("median_ms", 0.0)}


def table_rows(results: list[dict]) -> list[dict]:
    rows = []
    keys = sorted({(r["sequence"], r["config"]) for r in results}, key=lambda k: (k[0], DEFAULT_CONFIGS.index(k[1])
                                                                                 if k[1] in DEFAULT_CONFIGS else 99))
    for seq, cfg in keys:
        runs = [r for r in results if r["sequence"] == seq and r["config"] == cfg]
        ok = [r for r in runs if r.get("ate") is not None]
        ates = np.array([r["ate"] for r in ok])
        rows.append({
            "sequence": seq, "config": cfg, "runs": len(runs), "failed": len(runs) - len(ok),
            "ate_median": float(np.median(ates)) if len(ates) else float("nan"),
            "ate_min": float(ates.min()) if len(ates) else float("nan"),
            "ate_max": float(ates.max()) if len(ates) else float("nan"),
            "tracked": min((f"{r['tracked']}/{r['frames']}" for r in ok), default="–"),
            "median_ms": float(np.median([r["median_ms"] for r in ok])) if ok else float("nan"),
            "mean_ms": float(np.median([r["mean_ms"] for r in ok])) if ok else float("nan"),
            "dynamic_ms": float(np.median([r["dynamic_ms"] for r in ok])) if ok else float("nan"),
        })
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| sequence | configuration | ATE RMSE median (m) | min – max | tracked (worst) | dynamic ms | "
             "total ms median | total ms mean |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['sequence']} | {r['config']} | {r['ate_median']:.4f} | {r['ate_min']:.4f} – "
                     f"{r['ate_max']:.4f} | {r['tracked']} | {r['dynamic_ms']:.1f} | {r['median_ms']:.1f} | "
                     f"{r['mean_ms']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="*", type=Path, default=[SHARED_DATA / "rgbd_bonn_crowd_first480"])
    parser.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes")
    parser.add_argument("--set", action="append", default=[], help="override for every run, key=value")
    parser.add_argument("--output", "-o", type=Path, default=REPO / "results" / "ablation")
    args = parser.parse_args(argv)
    missing = [s for s in args.sequences if not s.is_dir()]
    if missing:
        print(f"ablation: sequence folder not found: {', '.join(map(str, missing))}", file=sys.stderr)
        return 2
    args.output.mkdir(parents=True, exist_ok=True)
    jobs = [(str(s), c, r, str(args.output), args.set) for s in args.sequences for c in args.configs
            for r in range(args.repeats)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(run_one, jobs))
    for r in results:
        if "error" in r:
            print(f"ablation: {r['sequence']} {r['config']} #{r['repeat']} failed: {r['error']}", file=sys.stderr)
    rows = table_rows(results)
    text = markdown(rows)
    (args.output / "ablation.md").write_text(text + "\n")
    (args.output / "runs.json").write_text(json.dumps(results, indent=2) + "\n")
    with open(args.output / "ablation.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
