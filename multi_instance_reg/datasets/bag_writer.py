"""Write RGB-D frames (and optional ground truth) as a real rosbag2, the way realsense-ros
publishes them: topics, message types, encodings, frame ids, identical stamps per frame.

    with RealSenseBagWriter("out/scene", storage="sqlite3") as bag:
        bag.write_object_description(stamp_ns, {"name": ..., "shape": ..., ...})
        bag.write_accel_samples(stamp_ns, offsets_ns, accel)     # the IMU's samples before the frame
        bag.write_frame(stamp_ns, rgb, depth_mm, intrinsics, poses=T_cam_obj, visibility=v)
        # or depth as the depth imager sees it (realsense-ros without align_depth.enable):
        bag.write_frame(stamp_ns, rgb, depth_mm_d, intrinsics, poses=T_cam_obj,
                        depth_intrinsics=depth_intr, colour_from_depth=T_colour_depth)

Uses ``rosbags`` (pure Python, no ROS install): rosbag2 format version 9, sqlite3 or mcap.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..gravity import ACCEL_FRAME_ID, ACCEL_TOPIC, IMU_TOPIC
from ..messages import CameraIntrinsics, array_to_image_fields, compressed_colour_fields, compressed_depth_fields
from ..transforms import matrix_to_pose
from .typestores import EXTRINSICS_TYPE

TOPIC_COLOUR = "/camera/camera/color/image_raw"
TOPIC_COLOUR_INFO = "/camera/camera/color/camera_info"
TOPIC_DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"
TOPIC_DEPTH_INFO = "/camera/camera/aligned_depth_to_color/camera_info"
TOPIC_UNALIGNED_DEPTH = "/camera/camera/depth/image_rect_raw"
TOPIC_UNALIGNED_DEPTH_INFO = "/camera/camera/depth/camera_info"
TOPIC_EXTRINSICS = "/camera/camera/extrinsics/depth_to_color"
TOPIC_GT_POSES = "/ground_truth/poses"
TOPIC_GT_OBJECT = "/ground_truth/object"
# Per instance, the fraction of its silhouette that is in the image and not hidden
# (std_msgs/Float32MultiArray, same stamp as the image, same order as the poses).
TOPIC_GT_VISIBILITY = "/ground_truth/visibility"
COLOUR_FRAME_ID = "camera_color_optical_frame"
DEPTH_FRAME_ID = "camera_depth_optical_frame"
STORAGES = ("sqlite3", "mcap")
# image_transport's names: "raw" sensor_msgs/Image on the topic itself; "compressed" colour as
# JPEG on <topic>/compressed and depth as PNG on <topic>/compressedDepth (sensor_msgs/CompressedImage),
# what a bag recorded from realsense-ros with its compressed topics holds.
TRANSPORTS = ("raw", "compressed")
CUSTOM_DATA_OBJECT_KEY = "multi_instance_reg.object"


def _qos(transient_local: bool = False, sensor_data: bool = False):
    """realsense-ros offers reliable, keep-last 10 (its IMU topics best effort, keep-last 5:
    "SENSOR_DATA"); the object description is latched."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1 if transient_local else 5 if sensor_data else 10,
               reliability=QosReliability.BEST_EFFORT if sensor_data else QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               deadline=zero, lifespan=zero, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=zero, avoid_ros_namespace_conventions=False)


