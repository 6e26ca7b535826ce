"""The RealSense Viewer's recordings: ROS 1 .bag files in librealsense's own topic layout.

The Viewer (and librealsense's recorder) writes each stream under
``/device_<d>/sensor_<s>/<Stream>_<i>/``: ``image/data`` (sensor_msgs/Image; depth mono16 in
the sensor's depth units, colour rgb8), ``info/camera_info`` (sensor_msgs/CameraInfo) and
``tf/<ref>`` (geometry_msgs/Transform, once: the stream's extrinsics from the reference
stream of group <ref>, i.e. p_stream = R p_ref + t; on D4xx cameras the reference is the
depth stream). The depth units are the depth sensor's option,
``/device_<d>/sensor_<s>/option/Depth_Units/value`` (std_msgs/Float32, metres per unit).
Depth is not aligned to colour: ``RGBDBag`` registers it with the two streams' intrinsics and
``colour_from_depth`` = T_colour_from_ref @ inverse(T_depth_from_ref).

    layout = viewer_layout(reader, path)     # None for a bag of another layout
    with ViewerBagWriter("out/scene.bag") as bag: ...   # the same layout, for synthetic scenes

The ground truth of a synthetic scene goes on the same topics as in the rosbag2 bags
(``/ground_truth/poses`` ...), which a real Viewer recording does not have.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics, array_to_image_fields
from ..transforms import pose_to_matrix

# The Viewer's ROS 1 layout (librealsense's ros file format, version 3 and later).
DEVICE = "/device_0"
DEPTH_SENSOR, COLOUR_SENSOR = "sensor_0", "sensor_1"      # a D4xx: stereo module, RGB camera
_STREAM_TOPIC = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/image/data$")
DEPTH_UNITS_OPTION = "option/Depth_Units/value"
DEFAULT_DEPTH_UNITS_M = 0.001


def stream_prefix(stream: str, sensor: str = "", device: str = DEVICE) -> str:
    """'/device_0/sensor_0/Depth_0' for stream 'Depth' (sensor: the D4xx's when not given)."""
    sensor = sensor or (DEPTH_SENSOR if stream == "Depth" else COLOUR_SENSOR)
    return f"{device}/{sensor}/{stream}_0"


@dataclass
class ViewerLayout:
    """Where a Viewer bag keeps what ``RGBDBag`` reads."""
    colour_topic: str
    depth_topic: str
    info_topic: str
    depth_info_topic: str
    colour_from_depth: np.ndarray        # (4, 4) depth optical frame -> colour optical frame
    depth_scale: float                   # metres per depth unit


def is_viewer_bag(topics) -> bool:
    """Does a bag with these topic names hold a librealsense recording?"""
    return any(_STREAM_TOPIC.match(t) for t in topics)


def _first_message(reader, topic: str):
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, _, raw in reader.messages(connections=conns):
        return reader.deserialize(raw, conn.msgtype)
    return None


def _transform_matrix(msg) -> np.ndarray:
    t, q = msg.translation, msg.rotation
    return pose_to_matrix((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


def _stream(topics, kind: str) -> tuple[str, str] | None:
    """(device prefix, stream prefix) of the first ``kind`` ("Depth" or "Color") stream."""
    found = sorted((int(m.group(1)), int(m.group(2)), int(m.group(4)), t) for t in topics
                   if (m := _STREAM_TOPIC.match(t)) and m.group(3) == kind)
    if not found:
        return None
    topic = found[0][3]
    prefix = topic[:-len("/image/data")]
    return prefix.split("/sensor_")[0], prefix


def viewer_layout(reader, path) -> ViewerLayout | None:
    """The layout of an opened bag recorded by the RealSense Viewer, None if it is not one.
    InputError naming what to record when a part the frames need is missing."""
    topics = reader.topics
    if not is_viewer_bag(topics):
        return None
    depth, colour = _stream(topics, "Depth"), _stream(topics, "Color")
    if colour is None or depth is None:
        missing = "colour (Color_0)" if colour is None else "depth (Depth_0)"
        raise InputError(f"RealSense Viewer bag {path} has no {missing} stream; record it with both the depth "
                         f"and the RGB camera switched on")
    (_, depth_prefix), (_, colour_prefix) = depth, colour
    need = {f"{colour_prefix}/info/camera_info": "the colour stream's camera_info",
            f"{depth_prefix}/info/camera_info": "the depth stream's camera_info"}
    missing = [f"{t} ({what})" for t, what in need.items() if t not in topics]
    if missing:
        raise InputError(f"RealSense Viewer bag {path} has no {', '.join(missing)}; the Viewer writes it with "
                         f"every stream: is the file complete?")
    colour_tf = sorted(t for t in topics if t.startswith(f"{colour_prefix}/tf/"))
    if not colour_tf:
        raise InputError(f"RealSense Viewer bag {path} has no extrinsics of the colour stream ({colour_prefix}/tf/0): "
                         f"without them depth cannot be registered to colour; record with a newer Viewer "
                         f"(librealsense 2.10 or later)")
    ref = colour_tf[0].rsplit("/", 1)[1]
    try:
        T_colour_ref = _transform_matrix(_first_message(reader, colour_tf[0]))
        depth_tf = _first_message(reader, f"{depth_prefix}/tf/{ref}") if f"{depth_prefix}/tf/{ref}" in topics else None
        # No depth extrinsics: the depth stream is the reference (as on every D4xx).
        T_depth_ref = np.eye(4) if depth_tf is None else _transform_matrix(depth_tf)
        units_topic = f"{depth_prefix.rsplit('/', 1)[0]}/{DEPTH_UNITS_OPTION}"
        units = _first_message(reader, units_topic) if units_topic in topics else None
    except (AttributeError, TypeError, ValueError) as exc:
        raise InputError(f"RealSense Viewer bag {path}: its extrinsics or depth units cannot be read "
                         f"({type(exc).__name__}: {exc})") from None
    scale = float(units.data) if units is not None else DEFAULT_DEPTH_UNITS_M
    if not (np.isfinite(scale) and 0 < scale < 1):
        raise InputError(f"RealSense Viewer bag {path}: depth units of {scale} m are not plausible")
    return ViewerLayout(colour_topic=f"{colour_prefix}/image/data", depth_topic=f"{depth_prefix}/image/data",
                        info_topic=f"{colour_prefix}/info/camera_info",
                        depth_info_topic=f"{depth_prefix}/info/camera_info",
                        colour_from_depth=T_colour_ref @ np.linalg.inv(T_depth_ref), depth_scale=scale)


class ViewerBagWriter:
    """Writes RGB-D frames as the RealSense Viewer records a D4xx: a ROS 1 .bag with depth
    (mono16, 1 mm units) and colour (rgb8) under /device_0/sensor_0/Depth_0 and
    /device_0/sensor_1/Color_0, their camera_infos, each stream's extrinsics once on tf/0 (the
    depth stream is the reference), the depth units option, and, for synthetic scenes, the
    ground truth on the rosbag2 bags' topics. The path must not exist."""

    def __init__(self, path, colour_from_depth: np.ndarray):
        from rosbags.rosbag1 import Writer

        from .typestores import ros1_typestore

        self.path = Path(path)
        if self.path.exists():
            raise InputError(f"output '{self.path}' already exists; remove it or choose another path")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.typestore = ros1_typestore()
        self._types = self.typestore.types
        self.colour_from_depth = np.asarray(colour_from_depth, dtype=np.float64)
        self._writer = Writer(self.path)
        self._writer.open()
        self._connections: dict = {}
        self._seq = 0
        self.frames_written = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _write(self, topic: str, msg, time_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._connections[topic] = self._writer.add_connection(topic, msg.__msgtype__,
                                                                          typestore=self.typestore)
        self._writer.write(conn, int(time_ns), self.typestore.serialize_ros1(msg, msg.__msgtype__))

    def _header(self, stamp_ns: int, frame_id: str):
        T = self._types
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return T["std_msgs/msg/Header"](seq=self._seq, stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                        frame_id=frame_id)

    def _transform(self, M: np.ndarray):
        from ..transforms import matrix_to_pose

        T = self._types
        xyz, q = matrix_to_pose(M)
        return T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))

    def _static(self, time_ns: int) -> None:
        """What the Viewer writes once, before the frames: extrinsics and depth units."""
        depth, colour = stream_prefix("Depth"), stream_prefix("Color")
        self._write(f"{depth}/tf/0", self._transform(np.eye(4)), time_ns)
        self._write(f"{colour}/tf/0", self._transform(self.colour_from_depth), time_ns)
        self._write(f"{DEVICE}/{DEPTH_SENSOR}/{DEPTH_UNITS_OPTION}",
                    self._types["std_msgs/msg/Float32"](data=DEFAULT_DEPTH_UNITS_M), time_ns)

    def write_object_description(self, stamp_ns: int, description: dict) -> None:
        """The scene's description as JSON on /ground_truth/object, as in the rosbag2 bags."""
        import json

        from .bag_writer import TOPIC_GT_OBJECT

        self._write(TOPIC_GT_OBJECT, self._types["std_msgs/msg/String"](data=json.dumps(description, sort_keys=True)),
                    stamp_ns)

    def write_frame(self, stamp_ns: int, rgb: np.ndarray, depth_mm: np.ndarray, intrinsics: CameraIntrinsics,
                    depth_intrinsics: CameraIntrinsics, poses: np.ndarray | None = None,
                    visibility: np.ndarray | None = None, depth_stamp_ns: int | None = None) -> None:
        """One frame: colour at ``stamp_ns``, the depth imager's own depth (uint16 mm, the size of
        ``depth_intrinsics``) at ``depth_stamp_ns`` (default the same; the Viewer's streams
        tick apart), ground truth (object -> colour optical frame) at the colour's stamp."""
        from .bag_writer import camera_info_message, ground_truth_messages

        T = self._types
        rgb, depth_mm = np.asarray(rgb), np.asarray(depth_mm)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"colour must be HxWx3 uint8, got {rgb.shape} {rgb.dtype}")
        if depth_mm.shape != (depth_intrinsics.height, depth_intrinsics.width) or depth_mm.dtype != np.uint16:
            raise InputError(f"depth must be uint16 millimetres of its camera_info's size "
                             f"{depth_intrinsics.width}x{depth_intrinsics.height}, got {depth_mm.shape} {depth_mm.dtype}")
        depth_stamp_ns = stamp_ns if depth_stamp_ns is None else int(depth_stamp_ns)
        if self.frames_written == 0:
            self._static(min(stamp_ns, depth_stamp_ns))
        depth, colour = stream_prefix("Depth"), stream_prefix("Color")
        Image = T["sensor_msgs/msg/Image"]
        dh, ch = self._header(depth_stamp_ns, "0"), self._header(stamp_ns, "0")
        for time_ns, prefix, header, image, info in sorted(
                [(depth_stamp_ns, depth, dh, Image(header=dh, **array_to_image_fields(depth_mm, "mono16")),
                  depth_intrinsics),
                 (stamp_ns, colour, ch, Image(header=ch, **array_to_image_fields(rgb, "rgb8")), intrinsics)],
                key=lambda item: item[0]):
            self._write(f"{prefix}/info/camera_info", camera_info_message(T, header, info), time_ns)
            self._write(f"{prefix}/image/data", image, time_ns)
        for topic, msg in ground_truth_messages(T, self._header(stamp_ns, "camera_color_optical_frame"), poses, visibility):
            self._write(topic, msg, stamp_ns)
        self._seq += 1
        self.frames_written += 1
