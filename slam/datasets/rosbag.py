"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``) recordings, read without ROS via ``rosbags``.

Colour and depth come from ``sensor_msgs/Image`` topics, picked by encoding unless named: colour is
rgb8/bgr8/rgba8/bgra8/mono8 on a topic without "depth" in its name; depth is 32FC1 (metres) or
16UC1/mono16 (millimetres, REP 118), preferring topics named "depth" and among them ones registered to
the colour camera ("aligned", "registered"). Pairs are formed by nearest header timestamp (≤ 20 ms) like
TUM's lists. Intrinsics come from the ``sensor_msgs/CameraInfo`` topic beside the colour topic.

The bag is streamed twice: once when opening (timestamps only, to associate) and once per iteration,
decoding only the messages of the chosen pairs, so memory stays small whatever the bag's length.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Union

import numpy as np

from .base import DatasetDefaults, RGBDFrame
from .tum import DatasetError, DatasetWarning, associate

PathLike = Union[str, Path]

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
COLOUR_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
"""Colour encoding -> channels (all 8-bit)."""
DEPTH_ENCODINGS = {"32FC1": (np.float32, 1.0), "16UC1": (np.uint16, 1000.0), "mono16": (np.uint16, 1000.0)}
"""Depth encoding -> (pixel type, units per metre): REP 118 puts float depth in metres, integer in mm."""
REGISTERED_WORDS = ("aligned", "registered")


def is_rosbag(path: PathLike) -> bool:
    """A ROS 1 ``.bag`` file, or a ROS 2 bag folder (``metadata.yaml`` beside .db3 or .mcap files)."""
    path = Path(path)
    if path.is_file():
        return path.suffix == ".bag"
    return path.is_dir() and (path / "metadata.yaml").is_file() and \
        any(p.suffix in (".db3", ".mcap") for p in path.iterdir())


@dataclass(frozen=True)
class BagTopics:
    """The topics a RosbagDataset reads and their encodings."""

    rgb: str
    depth: str
    camera_info: Optional[str]
    rgb_encoding: str
    depth_encoding: str


def open_reader(path: PathLike):
    """An unopened ``rosbags.highlevel.AnyReader`` for ``path``; the ROS 2 Humble types serve bags that
    carry no message definitions of their own."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"bag {path} does not exist")
    if not is_rosbag(path):
        raise DatasetError(f"{path} is not a ROS bag (expected a .bag file, or a folder with metadata.yaml "
                           "and .db3/.mcap files)")
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _reader_errors() -> tuple[type[BaseException], ...]:
    """What rosbags raises for a bag it cannot parse (turned into DatasetError naming the bag)."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Ros1ReaderError
    from rosbags.rosbag2 import ReaderError as Ros2ReaderError

    return (AnyReaderError, Ros1ReaderError, Ros2ReaderError)


def select_topics(reader, path: Path, rgb_topic: Optional[str] = None, depth_topic: Optional[str] = None,
                  camera_info_topic: Optional[str] = None) -> BagTopics:
    """Named topics are checked, missing ones picked by message type and encoding (module docstring)."""
    image_topics = sorted({c.topic for c in reader.connections if c.msgtype == IMAGE_TYPE})
    firsts = {t: _first_message(reader, t) for t in image_topics}
    encodings = {topic: msg.encoding for topic, msg in firsts.items() if msg is not None}  # skip empty topics
    listing = ", ".join(f"{t} ({e})" for t, e in encodings.items()) or "none"
    rgb = _pick(path, rgb_topic, encodings, COLOUR_ENCODINGS, "colour", listing,
                lambda t: ("depth" in t.lower(), not any(w in t.lower() for w in ("color", "colour", "rgb")), t))
    depth = _pick(path, depth_topic, encodings, DEPTH_ENCODINGS, "depth", listing,
                  lambda t: ("depth" not in t.lower(), not any(w in t.lower() for w in REGISTERED_WORDS), t))
    infos = sorted({c.topic for c in reader.connections if c.msgtype == CAMERA_INFO_TYPE})
    if camera_info_topic is not None and camera_info_topic not in infos:
        raise DatasetError(f"{path}: no CameraInfo topic '{camera_info_topic}' (CameraInfo topics: "
                           f"{', '.join(infos) or 'none'})")
    info = camera_info_topic or (max(infos, key=lambda t: (_shared_prefix(t, rgb), t)) if infos else None)
    return BagTopics(rgb, depth, info, encodings[rgb], encodings[depth])


