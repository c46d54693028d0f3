#!/usr/bin/env python3
"""Benchmark sweep: sequences × configurations × repeats, each run in its own process, one table.

    python tools/sweep.py tools/sweeps/bonn_ablation.yaml --jobs 2 --detection-cache /tmp/detcache
    python tools/sweep.py --sequences ../shared/data/rgbd_dataset_freiburg1_rpy_first400 --configs none dynamic_all
    python tools/sweep.py --sequences synthetic:people --configs none dynamic_box_depth --max-frames 60

A sweep file (YAML; ``tools/sweeps/bonn_ablation.yaml`` documents the keys) lists sequences (folders,
or ``synthetic[:MOVERS][:seed=N][:path=P]`` generated with ground-truth boxes as the detector, or
``hard:SCENE[:seed=N]``, a scripted hard scene with its detector's misses, or
``composite:SCENE:path=FOLDER[:seed=N]``, its people composited into a real sequence; tools/sweep_sequences.py),
presets for every run, labelled configurations, the baseline of the "vs." column, repeats (repeat k
uses seed k) and max_frames; command-line options override it. Each run is this script with
``--run-one`` in its own process (a crash or a ``--timeout`` fails only that run) writing
``OUTPUT/runs/<sequence>__<config>__r<k>/``; ``sweep.csv`` (per run), ``sweep.md`` (per sequence ×
configuration) and ``sweep.json`` are rewritten atomically after every run; ``--resume`` keeps the
finished runs of an identical earlier sweep (each run folder keeps its ``job.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
import traceback
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import yaml

from sweep_sequences import build_pipeline, check_generated, is_generated, sequence_label
from sweep_tables import csv_text, markdown_table

REPO = Path(__file__).resolve().parents[1]
NONE_CONFIGS = ("none", "off")  # --configs names that mean "dynamic handling off, no preset"


class SweepError(Exception):
    """A sweep that cannot start (bad sweep file, missing sequence, unknown baseline)."""


# --------------------------------------------------------------------------------------------- spec
@dataclass(frozen=True)
class ConfigSpec:
    label: str
    presets: tuple[str, ...] = ()
    overrides: tuple[tuple[str, Any], ...] = ()
    description: str = ""


@dataclass
class SweepSpec:
    sequences: list[str]
    configs: list[ConfigSpec]
    presets: list[str] = field(default_factory=list)
    overrides: dict[str, Any] = field(default_factory=dict)
    baseline: Optional[str] = None
    repeats: int = 1
    max_frames: Optional[int] = None
    detection_cache: Optional[str] = None


def _resolve_path(text: str) -> str:
    """Sweep-file paths are relative to the repository root; preset names and synthetic specs stay as they are."""
    if is_generated(text) or ("/" not in text and not text.endswith((".yaml", ".yml"))):
        return text
    path = Path(text).expanduser()
    return str(path if path.is_absolute() else (REPO / path).resolve())


def config_from_entry(label: str, value: Any) -> ConfigSpec:
    """A sweep file's ``label: presets`` entry (a list, one name, null, or a dict with presets/set/description)."""
    if isinstance(value, dict):
        unknown = set(value) - {"presets", "set", "description"}
        if unknown:
            raise SweepError(f"config {label!r}: unknown keys {sorted(unknown)} (expected presets, set, description)")
        presets, overrides, description = value.get("presets"), value.get("set"), value.get("description")
    else:
        presets, overrides, description = value, None, None
    presets, overrides = presets or [], overrides or {}
    presets = [presets] if isinstance(presets, str) else list(presets)
    return ConfigSpec(str(label), tuple(_resolve_path(p) for p in presets), tuple(sorted(overrides.items())),
                      str(description or ""))


def config_from_name(name: str) -> ConfigSpec:
    """A --configs item: a preset name or YAML file (labelled by its stem), or none/off."""
    if name in NONE_CONFIGS:   # dynamic handling is on by default: "off" is the static preset
        return ConfigSpec(name, ("static",))
    return ConfigSpec(Path(name).stem if name.endswith((".yaml", ".yml")) else name, (name,))


