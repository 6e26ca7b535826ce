"""Instances -> vision_msgs/Detection3DArray and vision_msgs/LabelInfo, the messages ROS 2
perception stacks read detections in (Isaac ROS, DOPE, the RViz vision_msgs plugin).

vision_msgs is optional: every ROS install with ros-jazzy-vision-msgs has it, and ``make
install`` builds it into the venv (interfaces/install_vision_msgs.py). Without it the node
publishes everything else and says once why detections are off (``DetectionPublisher.create``).

Per instance, one Detection3D: ``results[0]`` carries the object's name as ``class_id``, the
instance's score and its pose (the model frame in the camera optical frame, as in the
PoseArray); ``bbox`` is the model's box (centre = the box centre moved by the pose, size =
the model's extent); ``id`` is the track id as a string once a tracker gives one (an instance
with a ``track_id``), else empty. The class is the instance's ``object`` (its model's name).
"""
from __future__ import annotations

import numpy as np

from .conversions import ObjectClass, matrix_to_pose_msg, object_of

DETECTIONS_TOPIC = "instances/detections"
# Beside the detections, as camera_info is beside image_raw (vision_msgs: "each vision pipeline
# should publish its LabelInfo messages to its own topic, in a manner similar to CameraInfo").
LABEL_INFO_TOPIC = "instances/label_info"


def vision_msgs_missing() -> str | None:
    """None when vision_msgs' messages can be published, else why not and what to do (one line).
    Its Python package may import while its C type support does not load: the node started
    with an LD_LIBRARY_PATH that names another ROS's libraries (rclpy would refuse the
    publisher with UnsupportedTypeSupport)."""
    try:
        from vision_msgs.msg import Detection3DArray, LabelInfo
    except ImportError as exc:
        return (f"vision_msgs is not installed ({exc}); install ROS' ros-jazzy-vision-msgs, or run `make install` "
                "(builds it into the venv)")
    try:
        for msg_type in (Detection3DArray, LabelInfo):
            msg_type.__class__.__import_type_support__()
    except Exception as exc:   # rosidl's UnsupportedTypeSupport, or an ImportError of the C library
        return (f"vision_msgs imports but its type support cannot be loaded ({exc}); "
                f"{_vision_msgs_library_hint()}")
    return None


def _vision_msgs_library_hint() -> str:
    import os
    import sys
    from pathlib import Path

    name = "libvision_msgs__rosidl_typesupport_c.so"
    prefixes = [sys.prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    found = next((Path(p) / "lib" for p in prefixes if p and (Path(p) / "lib" / name).is_file()), None)
    if found is not None:
        return (f"put {found} on LD_LIBRARY_PATH (it holds {name}; the program that started this one set "
                "LD_LIBRARY_PATH without it)")
    return f"LD_LIBRARY_PATH must reach {name}: source the ROS install that has vision_msgs"


def detection_array(instances, header, objects: dict[str, ObjectClass]):
    """One Detection3D per instance, in the order given; header = the colour image's."""
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose

    out = Detection3DArray()
    out.header = header
    for inst in instances:
        kind = object_of(inst, objects)
        T = np.asarray(inst.T, dtype=np.float64)
        hypothesis = ObjectHypothesisWithPose()
        hypothesis.hypothesis.class_id = kind.name
        hypothesis.hypothesis.score = float(inst.score)
        hypothesis.pose.pose = matrix_to_pose_msg(T)   # covariance: unknown (zeros)
        detection = Detection3D()
        detection.header = header
        detection.results = [hypothesis]
        detection.bbox.center = matrix_to_pose_msg(kind.box_pose(T))
        detection.bbox.size.x, detection.bbox.size.y, detection.bbox.size.z = (float(v) for v in kind.box_size)
        track_id = getattr(inst, "track_id", None)
        detection.id = "" if track_id is None else str(track_id)
        out.detections.append(detection)
    return out


def label_info(names, header=None):
    """vision_msgs/LabelInfo: class k = the k-th name (the order the node loaded the models)."""
    from vision_msgs.msg import LabelInfo, VisionClass

    msg = LabelInfo()
    if header is not None:
        msg.header = header
    msg.class_map = [VisionClass(class_id=k, class_name=name) for k, name in enumerate(names)]
    return msg


class DetectionPublisher:
    """The node's Detection3DArray and LabelInfo publishers; ``create`` gives None (and logs
    once why) when vision_msgs is not installed."""

    def __init__(self, node, qos, objects: list[ObjectClass]):
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from vision_msgs.msg import Detection3DArray, LabelInfo

        self._node = node
        self._detections = node.create_publisher(Detection3DArray, DETECTIONS_TOPIC, qos)
        # Transient local: a subscriber that joins later still gets the class names.
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._labels = node.create_publisher(LabelInfo, LABEL_INFO_TOPIC, latched)
        self.set_objects(objects)

    def set_objects(self, objects: list[ObjectClass]) -> None:
        """The objects from now on; LabelInfo is published again (class k = the k-th)."""
        from std_msgs.msg import Header

        self.objects = {o.name: o for o in objects}
        self._labels.publish(label_info(list(self.objects), Header(stamp=self._node.get_clock().now().to_msg())))

    @classmethod
    def create(cls, node, qos, objects: list[ObjectClass]) -> "DetectionPublisher | None":
        missing = vision_msgs_missing()
        if missing is not None:
            node.get_logger().warn(f"{DETECTIONS_TOPIC} is off: {missing}")
            return None
        return cls(node, qos, objects)

    def publish(self, instances, header) -> None:
        self._detections.publish(detection_array(instances, header, self.objects))
