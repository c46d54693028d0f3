"""``dynslam`` command line: run, demo, eval, export-trajectory, export, vocabulary, download, config.

The CLI only parses arguments, resolves the config and calls the library; heavy imports happen
inside the commands so ``dynslam --help`` stays instant. Every deliberate failure is a
``slam.core.errors.DynslamError``: one clear line and its exit status (2 for a bad path, config value
or file, 1 for a failure while running); Ctrl-C gives 130.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

from slam.core.errors import EXIT_INTERRUPTED, EXIT_USAGE   # the CLI's exit codes (light: --help stays instant)
from slam.run.sources import resolve_run_config  # noqa: F401  (re-exported; light: imports lazily)

# = slam.datasets.synthetic_movers.MOVER_PRESETS, then slam.datasets.synthetic_scenes.HARD_SCENES (not imported:
# --help stays light; tests/test_cli.py checks both lists)
DEMO_MOVERS = ("none", "boxes", "people", "crowd", "drag", "close_pass", "three_close", "stand_walk", "border")
MODEL_NAMES = ("yolox-nano", "nanodet-m")   # = slam.core.model_files.MODELS (not imported: --help stays light)
TRAJECTORY_FORMAT_NAMES = ("tum", "kitti", "euroc")   # = slam.core.config.TRAJECTORY_FORMATS (not imported: --help stays light)


def _parse_overrides(pairs: Sequence[str]) -> dict:
    from slam.run.run_config import parse_overrides

    return parse_overrides(pairs)


def resolve_run_config(dataset_path: Optional[Path], config_files: Sequence[str], overrides: dict,
                       fixed: Optional[dict] = None, fixed_source: str = "demo"):
    """See ``slam.run.run_config.resolve_run_config`` (imported here lazily: --help stays light)."""
    from slam.run.run_config import resolve_run_config as resolve

    return resolve(dataset_path, config_files, overrides, fixed, fixed_source)


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
        if hasattr(dataset, "close"):   # a live camera: stopped on every way out (Ctrl-C, errors)
            stack.callback(dataset.close)
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


def _config_options(p) -> None:
    p.add_argument("--config", "-c", action="append", default=[],
                   help="preset name (tum_fr1, tum_fr2, tum_fr3, bonn) or YAML file; repeatable")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set tracking.match_ratio=0.8")


def _viz_options(p) -> None:
    viz = p.add_mutually_exclusive_group()
    viz.add_argument("--viz", action="store_true",
                     help='watch the run live in the rerun viewer (needs pip install "dynslam[viz]")')
    viz.add_argument("--viz-save", metavar="FILE.rrd",
                     help="record the live view to FILE.rrd instead (open it later with `rerun FILE.rrd`)")


def _slam_parsers(sub) -> None:
    """run and demo: the commands that run SLAM."""
    run = _command(sub, "run", help="run SLAM on a TUM/Bonn folder, a ROS 1/2 bag, an image folder or a "
                                    "live RealSense camera")
    run.add_argument("dataset", help="TUM/Bonn folder (rgb.txt, depth.txt), ROS bag (.bag file, RealSense "
                                     "Viewer recordings too, or ROS 2 bag folder), a folder with color/, "
                                     "depth/ and intrinsics.yaml, or realsense[:SERIAL] for a live camera "
                                     "(needs pip install \"dynslam[realsense]\"; Ctrl-C stops it)")
    run.add_argument("--output", "-o", help="results folder (default results/<name>_<time>)")
    run.add_argument("--max-frames", type=int, help="stop after this many frames")
    run.add_argument("--blackout", metavar="START:COUNT",
                     help="fault injection: blank COUNT frames from frame START (tests recovery)")
    run.add_argument("--save-map", metavar="PATH", help="save the final map to PATH (.npz, written atomically)")
    run.add_argument("--realtime", action="store_true",
                     help="realtime mode (runtime.realtime; a live camera's default): replay a recording at its "
                          "recorded rate, dropping frames SLAM has no time for (summary.json: dropped_frames), "
                          "and never wait for the back end; not deterministic")
    run.add_argument("--load-map", metavar="PATH",
                     help="localisation only: track against the map saved at PATH, which stays unchanged")
    _viz_options(run)
    _config_options(run)
    run.set_defaults(func=cmd_run)

    demo = _command(sub, "demo", help="generate a synthetic RGB-D room and run SLAM on it")
    demo.add_argument("--frames", type=int, default=120, help="length of the generated sequence (default 120)")
    demo.add_argument("--seed", type=int, default=0, help="seed of the room, the path and the movers (default 0)")
    demo.add_argument("--movers", choices=DEMO_MOVERS, default="people",
                      help="moving objects in the room (their true boxes stand in for the detector): random "
                           "walkers (people, crowd, ...) or a scripted hard scene (close_pass, three_close, "
                           "stand_walk, border); default people")
    demo.add_argument("--no-compare", action="store_true",
                      help="skip the second run with dynamic handling off (written to OUTPUT/without_dynamic)")
    demo.add_argument("--output", "-o", help="results folder (default results/synthetic_<time>)")
    _viz_options(demo)
    _config_options(demo)
    demo.set_defaults(func=cmd_demo)


def _result_parsers(sub) -> None:
    """eval, export-trajectory and export: working on finished runs."""
    ev = _command(sub, "eval", help="ATE and RPE of a TUM trajectory against ground truth")
    ev.add_argument("groundtruth", help="ground-truth trajectory (TUM format)")
    ev.add_argument("estimate", help="estimated trajectory (TUM format, e.g. a run's trajectory.txt)")
    ev.add_argument("--max-dt", type=float, default=0.02, help="timestamp association tolerance (s)")
    ev.add_argument("--json", action="store_true", help="print the full report as JSON")
    ev.set_defaults(func=cmd_eval)

    xt = _command(sub, "export-trajectory", help="write a results folder's trajectory as KITTI or EuRoC",
                        description="Converts trajectory.txt (or the online / keyframe file) of a results "
                                    "folder; names: trajectory.kitti.txt + trajectory.kitti.times.txt, "
                                    "trajectory.euroc.csv, trajectory_online.*, keyframes.* (see README, Outputs).")
    xt.add_argument("results_dir", help="a dynslam results folder")
    xt.add_argument("--format", "-f", required=True, choices=TRAJECTORY_FORMAT_NAMES, help="output format")
    which = xt.add_mutually_exclusive_group()
    which.add_argument("--online", action="store_true", help="the causal poses (trajectory_online.txt)")
    which.add_argument("--keyframes", action="store_true", help="the optimised keyframes (keyframes.txt)")
    xt.set_defaults(func=cmd_export_trajectory)

    exp = _command(sub, "export", help="sparse and dense (TSDF) maps of a finished run")
    exp.add_argument("results", nargs="?", help="results folder of a run (or give --map)")
    exp.add_argument("--map", metavar="FILE", help="a saved map (.npz) instead of a results folder")
    exp.add_argument("--dataset", metavar="PATH", help="read keyframe images from this TUM/Bonn folder")
    exp.add_argument("--sparse", action="store_true", help="only the landmark point cloud (default: both)")
    exp.add_argument("--dense", action="store_true", help="only the TSDF mesh and point cloud (default: both)")
    exp.add_argument("--by-dynamic", action="store_true",
                     help="colour landmarks by dynamic evidence (map_sparse_dynamic.ply) instead of the image")
    exp.add_argument("--voxel", type=float, metavar="M", help="TSDF voxel size in metres (truncation 4 voxels)")
    exp.add_argument("--no-masks", action="store_true", help="fuse dynamic pixels too (for comparison)")
    exp.add_argument("--out", metavar="DIR", help="output folder (default: the results / map folder)")
    exp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override an export setting, e.g. --set export.depth_max=3.0")
    exp.set_defaults(func=cmd_export)


def _tool_parsers(sub) -> None:
    """vocabulary, download and config."""
    voc = _command(sub, "vocabulary", help="build a place-recognition vocabulary from images")
    voc.add_argument("images", nargs="+", help="folders searched recursively for PNG/JPEG images")
    voc.add_argument("--output", "-o", required=True, help="vocabulary file (.npz)")
    voc.add_argument("--step", type=int, default=5, help="use every STEP-th image")
    voc.add_argument("--branches", type=int, default=10, help="children per node of the vocabulary tree")
    voc.add_argument("--levels", type=int, default=3, help="depth of the tree (words = branches^levels at most)")
    voc.add_argument("--seed", type=int, default=0, help="seed of the k-majority clustering")
    voc.set_defaults(func=cmd_vocabulary)

    dl = _command(sub, "download", help="download a TUM RGB-D or Bonn sequence, or a detector model",
                  description="dynslam download tum|bonn SEQUENCE: fetch, verify and unpack a sequence; "
                              "dynslam download model [NAME]: fetch a detector model into the cache.")
    kinds = dl.add_subparsers(dest="kind", required=True, metavar="{tum,bonn,model}", help="what to download")
    for kind, label, example in (("tum", "TUM RGB-D", "freiburg1_xyz"), ("bonn", "Bonn RGB-D Dynamic", "crowd")):
        seq = _command(kinds, kind, help=f"an official {label} sequence, e.g. {example}")
        seq.add_argument("sequence", help=f"e.g. {example}; full folder names work too")
        seq.add_argument("--output", "-o", default=".", help="folder to unpack into (default: current folder)")
        seq.add_argument("--base-url", help="download server root instead of the official one "
                                            "(also $DYNSLAM_DOWNLOAD_BASE_URL)")
        seq.add_argument("--checksum", metavar="ALGO:HEX", help="expected md5:HEX or sha256:HEX of the archive")
        seq.add_argument("--keep-archive", action="store_true", help="keep the archive after unpacking")
        seq.set_defaults(func=cmd_download)
    model = _command(kinds, "model", help="a detector model (ONNX), verified, into the model cache",
                     description="Fetches the detector model, checks its pinned size and sha256 and puts it "
                                 "where runs look for it: $DYNSLAM_CACHE_DIR/models, else the user cache "
                                 "(Linux: $XDG_CACHE_HOME/dynslam/models or ~/.cache/dynslam/models). "
                                 "An interrupted download resumes.")
    model.add_argument("name", nargs="?", default="yolox-nano", choices=MODEL_NAMES,
                       help="yolox-nano (default, dynamic.detector.model: yolox_nano) or nanodet-m (nanodet)")
    model.add_argument("--dir", metavar="DIR", help="put the model in DIR instead of the cache (then point "
                                                    "dynamic.detector.path or $DYNSLAM_DETECTOR_MODEL at it)")
    model.add_argument("--base-url", metavar="URL", help="replace the scheme and host of the model's URL "
                                                         "(a mirror keeping the same paths)")
    model.add_argument("--sha256", metavar="HEX", help="expert: accept this digest instead of the pinned one "
                                                       "(a mirror serving another build of the model)")
    model.set_defaults(func=cmd_download_model)

    cfg = _command(sub, "config", help="print the default (or resolved) configuration as YAML")
    _config_options(cfg)
    cfg.add_argument("--schema", action="store_true",
                     help="print the JSON schema of config files instead (for editors, e.g. the YAML "
                          "language server: '# yaml-language-server: $schema=dynslam.schema.json')")
    cfg.set_defaults(func=cmd_config)


def _verbosity_options(parser: argparse.ArgumentParser, default) -> None:
    parser.add_argument("-v", "--verbose", action="store_true", default=default, help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", default=default,
                        help="no progress bar or progress lines, warnings and errors only")


def _command(sub, name: str, **kwargs) -> argparse.ArgumentParser:
    """A subcommand that also takes -v / -q after its name (``dynslam run SEQ -q``). Its defaults are
    SUPPRESS, so an option given before the subcommand is not reset by the subcommand's parser."""
    common = argparse.ArgumentParser(add_help=False)
    _verbosity_options(common, argparse.SUPPRESS)
    return sub.add_parser(name, parents=[common], **kwargs)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("dynslam")
    except PackageNotFoundError:   # run from a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dynslam", description="RGB-D SLAM for dynamic scenes")
    parser.add_argument("--version", action="version", version=f"dynslam {_version()}")
    _verbosity_options(parser, False)
    sub = parser.add_subparsers(dest="command", required=True)
    _slam_parsers(sub)
    _result_parsers(sub)
    _tool_parsers(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="dynslam: %(message)s")
    warnings.simplefilter("default")
    warnings.formatwarning = lambda message, category, *_args, **_kw: f"dynslam: warning: {message}\n"
    from slam.core.errors import DynslamError

    try:
        return args.func(args)
    except DynslamError as exc:   # every deliberate error: one line, its exit status (no traceback)
        print(f"dynslam {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except FileNotFoundError as exc:
        print(f"dynslam {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:   # Ctrl-C before the run started (a run itself stops cleanly, see Pipeline)
        print(f"dynslam {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
