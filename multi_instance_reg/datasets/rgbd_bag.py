"""RGB-D frames from a recorded bag: colour + aligned depth + camera_info (+ ground truth).

Reads rosbag2 directories and bare .db3 / .mcap files (and ROS 1 .bag) with rosbags'
AnyReader. Colour and depth are paired by header stamp (within ``max_dt_ns``), each frame
gets the latest camera_info, and, when the bag has ``/ground_truth/poses``, the ground-truth
poses of the same stamp. Frames that cannot be decoded are skipped and counted, never raised.
Images may be raw (sensor_msgs/Image) or compressed (image_transport's ``compressed`` colour and
``compressedDepth`` PNG depth); a bag without the raw topics is read from ``<topic>/compressed``
and ``<topic>/compressedDepth``. When the bag holds the camera's accelerometer (realsense-ros'
``/camera/camera/accel/sample``, else its united ``/camera/camera/imu``), each frame carries the
direction of gravity from the samples just before its stamp (``multi_instance_reg.gravity``).

Depth recorded unaligned is registered to colour (``rgbd.registration``): a bag without the
aligned depth topic but with realsense-ros' ``depth/image_rect_raw``, ``depth/camera_info`` and
``extrinsics/depth_to_color`` (what it records without ``align_depth.enable``), and a
RealSense Viewer .bag (``realsense_viewer``), are read as if the depth had been aligned.
"""
from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError
from ..gravity import ACCEL_TOPIC, IMU_TOPIC, IMU_TYPE, AccelWindow, imu_accel
from ..messages import CameraIntrinsics, camera_info_to_intrinsics, colour_to_rgb, depth_to_metres
from ..transforms import pose_to_matrix

COLOUR_TOPIC = "/camera/camera/color/image_raw"
DEPTH_TOPIC = "/camera/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/camera/color/camera_info"
# realsense-ros without align_depth.enable: depth in the depth imager's pixels, its own
# camera_info, and the extrinsics from depth to colour (published once, latched).
UNALIGNED_DEPTH_TOPIC = "/camera/camera/depth/image_rect_raw"
DEPTH_INFO_TOPIC = "/camera/camera/depth/camera_info"
EXTRINSICS_TOPIC = "/camera/camera/extrinsics/depth_to_color"
GT_POSES_TOPIC = "/ground_truth/poses"
GT_OBJECT_TOPIC = "/ground_truth/object"
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
GT_VISIBILITY_TOPIC = "/ground_truth/visibility"   # std_msgs/Float32MultiArray: visible fraction per instance


@dataclass
class RGBDFrame:
    stamp_ns: int
    frame_id: str
    rgb: np.ndarray                      # (H, W, 3) uint8 RGB
    depth_m: np.ndarray                  # (H, W) float32 metres, 0 = invalid
    intrinsics: CameraIntrinsics
    gt_poses: np.ndarray | None = None   # (K, 4, 4) object frame -> optical frame, or None without ground truth
    gt_visibility: np.ndarray | None = None   # (K,) visible fraction of each instance, when the bag has it
    gravity: np.ndarray | None = None    # (3,) unit "up" in the optical frame from the accelerometer, None without


@dataclass
class SkipCounter:
    """Frames that were left out, with the reason of each (the first few kept verbatim)."""
    count: int = 0
    reasons: dict[str, int] = field(default_factory=dict)

    def add(self, reason: str) -> None:
        self.count += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1

    def summary(self) -> str:
        return "; ".join(f"{n} x {r}" for r, n in sorted(self.reasons.items(), key=lambda kv: -kv[1]))


