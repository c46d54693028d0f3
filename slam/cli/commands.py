"""The ``dynslam`` subcommands: each turns parsed arguments into library calls and returns an exit status.

Heavy imports happen inside each command, so building the parser (``dynslam --help``) stays instant.
"""
from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Sequence

from slam.core.errors import EXIT_INTERRUPTED
from slam.run.sources import resolve_run_config


def _parse_overrides(pairs: Sequence[str]) -> dict:
    from slam.run.run_config import parse_overrides

    return parse_overrides(pairs)


def _default_output(name: str) -> Path:
    return Path("results") / f"{name}_{time.strftime('%Y%m%d_%H%M%S')}"


def _progress_printer(total: int, quiet: bool):
    """A one-line bar redrawn in place on a terminal, a plain line every 50 frames otherwise."""
    from slam.run.progress import ProgressPrinter

    return ProgressPrinter(total, sys.stderr, quiet=quiet)


def _viz_observers(args, config, dataset) -> list:
    """The rerun observer asked for by --viz / --viz-save (none otherwise). Made before the dataset is
    run, so a missing rerun SDK, a missing display or a bad path fails at once (exit status 2)."""
    if not (args.viz or args.viz_save):
        return []
    from slam.run.viz_rerun import RerunObserver

    return [RerunObserver(config, dataset.groundtruth(), save_path=args.viz_save)]


def cmd_run(args) -> int:
    from slam.core.atomic_io import ensure_output_dir
    from slam.datasets.realsense_live import is_live_source
    from slam.run.pipeline import Pipeline
    from slam.run.sources import frames_to_run, open_live, open_recorded

    overrides = _parse_overrides(args.set)
    if args.realtime:
        overrides["runtime.realtime"] = True
    opener = open_live if is_live_source(args.dataset) else open_recorded
    dataset, config = opener(args.dataset, args.config, overrides, args.output)
    with contextlib.ExitStack() as stack:
        stack.callback(dataset.close)   # a live camera stops on every way out (Ctrl-C, errors)
        if args.blackout:
            dataset = _blackout(dataset, args.blackout)
        output = ensure_output_dir(args.output or _default_output(dataset.name))
        total = frames_to_run(dataset, args.max_frames)
        prior_map = None
        if args.load_map:
            from backend.map_io import check_camera_compatible, load_map

            prior_map = load_map(args.load_map)
            check_camera_compatible(prior_map.camera_info, config.camera, args.load_map)
        if args.save_map and not Path(args.save_map).parent.is_dir():
            raise FileNotFoundError(f"--save-map: folder {Path(args.save_map).parent} does not exist")
        observers = _viz_observers(args, config, dataset)
        progress = _progress_printer(total, args.quiet)
        pipeline = Pipeline(dataset, config, output, args.max_frames, progress,
                            save_map=args.save_map, prior_map=prior_map, observers=observers)
        summary = pipeline.run()
        progress.finish()
    print(pipeline.format_summary())
    return EXIT_INTERRUPTED if summary.interrupted else 0


def _blackout(dataset, spec: str):
    from slam.core.config import ConfigError
    from slam.datasets.faults import Blackout

    try:
        start, count = (int(x) for x in spec.split(":"))
        return Blackout(dataset, start, count)
    except ValueError as exc:
        raise ConfigError(f"--blackout expects START:COUNT (e.g. 185:30), got '{spec}' ({exc})") from None


def cmd_demo(args) -> int:
    from slam.core.atomic_io import ensure_output_dir

    sequence = _demo_sequence(args)
    fx, fy, cx, cy = sequence.intrinsics
    generated = {"camera.name": "synthetic", "camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
                 "camera.width": sequence.width, "camera.height": sequence.height,
                 "camera.distortion": [0.0] * 5, "seed": args.seed}
    overrides = _parse_overrides(args.set)
    config = resolve_run_config(None, args.config, overrides, generated, "demo (generated room)")
    observers = _viz_observers(args, config, sequence)   # refuses before anything is written
    output = ensure_output_dir(args.output or _default_output("synthetic"))
    movers = "" if args.movers == "none" else f" with {args.movers.replace('_', ' ')}"
    print(f"dynslam demo: {args.frames} frames of a generated textured room{movers} (seed {args.seed})",
          file=sys.stderr)
    dynamic_on = bool(config.dynamic.methods) or config.dynamic.box_prior > 0
    summary, interrupted = _demo_run(sequence, config, output, args, observers)
    if interrupted or not dynamic_on or args.no_compare:
        return EXIT_INTERRUPTED if interrupted else 0
    # The same room and path with dynamic handling off: what the front end buys, side by side.
    off = resolve_run_config(None, args.config, {**overrides, "dynamic.methods": [], "dynamic.box_prior": 0.0},
                             generated, "demo (generated room)")
    print("dynslam demo: the same run with dynamic handling off, for comparison", file=sys.stderr)
    off_summary, interrupted = _demo_run(_demo_sequence(args), off, ensure_output_dir(output / "without_dynamic"),
                                         args, ())
    if summary.ate_rmse_m is not None and off_summary.ate_rmse_m is not None:
        print(f"ATE with dynamic handling {summary.ate_rmse_m * 1000:.1f} mm ({output}), "
              f"without {off_summary.ate_rmse_m * 1000:.1f} mm ({output / 'without_dynamic'})")
    return EXIT_INTERRUPTED if interrupted else 0


