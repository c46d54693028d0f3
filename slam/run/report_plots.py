"""The images of a run report: matplotlib figures and the dynamic-feature strip.

Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas, never through pyplot: no
global backend switch, no figure registry to leak, safe in threads and in test processes that
also use matplotlib. Every figure has the same fixed pixel size (``FIGURE_SIZE_PX``: no tight
bounding box, so sizes do not depend on the labels), and is written atomically.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import cv2
import numpy as np

from slam.core.atomic_io import write_atomic

if TYPE_CHECKING:
    from matplotlib.figure import Figure

FIGURE_SIZE_PX = (960, 720)     # width, height of every matplotlib image
_DPI = 120
_AXIS_NAMES = ("x", "y", "z")
STATIC_BGR = (60, 200, 60)      # features below the dynamic threshold
DYNAMIC_BGR = (40, 40, 230)     # features at or above it, and the mask tint
_MASK_ALPHA = 0.55


def preload_matplotlib() -> None:
    """Import what the figures need. matplotlib takes 1-2 s to import: imported here only when a figure
    is made, so the dynamic strip's thumbnails (OpenCV alone) do not pay for it inside the tracking loop,
    and a run imports it on a thread while its final adjustment runs (``Pipeline.run``)."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401


def _new_figure(rows: int = 1) -> tuple[Figure, list]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(FIGURE_SIZE_PX[0] / _DPI, FIGURE_SIZE_PX[1] / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(rows, 1, i + 1) for i in range(rows)]
    return fig, axes


def _save(fig: Figure, path: Path) -> Path:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=_DPI)
    return write_atomic(path, lambda handle: handle.write(buffer.getvalue()))


def top_view_axes(gt_xyz: np.ndarray) -> tuple[int, int]:
    """The two world axes along which the ground truth spreads most: the "top" view of a
    trajectory whatever the world's up axis is (z for motion capture, -y for camera-first worlds)."""
    spread = np.ptp(np.asarray(gt_xyz).reshape(-1, 3), axis=0)
    first, second = sorted(np.argsort(spread)[-2:])
    return int(first), int(second)


