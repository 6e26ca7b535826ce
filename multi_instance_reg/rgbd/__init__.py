"""RGB-D front end (no ROS).

- ``features``: SIFT extraction;  ``model``: the stored object model (file format, building);
- ``lifting``: robust depth lookup, undistortion, back-projection;  ``matching``: one-to-many;
- ``pipeline``: ``InstanceRegistration.register_frame(rgb, depth_m, intrinsics) -> FrameResult``.
"""
