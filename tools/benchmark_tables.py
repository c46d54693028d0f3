"""The text ``tools/benchmark.py`` prints: Markdown tables and one-line summaries of its result rows.

Kept apart from the runs that make the rows (``tools/benchmark.py``) so each reads on its own; a row is the dict
``benchmark.run_dynslam`` / ``run_peer`` return (``benchmark.json`` holds them), a long run's report the JSON of
``tools/memory.py``.
"""
from __future__ import annotations

import numpy as np

MODULES = ("extract", "dynamic", "tracking", "mapping", "backend", "total")
KEYFRAME_MARKS = (50, 100, 200, 500)   # back-end cost reported around these keyframe counts
KEYFRAME_WINDOW = 10                   # ... as the median over the keyframes up to the mark


def backend_cost_at_marks(keyframe_ms: np.ndarray) -> dict[int, float]:
    """Median back-end ms of the KEYFRAME_WINDOW keyframes up to each mark the run reached."""
    return {mark: float(np.median(keyframe_ms[mark - KEYFRAME_WINDOW:mark]))
            for mark in KEYFRAME_MARKS if len(keyframe_ms) >= mark}


def speed_table(rows: list[dict]) -> str:
    """Whole-run time, latency and back-end growth of each dynslam row, beside the peer's tracking."""
    peers = {r["sequence"]: r for r in rows if r["system"] != "dynslam"}
    marks = " | ".join(f"backend ms/kf @{m}" for m in KEYFRAME_MARKS)
    lines = [f"| sequence | whole-run ms/frame | latency median | latency p95 | step mean first / last quarter | "
             f"{marks} | ORB-SLAM3 tracking median | ratio (whole run / peer) |",
             "|---|" + "---|" * (6 + len(KEYFRAME_MARKS))]
    for r in rows:
        if r["system"] != "dynslam":
            continue
        at = r["backend_ms_at_keyframes"]
        peer = peers.get(r["sequence"])
        peer_ms = peer["median_ms"]["total"] if peer else None
        ratio = f"{r['whole_run_ms_per_frame'] / peer_ms:.1f}x" if peer_ms else "–"
        trend = r.get("cost_trend") or {}
        climb = f"{trend['first_ms']:.1f} / {trend['last_ms']:.1f} ({trend['ratio']:.2f})" if trend else "–"
        lines.append(f"| {r['sequence']} | {r['whole_run_ms_per_frame']:.1f} | {r['latency_ms']['median']:.1f} | "
                     f"{r['latency_ms']['p95']:.1f} | {climb} | " + " | ".join(_num(at.get(m)) for m in KEYFRAME_MARKS)
                     + f" | {_num(peer_ms)} | {ratio} |")
    return "\n".join(lines)


def compile_line(row: dict) -> str:
    """A line when numba compiled kernels inside the timed run (a one-time cost the whole-run time then holds)."""
    seconds = row.get("kernel_compile_s", 0.0)
    if seconds < 0.5:
        return ""
    return (f"\n{row['sequence']}: numba compiled kernels for {seconds:.1f} s inside the timed run (once per "
            f"install; {1e3 * seconds / max(row['frames'], 1):.1f} ms of the whole run's ms per frame)")


def markdown_table(rows: list[dict]) -> str:
    head = "| system | sequence | frames tracked | keyframes | ATE RMSE (m) | " + \
           " | ".join(f"{m} ms" for m in MODULES) + " | mean total ms | backend ms/keyframe |" + \
           " loops active/added | loop ms/keyframe (median, max) | relocalized/attempts | reloc ms/attempt (median, max) |"
    lines = [head, "|" + "---|" * (11 + len(MODULES))]
    for r in rows:
        ms = " | ".join(f"{r['median_ms'][m]:.1f}" if m in r["median_ms"] else "–" for m in MODULES)
        frames = f"{r['tracked']}/{r['frames']}" if "frames" in r else str(r.get("tracked", ""))
        lines.append(f"| {r['system']} | {r['sequence']} | {frames} | {r.get('keyframes', '–')} | "
                     f"{r['ate_rmse_m']:.4f} | {ms} | {_num(r.get('mean_total_ms'))} | "
                     f"{_num(r.get('backend_ms_per_keyframe'))} | {r.get('loops', '–')} | "
                     f"{_num(r.get('loop_ms_per_keyframe'))}, {_num(r.get('loop_ms_max'))} | "
                     f"{r.get('relocalizations', '–')} | {_num(r.get('reloc_ms_per_attempt'))}, "
                     f"{_num(r.get('reloc_ms_max'))} |")
    return "\n".join(lines)


