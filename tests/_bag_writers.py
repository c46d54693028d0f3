"""ROS 1, ROS 2 and RealSense Viewer bags of a SyntheticSequence, written with rosbags (the readers'
counterpart: slam.datasets.rosbag, slam.datasets.realsense_bag). The factories are shared through
``tests/conftest.py``; this module holds the formats' encoding, which is most of their lines."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from slam.datasets import SyntheticSequence


# ------------------------------------------------------------------------- ROS bags written here
# A SyntheticSequence as a ROS 1 or ROS 2 bag in the RealSense topic layout (test_rosbag.py, faults).
RGB_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/color/camera_info"
DEPTH_DELAY_S = 0.005  # depth stamped 5 ms after colour: association must pair them anyway
START_S = 1_700_000_000.0


def _image(types, header, pixels: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False):
    """A sensor_msgs/Image of ``pixels`` (HxW or HxWxC) with ``pad`` spare bytes at the end of each row."""
    height, width = pixels.shape[:2]
    if bigendian:
        pixels = pixels.astype(pixels.dtype.newbyteorder(">"))
    rows = pixels.reshape(height, -1).view(np.uint8)
    rows = np.concatenate([rows, np.zeros((height, pad), np.uint8)], axis=1)
    return types["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding=encoding,
                                          is_bigendian=int(bigendian), step=rows.shape[1], data=rows.ravel())


def _camera_info(types, header, seq: SyntheticSequence, ros1: bool, distortion):
    fx, fy, cx, cy = seq.intrinsics
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    matrices = {"D": np.asarray(distortion, np.float64),
                "K": np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64),
                "R": np.eye(3).ravel(), "P": np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], np.float64)}
    fields = {(k if ros1 else k.lower()): v for k, v in matrices.items()}
    return types["sensor_msgs/msg/CameraInfo"](header=header, height=seq.height, width=seq.width,
                                               distortion_model="plumb_bob", binning_x=0, binning_y=0,
                                               roi=roi, **fields)


def write_bag(path: Path, seq: SyntheticSequence, ros_version: int = 1, depth_encoding: str = "16UC1",
              rgb_encoding: str = "rgb8", pad: int = 0, distortion=(0.01, -0.02, 0.0, 0.0, 0.0),
              extra_rgb: bool = True, depth_topic: str = DEPTH_TOPIC, bigendian: bool = False,
              camera_info: bool = True) -> Path:
    """``seq`` as a bag: colour, depth (5 ms later) and camera info, plus an unmatched colour message."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = ros_version == 1
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    if ros1:
        from rosbags.rosbag1 import Writer
        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer
        writer, serialize = Writer(path, version=9), store.serialize_cdr

    def header(t: float):
        stamp = types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        extra = {"seq": 0} if ros1 else {}
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera", **extra)

    with writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype in
                 ((RGB_TOPIC, "sensor_msgs/msg/Image"), (depth_topic, "sensor_msgs/msg/Image"),
                  (INFO_TOPIC, "sensor_msgs/msg/CameraInfo"))}

        def put(topic, msg, t):
            writer.write(conns[topic], int(round(t * 1e9)), serialize(msg, msg.__msgtype__))

        if camera_info:
            put(INFO_TOPIC, _camera_info(types, header(START_S), seq, ros1, distortion), START_S)
        for frame in seq:
            t = START_S + frame.timestamp
            colour = frame.rgb[..., ::-1] if rgb_encoding == "rgb8" else frame.rgb
            put(RGB_TOPIC, _image(types, header(t), np.ascontiguousarray(colour), rgb_encoding, pad), t)
            depth = (np.round(frame.depth * 1000).astype(np.uint16) if depth_encoding in ("16UC1", "mono16")
                     else frame.depth.astype(np.float32) if depth_encoding == "32FC1"
                     else frame.depth.astype(np.float64))
            td = t + DEPTH_DELAY_S
            put(depth_topic, _image(types, header(td), depth, depth_encoding, pad, bigendian), td)
        if extra_rgb:  # a colour frame whose depth never came: left out by the association
            t = START_S + len(seq) / seq.fps + 1.0
            put(RGB_TOPIC, _image(types, header(t), np.ascontiguousarray(frame.rgb), rgb_encoding), t)
    return path


# ------------------------------------------------------ RealSense (librealsense) bags written here
# The layout the RealSense Viewer records (slam.datasets.realsense_bag): depth from its own camera beside
# the colour one, extrinsics relative to the depth stream (the group's reference), depth units as an option.
RS_COLOUR = "/device_0/sensor_1/Color_0"
RS_DEPTH = "/device_0/sensor_0/Depth_0"
RS_UNITS_TOPIC = "/device_0/sensor_0/option/Depth_Units/value"
RS_DEPTH_DELAY_S = 0.002   # depth stamped 2 ms after colour, as a hardware-synchronised pair is


def rs_extrinsic(baseline_m: float = 0.015, yaw_deg: float = 0.5) -> np.ndarray:
    """T_colour_depth of a D400-like rig: the colour camera ``baseline_m`` to the right, slightly turned."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = [baseline_m, 0.0, 0.0]
    return T


def render_depth_camera(seq: SyntheticSequence, index: int, depth_camera: tuple, T_colour_depth: np.ndarray,
                        cache: dict) -> np.ndarray:
    """The exact depth image that a camera of intrinsics ``depth_camera`` (fx, fy, cx, cy, w, h), rigidly
    mounted at ``T_colour_depth`` from ``seq``'s camera, sees at frame ``index`` (same room, same path)."""
    fx, fy, cx, cy, w, h = depth_camera
    key = (depth_camera, seq.seed)
    if key not in cache:
        cache[key] = SyntheticSequence(n_frames=seq.n_frames, width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy,
                                       seed=seq.seed, fps=seq.fps)
    t = float(seq.timestamps[index])
    return cache[key].raycast(seq.pose(t) @ T_colour_depth, t)[0]


