"""Reasoning over time, without ROS: instance tracks with stable ids (``tracker.py``) kept up
to date on every frame by projective ICP against the depth image (``icp.py``)."""
from .icp import IcpResult, ProjectiveICP
from .tracker import InstanceTracker, TrackedInstance, TrackerConfig

__all__ = ["InstanceTracker", "TrackedInstance", "TrackerConfig", "ProjectiveICP", "IcpResult"]
