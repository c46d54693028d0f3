#!/usr/bin/env python3
"""Is a change faster? This tree against another commit, run alternately, on the same machine and sequences.

    python tools/speed_ab.py BASE [SEQ_DIR ...] [--rounds 3] [-c CONFIG] [--set KEY=VALUE]
    python tools/speed_ab.py HEAD~1 ../shared/data/rgbd_dataset_freiburg1_rpy_first400 --rounds 3

A run's whole-run time moves by +-10 % between identical runs on a shared 2-core machine (2026-11-28:
155.0 and 140.2 ms/frame for the same commit within 20 minutes), as much as most changes gain, so one run of
each side says little. This runs ``tools/benchmark.py`` of each tree (each side measured by its own code) in
its own process, the two sides alternately in the order ABBA ABBA ... (a drift of the machine's speed
within a round hits both sides alike), and prints per sequence each side's whole-run ms per frame (every
round and the mean), CPU ms per frame (all threads and processes: the steadier measure on a CPU-bound
machine), the ratio of the means, ATE, and whether the two trajectories are the same bits (a speed-only
change must leave them so).

Each side first runs 40 frames untimed (a new worktree compiles its numba kernels on its first run).
BASE is any git revision; it is checked out with ``git worktree`` beside this checkout (so that
``../shared`` resolves for both, as for the detector model) and removed at the end, Ctrl-C included. The
runs' folders stay in ``--output`` (default results/speed_ab). One measurement at a time on a 2-core machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCES = [REPO.parent / "shared" / "data" / "rgbd_dataset_freiburg1_rpy_first400"]
SIDES = ("this tree", "base")


@dataclass
class SideRuns:
    """One side's runs of one sequence."""

    whole_ms: list[float] = field(default_factory=list)      # whole-run ms per frame, per round
    cpu_ms: list[float] = field(default_factory=list)        # CPU ms per frame (all threads), per round
    ate: list[float] = field(default_factory=list)
    trajectories: list[bytes] = field(default_factory=list)


def round_order(rounds: int) -> list[int]:
    """Side indices in the order they run: ABBA per pair of rounds (0 = this tree, 1 = the base)."""
    return [side for r in range(rounds) for side in ((0, 1) if r % 2 == 0 else (1, 0))]


def summary_table(results: dict[str, tuple[SideRuns, SideRuns]]) -> str:
    """Markdown: per sequence and side the rounds, their mean, CPU, ATE; the ratio of the means; same bits."""
    lines = ["| sequence | side | whole-run ms/frame (rounds) | mean | CPU ms/frame (mean) | ATE (m) |",
             "|---|---|---|---|---|---|"]
    verdicts = []
    for seq, sides in results.items():
        for name, runs in zip(SIDES, sides):
            rounds = ", ".join(f"{x:.1f}" for x in runs.whole_ms)
            ate = ", ".join(sorted({f"{a:.4f}" for a in runs.ate}))
            lines.append(f"| {seq} | {name} | {rounds} | {np.mean(runs.whole_ms):.1f} | "
                         f"{np.mean(runs.cpu_ms):.1f} | {ate} |")
        this, base = sides
        same = len(set(this.trajectories) | set(base.trajectories)) == 1    # every run of both sides alike
        verdicts.append(f"{seq}: this tree / base = {np.mean(this.whole_ms) / np.mean(base.whole_ms):.3f} "
                        f"(whole run), {np.mean(this.cpu_ms) / np.mean(base.cpu_ms):.3f} (CPU); spread of one side "
                        f"{_spread(this.whole_ms)} / {_spread(base.whole_ms)}; trajectories "
                        f"{'the same bits' if same else 'differ'}")
    return "\n".join(lines + [""] + verdicts)


def _spread(values: list[float]) -> str:
    """(max - min) / mean of a side's rounds, the noise a ratio has to beat."""
    return f"{(max(values) - min(values)) / np.mean(values):.1%}" if len(values) > 1 else "–"


