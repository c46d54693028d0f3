"""Trajectory files in the TUM, KITTI and EuRoC formats, and their names in a results folder.

Poses are 4x4 camera-to-world ``T_wc`` matrices, as everywhere in dynslam (see ``slam.run.trajectory``).

* TUM (default, ``slam.run.trajectory``): ``timestamp tx ty tz qx qy qz qw`` per line, quaternion last.
* KITTI: per line the 12 values of the top 3x4 block of ``T_wc``, row-major, space-separated, no
  header (the KITTI devkit reads plain numbers). KITTI poses carry no time, so every KITTI file
  ``<name>.kitti.txt`` has a companion ``<name>.kitti.times.txt`` with one timestamp (s) per line,
  in the same order.
* EuRoC: the CSV layout of EuRoC ground-truth files: header
  ``#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []``,
  integer nanoseconds, quaternion scalar *first*.

Names in a results folder (one row per kind of trajectory, one column per format):

=============================  ==========================  ==================================  ============================
kind                           TUM                         KITTI (+ ``.times.txt``)            EuRoC
=============================  ==========================  ==================================  ============================
final per frame (optimised)    ``trajectory.txt``          ``trajectory.kitti.txt``            ``trajectory.euroc.csv``
online per frame (causal)      ``trajectory_online.txt``   ``trajectory_online.kitti.txt``     ``trajectory_online.euroc.csv``
keyframes (optimised)          ``keyframes.txt``           ``keyframes.kitti.txt``             ``keyframes.euroc.csv``
=============================  ==========================  ==================================  ============================

The TUM files are the source: the other formats are converted from them (``export_trajectory``),
so every format holds exactly the same poses. Untracked frames appear in the TUM files as
``# <t> LOST`` comments; KITTI and EuRoC files hold the tracked poses only (KITTI has no comment
convention). Timestamps keep the TUM files' microsecond resolution, so EuRoC nanoseconds end in 000.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.core.atomic_io import write_text_atomic
from slam.core.config import TRAJECTORY_FORMATS
from slam.run.trajectory import (PathLike, TrajectoryFormatError, _check_trajectory, matrix_to_quaternion,
                             poses_from_tum_rows, read_tum)

# Kinds of trajectory in a results folder -> the stem shared by all their files.
TRAJECTORY_KINDS = {"final": "trajectory", "online": "trajectory_online", "keyframes": "keyframes"}
EUROC_HEADER = ("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],"
                "q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []")
_SECONDS_FMT = "%.6f"        # the TUM files' timestamp resolution (microseconds)
_KITTI_FMT = "%.12e"         # 13 significant digits: re-prints every %.9f TUM value exactly
_EUROC_FMT = "%.9f"          # as the TUM files, so EuRoC positions equal the TUM ones bit for bit


def check_format(fmt: str) -> str:
    """The format name, or ValueError listing the valid ones."""
    if fmt not in TRAJECTORY_FORMATS:
        raise ValueError(f"unknown trajectory format '{fmt}' (valid: {', '.join(TRAJECTORY_FORMATS)})")
    return fmt


def trajectory_kind(online: bool = False, keyframes: bool = False) -> str:
    """'final', 'online' or 'keyframes' from the CLI flags (keyframes exist only optimised)."""
    if online and keyframes:
        raise ValueError("--online and --keyframes exclude each other: keyframe poses are only written "
                         "optimised (keyframes.txt)")
    return "online" if online else "keyframes" if keyframes else "final"


def trajectory_path(results_dir: PathLike, fmt: str, kind: str = "final") -> Path:
    """The file of ``kind`` in ``fmt`` inside a results folder (see the module docstring's table)."""
    if kind not in TRAJECTORY_KINDS:
        raise ValueError(f"unknown trajectory kind '{kind}' (valid: {', '.join(TRAJECTORY_KINDS)})")
    stem = TRAJECTORY_KINDS[kind]
    suffix = {"tum": ".txt", "kitti": ".kitti.txt", "euroc": ".euroc.csv"}[check_format(fmt)]
    return Path(results_dir) / f"{stem}{suffix}"


def kitti_times_path(kitti_path: PathLike) -> Path:
    """``x.kitti.txt`` -> ``x.kitti.times.txt`` (any other name gets ``.times.txt`` appended)."""
    path = Path(kitti_path)
    stem = path.name[:-4] if path.name.endswith(".txt") else path.name
    return path.with_name(f"{stem}.times.txt")


# -------------------------------------------------------------------- writing
def _sorted(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t, P = _check_trajectory(stamps, poses)
    order = np.argsort(t, kind="stable")
    return t[order], P[order]


def write_kitti(path: PathLike, stamps: np.ndarray, poses: np.ndarray) -> tuple[Path, Path]:
    """Write ``path`` (12 values per pose) and its ``.times.txt`` atomically, sorted by time."""
    t, P = _sorted(stamps, poses)
    rows = P[:, :3, :4].reshape(-1, 12)
    poses_text = "".join(" ".join(_KITTI_FMT % v for v in row) + "\n" for row in rows)
    times_text = "".join(_SECONDS_FMT % ts + "\n" for ts in t)
    times = kitti_times_path(path)
    return write_text_atomic(path, poses_text), write_text_atomic(times, times_text)


def seconds_to_nanoseconds(stamps: np.ndarray) -> list[int]:
    """Integer nanoseconds of each stamp as printed in TUM files (%.6f): exact integers, where
    ``t * 1e9`` in floating point would be off by up to ~100 ns at Unix-epoch magnitudes."""
    return [int((_SECONDS_FMT % t).replace(".", "")) * 1000 for t in np.asarray(stamps, dtype=np.float64)]


def write_euroc(path: PathLike, stamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write an EuRoC ground-truth-style CSV atomically, sorted by time."""
    t, P = _sorted(stamps, poses)
    quat_xyzw = matrix_to_quaternion(P[:, :3, :3]) if len(P) else np.zeros((0, 4))
    values = np.hstack([P[:, :3, 3], quat_xyzw[:, [3, 0, 1, 2]]])  # scalar first
    lines = [f"{ns}," + ",".join(_EUROC_FMT % v for v in row)
             for ns, row in zip(seconds_to_nanoseconds(t), values)]
    return write_text_atomic(path, "\n".join([EUROC_HEADER, *lines]) + "\n")


def write_trajectory(path: PathLike, fmt: str, stamps: np.ndarray, poses: np.ndarray) -> list[Path]:
    """Write a trajectory in ``fmt``; returns the files written (two for KITTI)."""
    from slam.run.trajectory import write_tum

    if check_format(fmt) == "tum":
        write_tum(path, stamps, poses)
        return [Path(path)]
    if fmt == "kitti":
        return list(write_kitti(path, stamps, poses))
    return [write_euroc(path, stamps, poses)]


# -------------------------------------------------------------------- reading
def _numeric_rows(path: PathLike, delimiter: str | None, n_columns: int, what: str,
                  extra_columns: bool = False, quaternion: slice | None = None) -> np.ndarray:
    """The first ``n_columns`` floats of every non-comment line as an (N, n_columns) array;
    a malformed line (or a zero ``quaternion`` in it) raises :class:`TrajectoryFormatError`
    naming the file and line."""
    rows: list[list[float]] = []
    with open(path, encoding="utf-8-sig") as handle:
        for number, raw in enumerate(handle, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split(delimiter)
            if len(fields) < n_columns or (len(fields) > n_columns and not extra_columns):
                raise TrajectoryFormatError(path, number, f"expected {what}, got {len(fields)} values")
            try:
                values = [float(f) for f in fields[:n_columns]]
            except ValueError as exc:
                raise TrajectoryFormatError(path, number, f"not a number ({exc})") from None
            if not np.all(np.isfinite(values)):
                raise TrajectoryFormatError(path, number, "non-finite value (nan or inf)")
            if quaternion is not None and np.linalg.norm(values[quaternion]) < 1e-9:
                raise TrajectoryFormatError(path, number, "zero-norm quaternion")
            rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, n_columns)


def read_kitti(path: PathLike, times_path: PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI pose file and its times file (default: :func:`kitti_times_path`) into
    ``(timestamps (N,), poses (N,4,4))``; the two must have the same number of lines."""
    times_path = kitti_times_path(path) if times_path is None else Path(times_path)
    rows = _numeric_rows(path, None, 12, "12 values (3x4 pose, row-major)")
    stamps = _numeric_rows(times_path, None, 1, "1 timestamp").reshape(-1)
    if len(stamps) != len(rows):
        raise ValueError(f"{path} has {len(rows)} poses but {times_path} has {len(stamps)} timestamps")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return stamps, poses


def read_euroc(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an EuRoC CSV (nanoseconds, position, quaternion w first; extra columns such as the
    ground truth's velocities and biases are ignored) into ``(timestamps (N,) s, poses (N,4,4))``."""
    rows = _numeric_rows(path, ",", 8, "at least 8 values 't_ns,px,py,pz,qw,qx,qy,qz'",
                         extra_columns=True, quaternion=slice(4, 8))
    return rows[:, 0] / 1e9, poses_from_tum_rows(np.hstack([rows[:, 1:4], rows[:, [5, 6, 7, 4]]]))


# ------------------------------------------------------------ results folders
def export_trajectory(results_dir: PathLike, fmt: str, kind: str = "final") -> list[Path]:
    """Convert the TUM file of ``kind`` in a results folder to ``fmt`` beside it (names in the
    module docstring); returns the files written, or the TUM file itself for ``fmt='tum'``."""
    source = trajectory_path(results_dir, "tum", kind)
    if not Path(results_dir).is_dir():
        raise FileNotFoundError(f"results folder {results_dir} does not exist")
    if not source.is_file():
        raise FileNotFoundError(f"{source} not found: is {results_dir} a dynslam results folder?")
    if check_format(fmt) == "tum":
        return [source]
    stamps, poses = read_tum(source)
    return write_trajectory(trajectory_path(results_dir, fmt, kind), fmt, stamps, poses)


def export_formats(results_dir: PathLike, formats: list[str]) -> list[Path]:
    """Every kind whose TUM file exists in ``results_dir``, in every non-TUM format of ``formats``."""
    written: list[Path] = []
    for fmt in dict.fromkeys(formats):
        if check_format(fmt) == "tum":
            continue
        for kind in TRAJECTORY_KINDS:
            if trajectory_path(results_dir, "tum", kind).is_file():
                written += export_trajectory(results_dir, fmt, kind)
    return written
