"""The sequences of ``tools/sweep.py`` and the Pipeline a child process runs on one of them.

A sequence is a TUM/Bonn folder, or a generated one: ``synthetic[:MOVERS][:seed=N][:path=P]`` (random
walkers, ground-truth boxes as the detector) or ``hard:SCENE[:seed=N]`` (a scripted hard scene of
``slam/datasets/synthetic_scenes.py``, whose detector misses the person on the scene's
``detector_misses`` frames, as ``tools/hard_scenes.py`` and ``dynslam demo`` run it), or
``composite:SCENE:path=FOLDER[:seed=N]`` (the people of a scene composited into a real sequence,
``slam/datasets/composite.py``: its frames, its camera, its ground truth; all its frames unless
``--max-frames``; a relative FOLDER is relative to the repository root).
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Optional

SYNTHETIC_PREFIX = "synthetic"
HARD_PREFIX = "hard:"
COMPOSITE_PREFIX = "composite:"
REPO = Path(__file__).resolve().parents[1]
SYNTHETIC_FRAMES = 120          # frames of a random-walker sequence when --max-frames is not given
HARD_FRAMES = 150               # frames of a hard scene when --max-frames is not given (tools/hard_scenes.py's)


class SequenceSpecError(ValueError):
    """A generated-sequence spec that names an unknown option or scene."""


def is_generated(sequence: str) -> bool:
    """A generated sequence (no folder to check, no path to resolve)."""
    return sequence.startswith((SYNTHETIC_PREFIX, HARD_PREFIX, COMPOSITE_PREFIX))


def sequence_label(sequence: str) -> str:
    """The table's and run folder's name: a folder's name, a generated spec with ':' etc. made safe."""
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", sequence) if is_generated(sequence) else Path(sequence).name


def _options(spec: str, allowed: dict[str, type], positional: str) -> dict[str, Any]:
    """``prefix:VALUE:key=value...``: the bare token is ``positional``, the others must be in ``allowed``."""
    options: dict[str, Any] = {}
    for token in spec.split(":")[1:]:
        key, _, value = token.partition("=")
        if not value:
            options[positional] = key
        elif key in allowed:
            options[key] = allowed[key](value)
        else:
            raise SequenceSpecError(f"{spec}: unknown option {key!r} (expected {positional.upper()} or "
                                    f"{', '.join(f'{k}=...' for k in allowed)})")
    return options


def open_synthetic(spec: str, n_frames: int):
    """``synthetic[:MOVERS][:seed=N][:path=P]``, e.g. ``synthetic:people`` or ``synthetic:crowd:seed=2``."""
    from slam.datasets import SyntheticSequence

    options = {"movers": "none", **_options(spec, {"seed": int, "path": str}, "movers")}
    return SyntheticSequence(n_frames=n_frames, **options)


def hard_scene_options(spec: str) -> dict[str, Any]:
    """``hard:SCENE[:seed=N]`` -> {"scene": SCENE, "seed": N (default 0)}; refuses an unknown scene."""
    from slam.datasets.synthetic_scenes import HARD_SCENES

    options = {"seed": 0, **_options(spec, {"seed": int}, "scene")}
    if options.get("scene") not in HARD_SCENES:
        raise SequenceSpecError(f"{spec}: expected hard:SCENE[:seed=N] with SCENE one of {', '.join(HARD_SCENES)}")
    return options


def open_hard(spec: str, n_frames: int):
    from slam.datasets.synthetic_scenes import HardScene

    options = hard_scene_options(spec)
    return HardScene(options["scene"], n_frames=n_frames, seed=options["seed"])


def composite_options(spec: str) -> dict[str, Any]:
    """``composite:SCENE:path=FOLDER[:seed=N]`` -> {"scene", "path" (absolute), "seed"}; refuses an unknown
    scene, a missing path= and a folder without ground truth."""
    from slam.datasets.composite import COMPOSITE_SCENES

    options = {"seed": 0, **_options(spec, {"seed": int, "path": str}, "scene")}
    if options.get("scene") not in COMPOSITE_SCENES or "path" not in options:
        raise SequenceSpecError(f"{spec}: expected composite:SCENE:path=FOLDER[:seed=N] with SCENE one of "
                                f"{', '.join(COMPOSITE_SCENES)}")
    folder = Path(options["path"])
    options["path"] = folder if folder.is_absolute() else (REPO / folder).resolve()
    if not (options["path"] / "groundtruth.txt").is_file():
        raise SequenceSpecError(f"{spec}: {options['path']} has no groundtruth.txt to composite from")
    return options


def build_pipeline(job: dict):
    """The Pipeline of one job, configured as ``dynslam run`` would be plus the job's seed."""
    from slam.run.run_config import resolve_run_config, seeded
    from slam.datasets import TumDataset
    from slam.run.demo import demo_detector
    from slam.run.pipeline import Pipeline

    files, overrides, max_frames = list(job["presets"]), dict(job["overrides"]), job["max_frames"]
    if is_generated(job["sequence"]) and not job["sequence"].startswith(COMPOSITE_PREFIX):
        hard = job["sequence"].startswith(HARD_PREFIX)
        sequence = (open_hard(job["sequence"], max_frames or HARD_FRAMES) if hard
                    else open_synthetic(job["sequence"], max_frames or SYNTHETIC_FRAMES))
        fx, fy, cx, cy = sequence.intrinsics
        camera = {"camera.name": "synthetic", "camera.fx": fx, "camera.fy": fy, "camera.cx": cx, "camera.cy": cy,
                  "camera.width": sequence.width, "camera.height": sequence.height, "camera.distortion": [0.0] * 5}
        config = seeded(resolve_run_config(None, files, {**camera, **overrides}), job["seed"])
        # YOLOX does not detect the generated people: their true boxes (8 px wider) stand in, without the
        # frames a hard scene's detector misses.
        return Pipeline(sequence, config, job["run_dir"], max_frames, detector=demo_detector(sequence))
    if job["sequence"].startswith(COMPOSITE_PREFIX):
        from slam.datasets.composite import CompositeScene

        options = composite_options(job["sequence"])
        config = seeded(resolve_run_config(options["path"], files, overrides), job["seed"])
        camera = config.camera
        sequence = CompositeScene(options["scene"], options["path"], (camera.fx, camera.fy, camera.cx, camera.cy),
                                  n_frames=max_frames, seed=options["seed"])
        return Pipeline(sequence, config, job["run_dir"], max_frames, detector=demo_detector(sequence))
    root = Path(job["sequence"])
    config = seeded(resolve_run_config(root, files, overrides), job["seed"])
    dataset = TumDataset(root, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt)
    return Pipeline(dataset, config, job["run_dir"], max_frames)


def check_generated(sequence: str) -> Optional[str]:
    """Why a generated spec cannot run (None if it can), checked before any run starts."""
    try:
        if sequence.startswith(HARD_PREFIX):
            hard_scene_options(sequence)
        elif sequence.startswith(COMPOSITE_PREFIX):
            composite_options(sequence)
        else:
            _options(sequence, {"seed": int, "path": str}, "movers")
    except (SequenceSpecError, ValueError) as exc:
        return str(exc)
    return None
