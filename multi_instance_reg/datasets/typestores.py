"""rosbags type stores with the one message type of realsense-ros' that the bags use.

realsense-ros publishes the depth-to-colour extrinsics as realsense2_camera_msgs/Extrinsics,
which has no Python package outside a realsense-ros install. Its definition (two fixed
arrays; the rotation column-major, as librealsense's rs2_extrinsics) is registered here, so
bags without message definitions of their own (older rosbag2 versions) read it, and the
synthetic bags write it with its definition inside.
"""
from __future__ import annotations

import functools

EXTRINSICS_TYPE = "realsense2_camera_msgs/msg/Extrinsics"
EXTRINSICS_MSG = """\
# Cross-stream extrinsics: encodes the topology describing how the different devices are oriented
float64[9] rotation     # Column - major 3x3 rotation matrix
float64[3] translation  # Three-element translation vector, in meters
"""


@functools.lru_cache(maxsize=None)
def ros2_typestore():
    """ROS 2 Jazzy's message types plus realsense2_camera_msgs/Extrinsics (shared, not to be changed)."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(EXTRINSICS_MSG, EXTRINSICS_TYPE))
    return store


@functools.lru_cache(maxsize=None)
def ros1_typestore():
    """ROS 1 Noetic's message types (what the RealSense Viewer's .bag files hold)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC)
