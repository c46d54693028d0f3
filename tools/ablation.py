#!/usr/bin/env python3
"""The former ablation tool's command line, kept so old commands work; ``tools/sweep.py`` does the work.

    python tools/ablation.py --repeats 3      # = tools/sweep.py tools/sweeps/bonn_ablation.yaml --repeats 3
    python tools/ablation.py SEQ --configs none dynamic_all   # = tools/sweep.py --sequences SEQ --configs ...

Without sequence folders it runs the README's ablation (``tools/sweeps/bonn_ablation.yaml``); with
them, the given configurations (default: off, each method alone, fused) with each folder's camera
guessed from its name, as ``dynslam run`` does. Tables go to ``--output`` (default results/ablation).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
sys.path.insert(0, str(TOOLS))

import sweep  # noqa: E402  (a sibling script, not a package)

ABLATION_SWEEP = TOOLS / "sweeps" / "bonn_ablation.yaml"
DEFAULT_CONFIGS = ["none", "dynamic_cpr", "dynamic_box_depth", "dynamic_flow_epipolar", "dynamic_depth_sdf",
                   "dynamic_all"]


def sweep_arguments(argv=None) -> list[str]:
    """The ``tools/sweep.py`` command line equivalent to an ``ablation.py`` one."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="*", help="sequence folders (default: the README's Bonn crowd ablation)")
    parser.add_argument("--configs", nargs="+", help="preset names or YAML files, 'none' = off")
    parser.add_argument("--repeats", type=int)
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes")
    parser.add_argument("--set", action="append", default=[], help="override for every run, key=value")
    parser.add_argument("--output", "-o", default=str(sweep.REPO / "results" / "ablation"))
    args = parser.parse_args(argv)
    if args.sequences:
        out = ["--sequences", *args.sequences, "--configs", *(args.configs or DEFAULT_CONFIGS)]
    else:
        out = [str(ABLATION_SWEEP)] + (["--configs", *args.configs] if args.configs else [])
    if args.repeats is not None:
        out += ["--repeats", str(args.repeats)]
    for pair in args.set:
        out += ["--set", pair]
    return out + ["--jobs", str(args.jobs), "--output", args.output]


if __name__ == "__main__":
    sys.exit(sweep.main(sweep_arguments()))
