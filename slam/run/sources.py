"""Where a run's frames and configuration come from: a folder or bag on disk, or a live camera.

``resolve_run_config`` (slam/run/run_config.py) layers the configuration (defaults, the source's camera,
the user's files, --set);
``open_recorded`` / ``open_live`` give (frame source, config) for ``dynslam run``. Imports of the heavy
parts happen inside the functions: the command line imports this module for ``--help`` too.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

from slam.run.run_config import resolve_run_config


def frames_to_run(dataset, max_frames: Optional[int]) -> Optional[int]:
    """The run's length for the progress bar: None for a live camera without --max-frames."""
    try:
        total = len(dataset)
    except TypeError:   # a live camera has no length
        return max_frames
    return min(total, max_frames or total)


def open_recorded(source: str, config_files: Sequence[str], overrides: dict, output: Optional[str] = None):
    """(dataset, config) of a folder or bag on disk; ``output`` (if given) is checked to be writable
    once the dataset is known to exist."""
    from slam.datasets import DatasetError, is_rosbag, open_dataset

    root = Path(source)
    expected = ("a TUM RGB-D folder with rgb.txt, depth.txt, rgb/ and depth/; a ROS .bag file (RealSense "
                "Viewer recordings too) or ROS 2 bag folder; a folder with color/, depth/ and intrinsics.yaml; "
                "or 'realsense' for a live camera")
    if not root.exists():
        raise DatasetError(f"dataset {root} does not exist (expected {expected})")
    if not root.is_dir() and not is_rosbag(root):
        raise DatasetError(f"{root} is not a dataset (expected {expected})")
    config = resolve_run_config(root, config_files, overrides)
    check_output(output)
    return open_dataset(root, depth_scale=config.camera.depth_scale, max_dt=config.max_association_dt), config


def check_output(output: Optional[str]) -> None:
    """An unwritable results folder fails now, not after the whole run (or after starting a camera)."""
    from slam.core.atomic_io import ensure_output_dir

    if output:
        ensure_output_dir(output)


def open_live(source: str, config_files: Sequence[str], overrides: dict, output: Optional[str] = None):
    """(camera, config) of ``realsense[:SERIAL]``: the streams are requested at the configured
    camera.width x camera.height and camera.fps (640x480 at 30 by default); the intrinsics come from
    the device, which is stopped again if the configuration then fails."""
    from slam.datasets.realsense_live import RealSenseCamera, parse_serial

    wanted = resolve_run_config(None, config_files, overrides).camera
    check_output(output)
    camera = RealSenseCamera(parse_serial(source), wanted.width, wanted.height, int(round(wanted.fps)))
    try:
        return camera, resolve_run_config(None, config_files, overrides, camera=camera.intrinsics())
    except BaseException:
        camera.close()
        raise
