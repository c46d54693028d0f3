"""Run a dataset through the System and write a results folder (kiss-icp's Pipeline shape).

A results folder holds:
- ``config.yaml``              the resolved configuration (written first, atomically);
- ``trajectory_online.txt``    causal per-frame poses, appended and flushed as each frame is
                               tracked, so nothing is lost if the run stops (``# t LOST`` marks
                               untracked frames);
- ``trajectory.txt``           final per-frame poses following the optimised keyframes (TUM,
                               sorted; untracked frames appear only as ``# t LOST`` comments);
- ``keyframes.txt``            optimised keyframe poses (TUM);
- with ``output.trajectory_formats`` listing ``kitti`` / ``euroc``, the same three trajectories
  converted from those TUM files (``dynslam export-trajectory`` does it later for any folder):
  ``trajectory.kitti.txt`` + ``trajectory.kitti.times.txt`` (KITTI has no timestamps),
  ``trajectory_online.kitti.txt`` + ``.times.txt``, ``keyframes.kitti.txt`` + ``.times.txt``,
  ``trajectory.euroc.csv``, ``trajectory_online.euroc.csv``, ``keyframes.euroc.csv``. Use the
  ``trajectory*`` files to evaluate the final result, ``trajectory_online*`` to judge what a
  causal (live) system would have output, ``keyframes*`` for the optimised keyframes only; see
  ``slam.run.trajectory_formats`` for the formats;
- ``groundtruth.txt``          for generated sequences only, the exact camera path;
- ``evaluation.json``          ATE / RPE when ground truth exists;
- ``summary.json``             counts, per-module milliseconds per frame, ATE;
- ``graph.g2o``, ``graph.json``   the optimised keyframe graph (g2o text: ``gtsam.readG2o``);
- ``dynamic.csv``              with dynamic handling on: features flagged per frame, per method and fused;
- ``report/``                  with ``output.report`` (default on): ``index.html`` and the plots behind it
                               (trajectory, ATE over time, RPE, timing, dynamic strip; see slam.run.report).
For ``dynslam export`` (slam.run.run_artifacts): ``masks/`` (keyframes' dynamic masks), ``keyframes/``
(keyframe images, when the dataset cannot give them back), ``map.npz`` and ``map_sparse.ply``.
With ``save_map`` the final map is also written (dynslam-map .npz, see backend.map_io), atomically;
with ``prior_map`` the run localises against that fixed map instead of building one.
Final files are written atomically. Ctrl-C stops the run after the frame being processed and every
result is still written (``slam.run.interrupts``); ``summary.json`` then says ``"interrupted": true``.
A live camera's frames that were never processed (it does not wait for SLAM) are counted in
``summary.json``'s ``dropped_frames``. ``runtime.realtime`` (``--realtime``; on by default for a live
camera) replays a recording at its recorded rate the same way (``slam.datasets.replay``, dropped frames
counted alike) and never waits for the graph worker: not deterministic, unlike the default dataset mode.
Frames are checked before processing (``slam.run.input_checks``): a colour image of the wrong size is
skipped with a warning, frames without any depth are reported.
``FrameObserver``s (e.g. the rerun live view, ``slam.run.viz_rerun``) see every processed frame and the
end of the run; without any the pipeline does no extra work.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Protocol, Sequence

import numpy as np

from backend.map_io import LoadedMap
from slam.core.config import SlamConfig
from slam.core.kernel_compile import compile_seconds
from slam.datasets.base import RGBDDataset, RGBDFrame, frames_of
from slam.datasets.replay import RealtimeReplay
from slam.run.evaluation import EvaluationReport, format_report
from slam.run.input_checks import InputChecks
from slam.run.interrupts import DeferredInterrupt
from slam.run import report as run_report   # write_report looked up at the call: tests replace it
from slam.run.report import NullStripRecorder, StripRecorder, make_strip_recorder
from slam.runtime.system import FrameOutput, System, UpcomingFrame
from slam.core.atomic_io import ensure_output_dir, write_text_atomic
from slam.run.run_artifacts import RunArtifacts, needs_keyframe_copies
from slam.run.run_results import (RunSummary, evaluate_run, summarize_system, write_dynamic_counts,
                                  write_final_poses, write_graph, write_summary)
from slam.run.trajectory import TumStreamWriter

log = logging.getLogger("dynslam")


def _paced(dataset, config: SlamConfig):
    """(dataset, config) with ``runtime.realtime`` decided: null means realtime for a live camera only
    (it drops frames whatever the system does); a recording in realtime mode is replayed at its recorded
    rate (unless the caller already gave a replay, e.g. with its own clock). The caller's config is not
    changed."""
    live = bool(dataset.live)
    if config.runtime.realtime is None:
        config = config.model_copy(deep=True)
        config.runtime.realtime = live
    if config.runtime.realtime and not live and not isinstance(dataset, RealtimeReplay):
        dataset = RealtimeReplay(dataset)
    return dataset, config


class FrameObserver(Protocol):
    """Watches a run without changing it (a live view, a recorder). The pipeline calls ``on_frame``
    after each processed frame and ``on_finish`` exactly once at the end: after every result is
    written, and also when the run stops early (Ctrl-C, an error), so an observer can close what it
    holds open. An exception from ``on_frame`` ends the run like any other error."""

    def on_frame(self, frame: RGBDFrame, output: FrameOutput, system: System) -> None:
        """``frame`` as read, ``output`` what the System returned for it; ``system`` after the frame
        (its ``last_frame`` features, ``last_dynamic_mask``, ``trajectory()``, map)."""
        ...

    def on_finish(self, system: System, summary: "RunSummary", report: Optional[EvaluationReport]) -> None:
        """The run is over (``summary.interrupted`` after Ctrl-C); ``report`` is the evaluation against
        ground truth, None without one or when the run stopped before it."""
        ...


class Pipeline:
    def __init__(self, dataset: RGBDDataset, config: SlamConfig, output_dir: Path | str,
                 max_frames: Optional[int] = None, progress: Optional[Callable[[FrameOutput, float], None]] = None,
                 save_map: Optional[Path | str] = None, prior_map=None, detector=None,
                 observers: Sequence[FrameObserver] = ()):
        """``detector``: a ``frontend.detector.Detector`` instead of the configured ONNX model (e.g.
        ground-truth boxes of a generated sequence). ``observers`` see every frame and the end of the run.
        ``config.runtime.realtime`` null is decided here (realtime for a live camera); the config the run
        uses and writes is ``self.config``."""
        dataset, config = _paced(dataset, config)
        self.dataset = dataset
        self.observers = tuple(observers)
        self.config = config
        self.output_dir = Path(output_dir)
        self.max_frames = max_frames
        self.progress = progress
        self.save_map_path = Path(save_map) if save_map is not None else None
        if prior_map is None:
            self.system = System(config, sequence_name=dataset.name, detector=detector)
        else:  # a SlamMap, or a LoadedMap (backend.map_io.load_map) that also brings its vocabulary and words
            loaded = isinstance(prior_map, LoadedMap)
            places = prior_map.places if loaded else None
            self.system = System(config, sequence_name=dataset.name, detector=detector,
                                 prior_map=prior_map.slam_map if loaded else prior_map, localization_only=True,
                                 vocabulary=places.vocabulary if places else None,
                                 prior_words=places.bows if places else None)
        root = dataset.root
        self.summary = RunSummary(dataset=dataset.name, output_dir=str(self.output_dir),
                                  dataset_path=None if root is None else str(Path(root).resolve()),
                                  realtime=bool(config.runtime.realtime))
        self._pose_sigmas: list[tuple[float, int]] = []    # (sigma m, frame index) of tracked frames
        self.report: Optional[EvaluationReport] = None
        self.artifacts = RunArtifacts(self.output_dir, config, needs_keyframe_copies(dataset))  # export inputs
        self.checks = InputChecks(config.camera.width, config.camera.height, dataset.name)
        self.dynamic_strip: StripRecorder = NullStripRecorder()   # the run's own is made when it starts

    def run(self) -> RunSummary:
        # Ctrl-C only sets a flag (checked between frames), so neither a frame nor a final write is
        # cut in half and everything computed so far is written.
        with DeferredInterrupt() as interrupt:
            failing = True
            try:
                self._prepare_output()
                start = time.perf_counter()
                compiled_before = compile_seconds()[0]
                try:
                    self._run_pipeline(interrupt)
                except KeyboardInterrupt:   # raised by Python itself: no handler of ours outside the main thread
                    self.summary.interrupted = True
                finally:
                    interrupt.finishing()
                    if self.summary.interrupted:
                        log.warning("interrupted: writing the results of the %d frames processed", self.summary.frames)
                    self.summary.wall_time_s = time.perf_counter() - start
                    self._note_kernel_compilation(compile_seconds()[0] - compiled_before)
                    self._preload_report_imports()
                    self.system.close()
                    self._write_result_poses()
                self._save_map()
                self.artifacts.finish(self.system)
                self._write_graph()
                self._run_evaluation()
                self._write_summary()
                self._write_report()
                failing = False
            finally:   # also after an error: observers close (and finish writing) what they hold open
                self.artifacts.close(raise_errors=not failing)
                self._finish_observers(raise_errors=not failing)
        return self.summary

    # --- steps ------------------------------------------------------------------------------------
    def _note_kernel_compilation(self, seconds: float) -> None:
        self.summary.kernel_compile_s = seconds
        if seconds >= 1.0:
            log.info("numba compiled the kernels in %.0f s of this run (once: later runs load them from its cache)",
                     seconds)

    def _prepare_output(self) -> None:
        ensure_output_dir(self.output_dir)   # a clear error naming the folder, before any frame is read
        write_text_atomic(self.output_dir / "config.yaml", self.config.to_yaml())

    def _run_pipeline(self, interrupt: DeferredInterrupt) -> None:
        self.dynamic_strip = make_strip_recorder(self.config, self._expected_frames())
        frames = frames_of(self.dataset)
        try:
            with TumStreamWriter(self.output_dir / "trajectory_online.txt") as online:
                self._track_frames(frames, interrupt, online)
        finally:   # a generator's ``finally`` runs now, not when it is collected (a live camera stops)
            frames.close()

    def _track_frames(self, frames, interrupt: DeferredInterrupt, online: TumStreamWriter) -> None:
        # A dataset is read one frame ahead, so that frame's image work runs while this one is tracked
        # (slam/runtime/lookahead.py); a live source in realtime mode is never waited on for a frame ahead.
        lookahead = not self.config.runtime.realtime
        queued = None
        # Checked before the next frame is read, not after: a live camera is not waited on again once
        # the run is over (and a recording reads no frame it will not use).
        while not self._stop_before_next(interrupt):
            frame, queued = (queued, None) if queued is not None else (self._read_accepted(frames, interrupt), None)
            if frame is None:
                break
            read_error = None
            if lookahead and (self.max_frames is None or self.summary.frames + 1 < self.max_frames):
                try:
                    queued = self._read_accepted(frames, interrupt)
                except Exception as exc:   # the frame ahead is unreadable: this one is still processed first
                    read_error = exc
            upcoming = None if queued is None else UpcomingFrame(queued.rgb, queued.depth, queued.timestamp,
                                                                 queued.index)
            t0 = time.perf_counter()
            out = self.system.process(frame.rgb, frame.depth, frame.timestamp, frame.index, upcoming)
            self._record(out, online)
            self.artifacts.on_frame(out, frame, self.system)
            self.dynamic_strip.observe(self.summary.frames - 1, frame.rgb, self.system.last_frame,
                                       lambda: self.system.last_dynamic_mask)
            for observer in self.observers:
                observer.on_frame(frame, out, self.system)
            if self.progress is not None:
                self.progress(out, time.perf_counter() - t0)
            if read_error is not None:
                raise read_error

    def _read_accepted(self, frames, interrupt: DeferredInterrupt):
        """The next frame the input checks accept (None at the end of the input)."""
        for frame in frames:
            if self.checks.accept(frame):
                self.checks.observe_depth(frame)
                return frame
        self._stop_before_next(interrupt)   # a Ctrl-C while the last read ended still counts
        return None

    def _stop_before_next(self, interrupt: DeferredInterrupt) -> bool:
        if self.max_frames is not None and self.summary.frames >= self.max_frames:
            return True
        if interrupt.requested:   # Ctrl-C during the frame before: stop here, then write everything
            self.summary.interrupted = True
            return True
        return False

    def _record(self, out: FrameOutput, online: TumStreamWriter) -> None:
        self.summary.frames += 1
        if out.T_wc is None:
            self.summary.lost += 1
            self.summary.lost_frames.append(out.index)
            online.mark_lost(out.timestamp)
        else:
            self.summary.tracked += 1
            online.append(out.timestamp, out.T_wc)
            if np.isfinite(out.pose_sigma_m):
                self._pose_sigmas.append((out.pose_sigma_m, out.index))

    def _finish_observers(self, raise_errors: bool) -> None:
        """Every observer's ``on_finish``, each once, even when one of them fails; with ``raise_errors``
        the first failure is raised after all have run (off while the run already fails with its own
        error, which must not be replaced)."""
        error: Optional[BaseException] = None
        for observer in self.observers:
            try:
                observer.on_finish(self.system, self.summary, self.report)
            except Exception as exc:
                log.warning("%s failed at the end of the run: %s", type(observer).__name__, exc)
                error = error or exc
        self.observers = ()   # finished: never twice
        if error is not None and raise_errors:
            raise error

    def _write_result_poses(self) -> None:
        """trajectory.txt, keyframes.txt (and their other formats), dynamic.csv, and the summary's counts."""
        write_final_poses(self.output_dir, self.system, self.config.output.trajectory_formats)
        summarize_system(self.summary, self.system)
        write_dynamic_counts(self.output_dir, self.system)
        skipped = list(self.dataset.skipped) + self.checks.skipped
        self.summary.skipped_files = [f"{p}: {why}" for p, why in skipped]
        self.summary.no_depth_frames = list(self.checks.no_depth_frames)
        self.summary.missing_files = [str(p) for p in self.dataset.missing]
        dropped = self.dataset.dropped
        self.summary.dropped_frames = None if dropped is None else int(dropped)

    def _write_graph(self) -> None:
        if not self.system.localization_only:
            write_graph(self.output_dir, self.system, self.config)

    def _save_map(self) -> None:
        if self.save_map_path is None:
            return
        self.system.save_map(self.save_map_path)
        log.info("map saved to %s", self.save_map_path)

    def _run_evaluation(self) -> None:
        self.report = evaluate_run(self.output_dir, self.dataset, self.system, self.config.max_association_dt)
        if self.report is not None:
            self.summary.ate_rmse_m = self.report.ate.rmse

    def _write_summary(self) -> None:
        write_summary(self.output_dir, self.summary, self._pose_sigmas)

    def _expected_frames(self) -> Optional[int]:
        """Frames this run will process if it is not stopped (None when the dataset has no length)."""
        try:
            total = len(self.dataset)
        except TypeError:
            return self.max_frames
        return total if self.max_frames is None else min(total, self.max_frames)

    def _preload_report_imports(self) -> None:
        """Start importing matplotlib (1-2 s) on a thread while ``System.close`` waits for the final
        adjustment in the mapping worker: the report needs it last, and the main thread is idle here."""
        if not self.config.output.report:
            return
        from slam.run.report_plots import preload_matplotlib

        def preload() -> None:
            try:
                preload_matplotlib()
            except Exception:   # the report says what is missing when it is written (_write_report)
                pass

        threading.Thread(target=preload, name="dynslam-report-import", daemon=True).start()

    def _write_report(self) -> None:
        """report/: plots and index.html (slam.run.report). Never fails the run: the results are written."""
        if not self.config.output.report:
            return
        try:
            run_report.write_report(self.output_dir, self.summary.to_dict(), self.report, self.dynamic_strip.thumbnails)
        except Exception as exc:
            log.warning("report not written to %s (%s: %s)", self.output_dir / "report", type(exc).__name__, exc)

    def format_summary(self) -> str:
        s = self.summary
        lines = [f"{s.dataset}: {s.frames} frames, {s.tracked} tracked, {s.lost} lost, {s.keyframes} keyframes, "
                 f"{s.landmarks} landmarks, {s.wall_time_s:.1f} s"]
        timing = ", ".join(f"{name} {v['median_ms']:.1f}" for name, v in s.timing_ms.items())
        lines.append(f"median ms/frame: {timing}")
        if s.dropped_frames:
            source = "camera" if self.dataset.live else "recording's frame rate"
            lines.append(f"dropped {s.dropped_frames} frames (processing was slower than the {source})")
        elif s.realtime:
            lines.append("realtime: no frame dropped")
        if self.report is not None:
            lines.append(format_report(self.report))
        lines.append(f"results: {self.output_dir}")
        return "\n".join(lines)