class RealSenseBagWriter:
    """A rosbag2 writer for D455-style RGB-D streams plus ground truth.

    ``storage`` is "sqlite3" (default, what ``ros2 bag record`` writes) or "mcap". The path
    must not exist yet (rosbag2 never overwrites); missing parent folders are created.
    """

    def __init__(self, path, storage: str = "sqlite3", transport: str = "raw"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        from .typestores import ros2_typestore

        if storage not in STORAGES:
            raise InputError(f"storage '{storage}' is not supported; use one of: {', '.join(STORAGES)}")
        if transport not in TRANSPORTS:
            raise InputError(f"image transport '{transport}' is not supported; use one of: {', '.join(TRANSPORTS)}")
        self.transport = transport
        self.path = Path(path)
        if self.path.exists():
            raise InputError(f"output '{self.path}' already exists; rosbag2 does not overwrite, "
                             "so remove it or choose another path")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.typestore = ros2_typestore()
        self._types = self.typestore.types
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._writer.open()
        self._connections = {}
        self.frames_written = 0

    # -- context manager -------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    # -- writing ---------------------------------------------------------------------------
    def _connection(self, topic: str, msgtype: str, latched: bool = False):
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore,
                                               offered_qos_profiles=[_qos(latched, topic in (ACCEL_TOPIC, IMU_TOPIC))])
            self._connections[topic] = conn
        return conn

    def _write(self, topic: str, msg, stamp_ns: int, latched: bool = False) -> None:
        conn = self._connection(topic, msg.__msgtype__, latched)
        self._writer.write(conn, int(stamp_ns), self.typestore.serialize_cdr(msg, msg.__msgtype__))

    def _header(self, stamp_ns: int, frame_id: str = COLOUR_FRAME_ID):
        T = self._types
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                        frame_id=frame_id)

    def _camera_info(self, header, intr: CameraIntrinsics):
        return camera_info_message(self._types, header, intr)

    def write_object_description(self, stamp_ns: int, description: dict) -> None:
        """The placed object's description as JSON on /ground_truth/object (latched), and
        in the bag's metadata (custom_data) so a reader finds it without reading messages."""
        text = json.dumps(description, sort_keys=True)
        self._write(TOPIC_GT_OBJECT, self._types["std_msgs/msg/String"](data=text), stamp_ns, latched=True)
        self._writer.set_custom_data(CUSTOM_DATA_OBJECT_KEY, text)

    def write_accel_samples(self, stamp_ns: int, offsets_ns: np.ndarray, accel: np.ndarray,
                            topic: str = ACCEL_TOPIC, log_offset_ns: int = 0) -> None:
        """Accelerometer samples as realsense-ros publishes them (``enable_accel:=true``):
        sensor_msgs/Imu on /camera/camera/accel/sample in camera_accel_optical_frame, only
        linear_acceleration filled in (orientation_covariance[0] = -1: no orientation), each
        at ``stamp_ns + offsets_ns[i]``. ``topic``: another, e.g. the united IMU topic.
        ``log_offset_ns``: bag time minus stamp (a replayed loop: the stamps run back, bag time
        does not)."""
        T = self._types
        V = T["geometry_msgs/msg/Vector3"]
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        for off, a in zip(np.asarray(offsets_ns, np.int64), np.asarray(accel, np.float64).reshape(-1, 3)):
            stamp = int(stamp_ns) + int(off)
            msg = T["sensor_msgs/msg/Imu"](
                header=self._header(stamp, ACCEL_FRAME_ID),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0),
                orientation_covariance=no_orientation, angular_velocity=V(x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=V(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=np.diag([0.01, 0.01, 0.01]).reshape(-1))
            self._write(topic, msg, stamp + int(log_offset_ns))

    def write_frame(self, stamp_ns: int, rgb: np.ndarray, depth_mm: np.ndarray,
                    intrinsics: CameraIntrinsics, poses: np.ndarray | None = None,
                    visibility: np.ndarray | None = None, log_time_ns: int | None = None,
                    depth_intrinsics: CameraIntrinsics | None = None,
                    colour_from_depth: np.ndarray | None = None) -> None:
        """One RGB-D frame at ``stamp_ns``: colour (rgb8), aligned depth (16UC1 mm) (each
        compressed with ``transport`` "compressed"), both camera_infos, and, when given, ground-truth poses ((K, 4, 4) object -> colour optical
        frame, metres) and per-instance visibility. ``log_time_ns``: the bag time, when it is
        not the stamp (a replayed loop). With ``depth_intrinsics`` and ``colour_from_depth``
        ((4, 4) depth optical frame -> colour optical frame) the depth is the depth imager's
        own, unaligned: on depth/image_rect_raw with depth/camera_info, and the extrinsics once
        on extrinsics/depth_to_color (latched), as realsense-ros without align_depth.enable."""
        T = self._types
        rgb = np.asarray(rgb)
        depth_mm = np.asarray(depth_mm)
        unaligned = depth_intrinsics is not None
        if unaligned != (colour_from_depth is not None):
            raise InputError("unaligned depth needs both the depth intrinsics and the extrinsics from depth to colour")
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"colour must be HxWx3 uint8, got {rgb.shape} {rgb.dtype}")
        depth_shape = (depth_intrinsics.height, depth_intrinsics.width) if unaligned else rgb.shape[:2]
        if depth_mm.shape != depth_shape or depth_mm.dtype != np.uint16:
            raise InputError(f"depth must be HxW uint16 millimetres of shape {depth_shape} "
                             f"({'its camera_info' if unaligned else 'matching colour'}), got {depth_mm.shape} {depth_mm.dtype}")
        header = self._header(stamp_ns)
        depth_header = self._header(stamp_ns, DEPTH_FRAME_ID) if unaligned else header
        bag_time = stamp_ns if log_time_ns is None else int(log_time_ns)
        depth_topic = TOPIC_UNALIGNED_DEPTH if unaligned else TOPIC_DEPTH
        if unaligned and TOPIC_EXTRINSICS not in self._connections:
            R, t = np.asarray(colour_from_depth, np.float64)[:3, :3], np.asarray(colour_from_depth, np.float64)[:3, 3]
            self._write(TOPIC_EXTRINSICS, self._types[EXTRINSICS_TYPE](rotation=R.T.reshape(-1).copy(), translation=t.copy()),
                        bag_time, latched=True)       # column-major, as realsense-ros
        if self.transport == "compressed":
            Compressed = T["sensor_msgs/msg/CompressedImage"]
            colour = (TOPIC_COLOUR + "/compressed", Compressed(header=header, **compressed_colour_fields(rgb)))
            depth = (depth_topic + "/compressedDepth", Compressed(header=depth_header, **compressed_depth_fields(depth_mm)))
        else:
            Image = T["sensor_msgs/msg/Image"]
            colour = (TOPIC_COLOUR, Image(header=header, **array_to_image_fields(rgb, "rgb8")))
            depth = (depth_topic, Image(header=depth_header, **array_to_image_fields(depth_mm, "16UC1")))
        self._write(*colour, bag_time)
        self._write(TOPIC_COLOUR_INFO, self._camera_info(header, intrinsics), bag_time)
        self._write(*depth, bag_time)
        if unaligned:
            self._write(TOPIC_UNALIGNED_DEPTH_INFO, self._camera_info(depth_header, depth_intrinsics), bag_time)
        else:
            self._write(TOPIC_DEPTH_INFO, self._camera_info(header, intrinsics), bag_time)
        for topic, msg in ground_truth_messages(T, header, poses, visibility):
            self._write(topic, msg, bag_time)
        self.frames_written += 1


