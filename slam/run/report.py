"""The report a person looks at: plots, the series behind them and an ``index.html``, written to
``<results>/report/`` at the end of a run (``output.report: false`` turns it off).

=========================  ===================================================================
file                       content
=========================  ===================================================================
``index.html``             the summary numbers (frames, tracking, keyframes, ATE, RPE, ms/frame
                           per module, dynamic flags) and all images below; self-contained,
                           relative links, open it in a browser
``trajectory_top.png``     estimate after the ATE alignment over the ground truth, top view,
                           coloured by per-frame translation error (with ground truth)
``ate_over_time.png/.csv`` per-frame translation error after alignment (the CSV is the plotted
                           series; its RMSE is the summary's ATE RMSE)
``rpe.png``, ``rpe.csv``   translational / rotational RPE per frame (and over 1 s in the plot)
``timing.png``             median (bar) and mean (marker) milliseconds per frame per module
``dynamic_strip.png``      with dynamic handling on: ~6 evenly spaced frames, static features
                           green, dynamic red, the dynamic mask tinted red
=========================  ===================================================================

A report never breaks a run: each artefact is made on its own, and a failure logs a warning and
leaves that artefact out of the page.
"""
from __future__ import annotations

import html
import logging
import math
from pathlib import Path
from typing import Any, Callable, Optional, Protocol

import numpy as np

from slam.core.atomic_io import write_text_atomic
from slam.run.evaluation import EvaluationReport

log = logging.getLogger("dynslam")
REPORT_DIR = "report"
STRIP_FRAMES = 6
THUMBNAIL_WIDTH = 320


# ------------------------------------------------------------------ thumbnails
class StripRecorder(Protocol):
    """What a run asks of its dynamic-strip recorder (``DynamicStripRecorder`` or ``NullStripRecorder``)."""

    @property
    def thumbnails(self) -> list[np.ndarray]: ...

    def observe(self, position: int, bgr: np.ndarray, frame: Any,
                mask: Callable[[], Optional[np.ndarray]]) -> None: ...


class DynamicStripRecorder:
    """Keeps at most ``capacity`` small annotated frames, evenly spaced over the run.

    With the expected frame count known, the frames are fixed up front (``linspace`` over the
    run, first and last included). Otherwise every ``step``-th frame is kept and, whenever the
    buffer is full, every second one is dropped and the step doubled: the spacing stays even and
    memory bounded without knowing where the run ends. A run stopped early keeps fewer frames.
    """

    def __init__(self, dynamic_threshold: float, expected_frames: Optional[int] = None,
                 capacity: int = STRIP_FRAMES, width: int = THUMBNAIL_WIDTH):
        self.threshold, self.capacity, self.width = dynamic_threshold, capacity, width
        self._targets: Optional[set[int]] = None
        if expected_frames:
            self._targets = set(np.round(np.linspace(0, expected_frames - 1, capacity)).astype(int).tolist())
        self._step = 1
        self._kept: list[tuple[int, np.ndarray]] = []

    def _wanted(self, position: int) -> bool:
        if self._targets is not None:
            return position in self._targets
        if position % self._step:
            return False
        if len(self._kept) >= self.capacity:
            self._step *= 2
            self._kept = [(p, t) for p, t in self._kept if p % self._step == 0]
        return position % self._step == 0

    def observe(self, position: int, bgr: np.ndarray, frame: Any,
                mask: Callable[[], Optional[np.ndarray]]) -> None:
        """Offer the ``position``-th processed frame (image, its FeatureFrame, a callable giving its dynamic
        mask). The mask is asked for only for a kept frame: fusing it costs ~10 ms, ~6 frames are kept."""
        if frame is None or not self._wanted(position):
            return
        from slam.run.report_plots import draw_dynamic_thumbnail

        n_dynamic = int(np.count_nonzero(frame.dynamic_prob >= self.threshold))
        label = f"frame {position}: {n_dynamic}/{len(frame.dynamic_prob)} dynamic"
        thumb = draw_dynamic_thumbnail(bgr, frame.uv_raw, frame.dynamic_prob, mask(), self.threshold,
                                       self.width, label)
        self._kept.append((position, thumb))

    @property
    def thumbnails(self) -> list[np.ndarray]:
        return [thumb for _, thumb in self._kept]


class NullStripRecorder:
    """Stands in when there is no strip to make (dynamic handling or reports off)."""

    @property
    def thumbnails(self) -> list[np.ndarray]:
        return []

    def observe(self, position: int, bgr: np.ndarray, frame: Any,
                mask: Callable[[], Optional[np.ndarray]]) -> None:
        return None


