"""Trajectory I/O in the TUM RGB-D format and quaternion conversions.

Pose convention: every pose is a 4x4 float64 camera-to-world matrix ``T_wc``
(it maps points from the camera frame into the world frame), so its last
column is the camera centre in world coordinates. A TUM file stores one pose
per line as ``timestamp tx ty tz qx qy qz qw`` (Hamilton quaternion, scalar
last); lines starting with ``#`` are comments and blank lines are ignored.

Readers here are strict (a malformed line is an error naming file and line)
because a silently skipped pose changes evaluation results; writers are
atomic or line-flushed so that a crash never leaves a half-written pose.
"""
from __future__ import annotations

import os
from pathlib import Path
from types import TracebackType
from typing import IO, Union

import numpy as np
from scipy.spatial.transform import Rotation

from slam.core.atomic_io import write_text_atomic  # noqa: F401  (re-exported)
from slam.core.errors import DynslamError

PathLike = Union[str, "os.PathLike[str]"]  # str or pathlib.Path

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
_TIME_FMT = "%.6f"
_VALUE_FMT = "%.9f"
_QUAT_NORM_MIN = 1e-9


class TrajectoryFormatError(DynslamError, ValueError):
    """A trajectory file line that cannot be parsed as a TUM pose."""

    def __init__(self, path: PathLike, line_number: int, reason: str) -> None:
        self.path = str(path)
        self.line_number = line_number
        self.reason = reason
        super().__init__(f"{self.path}, line {line_number}: {reason}")


# ---------------------------------------------------------------- quaternions
def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Convert rotation matrices to unit quaternions ``(qx, qy, qz, qw)``.

    Accepts (3,3) or (N,3,3) (4x4 poses are accepted too, their rotation block
    is used) and returns (4,) or (N,4). Uses scipy's Shepperd-style conversion,
    which stays accurate near 180 degrees; the sign is canonicalised to
    ``qw >= 0`` so equal rotations always print the same quaternion.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] == (4, 4):
        R = R[..., :3, :3]
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise ValueError(f"expected (3,3) or (N,3,3) rotations, got shape {R.shape}")
    return Rotation.from_matrix(R).as_quat(canonical=True)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Convert quaternions ``(qx, qy, qz, qw)`` of shape (4,) or (N,4) to rotations.

    Quaternions are normalised first (TUM files store 4 decimals, so they are
    rarely exactly unit), matching what evo and the TUM scripts do. A
    (near-)zero quaternion raises ValueError because it encodes no rotation.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4 or q.ndim not in (1, 2):
        raise ValueError(f"expected (4,) or (N,4) quaternions, got shape {q.shape}")
    if np.any(np.linalg.norm(q, axis=-1) < _QUAT_NORM_MIN):
        raise ValueError("zero-norm quaternion cannot be converted to a rotation")
    return Rotation.from_quat(q).as_matrix()


def poses_from_tum_rows(rows: np.ndarray) -> np.ndarray:
    """Build (N,4,4) ``T_wc`` poses from (N,7) rows ``tx ty tz qx qy qz qw``."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if len(rows):
        poses[:, :3, :3] = quaternion_to_matrix(rows[:, 3:7])
        poses[:, :3, 3] = rows[:, :3]
    return poses


def tum_rows_from_poses(poses: np.ndarray) -> np.ndarray:
    """Inverse of :func:`poses_from_tum_rows`: (N,4,4) poses to (N,7) rows."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if not len(poses):
        return np.zeros((0, 7))
    return np.hstack([poses[:, :3, 3], matrix_to_quaternion(poses[:, :3, :3])])


