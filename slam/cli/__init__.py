"""``dynslam`` command line: run, demo, eval, export-trajectory, export, vocabulary, download, config.

The CLI only parses arguments (here) and calls the library (``slam.cli.commands``); heavy imports
happen inside the commands so ``dynslam --help`` stays instant. Every deliberate failure is a
``slam.core.errors.DynslamError``: one clear line and its exit status (2 for a bad path, config value
or file, 1 for a failure while running); Ctrl-C gives 130.
"""
from __future__ import annotations

import argparse
import logging
import sys
import warnings
from typing import Optional, Sequence

from slam.cli.commands import (cmd_config, cmd_demo, cmd_download, cmd_download_model, cmd_eval, cmd_export,
                               cmd_export_trajectory, cmd_run, cmd_vocabulary)
from slam.core.errors import EXIT_INTERRUPTED, EXIT_USAGE   # the CLI's exit codes (light: --help stays instant)
from slam.run.sources import resolve_run_config  # noqa: F401  (re-exported; light: imports lazily)

# = slam.datasets.synthetic_movers.MOVER_PRESETS, then slam.datasets.synthetic_scenes.HARD_SCENES (not imported:
# --help stays light; tests/test_cli_options.py checks both lists)
DEMO_MOVERS = ("none", "boxes", "people", "crowd", "drag", "close_pass", "three_close", "stand_walk", "border")
MODEL_NAMES = ("yolox-nano", "nanodet-m")   # = slam.core.model_files.MODELS (not imported: --help stays light)
TRAJECTORY_FORMAT_NAMES = ("tum", "kitti", "euroc")   # = slam.core.config.TRAJECTORY_FORMATS (not imported: --help stays light)


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
