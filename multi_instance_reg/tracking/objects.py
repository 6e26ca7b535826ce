"""Tracks of several objects: one InstanceTracker per object, so that a track belongs to one
object for its whole life and ids of different objects never meet in one association. No ROS.

    trackers = ObjectTrackers(models, TrackerConfig())
    out = trackers.step(stamp_ns, depth_m, intrinsics, detections)   # Instances with .object, or None
    for inst in out:                                                  # by object (models' order), then track_id
        inst.object, inst.track_id, inst.state, inst.T
"""
from __future__ import annotations

from dataclasses import replace

from .tracker import InstanceTracker, TrackedInstance, TrackerConfig


class ObjectTrackers:
    """One ``InstanceTracker`` per object model, fed that object's detections."""

    def __init__(self, models, config: TrackerConfig | None = None):
        self.trackers = {m.name: InstanceTracker(m, config) for m in models}

    def _split(self, detections):
        if detections is None:
            return {name: None for name in self.trackers}
        mine = {name: [] for name in self.trackers}
        for det in detections:
            mine[det.object].append(det)
        return mine

    def step(self, stamp_ns: int, depth_m, intrinsics, detections=None) -> list[TrackedInstance]:
        """Every object's tracker advanced to this frame (see ``InstanceTracker.step``)."""
        dets = self._split(detections)
        return [replace(inst, object=name) for name, tracker in self.trackers.items()
                for inst in tracker.step(stamp_ns, depth_m, intrinsics, dets[name])]

    def add_detections(self, stamp_ns: int, detections) -> None:
        """Detections found on an earlier frame, each to its object's tracker."""
        for name, dets in self._split(detections).items():
            if dets:
                self.trackers[name].add_detections(stamp_ns, dets)


__all__ = ["ObjectTrackers"]
