"""RealSense ``.bag`` recordings (RealSense Viewer, ``rs2::recorder``, ``rs.config.enable_record_to_file``).

librealsense writes ROS 1 bags in its own topic layout (file format version 3, ``/file_version``), not the
realsense-ros wrapper's ``/camera/...`` one (that layout is ``RosbagDataset``'s). Per stream
``/device_<d>/sensor_<s>/<Stream>_<i>`` (e.g. ``/device_0/sensor_1/Color_0``, ``/device_0/sensor_0/Depth_0``):

- ``<stream>/image/data``         sensor_msgs/Image; depth is Z16 (encoding mono16) in raw units;
- ``<stream>/info/camera_info``   sensor_msgs/CameraInfo: K, D (librealsense's coefficients) and the
                                  distortion model's name (e.g. "Brown Conrady") in ``distortion_model``;
- ``<stream>/tf/<group>``         geometry_msgs/Transform: the extrinsic *from* the group's reference
                                  stream *to* this stream (p_stream = R p_ref + t);
- ``/device_<d>/sensor_<s>/option/Depth_Units/value``  std_msgs/Float32, metres per depth unit.

The depth stream comes from the stereo module, beside the colour camera and with other intrinsics, so
each depth image is registered to the colour camera (``slam.datasets.depth_registration``) with
T_colour_depth = T_colour_ref · T_depth_ref⁻¹. A bag whose depth already shares the colour camera's
pixel grid (same size and intrinsics, identity or no extrinsic) is used as it is. Depth units default to
0.001 m when the option topic is missing (the D400 default). Pairs: every colour frame (the master) with
the nearest depth frame by header stamp within ``max_dt``, one-to-one (``associate``): a depth frame
used twice would give a moving camera's colour frame depth from another instant.

Distortion: coefficients that are all zero (the D400 depth stream and most colour streams) need no
model. Non-zero coefficients of the Brown-Conrady family are read as OpenCV's k1 k2 p1 p2 k3, as the
realsense-ros wrapper publishes them; other models with non-zero coefficients are an error.
"""
from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .base import RGBDFrame
from .depth_registration import DepthRegistration, StreamIntrinsics, is_identity
from .rosbag import (COLOUR_ENCODINGS, BagTopics, PathLike, RosbagDataset, _first_message, _reader_errors,
                     image_array, open_reader, raw_pixels)
from .tum import DatasetError, DatasetWarning

log = logging.getLogger("dynslam")

STREAM_IMAGE = re.compile(r"^(/device_\d+/sensor_\d+/(Color|Depth)_\d+)/image/data$")
DEFAULT_DEPTH_UNITS = 0.001
BROWN_CONRADY = ("brown conrady", "inverse brown conrady", "modified brown conrady")
YUV_ENCODINGS = {"yuv422": cv2.COLOR_YUV2BGR_UYVY, "UYVY": cv2.COLOR_YUV2BGR_UYVY, "YUYV": cv2.COLOR_YUV2BGR_YUYV}
"""librealsense writes UYVY as ROS's "yuv422", YUYV under its own name; 2 bytes per pixel."""
GREY_ENCODINGS = ("8UC1", "mono8")
DEPTH_RAW_ENCODINGS = ("mono16", "16UC1")


@dataclass(frozen=True)
class RealSenseStatic:
    """What a RealSense bag says about its streams before the first frame."""

    colour_prefix: str
    depth_prefix: str
    colour: StreamIntrinsics
    depth: StreamIntrinsics
    T_colour_depth: Optional[np.ndarray]   # None: no extrinsic recorded (only allowed for aligned depth)
    depth_units: float                      # metres per raw depth unit

    @property
    def aligned(self) -> bool:
        """Depth already on the colour grid: same intrinsics and no (or an identity) extrinsic."""
        return self.depth.same_as(self.colour) and (self.T_colour_depth is None or is_identity(self.T_colour_depth))


def is_realsense_bag(path: PathLike) -> bool:
    """A ROS 1 ``.bag`` with an image topic in librealsense's layout (a bag that cannot be read is not
    one: ``RosbagDataset`` then reports why)."""
    path = Path(path)
    if not (path.is_file() and path.suffix == ".bag"):
        return False
    try:
        with open_reader(path) as reader:
            return any(STREAM_IMAGE.match(c.topic) for c in reader.connections)
    except (*_reader_errors(), DatasetError):
        return False