def _pick(path: Path, named: Optional[str], encodings: dict[str, str], supported: dict, role: str,
          listing: str, preference) -> str:
    """The named topic (checked) or the preferred topic with a supported encoding for ``role``."""
    if named is not None:
        if named not in encodings:
            raise DatasetError(f"{path}: no Image topic '{named}' (Image topics: {listing})")
        if encodings[named] not in supported:
            raise DatasetError(f"{path}: {role} topic '{named}' has unsupported encoding '{encodings[named]}' "
                               f"(supported: {', '.join(supported)})")
        return named
    candidates = [t for t, e in encodings.items() if e in supported]
    if role == "colour":
        candidates = [t for t in candidates if "depth" not in t.lower()] or candidates
    if not candidates:
        near = [f"'{t}' has unsupported encoding '{e}'" for t, e in encodings.items()
                if (role == "depth") == ("depth" in t.lower())]
        raise DatasetError(f"{path}: no {role} image topic ({', '.join(supported)}); "
                           + ("; ".join(near) if near else f"Image topics: {listing}"))
    return min(candidates, key=preference)


def _shared_prefix(a: str, b: str) -> int:
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def _first_message(reader, topic: str):
    """The first message on ``topic`` (deserialised), or None when the topic has none."""
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, _, raw in reader.messages(connections=connections):
        return reader.deserialize(raw, connection.msgtype)
    return None


def _stamp(msg, bag_time_ns: int) -> float:
    """Header time in seconds (sensor time, as TUM's lists use), or the recording time when unset."""
    stamp = msg.header.stamp
    seconds = stamp.sec + stamp.nanosec * 1e-9
    return seconds if seconds > 0 else bag_time_ns * 1e-9


def _read_camera(reader, topics: BagTopics) -> Optional[dict]:
    """The camera of the first message on the chosen CameraInfo topic; None without one."""
    msg = None if topics.camera_info is None else _first_message(reader, topics.camera_info)
    return None if msg is None else camera_from_info(msg, topics.camera_info, topics.depth_encoding)


def camera_from_info(msg, topic: str, depth_encoding: str) -> dict:
    """Camera keys (fx fy cx cy width height distortion depth_scale) of a CameraInfo message; works with
    ROS 2 (k, d) and ROS 1 (K, D) field names."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64)
    d = [float(x) for x in (msg.d if hasattr(msg, "d") else msg.D)]
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        raise DatasetError(f"CameraInfo topic '{topic}': no valid camera matrix K (got {k.tolist()})")
    model = (msg.distortion_model or "plumb_bob").lower()
    if model not in ("plumb_bob", "rational_polynomial") and any(d):
        raise DatasetError(f"CameraInfo topic '{topic}': distortion model '{msg.distortion_model}' is not "
                           "supported (plumb_bob or rational_polynomial with k4..k6 = 0)")
    if any(d[5:]):
        raise DatasetError(f"CameraInfo topic '{topic}': {len(d)} distortion coefficients with non-zero "
                           f"k4..k6 ({d[5:]}); only k1 k2 p1 p2 k3 are supported")
    distortion = (d[:5] + [0.0] * 5)[:5]
    return {"fx": float(k[0]), "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5]),
            "width": int(msg.width), "height": int(msg.height), "distortion": distortion,
            "depth_scale": DEPTH_ENCODINGS[depth_encoding][1]}


def raw_pixels(msg, topic: str, dtype, channels: int) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as an HxWxC array of ``dtype`` in native byte order, honouring the
    row ``step`` (padding) and ``is_bigendian``; a message too short for its size is a DatasetError."""
    dtype = np.dtype(dtype)
    encoding, height, width, step = msg.encoding, int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if step < row_bytes or data.size < step * height:
        raise DatasetError(f"topic '{topic}': {encoding} image {width}x{height} has {data.size} bytes "
                           f"with step {step}, expected at least {row_bytes} per row")
    rows = np.ascontiguousarray(data[: step * height].reshape(height, step)[:, :row_bytes])
    return rows.view(dtype.newbyteorder(">" if msg.is_bigendian else "<")).reshape(height, width, channels)


