"""What the fault-table tests (tests/test_faults_*.py) share besides conftest's ``tum_folder`` fixture:
the strict reader of the TUM files dynslam writes."""
from __future__ import annotations

import re
import tempfile
from pathlib import Path

import pytest

from slam.run.trajectory import read_tum

LOST_LINE = re.compile(r"^# (\d+\.\d+) LOST$")


def frame_lines(path: Path, complete_only: bool = False) -> tuple[list[float], list[float]]:
    """(pose timestamps, LOST timestamps) of a TUM file written by dynslam; every line must parse.

    ``complete_only``: a file that may have been cut by a kill, so its last line may be partial.
    """
    text = path.read_text()
    lines = text.split("\n")
    if complete_only:
        lines = lines[:-1]   # the part after the last newline is partial (or empty)
    elif lines[-1] != "":
        pytest.fail(f"{path} does not end with a newline")
    with tempfile.TemporaryDirectory() as scratch:   # the complete lines, for the strict reader
        body = Path(scratch) / path.name
        body.write_text("\n".join(lines) + "\n")
        stamps, _ = read_tum(body)   # any malformed line is an error naming it
    poses = sorted(stamps.tolist())
    lost = [float(m.group(1)) for m in map(LOST_LINE.match, lines) if m]
    comments = [line for line in lines if line.startswith("#") and not LOST_LINE.match(line)]
    assert all(line.startswith("# timestamp") for line in comments), comments   # headers only
    return poses, lost