def read_static(reader, path: Path) -> RealSenseStatic:
    """Streams, intrinsics, extrinsic and depth units of an open RealSense bag (module docstring)."""
    streams: dict[str, list[str]] = {"Color": [], "Depth": []}
    for topic in sorted({c.topic for c in reader.connections}):
        m = STREAM_IMAGE.match(topic)
        if m:
            streams[m.group(2)].append(m.group(1))
    found = ", ".join(p for kind in streams.values() for p in kind) or "none"
    for kind in ("Color", "Depth"):
        if not streams[kind]:
            raise DatasetError(f"{path}: no {kind.lower()} stream (a '/device_*/sensor_*/{kind}_*/image/data' "
                               f"topic); streams found: {found}. Record colour and depth together")
    colour_prefix, depth_prefix = streams["Color"][0], streams["Depth"][0]
    colour = _intrinsics(reader, path, colour_prefix)
    depth = _intrinsics(reader, path, depth_prefix)
    T = _colour_from_depth(reader, path, colour_prefix, depth_prefix)
    units = _depth_units(reader, path, depth_prefix.rsplit("/", 1)[0])   # the depth stream's sensor
    static = RealSenseStatic(colour_prefix, depth_prefix, colour, depth, T, units)
    if T is None and not static.aligned:
        raise DatasetError(f"{path}: no extrinsics between {depth_prefix} and {colour_prefix} (topics "
                           f"'<stream>/tf/<group>'), and the depth is not aligned to colour: cannot register it")
    return static


def _messages(reader, topic: str, limit: int = 1) -> list:
    """Up to ``limit`` messages of ``topic`` (deserialised); none when the bag has no such topic (an
    empty connection list would make rosbags read every topic)."""
    connections = [c for c in reader.connections if c.topic == topic]
    out: list = []
    if connections:
        for c, _, raw in reader.messages(connections=connections):
            out.append(reader.deserialize(raw, c.msgtype))
            if len(out) >= limit:
                break
    return out


def _first(reader, topic: str):
    msgs = _messages(reader, topic)
    return msgs[0] if msgs else None


def _intrinsics(reader, path: Path, prefix: str) -> StreamIntrinsics:
    topic = f"{prefix}/info/camera_info"
    msg = _first(reader, topic)
    if msg is None:
        raise DatasetError(f"{path}: no intrinsics for {prefix} (topic '{topic}' missing or empty)")
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64)
    d = [float(x) for x in (msg.d if hasattr(msg, "d") else msg.D)]
    if k.size != 9 or not (k[0] > 0 and k[4] > 0) or int(msg.width) <= 0 or int(msg.height) <= 0:
        raise DatasetError(f"{path}: '{topic}' holds no valid camera (K {k.tolist()}, {msg.width}x{msg.height})")
    if any(d) and (msg.distortion_model or "").strip().lower() not in BROWN_CONRADY:
        raise DatasetError(f"{path}: '{topic}': distortion model '{msg.distortion_model}' with coefficients "
                           f"{d} is not supported (Brown-Conrady family or all-zero coefficients)")
    if any(d[5:]):
        raise DatasetError(f"{path}: '{topic}': {len(d)} distortion coefficients, only k1 k2 p1 p2 k3 are supported")
    return StreamIntrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(msg.width), int(msg.height),
                            tuple((d + [0.0] * 5)[:5]))


def _extrinsics(reader, prefix: str) -> dict[str, np.ndarray]:
    """Group index -> 4x4 T_stream_ref from the ``<prefix>/tf/<group>`` topics."""
    out = {}
    for topic in sorted({c.topic for c in reader.connections if c.topic.startswith(prefix + "/tf/")}):
        msgs = _messages(reader, topic)
        if not msgs:
            continue
        q, t = msgs[0].rotation, msgs[0].translation
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()   # normalises the quaternion too
        T[:3, 3] = [t.x, t.y, t.z]
        out[topic.rsplit("/", 1)[1]] = T
    return out


def _colour_from_depth(reader, path: Path, colour_prefix: str, depth_prefix: str) -> Optional[np.ndarray]:
    """T_colour_depth through a shared reference stream, None when either stream has no extrinsic."""
    colour, depth = _extrinsics(reader, colour_prefix), _extrinsics(reader, depth_prefix)
    if not colour or not depth:
        return None
    shared = sorted(set(colour) & set(depth))
    if not shared:
        raise DatasetError(f"{path}: the extrinsics of {colour_prefix} (groups {sorted(colour)}) and "
                           f"{depth_prefix} (groups {sorted(depth)}) share no reference stream")
    return colour[shared[0]] @ np.linalg.inv(depth[shared[0]])


def _depth_units(reader, path: Path, sensor_prefix: str) -> float:
    topic = f"{sensor_prefix}/option/Depth_Units/value"
    msgs = _messages(reader, topic)
    if not msgs:
        log.info("%s: no depth units recorded ('%s'); assuming %g m per unit", path, topic, DEFAULT_DEPTH_UNITS)
        return DEFAULT_DEPTH_UNITS
    units = float(msgs[0].data)
    if not (np.isfinite(units) and 0 < units < 1):
        raise DatasetError(f"{path}: '{topic}' says {units} m per depth unit (expected e.g. 0.001)")
    return units