def _stamp_ns(msg) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def _open_reader(path):
    from rosbags.highlevel import AnyReader, AnyReaderError

    from .typestores import ros2_typestore

    p = Path(path)
    if not p.exists():
        raise InputError(f"bag {p} does not exist")
    try:
        reader = AnyReader([p], default_typestore=ros2_typestore())
        reader.open()
    except (AnyReaderError, Exception) as exc:  # rosbags raises several types for unreadable bags
        if isinstance(exc, InputError):
            raise
        raise InputError(f"cannot read bag {p}: {exc or type(exc).__name__} (expected a rosbag2 directory, "
                         f"a .db3 or a .mcap file, or a RealSense Viewer .bag)") from None
    return reader


class RGBDBag:
    """A bag opened for RGB-D frames. Use as a context manager; iterate for RGBDFrame."""

    def __init__(self, path, colour_topic: str = COLOUR_TOPIC, depth_topic: str = DEPTH_TOPIC,
                 info_topic: str = INFO_TOPIC, gt_topic: str = GT_POSES_TOPIC, max_dt_ns: int | None = None,
                 max_pending: int = 30, accel_topic: str | None = ACCEL_TOPIC):
        """``accel_topic``: the accelerometer's sensor_msgs/Imu topic (the default falls back to
        the united IMU topic when only that is recorded); None: frames without gravity.
        ``max_dt_ns``: how far apart a colour and a depth stamp may be to make a frame (default
        5 ms for aligned depth, which shares the colour's stamp; half a colour frame period for
        depth recorded unaligned, which comes from another sensor's clock tick)."""
        self.path = Path(path)
        self.colour_topic, self.depth_topic, self.info_topic, self.gt_topic = colour_topic, depth_topic, info_topic, gt_topic
        self.max_pending = int(max_pending)
        self.skipped = SkipCounter()
        self._reader = _open_reader(self.path)
        try:
            self._choose_topics(colour_topic, depth_topic, info_topic, accel_topic)
        except InputError:
            self._reader.close()
            raise
        self.max_dt_ns = int(max_dt_ns) if max_dt_ns is not None else \
            5_000_000 if self.colour_from_depth is None else _half_frame_period_ns(self._reader, self.colour_topic)
        topics = self._reader.topics
        self.has_ground_truth = gt_topic in topics
        self.has_visibility = self.has_ground_truth and GT_VISIBILITY_TOPIC in topics
        self.num_colour_messages = int(topics[self.colour_topic].msgcount)
        self.object_description = _object_description(self._reader, self.path)

    @property
    def registers_depth(self) -> bool:
        """Is the depth recorded unaligned, and registered to colour here?"""
        return self.colour_from_depth is not None

    def _choose_topics(self, colour_topic, depth_topic, info_topic, accel_topic) -> None:
        from .realsense_viewer import viewer_layout

        topics = self._reader.topics
        self.depth_info_topic: str | None = None
        self.colour_from_depth: np.ndarray | None = None     # (4, 4) when the depth is registered here
        self.depth_scale = 0.001
        defaults = (colour_topic, depth_topic, info_topic) == (COLOUR_TOPIC, DEPTH_TOPIC, INFO_TOPIC)
        viewer = viewer_layout(self._reader, self.path) if defaults and COLOUR_TOPIC not in topics and \
            COLOUR_TOPIC + "/compressed" not in topics else None
        if viewer is not None:
            colour_topic, depth_topic, info_topic = viewer.colour_topic, viewer.depth_topic, viewer.info_topic
            self.depth_info_topic, self.colour_from_depth = viewer.depth_info_topic, viewer.colour_from_depth
            self.depth_scale = viewer.depth_scale
            accel_topic = None
        # realsense-ros without align_depth.enable: the depth imager's own stream.
        elif depth_topic == DEPTH_TOPIC and not {DEPTH_TOPIC, DEPTH_TOPIC + "/compressedDepth"} & set(topics) and \
                {UNALIGNED_DEPTH_TOPIC, UNALIGNED_DEPTH_TOPIC + "/compressedDepth"} & set(topics):
            depth_topic = UNALIGNED_DEPTH_TOPIC
        # A bag recorded with image_transport's compressed topics only: read those.
        if colour_topic not in topics and colour_topic + "/compressed" in topics:
            colour_topic = colour_topic + "/compressed"
        if depth_topic not in topics and depth_topic + "/compressedDepth" in topics:
            depth_topic = depth_topic + "/compressedDepth"
        self.colour_topic, self.depth_topic, self.info_topic = colour_topic, depth_topic, info_topic
        missing = [t for t in (colour_topic, depth_topic, info_topic) if t not in topics]
        if missing:
            present = ", ".join(sorted(topics)) or "none"
            raise InputError(f"bag {self.path} has no topic {', '.join(missing)}; topics present: {present} "
                             f"(choose others with --topics COLOUR DEPTH INFO)")
        if depth_topic.split("/compressedDepth")[0] == UNALIGNED_DEPTH_TOPIC:
            for topic, what in ((DEPTH_INFO_TOPIC, "the depth camera's intrinsics"),
                                (EXTRINSICS_TOPIC, "the extrinsics from depth to colour")):
                if topic not in topics:
                    raise InputError(f"bag {self.path} has depth unaligned to colour ({UNALIGNED_DEPTH_TOPIC}) but no "
                                     f"{topic} ({what}): record that topic too, or record with "
                                     f"align_depth.enable:=true")
            self.depth_info_topic = DEPTH_INFO_TOPIC
            self.colour_from_depth = _read_extrinsics(self._reader, self.path)
        checks = [(colour_topic, IMAGE_TYPES), (depth_topic, IMAGE_TYPES), (info_topic, ("sensor_msgs/msg/CameraInfo",))]
        if self.depth_info_topic is not None:
            checks.append((self.depth_info_topic, ("sensor_msgs/msg/CameraInfo",)))
        for topic, types in checks:
            if topics[topic].msgtype not in types:
                raise InputError(f"bag {self.path}: topic {topic} holds {topics[topic].msgtype}, not {' or '.join(types)} "
                                 f"(choose others with --topics COLOUR DEPTH INFO)")
        if accel_topic == ACCEL_TOPIC and accel_topic not in topics and IMU_TOPIC in topics:
            accel_topic = IMU_TOPIC
        self.accel_topic = accel_topic if accel_topic in topics and topics[accel_topic].msgtype == IMU_TYPE else None

    def instance_objects(self, count: int) -> list[str]:
        """Object name of each of ``count`` ground-truth instances: a mixed scene's
        ``instance_objects`` on /ground_truth/object, else its one ``name`` for all ("" when
        the bag does not say)."""
        return instance_objects(self.object_description, count)

    # -- context manager
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __iter__(self) -> Iterator[RGBDFrame]:
        reader = self._reader
        wanted = {self.colour_topic, self.depth_topic, self.info_topic}
        if self.depth_info_topic is not None:
            wanted.add(self.depth_info_topic)
        if self.has_ground_truth:
            wanted.add(self.gt_topic)
        if self.has_visibility:
            wanted.add(GT_VISIBILITY_TOPIC)
        if self.accel_topic is not None:
            wanted.add(self.accel_topic)
        accel = AccelWindow()
        conns = [c for c in reader.connections if c.topic in wanted]
        colour_q: deque = deque()   # (stamp, message)
        depth_q: deque = deque()
        gt: dict[int, np.ndarray] = {}
        visibility: dict[int, np.ndarray] = {}
        gt_stamp_at: dict[int, int] = {}      # bag time of a ground-truth pose message -> its stamp
        state = {"info": None, "depth_info": None, "gt_latest": -1, "vis_latest": -1, "colour_latest": -1}

        def decode(raw, conn):
            return reader.deserialize(raw, conn.msgtype)

        def emit_ready(flush: bool):
            while colour_q and depth_q:
                (tc, c), (td, d) = colour_q[0], depth_q[0]
                if abs(tc - td) > self.max_dt_ns:
                    # The older one has no partner: the other stream has moved past it.
                    if tc < td:
                        colour_q.popleft()
                        self.skipped.add("colour image without depth")
                    else:
                        depth_q.popleft()
                        self.skipped.add("depth image without colour")
                    continue
                waiting_gt = (self.has_ground_truth and tc not in gt and state["gt_latest"] < tc) or \
                    (self.has_visibility and tc not in visibility and state["vis_latest"] < tc)
                waiting_info = state["info"] is None or (self.registers_depth and state["depth_info"] is None)
                if (waiting_gt or waiting_info) and not flush and len(colour_q) < self.max_pending:
                    return
                colour_q.popleft()
                depth_q.popleft()
                if state["info"] is None:
                    self.skipped.add("no camera_info before the image")
                    continue
                if self.registers_depth and state["depth_info"] is None:
                    self.skipped.add("no depth camera_info before the depth image")
                    continue
                frame = self._make_frame(tc, c, d, state["info"], gt.pop(tc, None), visibility.pop(tc, None),
                                         accel.up_at(tc) if self.accel_topic is not None else None,
                                         state["depth_info"])
                for table in (gt, visibility):
                    for old in [s for s in table if s < tc]:
                        del table[old]
                if frame is not None:
                    yield frame

        for conn, bag_time, raw in reader.messages(connections=conns):
            try:
                msg = decode(raw, conn)
            except Exception as exc:  # a corrupt message: skip it, keep the stream going
                self.skipped.add(f"undecodable {conn.topic} message ({type(exc).__name__})")
                continue
            if conn.topic in (self.info_topic, self.depth_info_topic):
                try:
                    state["info" if conn.topic == self.info_topic else "depth_info"] = camera_info_to_intrinsics(msg)
                except InputError as exc:
                    self.skipped.add(str(exc))
                continue
            if conn.topic == GT_VISIBILITY_TOPIC:
                # Float32MultiArray has no header: it shares the bag time of its frame's poses,
                # and so their stamp (the same as the bag time, but in a replayed loop).
                stamp = gt_stamp_at.pop(int(bag_time), int(bag_time))
                visibility[stamp] = np.asarray(msg.data, dtype=np.float32)
                state["vis_latest"] = max(state["vis_latest"], stamp)
                yield from emit_ready(flush=False)
                continue
            stamp = _stamp_ns(msg)
            if conn.topic == self.accel_topic:
                accel.add(stamp, imu_accel(msg))
                continue
            if conn.topic == self.colour_topic:
                if stamp < state["colour_latest"]:
                    # The stamps jumped back (a bag recorded from a loop): finish the frames
                    # before it and wait for the ground truth of the new ones again.
                    yield from emit_ready(flush=True)
                    gt.clear()
                    visibility.clear()
                    state["gt_latest"] = state["vis_latest"] = -1
                state["colour_latest"] = stamp
                colour_q.append((stamp, msg))
            elif conn.topic == self.depth_topic:
                depth_q.append((stamp, msg))
            else:
                gt[stamp] = np.array([pose_to_matrix((p.position.x, p.position.y, p.position.z),
                                                     (p.orientation.x, p.orientation.y, p.orientation.z,
                                                      p.orientation.w)) for p in msg.poses]).reshape(-1, 4, 4)
                state["gt_latest"] = max(state["gt_latest"], stamp)
                if self.has_visibility:
                    gt_stamp_at[int(bag_time)] = stamp
            yield from emit_ready(flush=False)
        yield from emit_ready(flush=True)
        for _ in colour_q:
            self.skipped.add("colour image without depth")
        for _ in depth_q:
            self.skipped.add("depth image without colour")

    def _make_frame(self, stamp, colour_msg, depth_msg, info, gt_poses, gt_visibility, gravity=None,
                    depth_info: CameraIntrinsics | None = None) -> RGBDFrame | None:
        try:
            rgb = colour_to_rgb(colour_msg)
            depth = depth_to_metres(depth_msg, self.depth_scale)
            if self.colour_from_depth is not None:
                from ..rgbd.registration import register_to_colour   # (numba: only for bags that need it)

                depth = register_to_colour(depth, depth_info, info, self.colour_from_depth)
        except InputError as exc:
            self.skipped.add(str(exc))
            return None
        if gt_visibility is not None and (gt_poses is None or len(gt_visibility) != len(gt_poses)):
            gt_visibility = None
        return RGBDFrame(stamp, str(colour_msg.header.frame_id), rgb, depth, info, gt_poses, gt_visibility, gravity)


