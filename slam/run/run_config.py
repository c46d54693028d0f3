"""The config of one run: defaults, the dataset's camera, the user's files, the command's own values and
``--set`` overrides, merged as layers and validated once (used by the CLI and the tools)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Sequence

if TYPE_CHECKING:   # annotations only: the functions below import the config modules when called
    from slam.core.config import SlamConfig


def parse_overrides(pairs: Sequence[str]) -> dict:
    """``--set key=value`` pairs as a dict of dotted keys to YAML-parsed values."""
    import yaml

    from slam.core.config import ConfigError

    overrides = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set expects key=value (e.g. tracking.match_ratio=0.8), got '{pair}'")
        key, value = pair.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    return overrides


def resolve_run_config(dataset_path: Optional[Path], config_files: Sequence[str], overrides: dict,
                       fixed: Optional[dict] = None, fixed_source: str = "demo", camera: Optional[dict] = None):
    """Defaults, then the camera of the dataset (a bag's CameraInfo, an image folder's intrinsics.yaml,
    a TUM folder's camera.yaml, else a preset guessed from the name), then the user's files in order,
    then ``fixed`` dotted values of the command (the demo's generated camera), then --set overrides
    (``camera``: the keys a live camera reported, in place of the dataset's camera):
    merged first and validated once, an error naming the layer that set the key."""
    from slam.core.config import CameraConfig, build_config, overrides_layer, yaml_layer
    from slam.datasets import guess_camera, read_camera

    layers = []
    if camera is not None:
        known = {f"camera.{k}": v for k, v in camera.items() if k in CameraConfig.model_fields}
        layers.append(overrides_layer(known, "the camera"))
    if dataset_path is not None:
        found = read_camera(dataset_path)
        guessed = guess_camera(dataset_path)
        if found:
            intrinsics, source = found
            known = {f"camera.{k}": v for k, v in intrinsics.items() if k in CameraConfig.model_fields}
            layers.append(overrides_layer(known, str(source)))
        elif guessed:
            layers.append(yaml_layer(guessed))
    camera_known = bool(layers) or bool(config_files)
    layers += [yaml_layer(path) for path in config_files]
    if fixed:
        layers.append(overrides_layer(fixed, fixed_source))
    if overrides:
        layers.append(overrides_layer(overrides, "--set"))
    config = build_config(layers)
    if dataset_path is not None and not camera_known:
        logging.getLogger("dynslam").warning(
            "camera not recognised (no camera_info, intrinsics.yaml or camera.yaml, and the name "
            "says no freiburg1/2/3 or bonn); using default intrinsics "
            "(pass --config tum_fr1|tum_fr2|tum_fr3|bonn or your own YAML)")
    return config


def seeded(config: SlamConfig, seed: int) -> SlamConfig:
    """``config`` with every seed set to ``seed``: the run's (``seed``) and each dynamic method's. What a seed
    moves: cpr's k-means seeding and depth_sdf's pairs. OpenCV's RANSAC (tracking's and relocalization's PnP,
    flow_epipolar's F, box_depth's homography) draws from a generator fixed inside each call, whatever
    ``cv2.setRNGSeed`` was given, so it makes the same choices at every seed: runs that differ only here show
    how much a result owes to the two draws above, not to RANSAC's (``tools/sweep.py --repeats``, ``tools/hard_scenes.py
    --repeats``, the hard-scene test's median of three)."""
    from slam.core.dynamic_config import METHOD_NAMES

    config.seed = seed
    for method in METHOD_NAMES:
        section = getattr(config.dynamic, method)
        if "seed" in type(section).model_fields:       # box_depth makes no random choice
            section.seed = seed
    return config