def load_sweep_file(path: Path) -> SweepSpec:
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise SweepError(f"cannot read sweep file {path}: {exc}") from None
    known = {"sequences", "configs", "presets", "set", "baseline", "repeats", "max_frames", "detection_cache"}
    if not isinstance(data, dict) or set(data) - known:
        raise SweepError(f"{path}: expected a mapping with keys {sorted(known)}, "
                         f"got {sorted(data) if isinstance(data, dict) else type(data).__name__}")
    configs = data.get("configs") or {}
    if not isinstance(configs, dict):
        raise SweepError(f"{path}: 'configs' must map labels to presets")
    return SweepSpec(
        sequences=[_resolve_path(str(s)) for s in data.get("sequences") or []],
        configs=[config_from_entry(k, v) for k, v in configs.items()],
        presets=[_resolve_path(str(p)) for p in data.get("presets") or []],
        overrides=dict(data.get("set") or {}), baseline=data.get("baseline"), repeats=int(data.get("repeats", 1)),
        max_frames=data.get("max_frames"),
        detection_cache=str(REPO / Path(data["detection_cache"]).expanduser()) if data.get("detection_cache") else None)


def check_spec(spec: SweepSpec) -> None:
    """Refuse a sweep that cannot run; the baseline defaults to the first configuration."""
    if not spec.sequences or not spec.configs:
        raise SweepError("nothing to run: give a sweep file, or --sequences and --configs")
    missing = [s for s in spec.sequences if not is_generated(s) and not Path(s).is_dir()]
    if missing:
        raise SweepError(f"sequence folder not found: {', '.join(missing)}")
    bad_specs = [reason for reason in map(check_generated, filter(is_generated, spec.sequences)) if reason]
    if bad_specs:
        raise SweepError("; ".join(bad_specs))
    labels = [c.label for c in spec.configs]
    if len(set(labels)) != len(labels):
        raise SweepError(f"configuration labels must be distinct, got {labels}")
    spec.baseline = spec.baseline or labels[0]
    if spec.baseline not in labels:
        raise SweepError(f"baseline {spec.baseline!r} is not one of the configurations {labels}")
    if spec.repeats < 1:
        raise SweepError(f"repeats must be >= 1, got {spec.repeats}")


# ------------------------------------------------------------------------------------ one run (child)
def run_one(job: dict) -> int:
    """Child process: one run; on failure ``error.txt`` in the run folder says why (exit status 1)."""
    from slam.core.atomic_io import write_text_atomic

    try:
        summary = build_pipeline(job).run()
    except Exception as exc:
        traceback.print_exc()
        write_text_atomic(Path(job["run_dir"]) / "error.txt", f"{type(exc).__name__}: {exc}\n")
        return 1
    return 130 if summary.interrupted else 0


# ------------------------------------------------------------------------------------ runs (parent)
def make_jobs(spec: SweepSpec, output: Path, configs_first: bool = False) -> list[dict]:
    """Every run, sequence by sequence; with ``configs_first`` configuration by configuration (a sweep cut
    short then holds whole configurations across all sequences)."""
    jobs = []
    cache = {"dynamic.detector.cache_dir": spec.detection_cache} if spec.detection_cache else {}
    for sequence in spec.sequences:
        for config in spec.configs:
            for repeat in range(spec.repeats):
                name = f"{sequence_label(sequence)}__{config.label}__r{repeat}"
                jobs.append({"sequence": sequence, "sequence_label": sequence_label(sequence), "config": config.label,
                             "repeat": repeat, "seed": repeat, "presets": spec.presets + list(config.presets),
                             "overrides": {**cache, **spec.overrides, **dict(config.overrides)},
                             "max_frames": spec.max_frames, "run_dir": str(output / "runs" / name)})
    if configs_first:
        labels = [c.label for c in spec.configs]
        jobs.sort(key=lambda job: (labels.index(job["config"]), job["repeat"]))  # stable: sequences keep order
    return jobs


def launch(job: dict, timeout: Optional[float], resume: bool = False) -> dict:
    """Run one job in a child process and collect its row (never raises). With ``resume``, a run folder
    that already holds this very job, finished, is read instead of run again."""
    run_dir = Path(job["run_dir"])
    if resume and finished_before(job):
        return collect_row(job, 0, json.loads((run_dir / "summary.json").read_text())["wall_time_s"])
    shutil.rmtree(run_dir, ignore_errors=True)  # a stale summary.json must never pass for this run's
    run_dir.mkdir(parents=True)
    (run_dir / "job.json").write_text(json.dumps(job, indent=2) + "\n")
    command = [sys.executable, str(Path(__file__).resolve()), "--run-one", json.dumps(job)]
    start = time.perf_counter()
    with open(run_dir / "run.log", "wb") as log:
        try:
            status = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            status = None
    return collect_row(job, status, time.perf_counter() - start, timeout)


