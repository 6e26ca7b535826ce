"""The tracker in a live stream: stepped on every camera frame by one thread while detections,
computed on older frames by a slower detector, come in from others. No ROS.

    live = LiveTracker(model, TrackerConfig(), LiveConfig())
    # camera thread, every frame:        published = live.step(stamp_ns, depth_m, intrinsics)
    # detector thread, when it is done:  live.add_detections(stamp_ns_of_its_frame, instances)

On a loaded CPU the detector runs several hundred ms behind the camera. The tracker moves a
late detection forward by its track's motion since that frame, but a detection of an object
no track follows yet has no such motion: it would start a track where the object was, and a
moving camera has long taken it elsewhere (measured on the demo sweep with detections 15
frames late: no track survived). So each late detection is first *carried forward*: aligned
by the same projective ICP to every frame's depth since its own (the frames are kept for
``catch_up_frames``), one frame's motion at a time, and fused on the newest frame. A
detection the depth stops confirming on the way (occluded, left the view) is dropped.

A detection older than the depth images kept (the first one of a loaded host comes well over
a second late) is first moved by the camera's measured motions up to the oldest kept image
(the motions of every remembered frame are kept: a few numbers each); fused where it was
found, a new object's first pose was that old one, published on the newest frame (the demo
under load: every first pose 15 deg and 2-13 cm off).

A detection can only be fused for a frame the tracker has stepped and still remembers; one
from a frame it never saw, or too long ago, is refused and counted.
"""
from __future__ import annotations

import dataclasses
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..params import param, param_specs
from ..transforms import rotation_angle_deg
from .tracker import HISTORY, InstanceTracker, TrackedInstance, TrackerConfig, icp_for, proper_pose


@dataclass(frozen=True)
class LiveConfig:
    """Settings of tracking in a live stream (ROS parameters ``tracking.*`` beside TrackerConfig's)."""
    enabled: bool = param(True, "track instances over frames (read-only in the node): a pose for every camera frame, ids "
                                "kept by track; false = every frame solved alone as before tracking existed (poses only "
                                "for the frames the detector processed, ids are per-frame ranks)")
    catch_up_frames: int = param(30, "depth images kept to carry a late detection forward to the newest frame by ICP "
                                     "(a detection older than this is fused by its track's motion alone); 0 = never carry",
                                 0, HISTORY)


