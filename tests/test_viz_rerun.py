"""The live view (``--viz`` / ``--viz-save``, slam.run.viz_rerun) and the pipeline's observer hook.

The recording tests read the .rrd back with rerun's own reader and check what a user would see:
every entity, one camera pose and one trajectory per processed frame, the ground truth on top of the
estimate, and no half-written file under the final name after an error or Ctrl-C. They need the
optional ``viz`` extra: skipped without it on a user's machine, a failure in CI (which installs it).
"""
from __future__ import annotations

import collections
import os
import signal
import stat
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import pytest

from conftest import in_ci, read_summary, synthetic_config, synthetic_sequence
from slam.cli import main
from slam.datasets import DatasetDefaults, DatasetError
from slam.run.pipeline import Pipeline
from slam.run.viz_rerun import INSTALL_HINT, dynamic_colors, ground_truth_in_world, thin_path

FRAME_ENTITIES = {"/world/camera", "/world/camera/image", "/world/camera/image/keypoints", "/world/trajectory"}
STATIC_ENTITIES = {"/world", "/world/camera", "/world/ground_truth", "/world/trajectory_final"}


def require_rerun():
    try:
        import rerun
    except ImportError:
        message = f"rerun-sdk is not installed ({INSTALL_HINT})"
        if in_ci():
            pytest.fail(f"CI installs the viz extra: {message}", pytrace=False)
        pytest.skip(message)
    return rerun


class Recording:
    """An .rrd read back: per entity, the frames it has rows on, and its last static and timed batches."""

    def __init__(self, path: Path):
        rr = require_rerun()
        self.frames: dict[str, list[int]] = collections.defaultdict(list)
        self.static: dict[str, object] = {}
        self.last: dict[str, object] = {}
        for chunk in rr.chunk.RrdReader(path).stream():
            batch = chunk.to_record_batch()
            if chunk.is_static:
                self.static[chunk.entity_path] = batch
            else:
                self.frames[chunk.entity_path] += batch.column("frame").to_pylist()
                self.last[chunk.entity_path] = batch

    def strip(self, entity: str, static: bool = True) -> np.ndarray:
        """(N,3) points of the (last) line strip logged at ``entity``."""
        batch = (self.static if static else self.last)[entity]
        return np.array(batch.column("LineStrips3D:strips").to_pylist()[-1][0], dtype=np.float64)


def no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


# --- the recording ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def demo_recording(tmp_path_factory) -> tuple[int, Path, Path]:
    """``dynslam demo --frames 8 --movers people -c dynamic_box_depth --viz-save run.rrd``."""
    require_rerun()
    folder = tmp_path_factory.mktemp("viz")
    code = main(["demo", "--no-compare", "--frames", "8", "--movers", "people", "-c", "dynamic_box_depth", "-q",
                 "-o", str(folder / "results"), "--viz-save", str(folder / "run.rrd")])
    return code, folder / "results", folder / "run.rrd"


def test_viz_save_records_every_entity_once_per_frame(demo_recording):
    code, results, rrd = demo_recording
    assert code == 0
    frames = read_summary(results)["frames"]
    assert frames == 8
    recording = Recording(rrd)
    for entity in FRAME_ENTITIES:   # tracked throughout: one camera pose and one path per frame
        assert sorted(recording.frames[entity]) == list(range(frames)), entity
    for entity in ("/world/camera/depth", "/world/camera/image/dynamic_mask", "/world/landmarks"):
        assert 0 in recording.frames[entity], f"{entity} missing on the first frame"
    assert STATIC_ENTITIES <= set(recording.static), set(recording.static)
    pinhole = recording.static["/world/camera"].column("Pinhole:resolution").to_pylist()[0][0]
    assert pinhole == [640.0, 480.0]
    assert len(recording.strip("/world/trajectory", static=False)) == frames   # the whole path at the end


def test_viz_save_ground_truth_lies_on_the_estimate(demo_recording):
    """The generated room's exact path, aligned as the ATE aligns it, matches the final trajectory."""
    _, _, rrd = demo_recording
    recording = Recording(rrd)
    gt, final = recording.strip("/world/ground_truth"), recording.strip("/world/trajectory_final")
    assert gt.shape == final.shape == (8, 3)
    assert np.max(np.linalg.norm(gt - final, axis=1)) < 0.02


def test_viz_save_file_is_complete_and_shared(demo_recording):
    _, _, rrd = demo_recording
    assert rrd.read_bytes()[:4] == b"RRF2"   # rerun's file magic
    assert stat.S_IMODE(rrd.stat().st_mode) & 0o044, "readable by others, as every result file"
    assert no_temp_files(rrd.parent)


class FailingAt(DatasetDefaults):
    """A generated sequence whose reading fails (``error``) or is interrupted by Ctrl-C at frame ``stop``."""

    def __init__(self, sequence, stop: int, error: bool):
        self.sequence, self.stop, self.error = sequence, stop, error
        self.name = sequence.name

    def __len__(self) -> int:
        return len(self.sequence)

    def __iter__(self):
        for frame in self.sequence:
            if frame.index == self.stop:
                if self.error:
                    raise DatasetError(f"frame {self.stop}: unreadable (test)")
                signal.raise_signal(signal.SIGINT)   # Ctrl-C while reading this frame: none comes after
                return
            yield frame

    def groundtruth(self):
        return self.sequence.groundtruth()