def finished_before(job: dict) -> bool:
    run_dir = Path(job["run_dir"])
    try:
        same_job = json.loads((run_dir / "job.json").read_text()) == job
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return False
    return same_job and not summary.get("interrupted") and not (run_dir / "error.txt").exists()


def collect_row(job: dict, status: Optional[int], wall_s: float, timeout: Optional[float] = None,
                error: str = "") -> dict:
    """One CSV row from the run folder's summary.json / evaluation.json, or the reason it failed."""
    run_dir = Path(job["run_dir"])
    row: dict[str, Any] = {"sequence": job["sequence_label"], "config": job["config"], "repeat": job["repeat"],
                           "seed": job["seed"], "status": "failed", "error": "", "wall_s": round(wall_s, 1),
                           "run_dir": str(run_dir)}
    error_file = run_dir / "error.txt"
    if error or status is None:
        row["error"] = error or f"timed out after {timeout:g} s"
    elif error_file.exists():
        row["error"] = " ".join(error_file.read_text().split())  # one line for the CSV and the table
    elif status != 0:  # died without saying why: a signal (memory, a native crash) or an interruption
        tail = (run_dir / "run.log").read_text(errors="replace").strip().splitlines()[-1:]
        row["error"] = f"killed by signal {-status}" if status < 0 else f"exit status {status}: {''.join(tail)}"
    elif not (run_dir / "summary.json").exists():
        row["error"] = "the run wrote no summary.json"
    else:
        row.update(status="ok", **run_numbers(run_dir))
    return row


def run_numbers(run_dir: Path) -> dict[str, Any]:
    summary = json.loads((run_dir / "summary.json").read_text())
    timing = summary.get("timing_ms", {})
    numbers: dict[str, Any] = {
        "tracked": summary["tracked"], "frames": summary["frames"], "keyframes": summary.get("keyframes"),
        "median_ms": timing.get("total", {}).get("median_ms"), "mean_ms": timing.get("total", {}).get("mean_ms")}
    numbers.update({f"ms_{module}": value["median_ms"] for module, value in timing.items() if module != "total"})
    evaluation_file = run_dir / "evaluation.json"
    if evaluation_file.exists():
        evaluation = json.loads(evaluation_file.read_text())
        # max_error_m: the worst tracked frame's position error (the bar: none more than 5 cm off).
        numbers.update(ate_rmse_m=evaluation["ate"]["rmse"], max_error_m=evaluation["ate"]["max"],
                       rpe_trans_m=evaluation["rpe_frame"]["translation"]["rmse"],
                       rpe_rot_deg=evaluation["rpe_frame"]["rotation"]["rmse"])
    return numbers


def run_sweep(spec: SweepSpec, output: Path, jobs: int, timeout: Optional[float] = None, quiet: bool = False,
              resume: bool = False, configs_first: bool = False,
              on_rows: Optional[Callable[[list[dict]], None]] = None) -> list[dict]:
    """All runs, ``jobs`` at a time; the tables are rewritten (and ``on_rows`` called with the rows so
    far) after each finished run."""
    check_spec(spec)
    output.mkdir(parents=True, exist_ok=True)
    todo = make_jobs(spec, output, configs_first)
    order = {(j["sequence_label"], j["config"], j["repeat"]): i for i, j in enumerate(todo)}
    rows: list[dict] = []
    pool = ThreadPoolExecutor(max_workers=max(1, jobs))  # threads only wait on the child processes
    try:
        futures = {pool.submit(launch, job, timeout, resume): job for job in todo}
        for future in as_completed(futures):
            try:
                row = future.result()
            except OSError as exc:  # the run folder could not be prepared (disk full, permissions)
                row = collect_row(futures[future], None, 0.0, error=f"{type(exc).__name__}: {exc}")
            rows.append(row)
            rows.sort(key=lambda r: order[(r["sequence"], r["config"], r["repeat"])])
            write_tables(rows, spec, output)
            if on_rows is not None:
                on_rows(rows)
            if not quiet:
                print(f"sweep: [{len(rows)}/{len(todo)}] {describe_run(row)}", file=sys.stderr, flush=True)
    finally:  # on Ctrl-C, start nothing new (the running children get the signal themselves)
        pool.shutdown(wait=True, cancel_futures=True)
    return rows


