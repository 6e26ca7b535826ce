"""Start the instance_registration node behind a RealSense driver (full ROS 2 install).

    ros2 launch multi_instance_reg instance_registration.launch.py model_path:=/path/model.npz
    ros2 launch multi_instance_reg instance_registration.launch.py model_paths:='[/path/a.npz, /path/b.npz]'

Several objects: ``model_paths`` as a YAML list or comma-separated (a.npz,b.npz); with
``model_path`` too, both are loaded.

The camera topics default to realsense-ros' (with align_depth.enable:=true); point them
elsewhere with colour_topic:=... depth_topic:=... camera_info_topic:=... Every name is
relative: namespace:=/left moves the camera topics (/left/camera/camera/color/...) and the
node's outputs (/left/instances/...) together, one node per camera.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("multi_instance_reg"), "config", "params.yaml")
    args = {
        "model_path": ("", "object model file (mireg build-model)"),
        "model_paths": ("", "several object model files, one per object: '[a.npz, b.npz]' or a.npz,b.npz"),
        "params_file": (default_params, "ROS 2 parameter file with the node's settings"),
        "namespace": ("", "namespace of the node, its inputs and its outputs (e.g. /left)"),
        "colour_topic": ("camera/camera/color/image_raw", "colour image topic"),
        "depth_topic": ("camera/camera/aligned_depth_to_color/image_raw", "depth aligned to colour"),
        "camera_info_topic": ("camera/camera/color/camera_info", "colour camera_info topic"),
    }
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=value, description=text) for name, (value, text) in args.items()]
        + [OpaqueFunction(function=node_with_models)])


def node_with_models(context):
    """The node, its model parameters read from the launch arguments (a list needs parsing,
    which a plain substitution cannot do)."""
    from multi_instance_reg.ros.parameters import launch_model_parameters

    models = launch_model_parameters(LaunchConfiguration("model_path").perform(context),
                                     LaunchConfiguration("model_paths").perform(context))
    return [Node(
        package="multi_instance_reg",
        executable="instance_registration_node",
        name="instance_registration",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        parameters=[LaunchConfiguration("params_file"), models],
        remappings=[
            ("camera/camera/color/image_raw", LaunchConfiguration("colour_topic")),
            ("camera/camera/aligned_depth_to_color/image_raw", LaunchConfiguration("depth_topic")),
            ("camera/camera/color/camera_info", LaunchConfiguration("camera_info_topic")),
        ],
    )]