def image_array(msg, topic: str) -> np.ndarray:
    """A sensor_msgs/Image as an array: HxWx3 uint8 BGR for colour, HxW float32 metres for depth."""
    encoding = msg.encoding
    if encoding in COLOUR_ENCODINGS:
        dtype, channels = np.dtype(np.uint8), COLOUR_ENCODINGS[encoding]
    elif encoding in DEPTH_ENCODINGS:
        dtype, channels = np.dtype(DEPTH_ENCODINGS[encoding][0]), 1
    else:
        raise DatasetError(f"topic '{topic}': unsupported image encoding '{encoding}' (colour: "
                           f"{', '.join(COLOUR_ENCODINGS)}; depth: {', '.join(DEPTH_ENCODINGS)})")
    pixels = raw_pixels(msg, topic, dtype, channels)
    if encoding in DEPTH_ENCODINGS:
        metres = pixels[..., 0].astype(np.float32) / np.float32(DEPTH_ENCODINGS[encoding][1])
        metres[~np.isfinite(metres) | (metres < 0)] = 0.0  # NaN/inf/negative mark missing depth in ROS
        return metres
    if encoding == "mono8":
        return np.repeat(pixels, 3, axis=2)
    bgr = pixels[..., :3] if encoding.startswith("bgr") else pixels[..., 2::-1]
    return np.ascontiguousarray(bgr)


