"""RGB-D front end (no ROS): SIFT, the stored object model, matching, lifting, the per-frame pipeline."""
from .model import ObjectModel, load_model, save_model
from .pipeline import FrameResult, FrontEndConfig, Instance, InstanceRegistration, PipelineConfig

__all__ = ["ObjectModel", "load_model", "save_model", "FrameResult", "FrontEndConfig", "Instance",
           "InstanceRegistration", "PipelineConfig"]
