"""multi_instance_reg: find every instance of a known object in RGB-D and publish its pose.

Layers, from the bottom up (only the last one imports ROS):
- ``core``: ECC multi-instance registration on an N x 6 correspondence array (numpy/scipy/numba).
- ``rgbd``: the RGB-D front end (SIFT, object model, depth lifting) and the per-frame pipeline.
- ``datasets``: reading and writing rosbag2 files with rosbags (no ROS install needed).
- ``synthetic``: correspondence sets and rendered D455 tabletop scenes with ground truth.
- ``tools``: the ``mireg`` command line.
- ``ros``: the rclpy node, a thin wrapper over the pipeline.
"""

__version__ = "0.1.0"