def read_rgbd_frames(path, colour_topic: str = COLOUR_TOPIC, depth_topic: str = DEPTH_TOPIC,
                     info_topic: str = INFO_TOPIC, skipped: SkipCounter | None = None) -> Iterator[RGBDFrame]:
    """Yield the RGB-D frames of a bag in stamp order (see RGBDBag). Pass a SkipCounter to
    learn how many frames were left out and why. Raises InputError at once (not lazily) if the
    bag cannot be read or lacks a topic."""
    bag = RGBDBag(path, colour_topic, depth_topic, info_topic)

    def gen():
        with bag:
            yield from bag
            if skipped is not None:
                skipped.count += bag.skipped.count
                for r, n in bag.skipped.reasons.items():
                    skipped.reasons[r] = skipped.reasons.get(r, 0) + n
    return gen()


def _read_extrinsics(reader, path) -> np.ndarray:
    """T_colour_from_depth from the first message on realsense-ros' depth_to_color topic."""
    from ..rgbd.registration import extrinsics_matrix

    conns = [c for c in reader.connections if c.topic == EXTRINSICS_TOPIC]
    for conn, _, raw in reader.messages(connections=conns):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            return extrinsics_matrix(msg.rotation, msg.translation)
        except InputError as exc:
            raise InputError(f"bag {path}: {EXTRINSICS_TOPIC}: {exc}") from None
        except Exception as exc:  # rosbags raises several types for a message it cannot decode
            raise InputError(f"bag {path}: {EXTRINSICS_TOPIC} cannot be read as realsense2_camera_msgs/Extrinsics "
                             f"({type(exc).__name__})") from None
    raise InputError(f"bag {path}: {EXTRINSICS_TOPIC} has no message; record it from the camera's start "
                     f"(realsense-ros publishes it once, latched)")


