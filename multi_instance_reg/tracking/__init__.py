"""Reasoning over time, without ROS: instance tracks with stable ids (``tracker.py``) kept up
to date on every frame by projective ICP against the depth image (``icp.py``), one tracker per
object when there are several (``objects.py``)."""
from .icp import IcpResult, ProjectiveICP
from .objects import ObjectTrackers
from .tracker import InstanceTracker, TrackedInstance, TrackerConfig

__all__ = ["InstanceTracker", "ObjectTrackers", "TrackedInstance", "TrackerConfig", "ProjectiveICP", "IcpResult"]
