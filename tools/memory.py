#!/usr/bin/env python3
"""Memory of a long run: peak RSS and RSS growth per 1,000 frames of the full system on a generated sequence.

    python tools/memory.py                          # 2,000 frames of the generated room, seed 0
    python tools/memory.py --frames 4000 --json memory.json
    python tools/memory.py --frames 600 --tracemalloc 10   # also: the 10 allocation sites that grew most

Runs what ``dynslam demo`` runs (the default configuration with the generated sequence's camera, loop
closing and relocalization on, the whole ``Pipeline`` with its results folder) on ``--frames`` frames of
the "orbit" path, which returns to its start pose after 1,885 frames (62.8 s: the 2*pi s ellipse and
the 0.3 rad/s pan both close there) and sees the same walls from nearby every ~630 frames, so loops
are closed. Frames are generated one at a time and not kept (``SyntheticSequence.__iter__`` does not
cache; its ``frame()`` cache holds the last 3 ray casts), so the figures are the SLAM process's own.

Prints Markdown: the run (frames, keyframes, landmarks, tracked/lost, loops, ATE, wall ms per frame,
peak RSS from ``getrusage`` and from sampled ``VmRSS``, RSS growth per 1,000 frames = least-squares
slope of the per-frame VmRSS over the second half of the run, after warm-up) and per block of
``--block`` frames (mean ms per frame, keyframes, backend ms per keyframe, RSS at the block's end).
Numbers are reported, never asserted.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MIB = 1024.0 * 1024.0


# ------------------------------------------------------------------------------------ RSS sampling
def current_rss_mib(status: Path = Path("/proc/self/status")) -> float:
    """Resident set size now (``VmRSS``) in MiB; 0.0 where /proc is not available (not Linux)."""
    try:
        for line in status.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0   # kB
    except OSError:
        pass
    return 0.0


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (``getrusage`` ``ru_maxrss``) in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / MIB if sys.platform == "darwin" else peak / 1024.0   # bytes on macOS, kB on Linux


@dataclass
class FrameSampler:
    """Per processed frame: milliseconds spent on it and the RSS right after it (MiB)."""
    ms: list[float] = field(default_factory=list)
    rss_mib: list[float] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)

    def record(self, ms: float, keyframes: int = 0) -> None:
        self.ms.append(float(ms))
        self.rss_mib.append(current_rss_mib())
        self.keyframes.append(int(keyframes))


# ------------------------------------------------------------------------------------ statistics
def block_stats(ms: Sequence[float], rss_mib: Sequence[float], block: int = 1000,
                keyframes: Optional[Sequence[int]] = None, backend_ms: Optional[Sequence[float]] = None) -> list[dict]:
    """Per block of ``block`` frames (the last may be shorter): frame range (1-based, inclusive), mean
    ms per frame, RSS at the block's last frame and its peak in the block; with ``keyframes``
    (cumulative count after each frame) the count at the block's end and the keyframes added in it,
    with ``backend_ms`` (per frame, 0 on non-keyframes) the mean back-end ms per keyframe added."""
    ms, rss = np.asarray(ms, float), np.asarray(rss_mib, float)
    if len(ms) != len(rss):
        raise ValueError(f"{len(ms)} frame times but {len(rss)} RSS samples")
    if block < 1:
        raise ValueError(f"block must be >= 1 frame, got {block}")
    out = []
    for start in range(0, len(ms), block):
        end = min(start + block, len(ms))
        row = {"first": start + 1, "last": end, "mean_ms": float(ms[start:end].mean()),
               "rss_end_mib": float(rss[end - 1]), "rss_peak_mib": float(rss[start:end].max())}
        if keyframes is not None:
            kf = np.asarray(keyframes, int)
            row["keyframes"] = int(kf[end - 1])
            row["keyframes_added"] = int(kf[end - 1] - (kf[start - 1] if start else 0))
        if backend_ms is not None:
            b = np.asarray(backend_ms, float)[start:end]
            b = b[b > 0]
            row["backend_ms_per_keyframe"] = float(b.mean()) if len(b) else 0.0
        out.append(row)
    return out


def growth_per_1000(rss_mib: Sequence[float], from_fraction: float = 0.5) -> float:
    """RSS growth in MiB per 1,000 frames: least-squares slope of RSS over frame number, fitted to the
    frames from ``from_fraction`` of the run on (the default skips the first half as warm-up)."""
    rss = np.asarray(rss_mib, float)
    start = int(np.floor(len(rss) * from_fraction))
    tail = rss[start:]
    if len(tail) < 2:
        return 0.0
    slope = np.polyfit(np.arange(start, len(rss), dtype=float), tail, 1)[0]
    return float(slope * 1000.0)


# ------------------------------------------------------------------------------------ the run
def demo_config(sequence, seed: int, config_files: Sequence[str] = (), overrides: Sequence[str] = ()):
    """The configuration ``dynslam demo`` builds for ``sequence`` (see ``slam.cli.commands.cmd_demo``)."""
    from slam.run.run_config import parse_overrides, resolve_run_config

    fx, fy, cx, cy = sequence.intrinsics
    camera = {"camera.name": "synthetic", "camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
              "camera.width": sequence.width, "camera.height": sequence.height,
              "camera.distortion": [0.0] * 5, "seed": seed}
    return resolve_run_config(None, list(config_files), {**camera, **parse_overrides(list(overrides))})


def run(frames: int = 2000, seed: int = 0, path: str = "orbit", block: int = 1000, output: Optional[Path] = None,
        config_files: Sequence[str] = (), overrides: Sequence[str] = (), tracemalloc_top: int = 0,
        progress: bool = False) -> dict:
    """Run the demo pipeline on ``frames`` generated frames, sampling time and RSS after every frame.
    ``output``: the results folder (default: a temporary one, removed afterwards)."""
    if output is None:
        with tempfile.TemporaryDirectory(prefix="dynslam_memory_") as tmp:
            return run(frames, seed, path, block, Path(tmp), config_files, overrides, tracemalloc_top, progress)
    from slam.datasets import SyntheticSequence
    from slam.run.pipeline import Pipeline
    from slam.run.demo import demo_detector

    rss_start = current_rss_mib()
    sequence = SyntheticSequence(n_frames=frames, seed=seed, path=path)
    config = demo_config(sequence, seed, config_files, overrides)
    sampler = FrameSampler()
    traces = _Tracer(tracemalloc_top, block)
    pipeline: Optional[Pipeline] = None

    def on_frame(out, seconds: float) -> None:
        sampler.record(seconds * 1e3, pipeline.system.num_keyframes)
        traces.on_frame(len(sampler.ms))
        if progress and len(sampler.ms) % 100 == 0:
            print(f"memory: frame {len(sampler.ms)}/{frames}, {sampler.keyframes[-1]} keyframes, "
                  f"{np.mean(sampler.ms[-100:]):.1f} ms/frame, RSS {sampler.rss_mib[-1]:.0f} MiB",
                  file=sys.stderr, flush=True)

    pipeline = Pipeline(sequence, config, output, progress=on_frame, detector=demo_detector(sequence))
    rss_built = current_rss_mib()
    start = time.perf_counter()
    summary = pipeline.run()
    wall = time.perf_counter() - start
    rss_loop_peak = max(sampler.rss_mib) if sampler.rss_mib else 0.0
    n = len(sampler.ms)
    backend_ms = pipeline.system.timer.per_frame("backend")[:n]
    report = {
        "sequence": sequence.name, "path": path, "seed": seed, "frames": summary.frames,
        "tracked": summary.tracked, "lost": summary.lost, "keyframes": summary.keyframes,
        "landmarks": summary.landmarks, "loops_added": summary.place_recognition.get("loops_added", 0),
        "loops_active": summary.place_recognition.get("loops_active", 0), "ate_rmse_m": summary.ate_rmse_m,
        "wall_s": wall, "wall_ms_per_frame": wall * 1e3 / max(1, summary.frames),
        "frames_wall_s": summary.wall_time_s, "mean_frame_ms": float(np.mean(sampler.ms)) if n else 0.0,
        "rss_start_mib": rss_start, "rss_built_mib": rss_built, "rss_end_mib": current_rss_mib(),
        "rss_peak_frames_mib": rss_loop_peak, "peak_rss_mib": peak_rss_mib(),
        "growth_mib_per_1000": growth_per_1000(sampler.rss_mib),
        "block": block, "blocks": block_stats(sampler.ms, sampler.rss_mib, block, sampler.keyframes, backend_ms),
        "rss_every_frame_mib": [round(r, 2) for r in sampler.rss_mib],
    }
    if tracemalloc_top:
        report["tracemalloc"] = traces.finish()
    return report


class _Tracer:
    """Optional tracemalloc: the allocation sites whose live size grew most between the end of the
    first block and the end of the run (tracemalloc slows the run several-fold; numbers are Python's
    allocations only, not GTSAM's or OpenCV's)."""

    def __init__(self, top: int, block: int):
        self.top, self.block, self.first = top, block, None
        if top:
            import tracemalloc

            tracemalloc.start(8)

    def on_frame(self, n: int) -> None:
        if self.top and n == self.block and self.first is None:
            import tracemalloc

            self.first = tracemalloc.take_snapshot()

    def finish(self) -> list[dict]:
        import tracemalloc

        last = tracemalloc.take_snapshot()
        tracemalloc.stop()
        if self.first is None:
            return []
        rows = []
        for stat in last.compare_to(self.first, "traceback")[: self.top]:
            frames = [f"{f.filename}:{f.lineno}" for f in stat.traceback][:4]
            rows.append({"size_diff_mib": stat.size_diff / MIB, "count_diff": stat.count_diff, "where": frames})
        return rows


# ------------------------------------------------------------------------------------ output
def markdown(report: dict) -> str:
    loops = f"{report['loops_active']}/{report['loops_added']}"
    ate = "–" if report["ate_rmse_m"] is None else f"{report['ate_rmse_m']:.4f}"
    lines = [
        f"{report['sequence']}, {report['frames']} frames, `dynslam demo` configuration",
        "",
        "| frames | tracked/lost | keyframes | landmarks | loops active/added | ATE RMSE (m) | wall ms/frame (whole run) "
        "| peak RSS, ru_maxrss (MiB) | peak VmRSS while tracking (MiB) | RSS growth (MiB / 1,000 frames, 2nd half) |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {report['frames']} | {report['tracked']}/{report['lost']} | {report['keyframes']} | {report['landmarks']} "
        f"| {loops} | {ate} | {report['wall_ms_per_frame']:.1f} | {report['peak_rss_mib']:.0f} "
        f"| {report['rss_peak_frames_mib']:.0f} | {report['growth_mib_per_1000']:.1f} |",
        "",
        "| frames | mean ms/frame | keyframes (added) | backend ms/keyframe | RSS at end (MiB) |",
        "|---|---|---|---|---|",
    ]
    for b in report["blocks"]:
        lines.append(f"| {b['first']}–{b['last']} | {b['mean_ms']:.1f} | {b.get('keyframes', '–')} "
                     f"({b.get('keyframes_added', '–')}) | {b.get('backend_ms_per_keyframe', 0.0):.1f} "
                     f"| {b['rss_end_mib']:.0f} |")
    lines += ["", f"RSS {report['rss_start_mib']:.0f} MiB before the run, {report['rss_built_mib']:.0f} MiB with the "
              f"system built, {report['rss_end_mib']:.0f} MiB after writing the results. ms/frame per block: the "
              "pipeline's per-frame step (generation of the frame excluded); wall ms/frame: the whole run "
              "(frame generation and result writing included)."]
    for row in report.get("tracemalloc", []):
        lines.append(f"- tracemalloc {row['size_diff_mib']:+.2f} MiB ({row['count_diff']:+d} blocks) at "
                     + " < ".join(row["where"]))
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--path", default="orbit", help="camera path of the generated sequence (orbit, line, still)")
    parser.add_argument("--block", type=int, default=1000, help="frames per block of the per-block table")
    parser.add_argument("--config", "-c", action="append", default=[])
    parser.add_argument("--set", action="append", default=[])
    parser.add_argument("--output", "-o", type=Path, help="keep the results folder here (default: temporary)")
    parser.add_argument("--json", type=Path, help="also write the report (with RSS after every frame) as JSON")
    parser.add_argument("--tracemalloc", type=int, default=0, metavar="N",
                        help="list the N Python allocation sites that grew most after the first block (slow)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress every 100 frames on stderr")
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be >= 2")
    report = run(args.frames, args.seed, args.path, args.block, args.output, args.config, args.set,
                 args.tracemalloc, not args.quiet)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
