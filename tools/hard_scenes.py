#!/usr/bin/env python3
"""The scripted hard scenes (slam/datasets/synthetic_scenes.py): ATE against the same camera path without
people, frames LOST, the worst frame, and each method's precision/recall per feature and per keyframe-mask
pixel (p >= 0.5) against the exact masks.

    python tools/hard_scenes.py                               # all four, 150 frames, dynamic_all
    python tools/hard_scenes.py close_pass --frames 150 --preset dynamic_all --set tracking.x=...

The detector is the scene's ground-truth person boxes widened by 8 px (as `dynslam demo` uses), with the
frames on which the scene's detector misses the person left out (``HardScene.detector_misses``).
"""
from __future__ import annotations

import argparse
import sys


from slam.datasets import SyntheticSequence
from slam.datasets.synthetic_scenes import HARD_SCENES, HardScene
from slam.run.demo import DEMO_ORACLE_MARGIN_PX
from slam.run.run_config import parse_overrides
from slam.run.dynamic_eval import evaluate_synthetic, scene_detector, synthetic_config



def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="*", default=list(HARD_SCENES), help=f"scenes to run (default: all of {', '.join(HARD_SCENES)})")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default="dynamic_all")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value after the preset (repeatable)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.scenes) - set(HARD_SCENES))
    if unknown:
        parser.error(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(HARD_SCENES)}")
    overrides = parse_overrides(args.set)
    clean_seq = SyntheticSequence(n_frames=args.frames, seed=args.seed)
    clean = evaluate_synthetic(clean_seq, synthetic_config(clean_seq, preset=args.preset, **overrides))
    print(f"same path without people: ATE {clean.ate_rmse * 1000:.1f} mm, worst frame {clean.max_error * 1000:.1f} mm")
    rows = ["| scene | peak cover | misses | ATE mm | / clean | worst mm | LOST | fused P/R (features) "
            "| fused P/R (kf masks) |", "|---|---|---|---|---|---|---|---|---|"]
    details = []
    for name in args.scenes:
        scene = HardScene(name, n_frames=args.frames, seed=args.seed)
        result = evaluate_synthetic(scene, synthetic_config(scene, preset=args.preset, **overrides),
                                    detector=scene_detector(scene, DEMO_ORACLE_MARGIN_PX))
        cls, fused = result.classification, result.keyframe_masks.get("fused")
        mask_pr = f"{fused.precision:.2f} / {fused.recall:.2f}" if fused else "-"
        rows.append(f"| {name} | {scene.coverage.max():.2f} | {len(scene.detector_misses)} "
                    f"| {result.ate_rmse * 1000:.1f} | {result.ate_rmse / clean.ate_rmse:.2f} "
                    f"| {result.max_error * 1000:.1f} | {len(result.lost_frames)} "
                    f"| {cls.precision['fused']:.2f} / {cls.recall['fused']:.2f} | {mask_pr} |")
        details.append(f"\n{name}: per feature\n{cls.table()}\n{name}: keyframe masks "
                       f"({result.keyframes} keyframes)\n{result.mask_table()}")
        print(rows[-1], flush=True)
    print()
    print("\n".join(rows))
    print("".join(details))
    return 0


if __name__ == "__main__":
    sys.exit(main())