def _rs_camera_info(types, header, camera: tuple, model: str, coeffs=(0.0,) * 5):
    fx, fy, cx, cy, w, h = camera
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types["sensor_msgs/msg/CameraInfo"](
        header=header, height=h, width=w, distortion_model=model, D=np.asarray(coeffs, np.float64),
        K=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64), R=np.zeros(9), P=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi)


def _rs_header(types, t: float, seq_no: int = 0):
    stamp = types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
    return types["std_msgs/msg/Header"](seq=seq_no, stamp=stamp, frame_id="0")


def _rs_transform(types, T_ref: np.ndarray):
    q = Rotation.from_matrix(T_ref[:3, :3]).as_quat()
    return types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](x=T_ref[0, 3], y=T_ref[1, 3], z=T_ref[2, 3]),
        rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))


def _rs_topics(depth_stream: bool, depth_info: bool, extrinsics: bool, units_topic: bool) -> list[tuple[str, str]]:
    """(topic, message type) of a librealsense bag, less the parts a test leaves out."""
    topics = [("/file_version", "std_msgs/msg/UInt32"), (f"{RS_COLOUR}/image/data", "sensor_msgs/msg/Image"),
              (f"{RS_COLOUR}/info/camera_info", "sensor_msgs/msg/CameraInfo")]
    if depth_stream:
        topics.append((f"{RS_DEPTH}/image/data", "sensor_msgs/msg/Image"))
    if depth_info and depth_stream:
        topics.append((f"{RS_DEPTH}/info/camera_info", "sensor_msgs/msg/CameraInfo"))
    if extrinsics:
        topics += [(f"{RS_COLOUR}/tf/0", "geometry_msgs/msg/Transform"),
                   (f"{RS_DEPTH}/tf/0", "geometry_msgs/msg/Transform")]
    if units_topic:
        topics.append((RS_UNITS_TOPIC, "std_msgs/msg/Float32"))
    return topics


def write_realsense_bag(path: Path, seq: SyntheticSequence, depth_camera: Optional[tuple] = None,
                        T_colour_depth: Optional[np.ndarray] = None, depth_units: Optional[float] = 0.001,
                        extrinsics: bool = True, depth_info: bool = True, depth_stream: bool = True,
                        colour_coeffs=(0.0,) * 5, colour_model: str = "Inverse Brown Conrady") -> Path:
    """``seq`` as a librealsense bag: colour from ``seq``, depth (Z16 in ``depth_units``, None: no units
    topic, written as 0.001) rendered from ``depth_camera`` (default: a wider view, 6/7 of the colour focal length, other
    principal point, 15 mm baseline); ``extrinsics``/``depth_info``/``depth_stream`` False leave those out."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    fx, fy, cx, cy = seq.intrinsics
    colour_camera = (fx, fy, cx, cy, seq.width, seq.height)
    depth_camera = depth_camera or (fx * 6 / 7, fy * 6 / 7, cx + 2.0, cy - 1.5, seq.width, seq.height)
    T = rs_extrinsic() if T_colour_depth is None else T_colour_depth
    units = 0.001 if depth_units is None else depth_units
    cache: dict = {}
    with Writer(path) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store)
                 for topic, msgtype in _rs_topics(depth_stream, depth_info, extrinsics, depth_units is not None)}

        def put(topic, msg, t):
            if topic in conns:     # a topic left out is not written
                writer.write(conns[topic], int(round(t * 1e9)), store.serialize_ros1(msg, msg.__msgtype__))

        put("/file_version", types["std_msgs/msg/UInt32"](data=3), 0.0)
        put(f"{RS_COLOUR}/info/camera_info", _rs_camera_info(types, _rs_header(types, 0.0), colour_camera,
                                                             colour_model, colour_coeffs), 0.0)
        put(f"{RS_DEPTH}/info/camera_info", _rs_camera_info(types, _rs_header(types, 0.0), depth_camera,
                                                            "Brown Conrady"), 0.0)
        put(f"{RS_COLOUR}/tf/0", _rs_transform(types, T), 0.0)          # reference: the depth stream
        put(f"{RS_DEPTH}/tf/0", _rs_transform(types, np.eye(4)), 0.0)
        put(RS_UNITS_TOPIC, types["std_msgs/msg/Float32"](data=units), 0.0)
        for frame in seq:
            t = START_S + frame.timestamp
            rgb = np.ascontiguousarray(frame.rgb[..., ::-1])
            put(f"{RS_COLOUR}/image/data", _image(types, _rs_header(types, t, frame.index), rgb, "rgb8"), t)
            if depth_stream:
                depth = render_depth_camera(seq, frame.index, depth_camera, T, cache)
                raw = np.clip(np.round(depth / (units or 0.001)), 0, 65535).astype(np.uint16)   # 0: a bad units topic
                td = t + RS_DEPTH_DELAY_S
                put(f"{RS_DEPTH}/image/data", _image(types, _rs_header(types, td, frame.index), raw, "mono16"), td)
    return path
