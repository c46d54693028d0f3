"""What the CLI tests (tests/test_cli_*.py) share: ``main([...])`` run in-process with its output
captured, and the data lines of a TUM file."""
from __future__ import annotations

from pathlib import Path

from slam.cli import main


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def data_lines(path: Path) -> list[list[str]]:
    return [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