def _half_frame_period_ns(reader, topic: str) -> int:
    """Half the mean interval between the topic's messages (16.7 ms at 30 Hz; 16 ms when the
    bag has too few messages to tell)."""
    count = int(reader.topics[topic].msgcount)
    conns = [c for c in reader.connections if c.topic == topic]
    if count < 2 or not conns:
        return 16_000_000
    span = int(reader.end_time) - int(reader.start_time)
    return max(1_000_000, int(span / (count - 1) / 2)) if span > 0 else 16_000_000


def _object_description(reader, path) -> dict | None:
    conns = [c for c in reader.connections if c.topic == GT_OBJECT_TOPIC]
    if not conns:   # (an empty connection list would read every message)
        return None
    for conn, _, raw in reader.messages(connections=conns):
        try:
            return json.loads(reader.deserialize(raw, conn.msgtype).data)
        except (ValueError, AttributeError) as exc:
            raise InputError(f"bag {path}: {GT_OBJECT_TOPIC} is not the expected JSON ({exc})") from None
    return None


def instance_objects(description: dict | None, count: int) -> list[str]:
    """See ``RGBDBag.instance_objects``: the object names of ``count`` ground-truth instances
    from a bag's object description."""
    d = description or {}
    names = d.get("instance_objects")
    if isinstance(names, list) and len(names) == count:
        return [str(n) for n in names]
    return [str(d.get("name", ""))] * count


def read_object_description(path) -> dict | None:
    """The JSON object description on /ground_truth/object, or None if the bag has none."""
    reader = _open_reader(path)
    try:
        return _object_description(reader, path)
    finally:
        reader.close()