def plot_trajectory_top(path: Path, gt_xyz: np.ndarray, est_xyz: np.ndarray, errors: np.ndarray) -> Path:
    """Aligned estimate (coloured by its translation error) over the ground truth, top view."""
    a, b = top_view_axes(gt_xyz)
    fig, (ax,) = _new_figure()
    ax.plot(gt_xyz[:, a], gt_xyz[:, b], color="0.55", lw=2.0, label="ground truth")
    ax.plot(est_xyz[:, a], est_xyz[:, b], color="0.2", lw=0.6, alpha=0.6)
    points = ax.scatter(est_xyz[:, a], est_xyz[:, b], c=errors, cmap="viridis", s=9, zorder=3,
                        label="estimate (aligned)")
    fig.colorbar(points, ax=ax, label="translation error [m]")
    ax.plot(gt_xyz[0, a], gt_xyz[0, b], "k^", ms=8, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_title("Trajectory, top view (estimate after ATE alignment)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return _save(fig, path)


def plot_ate_over_time(path: Path, seconds: np.ndarray, errors: np.ndarray, rmse: float) -> Path:
    """Per-frame translation error after alignment, with its RMSE as a reference line."""
    fig, (ax,) = _new_figure()
    ax.plot(seconds, errors, color="tab:blue", lw=1.2, label="per-frame error")
    ax.axhline(rmse, color="tab:red", ls="--", lw=1.0, label=f"RMSE {rmse:.4f} m")
    ax.set_xlabel("time since first frame [s]")
    ax.set_ylabel("ATE [m]")
    ax.set_ylim(bottom=0.0)
    ax.set_title("Absolute trajectory error over time")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return _save(fig, path)


def plot_rpe(path: Path, frame_series: tuple[np.ndarray, np.ndarray, np.ndarray],
             second_series: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> Path:
    """Translational and rotational RPE, per frame and (when computed) over 1 s, against the time
    at which each pair ends. Series are ``(seconds, translation m, rotation deg)``."""
    fig, (ax_t, ax_r) = _new_figure(rows=2)
    for label, series, style in (("per frame", frame_series, "-"), ("over 1 s", second_series, "--")):
        if series is None:
            continue
        seconds, trans, rot = series
        ax_t.plot(seconds, trans, style, lw=1.0, label=label)
        ax_r.plot(seconds, rot, style, lw=1.0, label=label)
    ax_t.set_ylabel("translation [m]")
    ax_r.set_ylabel("rotation [deg]")
    ax_r.set_xlabel("time since first frame [s] (end of each pose pair)")
    ax_t.set_title("Relative pose error")
    for ax in (ax_t, ax_r):
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    fig.subplots_adjust(hspace=0.3)
    return _save(fig, path)


def plot_timing(path: Path, timing_ms: dict[str, dict[str, float]]) -> Path:
    """Median milliseconds per frame of each module as bars, the mean as a marker (the back end
    runs on keyframes only, so its median is 0 and its cost shows in the mean)."""
    names = list(timing_ms)
    medians = np.array([timing_ms[n]["median_ms"] for n in names], dtype=float)
    means = np.array([timing_ms[n].get("mean_ms", np.nan) for n in names], dtype=float)
    fig, (ax,) = _new_figure()
    y = np.arange(len(names))
    ax.barh(y, medians, color="tab:blue", label="median")
    ax.plot(means, y, "kD", ms=5, label="mean")
    right = np.fmax(medians, np.nan_to_num(means))
    pad = 0.01 * max(float(right.max(initial=0.0)), 1e-3)
    for row, (x, median, mean) in enumerate(zip(right, medians, means)):
        ax.text(x + 2 * pad, row, f"{median:.1f} / {mean:.1f}", va="center", fontsize="small")
    ax.set_xlim(0.0, 1.25 * float(right.max(initial=0.0)) + pad)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel("milliseconds per frame (labels: median / mean)")
    ax.set_title("Time per module")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="upper right", fontsize="small")
    fig.subplots_adjust(left=0.22)
    return _save(fig, path)


# ------------------------------------------------------------------ dynamic strip
def draw_dynamic_thumbnail(bgr: np.ndarray, uv: np.ndarray, dynamic_prob: np.ndarray,
                           mask: Optional[np.ndarray], threshold: float, width: int, label: str) -> np.ndarray:
    """A ``width``-pixel-wide copy of the image with the dynamic mask tinted red and each
    feature drawn green (static) or red (dynamic: probability >= ``threshold``)."""
    image = bgr if bgr.ndim == 3 else cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
    scale = width / image.shape[1]
    size = (width, max(1, round(image.shape[0] * scale)))
    small = cv2.resize(image[:, :, :3], size, interpolation=cv2.INTER_AREA).astype(np.float32)
    if mask is not None and mask.shape == image.shape[:2]:
        weight = _MASK_ALPHA * np.clip(cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA), 0, 1)
        small = small * (1.0 - weight[..., None]) + np.float32(DYNAMIC_BGR) * weight[..., None]
    out = np.ascontiguousarray(np.clip(small, 0, 255).astype(np.uint8))
    points = np.round(np.asarray(uv, dtype=float).reshape(-1, 2) * scale).astype(int)
    dynamic = np.asarray(dynamic_prob, dtype=float).reshape(-1) >= threshold
    for (u, v), is_dynamic in zip(points, dynamic):
        cv2.circle(out, (int(u), int(v)), 2, DYNAMIC_BGR if is_dynamic else STATIC_BGR, -1, cv2.LINE_AA)
    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):  # outlined: readable on any image
        cv2.putText(out, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, thickness, cv2.LINE_AA)
    return out


def compose_strip(thumbnails: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Thumbnails side by side (same height; narrower ones are padded) on a white background."""
    if not thumbnails:
        raise ValueError("no thumbnails to compose")
    height = max(t.shape[0] for t in thumbnails)
    width = sum(t.shape[1] for t in thumbnails) + gap * (len(thumbnails) - 1)
    strip = np.full((height, width, 3), 255, np.uint8)
    x = 0
    for thumb in thumbnails:
        strip[:thumb.shape[0], x:x + thumb.shape[1]] = thumb
        x += thumb.shape[1] + gap
    return strip


def write_png(path: Path, image: np.ndarray) -> Path:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode {path} as PNG")
    return write_atomic(path, lambda handle: handle.write(encoded.tobytes()))