class LiveTracker:
    def __init__(self, model, config: TrackerConfig | None = None, live: LiveConfig | None = None):
        self._tracker = InstanceTracker(model, config)
        self._model = model
        self._icp = icp_for(model, self._tracker.config)
        self._live = live or LiveConfig()
        self._lock = threading.Lock()
        self._stepped: deque[int] = deque(maxlen=HISTORY)   # stamps whose poses the tracks remember
        self._frames: deque = deque(maxlen=max(self._live.catch_up_frames, 1))  # (stamp_ns, depth_m, intrinsics, motion)
        self._motions: deque = deque(maxlen=HISTORY)   # (stamp_ns, camera motion since the frame before, or None)
        self.detections_fused = 0       # detector results fused
        self.detections_refused = 0     # ... refused: their frame was never stepped or is forgotten
        self.detections_lost = 0        # single detections the depth stopped confirming while carried forward

    @property
    def config(self) -> TrackerConfig:
        return self._tracker.config

    def set_config(self, config: TrackerConfig) -> None:
        icp = icp_for(self._model, config)
        with self._lock:
            self._tracker.set_config(config)
            self._icp = icp

    def step(self, stamp_ns: int, depth_m, intrinsics, camera_motion=None) -> list[TrackedInstance]:
        """Every live track brought to this frame (by track_id); what to publish for it.
        ``camera_motion``: the camera's motion since the frame stepped before (odometry), or
        None."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            if self._stepped and stamp_ns <= self._stepped[-1]:
                # Time went back (a bag looping, a camera restarted): the old frames are not
                # this stream's past, so older detections must not be fused into it (the
                # tracker ends its tracks itself).
                self._stepped.clear()
                self._frames.clear()
                self._motions.clear()
                camera_motion = None
            published = self._tracker.step(stamp_ns, depth_m, intrinsics, None, camera_motion)
            self._stepped.append(stamp_ns)
            self._motions.append((stamp_ns, camera_motion))
            if self._live.catch_up_frames:
                self._frames.append((stamp_ns, depth_m, intrinsics, camera_motion))
            return published

    def add_detections(self, stamp_ns: int, detections) -> bool:
        """Fuse the detector's instances found on the frame ``stamp_ns`` (stepped earlier);
        False if that frame is not known (any more) and the detections were dropped."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            if stamp_ns not in self._stepped:
                self.detections_refused += 1
                return False
            frames, icp = self._frames_after(stamp_ns), self._icp
            lead = None
            if frames is None and icp is not None and self._live.catch_up_frames and self._frames:
                # Older than the kept depth images: by the camera's motions up to them, then carried.
                lead = self._motion_between(stamp_ns, self._frames[0][0])
                if lead is not None:
                    frames = list(self._frames)
        if lead is not None:
            detections = [dataclasses.replace(det, T=proper_pose(lead @ proper_pose(det.T))) for det in detections]
        if frames is None or icp is None or not frames:
            with self._lock:   # too old to carry, nothing to carry with, or already the newest frame
                self._tracker.add_detections(stamp_ns, detections)
                self.detections_fused += 1
            return True
        # Carry forward outside the lock (the camera thread goes on), then the frames that
        # arrived meanwhile under it.
        carried = self._carry(list(detections), frames, icp)
        with self._lock:
            newer = self._frames_after(frames[-1][0]) or []
            carried = self._carry(carried, newer, icp)
            self._tracker.add_detections((newer or frames)[-1][0], carried)
            self.detections_fused += 1
        return True

    def _frames_after(self, stamp_ns: int):
        """The kept frames after ``stamp_ns``, or None if that frame is no longer kept."""
        stamps = [f[0] for f in self._frames]
        if stamp_ns not in stamps:
            return None
        return list(self._frames)[stamps.index(stamp_ns) + 1:]

    def _motion_between(self, stamp_ns: int, until_ns: int):
        """The camera's motion from frame ``stamp_ns`` to the frame before ``until_ns`` (the
        product of the measured steps), or None where a step was not measured or the frame is
        forgotten."""
        stamps = [m[0] for m in self._motions]
        if stamp_ns not in stamps:
            return None
        M = np.eye(4)
        for stamp, motion in list(self._motions)[stamps.index(stamp_ns) + 1:]:
            if stamp >= until_ns:
                return M
            if motion is None:
                return None
            M = np.asarray(motion, dtype=np.float64) @ M
        return None

    def _carry(self, detections, frames, icp) -> list:
        """Each detection moved by each frame's camera motion (where the odometry measured
        it) and aligned to that frame's depth in turn (the tracker's own acceptance rule per
        frame). One the depth stops confirming is dropped where the camera's motion is not
        known (occluded, left the view, or a jump the ICP cannot reach), or where the depth
        contradicts it; with the motion known it is carried by that alone."""
        c = self._tracker.config
        out = []
        for det in detections:
            T = proper_pose(det.T)
            for _, depth, intrinsics, motion in frames:
                if motion is not None:
                    T = proper_pose(motion @ T)
                res = icp.align(T, depth, intrinsics)
                step_m = float(np.linalg.norm(res.T[:3, 3] - T[:3, 3]))
                step_deg = rotation_angle_deg(res.T[:3, :3] @ T[:3, :3].T)
                if res.free_share > c.max_free_share:
                    T = None
                    break
                if res.fitness < c.icp_min_fitness or step_m > c.icp_max_step or step_deg > c.icp_max_step_deg:
                    if motion is None:
                        T = None
                        break
                    continue
                T = proper_pose(res.T)
            if T is None:
                self.detections_lost += 1
            else:
                out.append(dataclasses.replace(det, T=T))
        return out

    def counts(self) -> dict:
        with self._lock:
            return {"tracks_live": len(self._tracker.tracks), "tracks_started": self._tracker.next_id,
                    "tracks_ended": self._tracker.ended, "tracking_resets": self._tracker.resets,
                    "detections_fused": self.detections_fused,
                    "detections_refused": self.detections_refused, "detections_lost": self.detections_lost}


# The node's parameter, also read by `mireg offline --params`.
TRACKING_ENABLED = next(s for s in param_specs(LiveConfig(), "tracking.") if s.name == "tracking.enabled")

__all__ = ["LiveTracker", "LiveConfig", "TRACKING_ENABLED"]