class RosbagDataset(DatasetDefaults):
    """RGB-D frames of a ROS 1 or ROS 2 bag (see the module docstring); follows ``RGBDDataset``.

    ``frame.index`` is the pair's position in ``timestamps``; frames whose colour and depth sizes
    differ are skipped with a warning and recorded in ``skipped``.
    """

    def __init__(self, path: PathLike, rgb_topic: Optional[str] = None, depth_topic: Optional[str] = None,
                 camera_info_topic: Optional[str] = None, max_dt: float = 0.02) -> None:
        self.root = Path(path)
        self.name = self.root.stem if self.root.is_file() else self.root.resolve().name
        self.max_dt = float(max_dt)
        self.skipped: list[tuple[str, str]] = []
        self.missing: list[Path] = []
        self._camera: Optional[dict] = None
        try:
            with open_reader(self.root) as reader:
                self.topics = select_topics(reader, self.root, rgb_topic, depth_topic, camera_info_topic)
                self._index(reader)
                self._camera = _read_camera(reader, self.topics)
        except _reader_errors() as exc:
            raise DatasetError(f"{self.root}: cannot read the bag ({exc.__class__.__name__}: {exc})") from None

    def _index(self, reader) -> None:
        """Header stamps of every colour and depth message, then the one-to-one association."""
        stamps: dict[str, list[float]] = {self.topics.rgb: [], self.topics.depth: []}
        for connection, bag_time, raw in reader.messages(connections=self._connections(reader)):
            stamps[connection.topic].append(_stamp(reader.deserialize(raw, connection.msgtype), bag_time))
        t_rgb, t_depth = np.array(stamps[self.topics.rgb]), np.array(stamps[self.topics.depth])
        ia, ib = associate(t_rgb, t_depth, self.max_dt)
        if len(ia) == 0:
            raise DatasetError(f"{self.root}: no colour/depth pair within {self.max_dt * 1000:g} ms "
                               f"({len(t_rgb)} messages on {self.topics.rgb}, {len(t_depth)} on "
                               f"{self.topics.depth})")
        self.unmatched_rgb = len(t_rgb) - len(ia)
        self._rgb_ordinal, self._depth_ordinal = ia, ib
        self._t_rgb = t_rgb[ia]
        self._t_rgb.flags.writeable = False

    def _connections(self, reader) -> list:
        return [c for c in reader.connections if c.topic in (self.topics.rgb, self.topics.depth)]

    @property
    def timestamps(self) -> np.ndarray:
        """Colour timestamps of the frames (read-only), in seconds."""
        return self._t_rgb

    def intrinsics(self) -> Optional[dict]:
        """fx fy cx cy width height distortion depth_scale from the CameraInfo topic, or None without one."""
        return None if self._camera is None else dict(self._camera)

    def __len__(self) -> int:
        return len(self._t_rgb)

    def __iter__(self) -> Iterator[RGBDFrame]:
        """Stream the bag once, decoding only the chosen messages; yield pairs in timestamp order."""
        rgb_pair = {int(k): i for i, k in enumerate(self._rgb_ordinal)}
        depth_pair = {int(k): i for i, k in enumerate(self._depth_ordinal)}
        halves: dict[int, list] = {}
        ready: dict[int, list] = {}
        seen = {self.topics.rgb: 0, self.topics.depth: 0}
        next_pair = 0
        with open_reader(self.root) as reader:
            for connection, _, raw in reader.messages(connections=self._connections(reader)):
                is_rgb = connection.topic == self.topics.rgb
                ordinal = seen[connection.topic]
                seen[connection.topic] += 1
                pair = (rgb_pair if is_rgb else depth_pair).get(ordinal)
                if pair is None:
                    continue
                slot = halves.setdefault(pair, [None, None])
                slot[0 if is_rgb else 1] = reader.deserialize(raw, connection.msgtype)
                if slot[0] is not None and slot[1] is not None:
                    ready[pair] = halves.pop(pair)
                while next_pair in ready:
                    frame = self._frame(next_pair, *ready.pop(next_pair))
                    next_pair += 1
                    if frame is not None:
                        yield frame

    def _frame(self, i: int, rgb_msg, depth_msg) -> Optional[RGBDFrame]:
        rgb = image_array(rgb_msg, self.topics.rgb)
        depth = image_array(depth_msg, self.topics.depth)
        if depth.shape != rgb.shape[:2]:
            where = f"{self.topics.depth}@{self._t_rgb[i]:.6f}"
            reason = f"depth size {depth.shape} differs from colour size {rgb.shape[:2]}"
            self.skipped.append((where, reason))
            warnings.warn(f"{self.name}: skipping frame {i} ({where}): {reason}", DatasetWarning, stacklevel=3)
            return None
        return RGBDFrame(index=i, timestamp=float(self._t_rgb[i]), rgb=rgb, depth=depth)

    def groundtruth(self) -> None:
        """Bags carry no ground truth this reader knows of (evaluate against a separate file)."""
        return None

    def __repr__(self) -> str:
        return f"RosbagDataset({str(self.root)!r}, frames={len(self)}, rgb={self.topics.rgb!r}, " \
               f"depth={self.topics.depth!r})"


def read_bag_camera(path: PathLike) -> Optional[dict]:
    """The camera of a bag's auto-picked CameraInfo topic without indexing the whole bag (None without one)."""
    path = Path(path)
    try:
        with open_reader(path) as reader:
            return _read_camera(reader, select_topics(reader, path))
    except _reader_errors() as exc:
        raise DatasetError(f"{path}: cannot read the bag ({exc.__class__.__name__}: {exc})") from None
