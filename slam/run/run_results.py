"""What a finished run writes from the System's final state: the run's summary record and the end-of-run
files of a results folder (``trajectory.txt``, ``keyframes.txt`` and their other formats, ``dynamic.csv``,
``graph.g2o`` / ``graph.json``, ``groundtruth.txt`` and ``evaluation.json``, ``summary.json``).

``slam.run.pipeline`` calls these once the last frame is processed and ``System.close`` has applied the
final optimisation; the folder's layout is described there. Every file is written atomically.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from frontend.dynamic_filter import method_names
from slam.core.atomic_io import write_text_atomic
from slam.core.config import SlamConfig
from slam.datasets.base import RGBDDataset
from slam.run.evaluation import EvaluationError, EvaluationReport, evaluate
from slam.run.trajectory import format_tum_line, tum_rows_from_poses, write_tum
from slam.runtime.system import System

log = logging.getLogger("dynslam")


@dataclass
class RunSummary:
    dataset: str
    output_dir: str
    dataset_path: Optional[str] = None     # folder or file the frames came from (None: generated)
    frames: int = 0
    tracked: int = 0
    lost: int = 0
    keyframes: int = 0
    landmarks: int = 0
    wall_time_s: float = 0.0
    timing_ms: dict[str, dict[str, float]] = field(default_factory=dict)
    ate_rmse_m: Optional[float] = None
    lost_frames: list[int] = field(default_factory=list)
    skipped_files: list[str] = field(default_factory=list)    # unreadable, corrupt or wrong size (while running)
    missing_files: list[str] = field(default_factory=list)    # listed but absent, found when opening
    no_depth_frames: list[int] = field(default_factory=list)  # frames without a single valid depth pixel
    interrupted: bool = False                                 # stopped (Ctrl-C) before the last frame
    dropped_frames: Optional[int] = None                      # live camera / realtime replay: frames never
                                                              # processed (newest frame wins); None: dataset mode
    realtime: bool = False                                    # runtime.realtime: paced by the source, not deterministic
    dynamic_methods: list[str] = field(default_factory=list)
    dynamic_flagged: dict[str, dict[str, float]] = field(default_factory=dict)  # per method and fused
    loops: list[dict[str, Any]] = field(default_factory=list)   # every loop factor added, with timestamps
    place_recognition: dict[str, Any] = field(default_factory=dict)  # loop / relocalization counts and ms
    # Tracked frames' pose uncertainty (FrameOutput.pose_sigma_m, mm): median, p95, max and the frame of the
    # max; a weakly held stretch (few static features) shows here before it shows in the error.
    pose_sigma_mm: dict[str, float] = field(default_factory=dict)
    # Seconds numba spent compiling this project's kernels during the run (the first run after an install; 0 when
    # its cache had them): counted in wall_time_s, a one-time cost (slam/core/kernel_compile.py).
    kernel_compile_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def write_final_poses(output_dir: Path, system: System, formats: Sequence[str]) -> None:
    """trajectory.txt (every frame; untracked ones as ``# t LOST`` comments), keyframes.txt, and the same
    trajectories in the other ``formats`` (``output.trajectory_formats``)."""
    from slam.run.trajectory_formats import export_formats

    stamps, poses, tracked = system.trajectory()
    lines = ["# timestamp tx ty tz qx qy qz qw (untracked frames: '# timestamp LOST')"]
    rows = tum_rows_from_poses(poses[tracked]) if tracked.any() else np.zeros((0, 7))
    tracked_rows = iter(rows)
    for t, ok in zip(stamps, tracked):
        lines.append(format_tum_line(t, next(tracked_rows)).rstrip("\n") if ok else f"# {t:.6f} LOST")
    write_text_atomic(output_dir / "trajectory.txt", "\n".join(lines) + "\n")
    kf_t, kf_poses = system.keyframe_trajectory()
    write_tum(output_dir / "keyframes.txt", kf_t, kf_poses)
    export_formats(output_dir, formats)


def summarize_system(summary: RunSummary, system: System) -> None:
    """The System's share of the summary: map size, timings, dynamic methods and counts, loops."""
    summary.keyframes = system.num_keyframes
    summary.landmarks = system.num_landmarks
    summary.timing_ms = system.timer.summary()
    # What ran, not what was asked: without a detector model only the detector-free methods run.
    summary.dynamic_methods = method_names(system.dynamic_filter)
    stats = system.dynamic_filter.stats
    if stats is not None:
        summary.dynamic_flagged = stats.summary()
    summary.loops, summary.place_recognition = system.place_recognition_report()


def write_dynamic_counts(output_dir: Path, system: System) -> None:
    """dynamic.csv: per frame, how many features each method and the fusion flagged (with dynamic
    handling on)."""
    stats = system.dynamic_filter.stats
    if stats is None:
        return
    flagged = stats.flagged
    names = list(flagged)
    stamps = system.trajectory(smoothed=False)[0]
    rows = ["timestamp," + ",".join(names)]
    for i in range(min([len(stamps)] + [len(v) for v in flagged.values()])):
        rows.append(f"{stamps[i]:.6f}," + ",".join(str(flagged[n][i]) for n in names))
    write_text_atomic(output_dir / "dynamic.csv", "\n".join(rows) + "\n")


def write_graph(output_dir: Path, system: System, config: SlamConfig) -> None:
    """graph.g2o and graph.json: the optimised keyframe graph (odometry + covisibility + loop edges)."""
    from backend.graph_export import export_g2o, export_json, graph_edges_from_mapper, loop_edges, mapper_keyframes

    mapper = system.mapper
    if mapper.map.num_keyframes == 0:
        return
    ids, stamps, poses = mapper_keyframes(mapper)
    edges = graph_edges_from_mapper(mapper, config.backend.covisibility_min_shared)
    edges += loop_edges(system.loop_closer.loops, config.loop.sigma_t, config.loop.sigma_r_deg)
    export_g2o(output_dir / "graph.g2o", ids, poses, edges)
    export_json(output_dir / "graph.json", ids, stamps, poses, edges)


def evaluate_run(output_dir: Path, dataset: RGBDDataset, system: System, max_dt: float) -> Optional[EvaluationReport]:
    """ATE / RPE against the dataset's ground truth into evaluation.json (a generated sequence's exact path
    also into groundtruth.txt); None without ground truth or when the two cannot be associated (a
    warning says why)."""
    gt = dataset.groundtruth()
    if gt is None:
        return None
    if dataset.root is None:  # generated or live: keep the exact path beside the result
        write_tum(output_dir / "groundtruth.txt", *gt)
    stamps, poses, tracked = system.trajectory()
    try:
        report = evaluate(gt[0], gt[1], stamps[tracked], poses[tracked], max_dt, "groundtruth",
                          str(output_dir / "trajectory.txt"))
    except EvaluationError as exc:
        log.warning("evaluation skipped: %s", exc)
        return None
    write_text_atomic(output_dir / "evaluation.json", json.dumps(report.to_dict(), indent=2) + "\n")
    return report


def write_summary(output_dir: Path, summary: RunSummary, pose_sigmas: Sequence[tuple[float, int]]) -> None:
    """summary.json, with the tracked frames' pose sigmas ((sigma m, frame index) each) summarised."""
    if pose_sigmas:
        sigma = np.array([s for s, _ in pose_sigmas]) * 1e3
        worst = int(np.argmax(sigma))
        summary.pose_sigma_mm = {"median": round(float(np.median(sigma)), 3),
                                 "p95": round(float(np.percentile(sigma, 95)), 3),
                                 "max": round(float(sigma[worst]), 3),
                                 "max_frame": int(pose_sigmas[worst][1])}
    write_text_atomic(output_dir / "summary.json", json.dumps(summary.to_dict(), indent=2) + "\n")
