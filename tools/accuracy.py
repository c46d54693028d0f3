#!/usr/bin/env python3
"""The README's accuracy claims, re-measured with ``dynslam`` itself, and the gates that guard them.

    python tools/accuracy.py                    # every case, 2 runs at a time; prints the tables
    python tools/accuracy.py --cases rpy bonn --jobs 1
    python tools/accuracy.py --check            # exit 1 when a gate fails (tests/test_accuracy_gates.py)

Every case is one ``dynslam run`` / ``dynslam demo`` in its own process, exactly as a user types it.
Printed: per case, frames tracked, keyframes, ATE RMSE, the worst frame's error, loops (found, checked
against ground truth, false), and ms/frame (informational only: cases run in parallel); then every
gate with its measured value, its bound and why the bound is what it is; then the cross-process
determinism check (the same case run twice gives a byte-identical ``trajectory.txt``).

Gates. ``BASELINE_ATE`` holds the ATE measured for each case (date and commit in the README); a run
fails when its ATE is more than ``ATE_TOLERANCE`` (15 %) above it. The runs are deterministic (byte-
identical across processes), so the margin is not for run-to-run noise: it admits floating-point
differences between machines and libraries and small deliberate changes, and stops real regressions
(a fusion that returns zeros moves Bonn from ~0.013 m to ~0.5 m). Relations are checked on top: dynamic
handling on Bonn at least 20x better than off; on the static fr1/rpy no more than 10 % worse than off;
loop closing no worse than without it; a minimum number of loops, each within 10 cm / 5 deg of
ground truth; a blackout relocalized on its first frame.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RPY = "rgbd_dataset_freiburg1_rpy_first400"
XYZ = "rgbd_dataset_freiburg1_xyz_first37"
DESK = "rgbd_dataset_freiburg1_desk_9frames"
BONN = "rgbd_bonn_crowd_first480"
QUIET = ["-q", "--set", "output.report=false"]
ATE_TOLERANCE = 1.15          # a case fails above 1.15 x its baseline (see the module docstring)
DYNAMIC_GAIN_MIN = 20.0       # Bonn: ATE with dynamic handling off / on (measured 41x)
STATIC_COST_MAX = 1.10        # fr1/rpy (no people): ATE with dynamic_all / off
LOOP_GAIN_SLACK_M = 5e-4      # loops on may be at most 0.5 mm worse than off (loop factors are soft)
BLACKOUT = (185, 30)          # frames 185-214 blanked: 215 must be tracked again (relocalized)
BLACKOUT_FRAMES = 260         # and 45 frames after it; the 140 more of the full 400 test nothing new


@dataclass(frozen=True)
class Case:
    name: str
    sequence: str                        # folder in ../shared/data, or "" for a generated room
    args: tuple[str, ...]                # dynslam arguments; {seq} is the sequence folder
    label: str
    baseline_ate: Optional[float] = None  # None: measured for a relation only, no gate of its own
    min_loops: int = 0                   # about half the loops found today (the camera really revisits)
    # Frames that may be LOST honestly: where people leave the background too thin to fix the pose within
    # tracking.max_pose_sigma_m. Twice the worst of seeds 0-2 today; 0 elsewhere: every frame tracked.
    max_lost: int = 0
    # False: run by this tool only, not by the test suite, whose 15 minutes on 2 cores do not reach that far
    # (each real case is ~80 s of CPU); the suite's own tests cover the same behaviour on generated scenes.
    in_suite: bool = True


# Baselines: python tools/accuracy.py, 2026-11-26, with the final (robust) trajectory smoother (backend.smoothing_sigma_acc).
CASES = {c.name: c for c in [
    Case("rpy", RPY, ("run", "{seq}"), "fr1/rpy-400, default (dynamic handling on)", 0.0221, min_loops=3),
    Case("rpy_static", RPY, ("run", "{seq}", "-c", "static"), "fr1/rpy-400, -c static", 0.0235, min_loops=3),
    # Loops on against off: tests/test_loop_closing.py holds the gain on a room walked twice with drift.
    Case("rpy_loops_off", RPY, ("run", "{seq}", "--set", "loop.enabled=false"), "fr1/rpy-400, loops off",
         in_suite=False),
    # 0.0217 over all 400 frames; 0.0226 over the first 260 (2026-12-01)
    Case("rpy_blackout", RPY, ("run", "{seq}", "--blackout", f"{BLACKOUT[0]}:{BLACKOUT[1]}", "--max-frames",
                               str(BLACKOUT_FRAMES)), f"fr1/rpy, first {BLACKOUT_FRAMES}, frames 185-214 blank", 0.0226),
    # Bonn's LOST frames over seeds 0-2: 1-6 (319, 446-450, where people fill most of the view).
    Case("bonn", BONN, ("run", "{seq}"), "Bonn crowd-480, default (dynamic handling on)", 0.0104, min_loops=3,
         max_lost=12),
    Case("bonn_static", BONN, ("run", "{seq}", "-c", "static"), "Bonn crowd-480, -c static"),
    # 0.0055 while the graph was solved in line; 0.0070 since it is solved in the worker process and its
    # results reach tracking one keyframe later (8 keyframes in 37 frames: in line 0.0061 with the window).
    Case("xyz", XYZ, ("run", "{seq}"), "fr1/xyz-37, default", 0.0069),
    Case("desk", DESK, ("run", "{seq}"), "fr1/desk, 9 frames, default", 0.0037),
    Case("demo", "", ("demo", "--movers", "none", "--no-compare"), "generated room without people (dynslam demo "
         "--movers none), 120 frames", 0.0026),
    Case("demo_people", "", ("demo", "--no-compare"), "generated room, 3 people walking (dynslam demo)", 0.0029),
    Case("demo_people_off", "", ("demo", "--no-compare", "-c", "static"), "generated room, 3 people walking, "
         "-c static"),
]}
DETERMINISM_CASES = ("bonn", "demo_people")   # run twice, in separate processes
# The suite's: the generated room with people (dynamic_all, a loop closed, the worker process); Bonn's second
# process is another ~100 s of CPU, and tests/test_integration_real.py runs fr1/xyz twice with the real detector.
SUITE_DETERMINISM_CASES = ("demo_people",)
SUITE_CASES = tuple(name for name, case in CASES.items() if case.in_suite)


@dataclass
class CaseResult:
    case: Case
    results: Path
    returncode: int
    stderr: str
    summary: dict = field(default_factory=dict)
    max_error_m: Optional[float] = None
    loop_checks: list = field(default_factory=list)

    @property
    def ate(self) -> float:
        value = self.summary.get("ate_rmse_m")
        return float("nan") if value is None else float(value)


def sequence_path(case: Case) -> Optional[Path]:
    return DATA / case.sequence if case.sequence else None


def run_case(case: Case, results: Path) -> CaseResult:
    """One ``dynslam`` process; the summary, per-frame errors and loop checks of its results folder."""
    seq = sequence_path(case)
    args = [a.replace("{seq}", str(seq)) for a in case.args] + ["-o", str(results), *QUIET]
    proc = subprocess.run([sys.executable, "-m", "slam.cli", *args], capture_output=True, text=True, cwd=REPO)
    result = CaseResult(case, results, proc.returncode, proc.stderr[-2000:])
    if proc.returncode == 0:
        result.summary = json.loads((results / "summary.json").read_text())
        _check_against_groundtruth(result, seq / "groundtruth.txt" if seq else results / "groundtruth.txt")
    return result


def _check_against_groundtruth(result: CaseResult, gt_file: Path) -> None:
    from slam.run.evaluation import evaluate_files
    from slam.run.loop_evaluation import check_loops, estimate_body_rotation
    from slam.run.trajectory import read_tum

    report = evaluate_files(gt_file, result.results / "trajectory.txt", 0.02)
    result.max_error_m = float(report.ate.errors.max())
    gt = read_tum(gt_file)
    body = None
    if result.case.sequence.startswith("rgbd_bonn"):   # Bonn's ground truth is the marker, not the camera
        body, _ = estimate_body_rotation(*read_tum(result.results / "trajectory.txt"), *gt)
    result.loop_checks = check_loops(result.summary.get("loops", []), *gt, body_rotation=body)


def run_cases(names: list[str], root: Path, jobs: int = 2, twins: Sequence[str] = DETERMINISM_CASES
              ) -> tuple[dict[str, CaseResult], dict[str, bool]]:
    """Run the cases (``jobs`` at a time) and a second process of each of ``twins`` among them; returns
    the results and, per twin, whether both trajectories are byte-identical."""
    jobs_list = [(n, root / n) for n in names]
    twins = [n for n in twins if n in names]
    jobs_list += [(n, root / f"{n}_again") for n in twins]
    # The longest first, so the two job slots finish together.
    jobs_list.sort(key=lambda job: not job[0].startswith("bonn"))
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = {out: pool.submit(run_case, CASES[name], out) for name, out in jobs_list}
        done = {out: f.result() for out, f in futures.items()}
    results = {n: done[root / n] for n in names}
    identical = {n: same_trajectory(root / n, root / f"{n}_again") for n in twins}
    return results, identical


def same_trajectory(results_a: Path, results_b: Path) -> bool:
    """Both runs wrote a trajectory.txt, byte for byte the same."""
    a, b = results_a / "trajectory.txt", results_b / "trajectory.txt"
    return a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()


@dataclass
class Gate:
    claim: str
    value: float
    bound: float
    passed: bool
    why: str


def gates(results: dict[str, CaseResult]) -> list[Gate]:
    """Every gate whose cases were run."""
    out: list[Gate] = []
    for name, r in results.items():
        c = r.case
        if r.returncode != 0:
            out.append(Gate(f"{c.label}: runs", r.returncode, 0, False, r.stderr.strip().splitlines()[-1:] and
                            r.stderr.strip().splitlines()[-1] or "no message"))
            continue
        if c.baseline_ate is not None:
            bound = c.baseline_ate * ATE_TOLERANCE
            out.append(Gate(f"{c.label}: ATE RMSE (m)", r.ate, bound, r.ate <= bound,
                            f"baseline {c.baseline_ate} + 15 %"))
        lost = r.summary["lost_frames"]
        if name == "rpy_blackout":
            expected_lost = list(range(BLACKOUT[0], sum(BLACKOUT)))
            out.append(Gate(f"{c.label}: lost frames", len(lost), len(expected_lost), lost == expected_lost,
                            "exactly the blank frames (relocalized on the first frame after)"))
        else:
            out.append(Gate(f"{c.label}: lost frames", len(lost), c.max_lost, len(lost) <= c.max_lost,
                            "every frame tracked" if not c.max_lost else
                            "LOST only where people leave too little background: twice seeds 0-2's worst"))
        if c.min_loops:
            out.append(Gate(f"{c.label}: loops found", len(r.summary["loops"]), c.min_loops,
                            len(r.summary["loops"]) >= c.min_loops, "about half of those found today"))
        # Counted among the loops the run keeps: a loop the consistency check removed again had its
        # correction taken back (backend/window_loops.py). The early short-range loop of fr1/rpy is
        # 6-10 cm off in every back end (PnP's rotation/translation ambiguity at one depth) and is
        # removed in each; the table's "worst loop" column still shows every loop's error.
        kept = [lc for lc in r.loop_checks if lc.active]
        false = [lc for lc in kept if lc.false]
        if r.summary.get("loops") and c.baseline_ate is not None:   # the "off" cases are no claim
            out.append(Gate(f"{c.label}: false loops kept (of {len(kept)} kept, {len(r.loop_checks)} checked)",
                            len(false), 0, not false, "every loop the run keeps within 10 cm / 5 deg of ground truth"))
    out += _relations(results)
    return out


def _relations(results: dict[str, CaseResult]) -> list[Gate]:
    out = []
    ok = {n: r for n, r in results.items() if r.returncode == 0}
    if {"bonn", "bonn_static"} <= ok.keys():
        gain = ok["bonn_static"].ate / ok["bonn"].ate
        out.append(Gate("Bonn: ATE off / on", gain, DYNAMIC_GAIN_MIN, gain >= DYNAMIC_GAIN_MIN,
                        "dynamic handling at least 20x better than off"))
    if {"rpy", "rpy_static"} <= ok.keys():
        cost = ok["rpy"].ate / ok["rpy_static"].ate
        out.append(Gate("fr1/rpy: ATE dynamic on / off", cost, STATIC_COST_MAX, cost <= STATIC_COST_MAX,
                        "no people: dynamic handling within 10 % of off"))
    if {"rpy", "rpy_loops_off"} <= ok.keys():
        diff = ok["rpy"].ate - ok["rpy_loops_off"].ate
        out.append(Gate("fr1/rpy: ATE loops on - off (m)", diff, LOOP_GAIN_SLACK_M, diff <= LOOP_GAIN_SLACK_M,
                        "closing loops does not make it worse"))
    return out


def format_tables(results: dict[str, CaseResult], checks: list[Gate], identical: dict[str, bool]) -> str:
    lines = ["| case | command | frames tracked | keyframes | ATE RMSE (m) | worst frame (m) | loops (checked, "
             "false) | worst loop vs ground truth | ms/frame median |", "|---|---|---|---|---|---|---|---|---|"]
    for r in results.values():
        s = r.summary
        command = "dynslam " + " ".join(a.replace("{seq}", f"../shared/data/{r.case.sequence}") for a in r.case.args)
        if r.returncode != 0:
            lines.append(f"| {r.case.label} | `{command}` | failed ({r.returncode}) | | | | | | |")
            continue
        false = sum(lc.false for lc in r.loop_checks)   # all checked loops, removed ones included
        ms = s["timing_ms"].get("total", {}).get("median_ms", float("nan"))
        worst = (f"{max(lc.error_t for lc in r.loop_checks) * 100:.1f} cm / "
                 f"{max(lc.error_deg for lc in r.loop_checks):.1f}°") if r.loop_checks else "–"
        lines.append(f"| {r.case.label} | `{command}` | {s['tracked']}/{s['frames']} | {s['keyframes']} | "
                     f"{r.ate:.4f} | {r.max_error_m:.4f} | {len(s['loops'])} ({len(r.loop_checks)}, {false}) | "
                     f"{worst} | {ms:.1f} |")
    lines += ["", "| gate | measured | bound | pass | why |", "|---|---|---|---|---|"]
    for g in checks:
        lines.append(f"| {g.claim} | {g.value:.4g} | {g.bound:.4g} | {'yes' if g.passed else '**NO**'} | {g.why} |")
    if identical:
        lines += ["", "| determinism: two processes, same input | byte-identical trajectory.txt |", "|---|---|"]
        lines += [f"| {CASES[n].label} | {'yes' if same else '**NO**'} |" for n, same in identical.items()]
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--jobs", type=int, default=2, help="cases run at a time (default 2: this machine's cores)")
    parser.add_argument("--no-determinism", action="store_true", help="skip the second process of "
                        + " and ".join(DETERMINISM_CASES))
    parser.add_argument("--output", type=Path, help="keep the results folders here (default: a temporary folder)")
    parser.add_argument("--check", action="store_true", help="exit 1 when a gate fails")
    args = parser.parse_args(argv)
    missing = sorted({CASES[n].sequence for n in args.cases if CASES[n].sequence and not (DATA / CASES[n].sequence).is_dir()})
    if missing:
        print(f"accuracy: sequences not found in {DATA}: {', '.join(missing)}", file=sys.stderr)
        return 2
    start = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.output or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        results, identical = run_cases(args.cases, root, args.jobs, () if args.no_determinism else DETERMINISM_CASES)
        checks = gates(results)
        print(format_tables(results, checks, identical))
    print(f"\n{len(args.cases)} cases in {time.time() - start:.0f} s, {args.jobs} at a time", file=sys.stderr)
    failed = [g for g in checks if not g.passed] + [n for n, same in identical.items() if not same]
    return 1 if args.check and failed else 0


if __name__ == "__main__":
    sys.exit(main())