def mapping_line(update_ms: np.ndarray) -> str:
    """The back end's own CPU per keyframe update (what the worker spends, off the tracking path): the
    median over the run and around each mark it reached."""
    if len(update_ms) == 0:
        return "mapping back end: no keyframe update"
    at_marks = backend_cost_at_marks(update_ms)
    marks = "".join(f", @{mark} {ms:.1f}" for mark, ms in sorted(at_marks.items()))
    return (f"mapping back end, CPU ms per keyframe update: median {np.median(update_ms):.1f} over "
            f"{len(update_ms)}{marks} (median of the {KEYFRAME_WINDOW} up to each mark)")


def method_line(method_ms: dict[str, float]) -> str:
    """The dynamic methods' median wall ms per frame (cpr's registration runs on its thread while the
    other methods run; ``detector`` and ``prepare_wait`` are what tracking waited for)."""
    if not method_ms:
        return "dynamic front end: none (dynamic handling off)"
    return "dynamic front end (methods, detector wait, steps), median wall ms per frame: " + ", ".join(
        f"{name} {ms:.1f}" for name, ms in sorted(method_ms.items(), key=lambda kv: -kv[1]))


def module_cpu_line(cpu_ms: dict[str, float]) -> str:
    """Each module's CPU (mean ms per frame, of the thread that ran it), largest first: beside the wall
    times above it says how much of a module's wall time was waiting for a core."""
    if not cpu_ms:
        return "module CPU: not measured"
    return "module CPU, mean ms per frame (the thread that ran it): " + ", ".join(
        f"{name} {ms:.1f}" for name, ms in sorted(cpu_ms.items(), key=lambda kv: -kv[1]) if name != "total")


TREND_LINE_MODULES = 6   # the modules whose mean changed most between the quarters


def module_trend_line(trends: dict[str, dict], clock: str = "wall") -> str:
    """The modules whose mean ``clock`` ms per frame ("wall", or "CPU" of the thread that ran each) changed
    most from the first quarter of the run to the last (``cost_trend``), largest change first: where a
    climbing step comes from. On a run bound by its cores the wall also holds the wait for a core (Bonn
    crowd-480's box_depth, 2026-12-03: wall 2.3 -> 21.1 ms per frame, CPU 0.7 -> 7.9)."""
    moved = sorted(((name, t) for name, t in trends.items() if t),
                   key=lambda kv: -abs(kv[1]["last_ms"] - kv[1]["first_ms"]))
    if not moved:
        return "step by module, first / last quarter: run too short"
    return f"step by module, mean {clock} ms per frame, first -> last quarter: " + ", ".join(
        f"{name} {t['first_ms']:.1f} -> {t['last_ms']:.1f}" for name, t in moved[:TREND_LINE_MODULES])


def _num(value) -> str:
    return "–" if value is None else f"{value:.1f}"


def long_run_table(report: dict, target_ratio: float) -> str:
    """First and last block of a long run, their ratio (beside ``target_ratio``, the most it may be), keyframes
    and memory, as Markdown."""
    first, last = report["blocks"][0], report["blocks"][-1]
    ratio = last["mean_ms"] / first["mean_ms"] if first["mean_ms"] > 0 else float("nan")
    ate = f", ATE {report['ate_rmse_m']:.4f} m" if report.get("ate_rmse_m") is not None else ""
    return "\n".join([
        f"long run: {report['sequence']}, {report['frames']} frames ({report['tracked']} tracked){ate}",
        "",
        "| frames | mean ms/frame | keyframes at the end (added) | RSS at the end (MiB) |",
        "|---|---|---|---|",
        *(f"| {b['first']}–{b['last']} | {b['mean_ms']:.1f} | {b['keyframes']} ({b['keyframes_added']}) "
          f"| {b['rss_end_mib']:.0f} |" for b in (first, last)),
        "",
        f"last / first: **{ratio:.2f}** (target ≤ {target_ratio}); whole run "
        f"{report['wall_ms_per_frame']:.1f} ms/frame; peak RSS {report['peak_rss_mib']:.0f} MiB (ru_maxrss), "
        f"{report['rss_peak_frames_mib']:.0f} MiB while tracking; RSS growth "
        f"{report['growth_mib_per_1000']:.1f} MiB per 1,000 frames (second half)",
    ])


