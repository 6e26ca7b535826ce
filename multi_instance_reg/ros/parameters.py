"""ROS parameters from the project's declarative settings (``multi_instance_reg.params``).

One ROS parameter per ParamSpec, with its description and range in the descriptor, so
``ros2 param describe`` shows them and out-of-range sets are refused with a reason. The
node's own settings are declared the same way (``NodeSettings``); the pipeline's come from
``param_specs(PipelineConfig())`` under their dotted names (``ecc.inlier_thresh``), the
tracker's from ``TrackerConfig`` and ``LiveConfig`` under ``tracking.`` (``tracking.coast_s``,
``tracking.enabled``).
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

from ..errors import InputError
from ..params import ParamSpec, param, param_specs

_ROS_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
              float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
              tuple: ParameterType.PARAMETER_STRING_ARRAY}


@dataclass(frozen=True)
class NodeSettings:
    """Settings of the ROS wrapper itself (the algorithm's live in PipelineConfig)."""
    model_path: str = param("", "object model file built by `mireg build-model` (read-only: fixed at start-up; "
                                "for several objects, or to change them at run time, use model_paths)")
    model_paths: tuple = param((), "object model files, one per object (`mireg build-model --name`; names must differ), "
                                   "found together in one SIFT pass; settable at run time (models are loaded and "
                                   "unloaded without a restart). With model_path too, both are loaded (model_path first)")
    sync_slop_s: float = param(0.02, "largest stamp difference between a colour and a depth image that still pair up (s)", 0.0, 1.0)
    qos_reliability: str = param("reliable", "subscription reliability (read-only); best_effort loses large frames over Fast DDS",
                                 choices=("reliable", "best_effort"))
    image_transport: str = param("raw", "how the images arrive (read-only): raw (sensor_msgs/Image on the colour and depth "
                                        "topics) or compressed (sensor_msgs/CompressedImage on <colour topic>/compressed, JPEG or "
                                        "PNG, and <depth topic>/compressedDepth, PNG, as image_transport publishes them)",
                                 choices=("raw", "compressed"))
    qos_depth: int = param(10, "subscription and publisher queue depth (read-only)", 1, 1000)
    pipeline_processes: int = param(1, "pipeline processes taking frames in turn (read-only); a second one shortens the wait "
                                       "for a busy pipeline when a core is free for it", 1, 8)
    wait_for_fresher: bool = param(True, "when the newest frame has waited more than half a frame interval for the busy pipeline, "
                                         "take the next one (due sooner) instead: at 30 Hz ~13 ms less latency for ~4 % fewer frames processed")
    depth_scale: float = param(0.001, "metres per unit of a 16UC1 depth image (realsense-ros: 0.001, millimetres)", 1e-6, 1.0)
    publish_debug_image: bool = param(False, "draw and publish the debug image on every frame even with no subscriber "
                                             "(it is drawn whenever someone subscribes)")
    stats_log_period_s: float = param(5.0, "how often frame counts and latency are logged and published on ~/stats (s)", 0.1, 3600.0)
    gravity_source: str = param("imu", "where each frame's direction of gravity comes from (the shape path takes the support "
                                       "below the objects along it, frontend.shape_gravity_tolerance_deg): imu = the camera's "
                                       "accelerometer on camera/camera/accel/sample (realsense-ros enable_accel:=true; remap it to "
                                       "camera/camera/imu for unite_imu_method), its samples of the 0.1 s before each frame "
                                       "averaged; while none arrive (or they are stale, or far from 1 g) a frame goes without, as "
                                       "with none: the largest support plane counts as below",
                                choices=("imu", "none"))
    detector_niceness: int = param(10, "niceness added to the pipeline (detector) processes while tracking is on (read-only), "
                                       "so that the tracking of every camera frame wins the CPU over full detections", 0, 19)


# Fixed for the node's lifetime: they shape subscriptions or the loaded model.
READ_ONLY = frozenset({"model_path", "qos_reliability", "image_transport", "qos_depth", "pipeline_processes", "detector_niceness",
                       "tracking.enabled", "tracking.catch_up_frames"})


def descriptor(spec: ParamSpec, read_only: bool = False) -> ParameterDescriptor:
    description = spec.description
    if spec.choices:
        description += f" (one of: {', '.join(map(str, spec.choices))})"
    desc = ParameterDescriptor(name=spec.name, type=_ROS_TYPES[spec.type],
                               description=description, read_only=read_only)
    if spec.choices:
        desc.additional_constraints = "one of: " + ", ".join(map(str, spec.choices))
    if spec.low is not None and spec.high is not None:
        if spec.type is int:
            desc.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)]
        elif spec.type is float:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    return desc


