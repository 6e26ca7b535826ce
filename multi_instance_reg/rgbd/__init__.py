"""The per-frame pipeline and what it shares between the front ends (no ROS).

- ``pipeline``: ``InstanceRegistration.register_frame(rgb, depth_m, intrinsics) -> FrameResult``.
- ``multi_model``: several objects' models in one pass over a frame.
- ``lifting``: robust depth lookup, undistortion, back-projection;  ``depth_noise``: the sensor's noise from the frame.
- ``verify``: checks of a pose against the depth image (the acceptors).
- ``workspace``: the box / image mask the search keeps to;  ``overlay``: the debug picture.
"""