def make_strip_recorder(config, expected_frames: Optional[int]):
    """The recorder for a run: a real one only when it will make a report with dynamic handling on."""
    if not (config.output.report and config.dynamic.methods):
        return NullStripRecorder()
    return DynamicStripRecorder(config.tracking.dynamic_threshold, expected_frames)


# ------------------------------------------------------------------ the report
def _write_csv(path: Path, header: str, columns: list[np.ndarray], fmt: str = "%.12e") -> Path:
    rows = np.column_stack(columns) if columns and len(columns[0]) else np.zeros((0, len(columns)))
    lines = [header] + [",".join(fmt % v for v in row) for row in rows]
    return write_text_atomic(path, "\n".join(lines) + "\n")


def _evaluation_artefacts(folder: Path, evaluation: EvaluationReport) -> dict[str, Callable[[], Any]]:
    from slam.run import report_plots as plots

    ate = evaluation.ate
    t0 = float(ate.timestamps[0])
    est_xyz = ate.aligned_poses[:, :3, 3]

    def series(rpe):
        return None if rpe is None else (rpe.pair_timestamps[:, 1] - t0, rpe.translation_errors,
                                         rpe.rotation_errors)

    def ate_over_time():
        _write_csv(folder / "ate_over_time.csv", "timestamp,gt_timestamp,ate_m",
                   [ate.timestamps, ate.gt_timestamps, ate.errors])
        plots.plot_ate_over_time(folder / "ate_over_time.png", ate.timestamps - t0, ate.errors, ate.rmse)

    def rpe():
        frame = evaluation.rpe_frame
        _write_csv(folder / "rpe.csv", "pair_start,pair_end,translation_m,rotation_deg",
                   [frame.pair_timestamps[:, 0], frame.pair_timestamps[:, 1], frame.translation_errors,
                    frame.rotation_errors])
        plots.plot_rpe(folder / "rpe.png", series(frame), series(evaluation.rpe_time))

    artefacts: dict[str, Callable[[], Any]] = {"ate_over_time.png": ate_over_time, "rpe.png": rpe}
    if ate.gt_positions is not None:
        artefacts["trajectory_top.png"] = lambda: plots.plot_trajectory_top(
            folder / "trajectory_top.png", ate.gt_positions, est_xyz, ate.errors)
    return artefacts


def write_report(output_dir: Path | str, summary: dict[str, Any], evaluation: Optional[EvaluationReport],
                 strip_thumbnails: list[np.ndarray]) -> Path:
    """Write ``<output_dir>/report/`` (see the module docstring); returns the index.html path.
    Images whose data is missing (no ground truth, no timing, no dynamic handling) are left out."""
    from slam.run import report_plots as plots

    folder = Path(output_dir) / REPORT_DIR
    folder.mkdir(parents=True, exist_ok=True)
    artefacts: dict[str, Callable[[], Any]] = {}
    if evaluation is not None:
        artefacts.update(_evaluation_artefacts(folder, evaluation))
    if summary.get("timing_ms"):
        artefacts["timing.png"] = lambda: plots.plot_timing(folder / "timing.png", summary["timing_ms"])
    if strip_thumbnails:
        artefacts["dynamic_strip.png"] = lambda: plots.write_png(folder / "dynamic_strip.png",
                                                                 plots.compose_strip(strip_thumbnails))
    written = []
    for name, make in artefacts.items():
        try:
            make()
            written.append(name)
        except Exception as exc:  # a plot must never cost the run its results
            log.warning("report: %s not written (%s: %s)", folder / name, type(exc).__name__, exc)
    return write_text_atomic(folder / "index.html", render_index(summary, evaluation, written))


# ------------------------------------------------------------------ index.html
_IMAGE_TITLES = {
    "trajectory_top.png": "Trajectory (top view, aligned, coloured by error)",
    "ate_over_time.png": "Absolute trajectory error over time",
    "rpe.png": "Relative pose error",
    "timing.png": "Milliseconds per frame by module",
    "dynamic_strip.png": "Dynamic features (green static, red dynamic, mask tinted red)",
}
_CSV_FOR_IMAGE = {"ate_over_time.png": "ate_over_time.csv", "rpe.png": "rpe.csv"}
_STYLE = ("body{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}"
          "table{border-collapse:collapse;margin:0.5em 0 1.5em}"
          "td,th{border:1px solid #ccc;padding:3px 10px;text-align:right}"
          "th:first-child,td:first-child{text-align:left}img{max-width:100%;border:1px solid #ddd}")


