"""A plain folder of colour and depth images with an ``intrinsics.yaml`` beside them.

    my_recording/
      intrinsics.yaml          fx fy cx cy width height depth_scale, optional distortion, fps, name
      color/ (colour/, rgb/)   000000.png 000001.png ...   8-bit colour, PNG or JPEG
      depth/                   000000.png 000001.png ...   16-bit PNG (or float TIFF), depth_scale units/metre

Colour and depth are paired by file name (same stem), else by the number in the name (``color_0007`` with
``depth_0007``), else, when both name decimal times that differ (separate sensors), by nearest time within
``max_dt`` like TUM. Unpaired files are skipped with one warning naming them. Timestamps are position/fps
when ``fps`` is given, else the times in the names, else position / 30 fps.
"""
from __future__ import annotations

import math
import re
import warnings
from pathlib import Path
from typing import Iterator, Optional, Union

import cv2
import numpy as np
import yaml

from .base import DatasetDefaults, RGBDFrame
from .tum import DatasetError, DatasetWarning, _imread, _name_list, associate

PathLike = Union[str, Path]

INTRINSICS_FILE = "intrinsics.yaml"
COLOUR_DIRS = ("color", "colour", "rgb")
DEPTH_DIR = "depth"
COLOUR_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".tif", ".tiff")
REQUIRED_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
OPTIONAL_KEYS = ("distortion", "fps", "name")
DEFAULT_FPS = 30.0
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def read_folder_intrinsics(folder: PathLike) -> dict:
    """The checked contents of ``folder/intrinsics.yaml``; DatasetError names the file and the key."""
    path = Path(folder) / INTRINSICS_FILE
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path} does not exist") from None
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping with keys {', '.join(REQUIRED_KEYS)}")
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {', '.join(missing)} (required: {', '.join(REQUIRED_KEYS)})")
    unknown = sorted(set(data) - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
    if unknown:
        raise DatasetError(f"{path}: unknown key(s) {', '.join(map(str, unknown))} (allowed: "
                           f"{', '.join(REQUIRED_KEYS + OPTIONAL_KEYS)})")
    camera = {k: _number(path, k, data[k], positive=k not in ("cx", "cy")) for k in REQUIRED_KEYS}
    for key in ("width", "height"):
        if camera[key] != int(camera[key]):
            raise DatasetError(f"{path}: '{key}' must be a whole number of pixels, got {data[key]!r}")
        camera[key] = int(camera[key])
    if "distortion" in data:
        coeffs = data["distortion"]
        if not isinstance(coeffs, list) or len(coeffs) not in (4, 5):
            raise DatasetError(f"{path}: 'distortion' must be a list of 4 or 5 numbers (k1 k2 p1 p2 [k3]), "
                               f"got {coeffs!r}")
        camera["distortion"] = [_number(path, "distortion", c) for c in coeffs]
    if "fps" in data:
        camera["fps"] = _number(path, "fps", data["fps"], positive=True)
    if "name" in data:
        camera["name"] = str(data["name"])
    return camera


def _number(path: Path, key: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{path}: '{key}' must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise DatasetError(f"{path}: '{key}' must be positive, got {value!r}")
    return float(value)


def is_image_folder(path: PathLike) -> bool:
    return (Path(path) / INTRINSICS_FILE).is_file()


def _images(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes]
    keys = [_number_in(p.stem) for p in files]
    if files and all(k is not None for k in keys):  # 2.png before 10.png
        return [p for _, p in sorted(zip(keys, files), key=lambda kp: (kp[0], kp[1].name))]
    return sorted(files)


def _number_in(stem: str) -> Optional[float]:
    """The last number in a file name (a frame number or a time in seconds), or None."""
    found = _NUMBER.findall(stem)
    return float(found[-1]) if found else None


def _is_time(stem: str) -> bool:
    found = _NUMBER.findall(stem)
    return bool(found) and "." in found[-1]


def pair_files(colour: list[Path], depth: list[Path], max_dt: float) -> tuple[np.ndarray, np.ndarray, str]:
    """Index arrays (ic, id) into the two sorted lists and a description of the rule used."""
    depth_by_stem = {p.stem: j for j, p in enumerate(depth)}
    ic = [i for i, p in enumerate(colour) if p.stem in depth_by_stem]
    if ic:
        return np.array(ic), np.array([depth_by_stem[colour[i].stem] for i in ic]), "same file name"
    kc = [_number_in(p.stem) for p in colour]
    kd = [_number_in(p.stem) for p in depth]
    if None in kc or None in kd:
        raise DatasetError(f"cannot pair colour and depth images: no file name appears in both folders and "
                           f"not every name has a number (e.g. {colour[0].name}, {depth[0].name})")
    depth_by_key = {k: j for j, k in enumerate(kd)}
    ic = [i for i, k in enumerate(kc) if k in depth_by_key]
    if ic:
        return np.array(ic), np.array([depth_by_key[kc[i]] for i in ic]), "same number in the name"
    if all(_is_time(p.stem) for p in colour + depth):
        ia, ib = associate(np.array(kc), np.array(kd), max_dt)
        return ia, ib, f"nearest time in the name within {max_dt * 1000:g} ms"
    raise DatasetError(f"cannot pair colour and depth images: no name or frame number appears in both "
                       f"folders (e.g. {colour[0].name}, {depth[0].name})")


class ImageFolderDataset(DatasetDefaults):
    """RGB-D frames of a folder of images plus ``intrinsics.yaml`` (module docstring); ``RGBDDataset``.

    ``depth_scale`` (units per metre) defaults to the YAML's; ``frame.index`` is the pair's position.
    """

    def __init__(self, root: PathLike, depth_scale: Optional[float] = None, max_dt: float = 0.02) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"image folder {self.root} does not exist")
        self.name = self.root.resolve().name
        self._camera = read_folder_intrinsics(self.root)
        self.depth_scale = float(depth_scale or self._camera["depth_scale"])
        self.skipped: list[tuple[Path, str]] = []
        self.missing: list[Path] = []
        colour_dir = next((self.root / d for d in COLOUR_DIRS if (self.root / d).is_dir()), None)
        if colour_dir is None or not (self.root / DEPTH_DIR).is_dir():
            raise DatasetError(f"{self.root} needs a colour folder ({'/, '.join(COLOUR_DIRS)}/) and a "
                               f"{DEPTH_DIR}/ folder beside {INTRINSICS_FILE}")
        colour, depth = _images(colour_dir, COLOUR_SUFFIXES), _images(self.root / DEPTH_DIR, DEPTH_SUFFIXES)
        if not colour or not depth:
            empty = colour_dir if not colour else self.root / DEPTH_DIR
            raise DatasetError(f"{empty} holds no images ({', '.join(COLOUR_SUFFIXES + DEPTH_SUFFIXES)})")
        try:
            ic, idp, self.pairing = pair_files(colour, depth, max_dt)
        except DatasetError as exc:
            raise DatasetError(f"{self.root}: {exc}") from None
        self._warn_unpaired(colour, depth, ic, idp)
        times = self._times(colour)
        self._rgb, self._depth = [colour[i] for i in ic], [depth[j] for j in idp]
        self._t_rgb = times[ic]
        self._t_rgb.flags.writeable = False
        self._check_size(self._rgb[0])

    def _warn_unpaired(self, colour: list[Path], depth: list[Path], ic: np.ndarray, idp: np.ndarray) -> None:
        if len(ic) == 0:
            raise DatasetError(f"{self.root}: no colour image pairs with a depth image (pairing by {self.pairing})")
        paired_colour, paired_depth = set(ic.tolist()), set(idp.tolist())
        lone = [p for i, p in enumerate(colour) if i not in paired_colour] + \
               [p for j, p in enumerate(depth) if j not in paired_depth]
        self.missing = lone
        if lone:
            warnings.warn(f"{self.name}: {len(colour)} colour and {len(depth)} depth images; pairing by "
                          f"{self.pairing}, {len(lone)} without a partner are skipped: "
                          f"{_name_list([p.name for p in lone])}", DatasetWarning, stacklevel=3)

    def _times(self, colour: list[Path]) -> np.ndarray:
        """Seconds per colour file: position / fps, or the times in the names (see module docstring)."""
        if "fps" not in self._camera and all(_is_time(p.stem) for p in colour):
            return np.array([_number_in(p.stem) for p in colour], dtype=np.float64)
        return np.arange(len(colour), dtype=np.float64) / self._camera.get("fps", DEFAULT_FPS)

    def _check_size(self, first: Path) -> None:
        """A wrong width/height in the YAML would silently distort every projection: check it once."""
        image = _imread(first, cv2.IMREAD_COLOR)
        if image is None:
            return  # reported when iterating, like any unreadable frame
        want = (self._camera["height"], self._camera["width"])
        if image.shape[:2] != want:
            raise DatasetError(f"{self.root / INTRINSICS_FILE}: width x height {want[1]}x{want[0]} differs from "
                               f"{first.name}'s {image.shape[1]}x{image.shape[0]}")

    @property
    def timestamps(self) -> np.ndarray:
        return self._t_rgb

    def intrinsics(self) -> dict:
        """Camera keys from intrinsics.yaml (fx fy cx cy width height depth_scale, and any optional ones)."""
        return dict(self._camera)

    def __len__(self) -> int:
        return len(self._rgb)

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            frame, reason = self._load(i)
            if frame is not None:
                yield frame
                continue
            path = self._rgb[i] if reason.startswith("colour") else self._depth[i]
            self.skipped.append((path, reason))
            warnings.warn(f"{self.name}: skipping frame {i} ({path}): {reason}", DatasetWarning, stacklevel=2)

    def _load(self, i: int) -> tuple[Optional[RGBDFrame], str]:
        rgb = _imread(self._rgb[i], cv2.IMREAD_COLOR)
        if rgb is None or rgb.dtype != np.uint8:
            return None, "colour image unreadable or not 8-bit"
        raw = _imread(self._depth[i], cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2 or raw.dtype == np.uint8:
            desc = "unreadable" if raw is None else f"{raw.dtype} with shape {raw.shape}"
            return None, f"depth image is not 16-bit or float single-channel ({desc})"
        if raw.shape != rgb.shape[:2]:
            return None, f"depth size {raw.shape} differs from colour size {rgb.shape[:2]}"
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        return RGBDFrame(index=i, timestamp=float(self._t_rgb[i]), rgb=rgb, depth=depth,
                         rgb_path=self._rgb[i], depth_path=self._depth[i]), ""

    def groundtruth(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(timestamps, poses) from an optional TUM-format groundtruth.txt in the folder, else None."""
        from .tum import load_groundtruth

        path = self.root / "groundtruth.txt"
        return load_groundtruth(path) if path.is_file() else None

    def __repr__(self) -> str:
        return f"ImageFolderDataset({str(self.root)!r}, frames={len(self)}, pairing={self.pairing!r})"
