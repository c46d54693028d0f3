"""Atomic file writes: readers see the old file or the complete new one, never half of one.

The data goes to a temporary file in the destination folder (same file system, so the rename is
atomic), is flushed and fsynced, then ``os.replace``-d over the target; the folder is fsynced so the
rename survives a crash. On any failure the temporary file is removed and the old file stays.
``ensure_output_dir`` checks a results folder up front, so an unwritable one fails before any work.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import IO, Callable, Union

import numpy as np

from slam.core.errors import DynslamError

PathLike = Union[str, "os.PathLike[str]"]


class OutputDirError(DynslamError, OSError):
    """A results folder that cannot be created or written to."""


def ensure_output_dir(path: PathLike) -> Path:
    """Create ``path`` (with its parents) and prove it writable by creating and removing a file in it.

    Checking permissions instead would be wrong for root (who passes every permission check yet
    cannot write under a regular file or into /proc), so the check does what the run will do.
    Raises OutputDirError naming the folder and why.
    """
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".dynslam-write-check.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        if isinstance(exc, FileExistsError) or (folder.exists() and not folder.is_dir()):
            reason = "it exists and is not a folder"
        elif isinstance(exc, NotADirectoryError):
            reason = "a part of its path is a file, not a folder"
        raise OutputDirError(f"output folder {folder} cannot be used: {reason}") from None
    return folder


def write_atomic(path: PathLike, write: Callable[[IO[bytes]], None]) -> Path:
    """Call ``write(handle)`` on a binary temporary file, then move it over ``path``."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; results are meant to be shared
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        if os.path.exists(tmp_name):
            os.unlink(tmp_name)
        raise
    fsync_directory(target.parent)
    return target


def write_text_atomic(path: PathLike, text: str) -> Path:
    return write_atomic(path, lambda handle: handle.write(text.encode("utf-8")))


def write_npz_atomic(path: PathLike, **arrays: np.ndarray) -> Path:
    """A compressed .npz of plain arrays (loadable with allow_pickle=False)."""
    return write_atomic(path, lambda handle: np.savez_compressed(handle, **arrays))


def fsync_directory(directory: Path) -> None:
    """Persist a rename on POSIX by fsyncing the folder (best effort: not every FS allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