def camera_keys(static: RealSenseStatic) -> dict:
    """The run config's camera keys: the colour camera (depth is registered to it)."""
    c = static.colour
    return {"name": "realsense", "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width,
            "height": c.height, "distortion": list(c.distortion),
            "depth_scale": float(f"{1.0 / static.depth_units:.7g}")}   # the float32 units 0.0010000000475: 1000


def read_realsense_camera(path: PathLike) -> dict:
    """The camera keys of a RealSense bag without indexing its frames."""
    path = Path(path)
    try:
        with open_reader(path) as reader:
            return camera_keys(read_static(reader, path))
    except _reader_errors() as exc:
        raise DatasetError(f"{path}: cannot read the bag ({exc.__class__.__name__}: {exc})") from None


class RealSenseBagDataset(RosbagDataset):
    """Colour frames of a RealSense bag with depth registered to them; follows ``RGBDDataset``.

    Streams the bag like ``RosbagDataset`` (whose association and iteration it reuses), decoding only the
    messages of the chosen pairs. ``registration`` is None when the bag's depth is already aligned.
    """

    def __init__(self, path: PathLike, max_dt: float = 0.02) -> None:
        self.root = Path(path)
        self.name = self.root.stem
        self.max_dt = float(max_dt)
        self.skipped: list[tuple[str, str]] = []
        self.missing: list[Path] = []
        try:
            with open_reader(self.root) as reader:
                self.static = read_static(reader, self.root)
                colour_topic = f"{self.static.colour_prefix}/image/data"
                depth_topic = f"{self.static.depth_prefix}/image/data"
                encodings = {t: getattr(_first(reader, t), "encoding", None) for t in (colour_topic, depth_topic)}
                self._check_encodings(encodings, colour_topic, depth_topic)
                self.topics = BagTopics(colour_topic, depth_topic, f"{self.static.colour_prefix}/info/camera_info",
                                        encodings[colour_topic], encodings[depth_topic])
                self._index(reader)
        except _reader_errors() as exc:
            raise DatasetError(f"{self.root}: cannot read the bag ({exc.__class__.__name__}: {exc})") from None
        self._camera = camera_keys(self.static)
        s = self.static
        self.registration = None if s.aligned else DepthRegistration(s.depth, s.colour, s.T_colour_depth)

    def _check_encodings(self, encodings: dict, colour_topic: str, depth_topic: str) -> None:
        colour_ok = (*COLOUR_ENCODINGS, *YUV_ENCODINGS, *GREY_ENCODINGS)
        for topic, supported, role in ((colour_topic, colour_ok, "colour"), (depth_topic, DEPTH_RAW_ENCODINGS, "depth")):
            if encodings[topic] not in supported:
                found = "no message" if encodings[topic] is None else f"unsupported encoding '{encodings[topic]}'"
                raise DatasetError(f"{self.root}: {role} topic '{topic}' has {found} (supported: {', '.join(supported)})")

    def _colour(self, msg) -> np.ndarray:
        if msg.encoding in YUV_ENCODINGS:
            return cv2.cvtColor(raw_pixels(msg, self.topics.rgb, np.uint8, 2), YUV_ENCODINGS[msg.encoding])
        if msg.encoding in GREY_ENCODINGS:
            return np.repeat(raw_pixels(msg, self.topics.rgb, np.uint8, 1), 3, axis=2)
        return image_array(msg, self.topics.rgb)

    def _frame(self, i: int, rgb_msg, depth_msg) -> Optional[RGBDFrame]:
        rgb = self._colour(rgb_msg)
        raw = raw_pixels(depth_msg, self.topics.depth, np.uint16, 1)[..., 0]
        depth = raw.astype(np.float32) * np.float32(self.static.depth_units)
        where = f"{self.topics.depth}@{self._t_rgb[i]:.6f}"
        expected = (self.static.depth.height, self.static.depth.width)
        if depth.shape != expected or rgb.shape[:2] != (self.static.colour.height, self.static.colour.width):
            reason = (f"colour {rgb.shape[1]}x{rgb.shape[0]} / depth {depth.shape[1]}x{depth.shape[0]} differ from "
                      f"their camera_info ({self.static.colour.width}x{self.static.colour.height} / "
                      f"{expected[1]}x{expected[0]})")
            self.skipped.append((where, reason))
            warnings.warn(f"{self.name}: skipping frame {i} ({where}): {reason}", DatasetWarning, stacklevel=3)
            return None
        if self.registration is not None:
            depth = self.registration(depth)
        return RGBDFrame(index=i, timestamp=float(self._t_rgb[i]), rgb=rgb, depth=depth)

    def __repr__(self) -> str:
        return (f"RealSenseBagDataset({str(self.root)!r}, frames={len(self)}, colour={self.topics.rgb!r}, "
                f"depth={self.topics.depth!r}, registered={self.registration is not None})")
