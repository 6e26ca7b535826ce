"""Reasoning over time, without ROS: instance tracks with stable ids (``tracker.py``) kept up
to date on every frame by projective ICP against the depth image (``icp.py``), one tracker per
object when there are several (``objects.py``), and fed by a detector running behind the
camera in a live stream (``live.py``)."""
from .icp import IcpResult, ProjectiveICP
from .live import TRACKING_ENABLED, LiveConfig, LiveTracker
from .objects import LiveObjectTrackers, ObjectTrackers
from .tracker import InstanceTracker, TrackedInstance, TrackerConfig

__all__ = ["InstanceTracker", "ObjectTrackers", "LiveObjectTrackers", "LiveTracker", "LiveConfig", "TRACKING_ENABLED", "TrackedInstance",
           "TrackerConfig", "ProjectiveICP", "IcpResult"]
