"""RGB-D sequence sources: TUM/Bonn folders, ROS bags, image folders with intrinsics.yaml, and a seeded
synthetic room."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

from .base import DatasetDefaults, RGBDDataset, RGBDFrame, frames_of
from .folder import INTRINSICS_FILE, ImageFolderDataset, is_image_folder, read_folder_intrinsics
from .realsense_bag import RealSenseBagDataset, is_realsense_bag, read_realsense_camera
from .replay import RealtimeReplay
from .rosbag import RosbagDataset, is_rosbag, read_bag_camera
from .synthetic import SyntheticSequence
from .synthetic_export import write_tum_layout
from .tum import (CAMERA_FILE, DatasetError, DatasetWarning, TumDataset, associate, guess_camera,
                  load_groundtruth, read_intrinsics)

__all__ = [
    "RGBDDataset", "RGBDFrame", "SyntheticSequence", "write_tum_layout", "DatasetError", "DatasetWarning",
    "TumDataset", "associate", "guess_camera", "load_groundtruth", "read_intrinsics", "open_dataset",
    "RosbagDataset", "ImageFolderDataset", "is_rosbag", "is_image_folder", "read_camera",
    "RealSenseBagDataset", "is_realsense_bag", "RealtimeReplay",
]

AnyDataset = Union[TumDataset, RosbagDataset, RealSenseBagDataset, ImageFolderDataset, SyntheticSequence]


def open_dataset(path_or_name: Union[str, Path], **kwargs) -> AnyDataset:
    """The reader that fits ``path_or_name``; kwargs go to its constructor.

    "synthetic" gives the default SyntheticSequence (write "./synthetic" for a folder of that name); a
    ``.bag`` recorded by librealsense (RealSense Viewer) gives a RealSenseBagDataset (depth registered to
    colour; only ``max_dt`` is used), any other ``.bag`` file or a ROS 2 bag folder a RosbagDataset
    (``depth_scale`` is dropped: a bag's encoding or depth-units topic fixes its units); a folder with
    intrinsics.yaml an ImageFolderDataset; anything else is opened as a TUM-layout folder.
    """
    if isinstance(path_or_name, str) and path_or_name == "synthetic":
        return SyntheticSequence(**kwargs)
    if is_rosbag(path_or_name):
        kwargs.pop("depth_scale", None)
        if is_realsense_bag(path_or_name):
            return RealSenseBagDataset(path_or_name, **{k: v for k, v in kwargs.items() if k == "max_dt"})
        return RosbagDataset(path_or_name, **kwargs)
    if is_image_folder(path_or_name):
        return ImageFolderDataset(path_or_name, **kwargs)
    return TumDataset(path_or_name, **kwargs)


def read_camera(path: Union[str, Path]) -> Optional[tuple[dict, Path]]:
    """(camera keys, where they came from) for a dataset path, or None when it names no camera.

    Bags: their CameraInfo topic (RealSense bags: the colour stream's); image folders: intrinsics.yaml;
    TUM folders: an optional camera.yaml.
    """
    path = Path(path)
    if is_realsense_bag(path):
        return read_realsense_camera(path), path
    if is_rosbag(path):
        camera = read_bag_camera(path)
        return None if camera is None else (camera, path)
    if is_image_folder(path):
        return read_folder_intrinsics(path), path / INTRINSICS_FILE
    camera = read_intrinsics(path)
    return None if camera is None else (camera, path / CAMERA_FILE)
