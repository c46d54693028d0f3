"""The fault table (issue 9), rows 1, 2 and 11: a run stopped from outside (SIGINT, SIGKILL, a
terminal's Ctrl-C), and a results folder that cannot be written.

Each test is one row: the fault is injected, and the behaviour checked is a clear exit, every result
file complete or absent, and nothing already computed lost.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from _fault_helpers import LOST_LINE, frame_lines
from conftest import FAULT_TUM_FRAMES as TUM_FRAMES
from conftest import REPO, RPY, read_summary, real_sequence, run_dynslam
from slam.cli import main
from slam.run.trajectory import read_tum

pytestmark = pytest.mark.usefixtures("restore_warning_format")

TEMP_NAME = re.compile(r"^\..+\.tmp$")     # slam.core.atomic_io's temporary files


# --- results folders: complete or absent ---------------------------------------------------------------

def check_final_file(path: Path) -> None:
    """A final result file parses completely (each kind with its own reader)."""
    import gtsam

    name = path.name
    if name in ("trajectory.txt", "keyframes.txt", "groundtruth.txt"):
        frame_lines(path)
    elif name.endswith(".json"):
        json.loads(path.read_text())
    elif name == "config.yaml":
        assert isinstance(yaml.safe_load(path.read_text()), dict)
    elif name == "graph.g2o":
        graph, initial = gtsam.readG2o(str(path), True)
        assert initial.size() > 0
    elif name == "map.npz":
        from backend.map_io import load_map

        load_map(path)
    elif name == "map_sparse.ply":
        header, _, body = path.read_bytes().partition(b"end_header\n")
        vertices = int(re.search(rb"element vertex (\d+)", header).group(1))
        assert vertices > 0 and len(body) > 0 and len(body) % vertices == 0
    elif name.endswith(".png"):
        assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None, path
    elif name == "frames.txt":
        assert all(len(line.split()) == 2 for line in path.read_text().splitlines()[1:])


def check_results_folder(out: Path) -> set[str]:
    """Every file under ``out`` is complete, or an atomic write's temporary file; returns the names."""
    names = set()
    for path in sorted(out.rglob("*")):
        if path.is_dir():
            continue
        names.add(path.name)
        if TEMP_NAME.match(path.name):
            continue
        if path.name == "trajectory_online.txt":
            frame_lines(path, complete_only=True)
        else:
            check_final_file(path)
    return names