def _run_in(tree: Path, args: list[str]) -> None:
    """``python args...`` with ``tree``'s code first on the path, in that folder; a failure raises with its
    command and the end of its error output."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    cmd = [sys.executable, *args]
    proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")


def _run_benchmark(tree: Path, sequence: Path, output: Path,
                   passthrough: list[str]) -> tuple[float, float, float, bytes]:
    """``tree``'s tools/benchmark.py on one sequence in its own process (its own code first on the path);
    (whole-run ms/frame, CPU ms/frame, ATE, trajectory bytes)."""
    _run_in(tree, [str(tree / "tools" / "benchmark.py"), str(sequence), "-o", str(output), *passthrough])
    row = json.loads((output / "benchmark.json").read_text())[0]
    cpu_ms = 1e3 * sum(row.get("cpu_s", {}).values()) / max(row["frames"], 1)
    trajectory = next(output.glob("*_run0/trajectory.txt")).read_bytes()
    return row["whole_run_ms_per_frame"], cpu_ms, row["ate_rmse_m"], trajectory


def _warm_up(tree: Path, sequence: Path, output: Path, passthrough: list[str]) -> None:
    """A short untimed run of ``tree`` on ``sequence`` (40 frames): a fresh worktree compiles its numba kernels
    on its first run (~20-30 s, once), which must not land in the first timed round."""
    _run_in(tree, ["-m", "slam.cli", "run", str(sequence), "-q", "--max-frames", "40", "-o", str(output), *passthrough])


def _checkout(revision: str) -> Path:
    """A detached worktree of ``revision`` beside this checkout."""
    sha = subprocess.run(["git", "rev-parse", "--verify", f"{revision}^{{commit}}"], cwd=REPO, capture_output=True,
                         text=True)
    if sha.returncode != 0:
        raise SystemExit(f"speed_ab: '{revision}' is not a commit of {REPO}: {sha.stderr.strip()}")
    tree = REPO.parent / f".speed_ab_{sha.stdout.strip()[:12]}"
    if tree.exists():
        raise SystemExit(f"speed_ab: {tree} exists (another comparison running, or left behind: "
                         f"git worktree remove --force {tree})")
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(tree), sha.stdout.strip()], cwd=REPO, check=True)
    return tree


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("base", help="the git revision to compare with (e.g. HEAD, HEAD~1, a commit)")
    parser.add_argument("sequences", nargs="*", type=Path, default=DEFAULT_SEQUENCES)
    parser.add_argument("--rounds", type=int, default=2, help="runs per side and sequence (default 2)")
    parser.add_argument("--config", "-c", action="append", default=[])
    parser.add_argument("--set", action="append", default=[])
    parser.add_argument("--output", "-o", type=Path, default=REPO / "results" / "speed_ab")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    missing = [s for s in args.sequences if not s.is_dir()]
    if missing:
        print(f"speed_ab: sequence folder not found: {', '.join(map(str, missing))}", file=sys.stderr)
        return 2
    passthrough = [a for c in args.config for a in ("-c", c)] + [a for s in args.set for a in ("--set", s)]
    base_tree = _checkout(args.base)
    results: dict[str, tuple[SideRuns, SideRuns]] = {}
    try:
        for side, tree in enumerate((REPO, base_tree)):
            _warm_up(tree, args.sequences[0].resolve(), args.output / f"warm_up_{SIDES[side].replace(' ', '_')}",
                     passthrough)
        for seq in args.sequences:
            sides = (SideRuns(), SideRuns())
            for k, side in enumerate(round_order(args.rounds)):
                tree = REPO if side == 0 else base_tree
                out = args.output / f"{seq.name}_{'this' if side == 0 else 'base'}_{k // 2}"
                whole, cpu, ate, trajectory = _run_benchmark(tree, seq.resolve(), out, passthrough)
                runs = sides[side]
                runs.whole_ms.append(whole)
                runs.cpu_ms.append(cpu)
                runs.ate.append(ate)
                runs.trajectories.append(trajectory)
                print(f"{seq.name}: {SIDES[side]} {whole:.1f} ms/frame, CPU {cpu:.1f}", flush=True)
            results[seq.name] = sides
    except RuntimeError as exc:           # a run failed: its command and the end of its error output
        print(f"speed_ab: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:             # the benchmark in flight got the Ctrl-C too and has stopped
        print("speed_ab: interrupted; the finished runs stay in " + str(args.output), file=sys.stderr)
        return 130
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(base_tree)], cwd=REPO, capture_output=True)
    table = summary_table(results)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "speed_ab.md").write_text(f"this tree vs {args.base}\n\n{table}\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