# -------------------------------------------------------------------- reading
def _parse_line(path: PathLike, number: int, line: str) -> list[float]:
    """Parse one non-comment line into 8 finite floats or raise with its location."""
    fields = line.replace(",", " ").split()
    if len(fields) != 8:
        raise TrajectoryFormatError(
            path, number, f"expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(fields)}"
        )
    try:
        values = [float(f) for f in fields]
    except ValueError as exc:
        raise TrajectoryFormatError(path, number, f"not a number ({exc})") from None
    if not np.all(np.isfinite(values)):
        raise TrajectoryFormatError(path, number, "non-finite value (nan or inf)")
    if np.linalg.norm(values[4:8]) < _QUAT_NORM_MIN:
        raise TrajectoryFormatError(path, number, "zero-norm quaternion")
    return values


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file into ``(timestamps (N,), poses (N,4,4))``.

    Blank lines and ``#`` comments (including the ``# <t> LOST`` markers of
    :class:`TumStreamWriter`) are skipped. Poses are returned sorted by
    timestamp (stable, so duplicates keep file order) because association
    assumes sorted stamps. Raises FileNotFoundError for a missing file and
    :class:`TrajectoryFormatError` for a malformed line. An empty file gives
    empty arrays.
    """
    rows: list[list[float]] = []
    with open(path, encoding="utf-8-sig") as handle:
        for number, raw in enumerate(handle, start=1):
            line = raw.strip()
            if line and not line.startswith("#"):
                rows.append(_parse_line(path, number, line))
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    data = data[np.argsort(data[:, 0], kind="stable")]
    return data[:, 0].copy(), poses_from_tum_rows(data[:, 1:])


# -------------------------------------------------------------------- writing
def _check_trajectory(timestamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and finiteness; return float64 copies."""
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    P = np.asarray(poses, dtype=np.float64)
    if P.shape != (len(t), 4, 4):
        raise ValueError(f"poses must have shape ({len(t)}, 4, 4) to match the timestamps, got {P.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(P))):
        raise ValueError("timestamps and poses must be finite")
    return t, P


def format_tum_line(timestamp: float, row: np.ndarray) -> str:
    """Format one pose row ``tx ty tz qx qy qz qw`` as a TUM line (with newline)."""
    values = " ".join(_VALUE_FMT % v for v in row)
    return f"{_TIME_FMT % timestamp} {values}\n"


def write_tum(path: PathLike, timestamps: np.ndarray, poses: np.ndarray) -> None:
    """Write a trajectory atomically as a TUM file, sorted by timestamp.

    The data goes to a temporary file in the destination directory, is flushed
    and fsynced, then ``os.replace``-d over ``path``: readers see either the
    old file or the complete new one, never a truncated mix. Timestamps use
    ``%.6f`` (the TUM convention), values ``%.9f`` (sub-micrometre).
    """
    t, P = _check_trajectory(timestamps, poses)
    order = np.argsort(t, kind="stable")
    rows = tum_rows_from_poses(P[order])
    text = TUM_HEADER + "\n" + "".join(format_tum_line(ts, r) for ts, r in zip(t[order], rows))
    write_text_atomic(path, text)


class TumStreamWriter:
    """Write poses to a TUM file one frame at a time, flushing every line.

    Meant for the tracker's live output: if the process dies, every frame
    appended so far is already in the file. ``mark_lost(t)`` records a
    tracking loss as the comment ``# <t> LOST``, which TUM readers (this
    module, evo, the TUM scripts) skip. Use as a context manager::

        with TumStreamWriter("est.txt") as out:
            out.append(t, T_wc)

    With ``fsync=True`` every line is also fsynced (survives power loss, but
    costs a disk sync per frame).
    """

    def __init__(self, path: PathLike, fsync: bool = False) -> None:
        self.path = Path(path)
        self._fsync = fsync
        self._handle: IO[str] | None = open(self.path, "w", encoding="utf-8")
        self._write(TUM_HEADER + "\n")

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has been called."""
        return self._handle is None

    def _write(self, text: str) -> None:
        if self._handle is None:
            raise ValueError(f"TumStreamWriter for {self.path} is closed")
        self._handle.write(text)
        self._handle.flush()
        if self._fsync:
            os.fsync(self._handle.fileno())

    def append(self, timestamp: float, pose: np.ndarray) -> None:
        """Write one ``T_wc`` pose (4x4) at ``timestamp`` and flush it."""
        t, P = _check_trajectory(np.array([timestamp]), np.asarray(pose)[None])
        self._write(format_tum_line(float(t[0]), tum_rows_from_poses(P)[0]))

    def mark_lost(self, timestamp: float) -> None:
        """Record that tracking was lost at ``timestamp`` (a comment line)."""
        if not np.isfinite(timestamp):
            raise ValueError("timestamp must be finite")
        self._write(f"# {_TIME_FMT % timestamp} LOST\n")

    def close(self) -> None:
        """Close the file; further writes raise ValueError. Idempotent."""
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def __enter__(self) -> "TumStreamWriter":
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