def camera_info_message(types, header, intr: CameraIntrinsics):
    """sensor_msgs/CameraInfo of ``intr`` from a rosbags type store's ``types`` (ROS 2 or ROS 1
    field names)."""
    K = np.asarray(intr.K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    d = np.asarray(intr.D, dtype=np.float64)
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    Info = types["sensor_msgs/msg/CameraInfo"]
    ros1 = "K" in Info.__dataclass_fields__
    arrays = dict(zip(("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p"),
                      (d, K.reshape(-1).copy(), np.eye(3).reshape(-1), P.reshape(-1))))
    return Info(header=header, height=int(intr.height), width=int(intr.width), distortion_model=intr.distortion_model,
                binning_x=0, binning_y=0, roi=roi, **arrays)


def ground_truth_messages(types, header, poses: np.ndarray | None, visibility: np.ndarray | None) -> list:
    """(topic, message) of a frame's ground truth: poses ((K, 4, 4) object -> colour optical
    frame, metres) and per-instance visibility, each when given; ``types``: a rosbags type
    store's message classes (ROS 2 or ROS 1)."""
    T = types
    out = []
    if poses is not None:
        P = T["geometry_msgs/msg/Pose"]
        pose_msgs = []
        for Tm in np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4):
            xyz, q = matrix_to_pose(Tm)
            pose_msgs.append(P(position=T["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                               orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]),
                                                                             z=float(q[2]), w=float(q[3]))))
        out.append((TOPIC_GT_POSES, T["geometry_msgs/msg/PoseArray"](header=header, poses=pose_msgs)))
    if visibility is not None:
        vis = np.asarray(visibility, dtype=np.float32).reshape(-1)
        dim = T["std_msgs/msg/MultiArrayDimension"](label="instance", size=len(vis), stride=len(vis))
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
        out.append((TOPIC_GT_VISIBILITY, T["std_msgs/msg/Float32MultiArray"](layout=layout, data=vis)))
    return out
