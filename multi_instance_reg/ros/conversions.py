"""Instances -> the node's output messages: PoseArray, MarkerArray and the JSON details.

Instances are duck-typed: anything with ``id``, ``T`` (4x4, model frame -> camera optical
frame, metres), ``inliers`` (a count or a list of indices), ``score`` and ``object`` (the
model's name). Tracked ones (``tracking.TrackedInstance``) also have ``track_id``, ``state``,
``source`` and ``age_s``: their markers are keyed and coloured by ``track_id`` and their
details carry those fields too.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import Pose, PoseArray
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from ..transforms import matrix_to_pose

LABEL_NS_SUFFIX = "_labels"   # markers: boxes in the namespace <object name>, labels in <name>_labels


@dataclass(frozen=True)
class ObjectClass:
    """What the outputs say about one kind of object: its name and its box in the model frame."""
    name: str
    box_centre: np.ndarray   # (3,) metres, model frame
    box_size: np.ndarray     # (3,) metres, along the model axes

    @classmethod
    def of_model(cls, model, model_path="") -> "ObjectClass":
        """The model's stored name, else its file's stem (``snack_bar.npz`` -> ``snack_bar``)."""
        from pathlib import Path

        return cls(str(getattr(model, "name", "") or "") or Path(model_path).stem, np.asarray(model.box_centre, dtype=np.float64).reshape(3),
                   np.asarray(model.extent, dtype=np.float64).reshape(3))

    def box_pose(self, T: np.ndarray) -> np.ndarray:
        """The box's pose for an instance at model pose ``T``: its centre moved by T, T's axes."""
        box_T = np.array(T, dtype=np.float64)
        box_T[:3, 3] = box_T[:3, :3] @ self.box_centre + box_T[:3, 3]
        return box_T


def object_of(instance, objects: dict[str, ObjectClass]) -> ObjectClass:
    """The instance's object (by its ``object`` name); an unnamed instance is the first one's."""
    return objects.get(getattr(instance, "object", "") or "") or next(iter(objects.values()))

# Distinct colours (RGB, 0-255) for instance ids; the debug image uses the same ones.
_PALETTE = np.array([
    (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
    (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212),
    (0, 128, 128), (220, 190, 255), (170, 110, 40), (255, 250, 200), (128, 0, 0),
    (170, 255, 195), (128, 128, 0), (255, 215, 180), (0, 0, 128), (128, 128, 128),
], dtype=np.uint8)


def instance_colour(instance_id: int) -> tuple[int, int, int]:
    """RGB 0-255 for an instance id (-1, an outlier, is grey)."""
    if instance_id < 0:
        return (160, 160, 160)
    return tuple(int(c) for c in _PALETTE[int(instance_id) % len(_PALETTE)])


def inlier_count(instance) -> int:
    inliers = instance.inliers
    return int(inliers) if np.isscalar(inliers) else len(inliers)


def marker_key(instance) -> int:
    """The marker id (and colour) of an instance: its track id if tracked, else its rank."""
    return int(getattr(instance, "track_id", instance.id))


def matrix_to_pose_msg(T: np.ndarray) -> Pose:
    xyz, quat = matrix_to_pose(np.asarray(T, dtype=np.float64))
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in xyz)
    (pose.orientation.x, pose.orientation.y,
     pose.orientation.z, pose.orientation.w) = (float(v) for v in quat)
    return pose


def pose_array(instances, header) -> PoseArray:
    """Pose k = the model frame of instance k in the camera optical frame (REP-103, metres),
    in the order given (the node gives tracks by track_id, per-frame instances by id)."""
    msg = PoseArray()
    msg.header = header
    msg.poses = [matrix_to_pose_msg(inst.T) for inst in instances]
    return msg


def marker_array(instances, header, objects: dict[str, ObjectClass], previous=()) -> tuple[MarkerArray, set]:
    """An oriented box (its object's) and a label (object name, id, inliers) per instance; the
    namespace is the object's name (labels: ``<name>_labels``), the marker id and colour
    ``marker_key``; plus DELETE markers for those published last time and gone now (a track that
    ended, an object unloaded). Returns (markers, (namespace, id) pairs now shown)."""
    out = MarkerArray()
    shown = set()
    for inst in instances:
        kind = object_of(inst, objects)
        box_T = kind.box_pose(inst.T)
        key = marker_key(inst)
        r, g, b = (c / 255.0 for c in instance_colour(key))
        box = Marker()
        box.header = header
        box.ns, box.id = kind.name, key
        box.type, box.action = Marker.CUBE, Marker.ADD
        box.pose = matrix_to_pose_msg(box_T)
        box.scale.x, box.scale.y, box.scale.z = (float(max(v, 1e-3)) for v in kind.box_size)
        box.color.r, box.color.g, box.color.b, box.color.a = r, g, b, 0.5
        label = Marker()
        label.header = header
        label.ns, label.id = kind.name + LABEL_NS_SUFFIX, key
        label.type, label.action = Marker.TEXT_VIEW_FACING, Marker.ADD
        # Above the box: "up" in the optical frame is -y.
        label.pose.position.x, label.pose.position.y, label.pose.position.z = (
            float(box_T[0, 3]), float(box_T[1, 3] - 0.6 * kind.box_size.max() - 0.01), float(box_T[2, 3]))
        label.pose.orientation.w = 1.0
        label.scale.z = 0.03
        label.color.r, label.color.g, label.color.b, label.color.a = 1.0, 1.0, 1.0, 1.0
        state = getattr(inst, "state", "confirmed")
        label.text = f"{kind.name} {key} ({inlier_count(inst)})" + ("" if state == "confirmed" else f" {state}")
        out.markers.extend([box, label])
        shown.update({(box.ns, key), (label.ns, key)})
    for ns, gone in sorted(set(previous) - shown):
        delete = Marker()
        delete.header = header
        delete.ns, delete.id, delete.action = ns, gone, Marker.DELETE
        out.markers.append(delete)
    return out, shown


def instance_details(instance) -> dict:
    """{"object", "id", "inliers", "score"}, and for a track also "track_id", "state", "source", "age_s"."""
    out = {"id": int(instance.id), "inliers": inlier_count(instance), "score": round(float(instance.score), 4)}
    if getattr(instance, "object", ""):
        out = {"object": instance.object, **out}
    if hasattr(instance, "track_id"):
        out.update(track_id=int(instance.track_id), state=instance.state, source=instance.source,
                   age_s=round(float(instance.age_s), 3))
    return out


def details_message(stamp_ns: int, frame_id: str, latency_ms: float, instances, **extra) -> String:
    """std_msgs/String with JSON (no custom messages in a pure-Python package):
    {"stamp_ns", "frame_id", "latency_ms", "instances": [instance_details(i), ...], ...extra}."""
    payload = {
        "stamp_ns": int(stamp_ns), "frame_id": frame_id, "latency_ms": round(float(latency_ms), 3),
        "instances": [instance_details(i) for i in instances],
    }
    payload.update(extra)
    return String(data=json.dumps(payload))
