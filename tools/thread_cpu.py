#!/usr/bin/env python3
"""CPU milliseconds per frame that named functions cost the tracking thread, over one run of a sequence.

    python tools/thread_cpu.py SEQ_DIR frontend.dynamic.free_space:FreeSpaceCheck._test \\
        frontend.dynamic.keyframe_masks:fused_pixel_mask slam.runtime.tracking_loop:TrackingLoop._add_keyframe
    python tools/thread_cpu.py SEQ_DIR MODULE:FUNCTION ... --set backend.worker_process=false
    python tools/thread_cpu.py SEQ_DIR MODULE:FUNCTION ... --tree ../before     # another checkout's code

Each target (``module:qualified.name``) is wrapped for the run and charged the thread CPU
(``time.thread_time``) of its calls on the main thread, the one that tracks; calls on other threads (cpr's,
the features' lookahead) run unwrapped. Prints the main thread's CPU per frame over the whole run (the writes
at its end included) and, per target, its CPU per frame and its calls, most costly first. A target called
inside another is counted in both. The benchmark's "module CPU" line says what each module costs; this says
what one function inside it costs, before and after a change, at a cost of ~1 us a call. A function imported
by name into another module (``from frontend.matching import search_by_projection``) is wrapped where it is
defined, so calls through the other module's own name are not seen: name that module instead.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def wrap(target: str, spent: dict, calls: Counter, thread_id: int) -> None:
    """Replace ``module:qualified.name`` by a wrapper that charges its main-thread CPU to ``spent[target]``."""
    if ":" not in target:
        raise SystemExit(f"{target}: expected module:qualified.name (e.g. frontend.dynamic.fusion:fuse_masks)")
    module_name, qualified = target.split(":", 1)
    owner = importlib.import_module(module_name)
    *path, name = qualified.split(".")
    for part in path:
        owner = getattr(owner, part)
    function = getattr(owner, name)

    def charged(*args, **kwargs):
        if threading.get_ident() != thread_id:
            return function(*args, **kwargs)
        start = time.thread_time()
        try:
            return function(*args, **kwargs)
        finally:
            spent[target] += time.thread_time() - start
            calls[target] += 1

    if isinstance(owner, type) and isinstance(owner.__dict__.get(name), staticmethod):
        charged = staticmethod(charged)
    setattr(owner, name, charged)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequence", type=Path)
    parser.add_argument("targets", nargs="+", metavar="MODULE:FUNCTION")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--output", type=Path, default=Path("results/thread_cpu"))
    parser.add_argument("--tree", type=Path, default=REPO,
                        help="the checkout whose code runs (default: this one; e.g. a worktree of a commit before)")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.tree.resolve()))

    from slam.datasets import TumDataset
    from slam.run.pipeline import Pipeline
    from slam.run.run_config import parse_overrides, resolve_run_config

    spent: dict[str, float] = defaultdict(float)
    calls: Counter = Counter()
    for target in args.targets:
        wrap(target, spent, calls, threading.get_ident())
    config = resolve_run_config(args.sequence, [], parse_overrides(args.set))
    dataset = TumDataset(args.sequence, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
    pipeline = Pipeline(dataset, config, args.output)
    start = time.thread_time()
    summary = pipeline.run()
    frames = max(summary.frames, 1)
    print(f"{args.sequence.name}: main thread CPU {(time.thread_time() - start) / frames * 1e3:.2f} ms per frame "
          f"over {summary.frames} frames")
    for target in sorted(args.targets, key=lambda t: -spent[t]):
        print(f"{spent[target] / frames * 1e3:8.2f} ms per frame  {calls[target]:7d} calls  {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