def declare(node, specs, read_only=frozenset()) -> dict:
    """Declare one parameter per spec (the value from a params file or ``-p`` wins over the
    default) and return {name: value}, each checked against its spec (InputError if not)."""
    from rclpy.parameter import Parameter

    values = {}
    for spec in specs:
        # rclpy cannot tell an empty list's type: a string array is declared by its type, and
        # without a value from a file or -p it is set to [] at once.
        default = Parameter.Type.STRING_ARRAY if spec.type is tuple else spec.default
        try:
            p = node.declare_parameter(spec.name, default, descriptor(spec, spec.name in read_only))
            if spec.type is tuple and p.value is None:
                p = Parameter(spec.name, Parameter.Type.STRING_ARRAY, [])
                node.set_parameters([p])
        except Exception as exc:  # rclpy refuses a value of the wrong type or out of range
            raise InputError(f"parameter {spec.name}: {exc}") from None
        values[spec.name] = spec.check(p.value)
    return values


def check_parameters(specs: dict[str, ParamSpec], params) -> str | None:
    """None if every rclpy Parameter in ``params`` is acceptable, else the reason why not."""
    for p in params:
        spec = specs.get(p.name)
        if spec is None:
            return f"unknown parameter {p.name}"
        try:
            spec.check(p.value)
        except InputError as exc:
            return str(exc)
    return None


def node_settings(values: dict) -> NodeSettings:
    return NodeSettings(**{k: v for k, v in values.items() if k in NodeSettings.__dataclass_fields__})


def launch_model_parameters(model_path: str, model_paths: str) -> dict:
    """The node's model parameters from the launch file's text arguments: ``model_path`` as
    it is, ``model_paths`` as a YAML list ("[a.npz, b.npz]") or comma-separated ("a.npz,b.npz").
    An empty ``model_paths`` is left out, so that the parameter file's value stands (and ROS
    could not tell the type of an empty list)."""
    import yaml

    text = model_paths.strip()
    try:
        value = yaml.safe_load(text) if text.startswith("[") else [p.strip() for p in text.split(",") if p.strip()]
    except yaml.YAMLError as exc:
        raise InputError(f"model_paths:={model_paths!r} is not a list: {str(exc).splitlines()[0]}; "
                         f"give model_paths:='[a.npz, b.npz]' or model_paths:=a.npz,b.npz") from None
    if not isinstance(value, list) or not all(isinstance(p, str) and p for p in value):
        raise InputError(f"model_paths:={model_paths!r} is not a list of file names; "
                         f"give model_paths:='[a.npz, b.npz]' or model_paths:=a.npz,b.npz")
    return {"model_path": model_path, **({"model_paths": value} if value else {})}


def node_specs() -> list[ParamSpec]:
    return list(param_specs(NodeSettings()))


def tracking_specs() -> list[ParamSpec]:
    """The live stream's tracking settings and the tracker's, as ``tracking.NAME``."""
    from ..tracking import LiveConfig, TrackerConfig

    return [*param_specs(LiveConfig(), "tracking."), *param_specs(TrackerConfig(), "tracking.")]


def all_specs() -> list[ParamSpec]:
    """Every parameter of the node, in the order of config/params.yaml."""
    from ..rgbd.pipeline import PipelineConfig

    return [*node_specs(), *param_specs(PipelineConfig()), *tracking_specs()]


def _yaml_scalar(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)
        mantissa, e, exponent = text.partition("e")
        if "." not in mantissa:  # YAML 1.1 readers need the dot to see a float ("1.0e-06")
            mantissa += ".0"
        return mantissa + e + exponent
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, tuple):
        return json.dumps(list(value))
    return str(value)


def default_params_yaml(node_name: str = "instance_registration", values: dict | None = None,
                        header: list[str] | None = None) -> str:
    """config/params.yaml: every node and pipeline parameter with its default and description,
    nested as ROS 2 parameter files expect (``frontend:`` / ``ecc:`` for dotted names).
    ``values``: dotted names whose value replaces the default (``mireg tune``'s settings),
    ``header``: the comment lines on top instead of config/params.yaml's."""
    values = values or {}
    unknown = sorted(set(values) - {spec.name for spec in all_specs()})
    if unknown:
        raise InputError(f"unknown parameter(s) {', '.join(unknown)}")
    lines = [f"# {line}" for line in header] if header is not None else [
        "# Every parameter of the instance_registration node with its default.",
        "# Generated by `python -m multi_instance_reg.ros.parameters > config/params.yaml`;",
        "# a unit test checks that it matches the code. Change values in a copy of this file."]
    lines += [f"# '/**/{node_name}': the node in any namespace (a bare name matches only the root one's).",
              f"/**/{node_name}:", "  ros__parameters:"]
    open_groups: list[str] = []
    for spec in all_specs():
        *groups, leaf = spec.name.split(".")
        if groups != open_groups:
            for depth, group in enumerate(groups):
                if depth >= len(open_groups) or open_groups[depth] != group:
                    lines.append("    " + "  " * depth + f"{group}:")
            open_groups = groups
        indent = "    " + "  " * len(groups)
        ranged = f" [{spec.low}, {spec.high}]" if spec.low is not None and spec.high is not None else ""
        choices = f" (one of: {', '.join(spec.choices)})" if spec.choices else ""
        lines.append(f"{indent}# {spec.description}{ranged}{choices}")
        lines.append(f"{indent}{leaf}: {_yaml_scalar(spec.check(values[spec.name]) if spec.name in values else spec.default)}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(default_params_yaml())