def popen_run(args: list[str], stderr_path: Path) -> subprocess.Popen:
    """``dynslam run ARGS`` as a child process with SIGINT at its default (Python's Ctrl-C), whatever
    the test runner's own disposition (a background job's SIGINT is ignored)."""
    with stderr_path.open("w") as stderr:   # the child keeps its own copy
        return subprocess.Popen([sys.executable, "-m", "slam.cli", "run", *args], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=stderr,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def wait_for(condition, process: subprocess.Popen, timeout: float, what: str, poll: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if process.poll() is not None:
            pytest.fail(f"the run ended (exit {process.returncode}) before {what}")
        if time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(poll)


def online_frames(out: Path) -> int:
    path = out / "trajectory_online.txt"
    if not path.is_file():
        return 0
    lines = path.read_text().split("\n")[:-1]
    return sum(1 for line in lines if line and (not line.startswith("#") or LOST_LINE.match(line)))


# --- 1. SIGINT -----------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.real
def test_sigint_stops_after_the_frame_and_writes_every_result(tmp_path):
    """Ctrl-C at frame ~40 of fr1/rpy, and again while the results are written: exit 130, every final
    file complete, the final trajectory covering exactly the frames the online one lists."""
    seq = real_sequence(RPY)
    out, err = tmp_path / "out", tmp_path / "stderr.txt"
    process = popen_run([str(seq), "-o", str(out), "-q", "--set", "output.report=false"], err)
    wait_for(lambda: online_frames(out) >= 40, process, 240, "40 frames were processed")
    process.send_signal(signal.SIGINT)
    wait_for(lambda: (out / "trajectory.txt").exists(), process, 120, "the final writes began", poll=0.005)
    process.send_signal(signal.SIGINT)   # during the final writes: deferred, nothing is cut short
    assert process.wait(timeout=180) == 130, err.read_text()
    stderr = err.read_text()
    assert "Traceback" not in stderr and "interrupted" in stderr, stderr

    summary = read_summary(out)
    assert summary["interrupted"] is True
    assert 40 <= summary["frames"] < 400 and summary["frames"] == summary["tracked"] + summary["lost"]
    names = check_results_folder(out)
    assert {"trajectory.txt", "trajectory_online.txt", "keyframes.txt", "summary.json", "config.yaml",
            "graph.json", "graph.g2o", "evaluation.json", "map.npz"} <= names, names
    assert not any(TEMP_NAME.match(n) for n in names), "every atomic write finished"
    online_poses, online_lost = frame_lines(out / "trajectory_online.txt")
    assert len(online_poses) + len(online_lost) == summary["frames"]
    final_poses, final_lost = frame_lines(out / "trajectory.txt")
    assert np.allclose(final_poses, online_poses) and np.allclose(final_lost, online_lost)
    keyframe_stamps, _ = read_tum(out / "keyframes.txt")
    assert len(keyframe_stamps) == summary["keyframes"] > 0
    assert json.loads((out / "evaluation.json").read_text())["ate"]["rmse"] < 0.05


# --- 2. SIGKILL ----------------------------------------------------------------------------------------

@pytest.mark.slow   # a whole run: kept out of the fast tier (< 2 min)
@pytest.mark.parametrize("moment", ["mid-run", "final writes"])
def test_sigkill_leaves_only_complete_files(tum_folder, tmp_path, moment):
    """Killed without warning: the online trajectory parses up to its last full line, and every final
    file is either absent or complete (an atomic write leaves at most its temporary file)."""
    out, err = tmp_path / "out", tmp_path / "stderr.txt"
    process = popen_run([str(tum_folder), "-o", str(out), "-q", "--set", "output.report=false"], err)
    if moment == "mid-run":
        wait_for(lambda: online_frames(out) >= 6, process, 120, "6 frames were processed")
    else:
        wait_for(lambda: (out / "trajectory.txt").exists(), process, 120, "the final writes began", poll=0.002)
    process.kill()
    assert process.wait(timeout=30) in (-signal.SIGKILL, 0)   # 0: it finished first; all the more complete
    names = check_results_folder(out)
    assert "config.yaml" in names and "trajectory_online.txt" in names
    poses, lost = frame_lines(out / "trajectory_online.txt", complete_only=True)
    assert len(poses) + len(lost) >= 6
    if moment == "mid-run":
        assert not {"trajectory.txt", "summary.json", "graph.g2o"} & names, "no final file before the end"


def session_processes(sid: int) -> list[int]:
    """Live processes of session ``sid`` (the run, its forkserver and its mapping worker all stay in
    the session they were started in)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":   # fields after the name: state, ppid, pgrp, session
            pids.append(int(stat.parent.name))
    return pids


def _stretched_recording(folder: Path, to: Path, factor: float) -> Path:
    """``folder`` (a TUM folder) with every timestamp of its lists ``factor`` times larger and the same
    images: a recording as slow as that, for realtime replay."""
    shutil.copytree(folder, to)
    columns = {"rgb.txt": (0,), "depth.txt": (0,), "groundtruth.txt": (0,), "associations.txt": (0, 2)}
    for name, stamps in columns.items():
        lines = []
        for line in (to / name).read_text().splitlines():
            fields = line.split()
            if fields and not line.startswith("#"):
                for k in stamps:
                    fields[k] = f"{float(fields[k]) * factor:.6f}"
                line = " ".join(fields)
            lines.append(line)
        (to / name).write_text("\n".join(lines) + "\n")
    return to


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
@pytest.mark.parametrize("mode", ["dataset", pytest.param("realtime", marks=pytest.mark.slow)])
def test_ctrl_c_at_a_terminal_stops_every_process_and_writes_complete_files(tum_folder, tmp_path, mode):
    """A terminal's Ctrl-C reaches the whole process group, the mapping worker included: exit 130,
    complete final files (the worker finished the last updates first), and no process left behind.
    The same in realtime mode, where the worker was never waited for before the end. Realtime replays
    the recording 10 times slower (0.33 s between frames): at its own 30 fps a loaded machine had
    dropped most of its 24 frames and was writing the results when the Ctrl-C came (exit 0)."""
    out, err = tmp_path / "out", tmp_path / "stderr.txt"
    realtime = ["--realtime"] if mode == "realtime" else []
    if realtime:
        tum_folder = _stretched_recording(tum_folder, tmp_path / "slow_room", 10.0)
    with err.open("w") as stderr:
        process = subprocess.Popen([sys.executable, "-m", "slam.cli", "run", str(tum_folder), "-o", str(out), "-q",
                                    "--set", "output.report=false", "--set", "backend.worker_process=true",
                                    "--set", "backend.optimizer=window", *realtime], cwd=REPO, stdout=subprocess.DEVNULL,
                                   stderr=stderr, start_new_session=True,
                                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_for(lambda: online_frames(out) >= 4, process, 120, "4 frames were processed")
        assert len(session_processes(process.pid)) >= 2, "the mapping worker runs beside the tracking process"
        os.killpg(process.pid, signal.SIGINT)
        assert process.wait(timeout=120) == 130, err.read_text()
    finally:
        if process.poll() is None:
            process.kill()
    deadline = time.monotonic() + 10
    while session_processes(process.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert session_processes(process.pid) == [], "a process of the run outlived it"
    assert "Traceback" not in err.read_text()
    summary = read_summary(out)
    assert summary["interrupted"] is True and 4 <= summary["frames"] < TUM_FRAMES
    names = check_results_folder(out)
    assert {"trajectory.txt", "keyframes.txt", "summary.json", "graph.g2o", "map.npz"} <= names, names
    final_poses, final_lost = frame_lines(out / "trajectory.txt")
    assert len(final_poses) + len(final_lost) == summary["frames"]


# --- 11. unwritable results folder ---------------------------------------------------------------------

def test_unwritable_output_folder_fails_before_processing(tum_folder, tmp_path, capsys, monkeypatch):
    import slam.datasets

    a_file = tmp_path / "somefile.txt"
    a_file.write_text("not a folder")
    opened = []
    monkeypatch.setattr(slam.datasets, "open_dataset", lambda *a, **k: opened.append(a) or pytest.fail("opened"))
    for output in (a_file / "out", Path("/proc/dynslam_out")):
        assert main(["run", str(tum_folder), "-o", str(output), "-q"]) == 2
        err = capsys.readouterr().err
        assert f"output folder {output} cannot be used" in err and "Traceback" not in err, err
    assert not opened, "the check runs before the dataset is even opened"


def test_unwritable_output_folder_is_exit_2_in_a_real_process(tum_folder, tmp_path):
    a_file = tmp_path / "somefile.txt"
    a_file.write_text("not a folder")
    proc = run_dynslam(["run", str(tum_folder), "-o", str(a_file / "out"), "-q"], timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert f"output folder {a_file / 'out'} cannot be used: a part of its path is a file" in proc.stderr
    assert "Traceback" not in proc.stderr