def _demo_sequence(args):
    from slam.run.demo import demo_sequence

    return demo_sequence(args.movers, args.frames, args.seed)


def _demo_run(sequence, config, output: Path, args, observers):
    """One run of the demo (``observers``: the live view, for the first run only); (summary, interrupted)."""
    from slam.run.demo import demo_detector
    from slam.run.pipeline import Pipeline

    progress = _progress_printer(args.frames, args.quiet)
    pipeline = Pipeline(sequence, config, output, None, progress, detector=demo_detector(sequence),
                        observers=observers)
    summary = pipeline.run()
    progress.finish()
    print(pipeline.format_summary())
    return summary, summary.interrupted


def cmd_eval(args) -> int:
    from slam.run.evaluation import evaluate_files, format_report

    report = evaluate_files(args.groundtruth, args.estimate, args.max_dt)
    print(json.dumps(report.to_dict(), indent=2) if args.json else format_report(report))
    return 0


def cmd_export_trajectory(args) -> int:
    """Write a results folder's trajectory in KITTI or EuRoC beside its TUM file; prints the files."""
    from slam.run.trajectory_formats import export_trajectory, trajectory_kind

    for path in export_trajectory(args.results_dir, args.format, trajectory_kind(args.online, args.keyframes)):
        print(path)
    return 0


def cmd_vocabulary(args) -> int:
    """Train a bag-of-binary-words vocabulary on the ORB features of a user's images."""
    from slam.run.vocabulary_training import train_vocabulary

    vocabulary, n_descriptors, n_images = train_vocabulary(args.images, args.step, args.branches, args.levels,
                                                           args.seed)
    vocabulary.save(args.output)
    print(f"{args.output}: {vocabulary.n_words} words from {n_descriptors} descriptors of {n_images} images")
    return 0


def cmd_download(args) -> int:
    """Fetch, verify and unpack one official TUM or Bonn sequence; prints the folder it made."""
    from slam.run.download import download_sequence, parse_checksum

    checksum = parse_checksum(args.checksum) if args.checksum else None
    folder = download_sequence(args.kind, args.sequence, args.output, base_url=args.base_url,
                               checksum=checksum, keep_archive=args.keep_archive)
    print(folder)
    print(f"dynslam download: ready, run it with: dynslam run {folder}", file=sys.stderr)
    return 0


def cmd_download_model(args) -> int:
    """Fetch and verify a detector model; prints its path."""
    from slam.run.model_download import download_model

    result = download_model(args.name, args.dir, base_url=args.base_url, sha256=args.sha256)
    print(result.path)
    state = "downloaded and verified" if result.downloaded else "already present and verified"
    print(f"dynslam download: {result.path.name} {state} (sha256 {result.sha256})", file=sys.stderr)
    return 0


def cmd_export(args) -> int:
    """Sparse (landmarks) and dense (TSDF mesh + cloud) maps of a finished run, without re-running SLAM."""
    from slam.core.config import ConfigError
    from slam.run.map_export import ExportRequest, export_maps

    if (args.results is None) == (args.map is None):
        raise ConfigError("export needs a results folder or --map FILE (one of them)")
    overrides = _parse_overrides(args.set)
    if args.voxel is not None:   # truncation follows as 4 voxels unless set explicitly
        overrides.setdefault("export.voxel_size", args.voxel)
        overrides.setdefault("export.truncation", 4.0 * args.voxel)
    both = not (args.sparse or args.dense)
    request = ExportRequest(results_dir=None if args.results is None else Path(args.results),
                            map_path=None if args.map is None else Path(args.map),
                            dataset=None if args.dataset is None else Path(args.dataset),
                            out_dir=None if args.out is None else Path(args.out), sparse=args.sparse or both,
                            dense=args.dense or both, by_dynamic=args.by_dynamic, use_masks=not args.no_masks,
                            overrides=overrides)
    print(export_maps(request).format())
    return 0


def cmd_config(args) -> int:
    if args.schema:
        from slam.core.config import ConfigError, config_schema

        if args.config or args.set:
            raise ConfigError("--schema describes every config file: it takes no --config or --set")
        print(json.dumps(config_schema(), indent=2))
        return 0
    config = resolve_run_config(None, args.config, _parse_overrides(args.set))
    print(config.to_yaml(), end="")
    return 0