def _fmt(value: Any, digits: int = 4) -> str:
    if isinstance(value, float):
        return "–" if not math.isfinite(value) else f"{value:.{digits}f}"
    return str(value)


def _table(header: list[str], rows: list[list[Any]], digits: int = 4) -> str:
    esc = html.escape
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(_fmt(v, digits))}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


_RUN_LABELS = {"dataset": "dataset", "dataset_path": "dataset path", "frames": "frames", "tracked": "tracked",
               "lost": "lost", "keyframes": "keyframes", "landmarks": "landmarks", "wall_time_s": "wall time [s]",
               "interrupted": "interrupted", "ate_rmse_m": "ATE RMSE [m]"}
_MAX_LOST_LISTED = 50


def _run_rows(summary: dict[str, Any]) -> list[list[Any]]:
    rows = [[label, summary[key]] for key, label in _RUN_LABELS.items() if summary.get(key) is not None]
    lost = summary.get("lost_frames") or []
    if lost:
        more = f" ... ({len(lost)} in all)" if len(lost) > _MAX_LOST_LISTED else ""
        rows.append(["lost frames", ", ".join(map(str, lost[:_MAX_LOST_LISTED])) + more])
    return rows


def _accuracy_tables(evaluation: EvaluationReport) -> str:
    ate = evaluation.ate
    stats = ("rmse", "mean", "median", "std", "min", "max")
    rows = [[f"ATE [m] ({ate.n_matched} poses)", *[getattr(ate, k) for k in stats]]]
    for label, res in (("RPE per frame", evaluation.rpe_frame), ("RPE over 1 s", evaluation.rpe_time)):
        if res is not None:
            rows.append([f"{label}, translation [{res.translation_unit}] ({res.n_pairs} pairs)",
                         *[getattr(res.translation, k) for k in stats]])
            rows.append([f"{label}, rotation [{res.rotation_unit}]", *[getattr(res.rotation, k) for k in stats]])
    notes = "".join(f"<p>note: {html.escape(n)}</p>" for n in evaluation.notes)
    return "<h2>Accuracy</h2>" + _table(["metric", *stats], rows) + notes


def _timing_table(timing: dict[str, dict[str, float]]) -> str:
    rows = [[name, v.get("median_ms", float("nan")), v.get("mean_ms", float("nan")), v.get("max_ms", float("nan"))]
            for name, v in timing.items()]
    return "<h2>Milliseconds per frame</h2>" + _table(["module", "median", "mean", "max"], rows, digits=1)


def _dynamic_table(summary: dict[str, Any]) -> str:
    flagged: dict[str, dict[str, float]] = summary.get("dynamic_flagged") or {}
    methods = ", ".join(summary.get("dynamic_methods") or [])
    rows = [[name, v.get("mean_flagged", float("nan")), v.get("max_flagged", ""), v.get("frames_with_flags", "")]
            for name, v in flagged.items()]
    table = _table(["method", "mean flagged / frame", "max flagged", "frames with flags"], rows, digits=1)
    return f"<h2>Dynamic features</h2><p>methods: {html.escape(methods)}</p>" + table


def render_index(summary: dict[str, Any], evaluation: Optional[EvaluationReport], images: list[str]) -> str:
    """The report page: summary tables, then each written image (relative links, escaped values)."""
    title = html.escape(f"dynslam report: {summary.get('dataset', '')}")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{title}</title>",
             f"<style>{_STYLE}</style></head><body><h1>{title}</h1>",
             "<h2>Run</h2>" + _table(["", "value"], _run_rows(summary))]
    parts.append(_accuracy_tables(evaluation) if evaluation is not None
                 else "<p>No ground truth: no accuracy figures.</p>")
    if summary.get("timing_ms"):
        parts.append(_timing_table(summary["timing_ms"]))
    if summary.get("dynamic_methods"):
        parts.append(_dynamic_table(summary))
    for name in images:
        src = html.escape(name, quote=True)
        data = _CSV_FOR_IMAGE.get(name)
        link = f" (<a href='{html.escape(data, quote=True)}'>data</a>)" if data else ""
        parts.append(f"<h2>{html.escape(_IMAGE_TITLES.get(name, name))}{link}</h2>"
                     f"<img src='{src}' alt='{src}'>")
    files = ["summary.json", "config.yaml"] + (["evaluation.json"] if evaluation is not None else [])
    links = ", ".join(f"<a href='../{name}'>{name}</a>" for name in files)
    parts.append(f"<p>Files of the run: {links}</p></body></html>")
    return "\n".join(parts) + "\n"
