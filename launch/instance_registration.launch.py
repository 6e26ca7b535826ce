"""Start the instance_registration node behind a RealSense driver (full ROS 2 install).

    ros2 launch multi_instance_reg instance_registration.launch.py model_path:=/path/model.npz

The camera topics default to realsense-ros' (with align_depth.enable:=true); point them
elsewhere with colour_topic:=... depth_topic:=... camera_info_topic:=... Every name is
relative: namespace:=/left moves the camera topics (/left/camera/camera/color/...) and the
node's outputs (/left/instances/...) together, one node per camera.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("multi_instance_reg"), "config", "params.yaml")
    args = {
        "model_path": ("", "object model file (mireg build-model)"),
        "params_file": (default_params, "ROS 2 parameter file with the node's settings"),
        "namespace": ("", "namespace of the node, its inputs and its outputs (e.g. /left)"),
        "colour_topic": ("camera/camera/color/image_raw", "colour image topic"),
        "depth_topic": ("camera/camera/aligned_depth_to_color/image_raw", "depth aligned to colour"),
        "camera_info_topic": ("camera/camera/color/camera_info", "colour camera_info topic"),
    }
    node = Node(
        package="multi_instance_reg",
        executable="instance_registration_node",
        name="instance_registration",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        parameters=[LaunchConfiguration("params_file"), {"model_path": LaunchConfiguration("model_path")}],
        remappings=[
            ("camera/camera/color/image_raw", LaunchConfiguration("colour_topic")),
            ("camera/camera/aligned_depth_to_color/image_raw", LaunchConfiguration("depth_topic")),
            ("camera/camera/color/camera_info", LaunchConfiguration("camera_info_topic")),
        ],
    )
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=value, description=text) for name, (value, text) in args.items()]
        + [node])
