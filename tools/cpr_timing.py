#!/usr/bin/env python3
"""The cpr dynamic method (frontend/dynamic/cpr.py) alone on a sequence: median ms per stage, and its masks.

    python tools/cpr_timing.py [SEQ_DIR] [--frames 480] [--save masks.npz] [--set cpr.FIELD=VALUE ...]
    python tools/cpr_timing.py --compare before.npz after.npz      # agreement of two saved runs

Frames are read before the clock starts; only ``CprMethod.process`` is timed (its ``info`` ms_<stage>).
Poses given to ``end_frame`` are None, so every initial guess is identity (the documented fallback): the
timing does not depend on a tracker. ``--save`` writes every frame's raw mask (bit-packed) for ``--compare``,
which prints the per-pixel agreement and the IoU of the dynamic pixels over all frames. Run one timing at a
time on a shared machine (2 cores) and repeat: medians of a busy machine are not comparable.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DEFAULT = REPO.parent / "shared" / "data" / "rgbd_bonn_crowd_first480"
STAGES = ("cloud", "kmeans", "target", "icp", "score", "mask", "refine")


def _empty_frame(index: int, timestamp: float):
    from slam.core.frame import FeatureFrame

    z2, z1 = np.zeros((0, 2)), np.zeros(0)
    return FeatureFrame(index, timestamp, z2, z2, np.zeros(0, int), np.zeros((0, 32), np.uint8), z1, z1, z1,
                        np.ones(1))


def run(sequence: Path, frames: int, overrides: list[str], save: str) -> None:
    import cv2

    from frontend.dynamic.base import DynamicContext
    from frontend.dynamic.cpr import CprMethod
    from slam.core.camera import PinholeCamera
    from slam.datasets import TumDataset
    from slam.run.run_config import parse_overrides, resolve_run_config

    config = resolve_run_config(sequence, [], parse_overrides([f"dynamic.{o}" for o in overrides]))
    camera = PinholeCamera.from_config(config.camera)
    dataset = TumDataset(sequence, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
    method = CprMethod(config.dynamic.cpr)
    rows: dict[str, list[float]] = {s: [] for s in STAGES}
    totals, masks = [], []
    for i, f in enumerate(dataset):
        if i >= frames:
            break
        ctx = DynamicContext(_empty_frame(f.index, f.timestamp), f.rgb, cv2.cvtColor(f.rgb, cv2.COLOR_BGR2GRAY),
                             f.depth, camera)
        t0 = time.perf_counter()
        out = method.process(ctx)
        totals.append((time.perf_counter() - t0) * 1e3)
        method.end_frame(ctx, out, None, False)
        for s in STAGES:
            if f"ms_{s}" in out.info:
                rows[s].append(out.info[f"ms_{s}"])
        mask = out.mask if out.mask is not None else np.zeros(f.depth.shape, np.float32)
        masks.append(np.packbits(mask >= 0.5))
    body = [s for s in STAGES if rows[s]]
    print(" | ".join(f"{s} {np.median(rows[s]):.2f}" for s in body)
          + f" | sum of stage medians {sum(np.median(rows[s]) for s in body):.2f}")
    t = np.array(totals[2:])                  # frames with a reference
    print(f"process: median {np.median(t):.2f} ms, p90 {np.percentile(t, 90):.2f} ms, mean {t.mean():.2f} ms "
          f"over {len(t)} frames")
    if save:
        np.savez_compressed(save, masks=np.stack(masks), shape=np.array(f.depth.shape))


def compare(a: str, b: str) -> None:
    da, db = np.load(a), np.load(b)
    n = int(np.prod(da["shape"]))
    ma = np.unpackbits(da["masks"], axis=1)[:, :n].astype(bool)
    mb = np.unpackbits(db["masks"], axis=1)[:, :n].astype(bool)
    same = (ma == mb).mean()
    inter, union = (ma & mb).sum(), (ma | mb).sum()
    frame_iou = np.array([(x & y).sum() / max((x | y).sum(), 1) for x, y in zip(ma, mb)])
    identical = int(np.sum(np.all(ma == mb, axis=1)))
    print(f"pixels equal {same:.4%}; dynamic-pixel IoU over all frames {inter / max(union, 1):.4f}; "
          f"dynamic pixels {ma.mean():.4%} -> {mb.mean():.4%}; identical frames {identical}/{len(ma)}; "
          f"per-frame IoU median {np.median(frame_iou):.3f}, p10 {np.percentile(frame_iou, 10):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", default=str(DEFAULT))
    ap.add_argument("--frames", type=int, default=480)
    ap.add_argument("--save", default="", help="write the raw masks here (.npz)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="cpr.FIELD=VALUE")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
    else:
        run(Path(args.sequence), args.frames, args.overrides, args.save)


if __name__ == "__main__":
    main()
