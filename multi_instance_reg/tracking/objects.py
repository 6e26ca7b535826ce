"""Tracks of several objects: one InstanceTracker per object, so that a track belongs to one
object for its whole life and ids of different objects never meet in one association. No ROS.
``LiveObjectTrackers`` does the same with one LiveTracker per object, for a live stream.

    trackers = ObjectTrackers(models, TrackerConfig())
    out = trackers.step(stamp_ns, depth_m, intrinsics, detections)   # Instances with .object, or None
    for inst in out:                                                  # by object (models' order), then track_id
        inst.object, inst.track_id, inst.state, inst.T
"""
from __future__ import annotations

from dataclasses import replace

from .live import LiveTracker
from .odometry import CameraOdometry
from .tracker import InstanceTracker, TrackedInstance, TrackerConfig


class ObjectTrackers:
    """One ``InstanceTracker`` per object model, fed that object's detections; the camera's
    motion (``odometry``) measured once a frame for all of them."""

    def __init__(self, models, config: TrackerConfig | None = None):
        config = config or TrackerConfig()
        self.trackers = {m.name: InstanceTracker(m, config) for m in models}
        self.odometry = CameraOdometry() if config.odometry else None

    def _split(self, detections):
        if detections is None:
            return {name: None for name in self.trackers}
        mine = {name: [] for name in self.trackers}
        for det in detections:
            mine[det.object].append(det)
        return mine

    def step(self, stamp_ns: int, depth_m, intrinsics, detections=None, rgb=None) -> list[TrackedInstance]:
        """Every object's tracker advanced to this frame (see ``InstanceTracker.step``);
        ``rgb``: the colour image, for the camera's motion."""
        dets = self._split(detections)
        motion = self.odometry.step(rgb, depth_m, intrinsics, stamp_ns) if self.odometry is not None else None
        return [replace(inst, object=name) for name, tracker in self.trackers.items()
                for inst in tracker.step(stamp_ns, depth_m, intrinsics, dets[name], motion)]

    def add_detections(self, stamp_ns: int, detections) -> None:
        """Detections found on an earlier frame, each to its object's tracker."""
        for name, dets in self._split(detections).items():
            if dets:
                self.trackers[name].add_detections(stamp_ns, dets)


__all__ = ["LiveObjectTrackers", "ObjectTrackers"]


class LiveObjectTrackers:
    """One ``LiveTracker`` per object in a live stream (the node's tracking), with the set of
    objects changeable while it runs: ``set_models`` ends the tracks of objects no longer
    loaded and starts empty trackers for new ones; the others keep their tracks and ids.
    Thread-safe like LiveTracker (each has its own lock; the set is swapped whole)."""

    def __init__(self, models, config: TrackerConfig | None = None, live=None):
        self._config, self._live = config, live
        self._trackers: dict = {}
        self._models: dict = {}
        self._odometry = CameraOdometry() if (config or TrackerConfig()).odometry else None
        self.set_models(models)

    def set_models(self, models) -> None:
        """Track these models from the next frame on (a model object kept keeps its tracks)."""
        kept = {m.name: (self._trackers[m.name] if self._models.get(m.name) is m else LiveTracker(m, self._config,
                                                                                                   self._live))
                for m in models}
        self._models = {m.name: m for m in models}
        self._trackers = kept   # one assignment: a step sees the old set or the new one

    @property
    def names(self) -> list[str]:
        return list(self._trackers)

    def set_config(self, config: TrackerConfig) -> None:
        self._config = config
        if (self._odometry is not None) != config.odometry:
            self._odometry = CameraOdometry() if config.odometry else None
        for tracker in self._trackers.values():
            tracker.set_config(config)

    def step(self, stamp_ns: int, depth_m, intrinsics, rgb=None) -> list[TrackedInstance]:
        """Every object's live tracks on this frame, by object (models' order), then track_id;
        ``rgb``: the colour image, for the camera's motion (one camera thread calls this)."""
        odometry = self._odometry
        motion = odometry.step(rgb, depth_m, intrinsics, stamp_ns) if odometry is not None else None
        return [replace(inst, object=name) for name, tracker in self._trackers.items()
                for inst in tracker.step(stamp_ns, depth_m, intrinsics, motion)]

    def add_detections(self, stamp_ns: int, detections) -> bool:
        """The detector's instances of the frame ``stamp_ns``, each to its object's tracker
        (those of objects no longer loaded are dropped); False if a tracker refused its own."""
        trackers = self._trackers
        mine: dict = {name: [] for name in trackers}
        for det in detections:
            if det.object in mine:
                mine[det.object].append(det)
        # Every tracker is told, also with no detections: nothing found there is news too.
        return all([tracker.add_detections(stamp_ns, mine[name]) for name, tracker in trackers.items()])

    def counts(self) -> dict:
        """LiveTracker.counts summed over the objects."""
        total: dict = {}
        for tracker in self._trackers.values():
            for key, value in tracker.counts().items():
                total[key] = total.get(key, 0) + value
        return total