@pytest.fixture
def python_ctrl_c():
    """SIGINT handled as Python does by default, also where the runner ignores it (a background job)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("error", [True, False], ids=["error", "ctrl-c"])
def test_viz_save_is_renamed_complete_after_an_error_or_ctrl_c(tmp_path, python_ctrl_c, error):
    require_rerun()
    from slam.run.viz_rerun import RerunObserver

    sequence = synthetic_sequence(12)
    config = synthetic_config(sequence)
    rrd = tmp_path / "run.rrd"
    pipeline = Pipeline(FailingAt(sequence, 5, error), config, tmp_path / "out",
                        observers=[RerunObserver(config, sequence.groundtruth(), save_path=rrd)])
    if error:
        with pytest.raises(DatasetError, match="frame 5"):
            pipeline.run()
    else:
        assert pipeline.run().interrupted
    assert sorted(Recording(rrd).frames["/world/camera"]) == [0, 1, 2, 3, 4]
    assert no_temp_files(tmp_path)


# --- usage errors (exit 2, one line, nothing run) ---------------------------------------------------------

def test_viz_without_rerun_says_how_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)   # import rerun -> ImportError
    code = main(["demo", "--no-compare", "--frames", "3", "-q", "-o", str(tmp_path / "out"), "--viz-save", str(tmp_path / "r.rrd")])
    err = capsys.readouterr().err
    assert code == 2 and 'pip install "dynslam[viz]"' in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists() and not (tmp_path / "r.rrd").exists()


def test_viz_without_a_display_is_refused(tmp_path, monkeypatch, capsys):
    require_rerun()
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux (X11 / Wayland)")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code = main(["demo", "--no-compare", "--frames", "3", "-q", "-o", str(tmp_path / "out"), "--viz"])
    err = capsys.readouterr().err
    assert code == 2 and "no display" in err and "--viz-save" in err, err


@pytest.mark.parametrize("target, says", [("missing/run.rrd", "does not exist"), (".", "is a folder")])
def test_viz_save_bad_target_is_refused(tmp_path, monkeypatch, capsys, target, says):
    require_rerun()
    monkeypatch.chdir(tmp_path)
    code = main(["demo", "--no-compare", "--frames", "3", "-q", "-o", str(tmp_path / "out"), "--viz-save", target])
    err = capsys.readouterr().err
    assert code == 2 and says in err, err


def test_viz_and_viz_save_are_exclusive(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--no-compare", "--viz", "--viz-save", "r.rrd"])
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err


# --- the observer hook (no rerun needed) ------------------------------------------------------------------

class CountingObserver:
    def __init__(self, fail_at_finish: bool = False):
        self.frames: list[int] = []
        self.finished: list[tuple[bool, Optional[float]]] = []
        self.fail_at_finish = fail_at_finish

    def on_frame(self, frame, output, system) -> None:
        assert frame.index == output.index and system.last_frame is not None
        self.frames.append(output.index)

    def on_finish(self, system, summary, report) -> None:
        self.finished.append((summary.interrupted, None if report is None else report.ate.rmse))
        if self.fail_at_finish:
            raise RuntimeError("observer failed")


def test_observers_see_every_frame_and_the_end_once(tmp_path):
    sequence = synthetic_sequence(6)
    watchers = [CountingObserver(), CountingObserver()]
    summary = Pipeline(sequence, synthetic_config(sequence), tmp_path, observers=watchers).run()
    for watcher in watchers:
        assert watcher.frames == list(range(6))
        assert len(watcher.finished) == 1 and watcher.finished[0][0] is False
        assert watcher.finished[0][1] == pytest.approx(summary.ate_rmse_m)   # the evaluation is done first


def test_observer_end_runs_after_an_error_without_hiding_it(tmp_path):
    sequence = synthetic_sequence(8)
    failing, watcher = CountingObserver(fail_at_finish=True), CountingObserver()
    pipeline = Pipeline(FailingAt(sequence, 3, error=True), synthetic_config(sequence), tmp_path,
                        observers=[failing, watcher])
    with pytest.raises(DatasetError):   # the run's own error, not the observer's
        pipeline.run()
    assert watcher.frames == [0, 1, 2] and len(watcher.finished) == 1 and len(failing.finished) == 1


def test_an_observer_failing_at_the_end_fails_the_run(tmp_path):
    sequence = synthetic_sequence(3)
    with pytest.raises(RuntimeError, match="observer failed"):
        Pipeline(sequence, synthetic_config(sequence), tmp_path, observers=[CountingObserver(True)]).run()
    assert (tmp_path / "summary.json").is_file()   # the results were written before


# --- helpers ----------------------------------------------------------------------------------------------

def test_dynamic_colors_go_from_green_to_red():
    colors = dynamic_colors(np.array([0.0, 1.0, 0.5, np.nan, 2.0]))
    assert colors.dtype == np.uint8
    assert colors[0].tolist() == [0, 255, 0] and colors[1].tolist() == [255, 0, 0]
    assert colors[3].tolist() == [0, 255, 0] and colors[4].tolist() == [255, 0, 0]


def test_thin_path_keeps_the_ends_and_the_limit():
    xyz = np.arange(30003, dtype=float).reshape(-1, 3)
    thinned = thin_path(xyz, 100)
    assert len(thinned) <= 100 and (thinned[0] == xyz[0]).all() and (thinned[-1] == xyz[-1]).all()
    assert thin_path(xyz[:5], 100) is not None and len(thin_path(xyz[:5], 100)) == 5


def test_ground_truth_in_world_applies_the_transform():
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, 3] = [1.0, 0.0, 0.0]
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]   # 90 degrees about z
    T[:3, 3] = [0.0, 0.0, 2.0]
    assert np.allclose(ground_truth_in_world(poses, T), [[0, 0, 2], [0, 1, 2]])