def describe_run(row: dict) -> str:
    head = f"{row['sequence']} {row['config']} r{row['repeat']}"
    if row["status"] != "ok":
        return f"{head} FAILED: {row['error']}"
    ate = "no ATE" if row.get("ate_rmse_m") is None else f"ATE {row['ate_rmse_m']:.4f} m"
    return (f"{head}: {ate}, {row['tracked']}/{row['frames']} tracked, {row['median_ms']:.1f} ms/frame, "
            f"{row['wall_s']:.0f} s")


def write_tables(rows: list[dict], spec: SweepSpec, output: Path) -> None:
    from slam.core.atomic_io import write_text_atomic

    write_text_atomic(output / "sweep.csv", csv_text(rows))
    write_text_atomic(output / "sweep.md", markdown_table(rows, spec))
    write_text_atomic(output / "sweep.json", json.dumps({"spec": asdict(spec), "runs": rows}, indent=2) + "\n")


# ---------------------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_file", nargs="?", type=Path, help="YAML sweep definition (see above)")
    parser.add_argument("--sequences", nargs="+",
                        help="folders, synthetic[:MOVERS], hard:SCENE or composite:SCENE:path=FOLDER (replace the file's)")
    parser.add_argument("--configs", nargs="+", help="preset names or YAML files, 'none' = off (replace the file's)")
    parser.add_argument("--preset", action="append", help="preset applied to every run first (replaces the file's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override for every run")
    parser.add_argument("--baseline", help="configuration label of the 'vs.' column")
    parser.add_argument("--repeats", type=int, help="runs per sequence × configuration (seeds 0..N-1)")
    parser.add_argument("--max-frames", type=int, help="frames per run (generated sequences: their length)")
    parser.add_argument("--jobs", "-j", type=int, default=os.cpu_count() or 1, help="parallel processes")
    parser.add_argument("--timeout", type=float, help="seconds after which a run is killed and recorded as failed")
    parser.add_argument("--detection-cache", metavar="DIR", help="reuse detections across runs and sweeps")
    parser.add_argument("--output", "-o", type=Path, help="folder for sweep.md/.csv/.json and runs/")
    parser.add_argument("--resume", action="store_true",
                        help="keep the finished runs of an earlier identical sweep in --output, rerun the others")
    parser.add_argument("--quiet", "-q", action="store_true", help="no per-run progress lines")
    parser.add_argument("--run-one", metavar="JSON", help=argparse.SUPPRESS)  # the child process's entry
    return parser


def spec_from_args(args) -> SweepSpec:
    from slam.run.run_config import parse_overrides

    spec = load_sweep_file(args.sweep_file) if args.sweep_file else SweepSpec(sequences=[], configs=[])
    if args.sequences:
        spec.sequences = [s if is_generated(s) else str(Path(s).resolve()) for s in args.sequences]
    if args.configs:
        spec.configs = [config_from_name(c) for c in args.configs]
        spec.baseline = spec.baseline if spec.baseline in [c.label for c in spec.configs] else None
    spec.presets = args.preset if args.preset is not None else spec.presets
    spec.overrides.update(parse_overrides(args.set))
    spec.baseline = args.baseline or spec.baseline
    spec.repeats = args.repeats if args.repeats is not None else spec.repeats
    spec.max_frames = args.max_frames if args.max_frames is not None else spec.max_frames
    cache = args.detection_cache or spec.detection_cache
    spec.detection_cache = str(Path(cache).expanduser().resolve()) if cache else None
    return spec


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.run_one:
        return run_one(json.loads(args.run_one))
    from slam.core.config import ConfigError

    try:
        spec = spec_from_args(args)
        output = args.output or REPO / "results" / "sweep" / (args.sweep_file.stem if args.sweep_file else "sweep")
        rows = run_sweep(spec, output, args.jobs, args.timeout, args.quiet, args.resume)
    except (SweepError, ConfigError) as exc:
        print(f"sweep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sweep: interrupted; the tables hold the runs that finished", file=sys.stderr)
        return 130
    print(markdown_table(rows, spec), end="")
    print(f"sweep: {sum(r['status'] == 'ok' for r in rows)}/{len(rows)} runs ok; tables in {output}", file=sys.stderr)
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
