"""The node's parameters: config/params.yaml equals the code's defaults; descriptors carry ranges."""
from pathlib import Path

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from multi_instance_reg.errors import InputError
from multi_instance_reg.params import flatten, param_specs, read_params_yaml
from multi_instance_reg.rgbd.pipeline import PipelineConfig
from multi_instance_reg.ros.parameters import (READ_ONLY, NodeSettings, all_specs, check_parameters,
                                               default_params_yaml, descriptor,
                                               launch_model_parameters)
from multi_instance_reg.tracking import LiveConfig, TrackerConfig

PARAMS_FILE = Path(__file__).resolve().parents[1] / "config" / "params.yaml"


def test_params_file_holds_every_default_and_nothing_else():
    expected = {**flatten(NodeSettings()), **flatten(PipelineConfig()), **flatten(LiveConfig(), "tracking."),
                **flatten(TrackerConfig(), "tracking.")}
    expected = {k: list(v) if isinstance(v, tuple) else v for k, v in expected.items()}   # string arrays
    assert read_params_yaml(PARAMS_FILE) == expected
    # Types too: a float written as "1" would be declared as an integer by ROS and then refused.
    for name, value in read_params_yaml(PARAMS_FILE).items():
        assert type(value) is type(expected[name]), name


def test_params_file_is_the_generated_one():
    assert PARAMS_FILE.read_text() == default_params_yaml(), \
        "regenerate: python -m multi_instance_reg.ros.parameters > config/params.yaml"


def test_the_faster_shape_setting_changes_known_parameters_within_their_ranges():
    # config/shape_fast.yaml (docs/frontends.md, "A faster setting"): read as the node and the tools read it.
    from multi_instance_reg.tools.offline import load_config

    fast = read_params_yaml(PARAMS_FILE.parent / "shape_fast.yaml")
    defaults = read_params_yaml(PARAMS_FILE)
    assert fast and set(fast) <= set(defaults)
    assert all(fast[k] != defaults[k] and type(fast[k]) is type(defaults[k]) for k in fast)
    specs = {s.name: s for s in all_specs()}
    assert check_parameters(specs, [Parameter(k, value=v) for k, v in fast.items()]) is None
    config = load_config(PARAMS_FILE.parent / "shape_fast.yaml")
    assert config.frontend.shape_pose_clusters == fast["frontend.shape_pose_clusters"]
    assert config.ecc.max_correspondences == fast["ecc.max_correspondences"]


def test_descriptors_carry_type_description_and_range():
    specs = {s.name: s for s in all_specs()}
    d = descriptor(specs["ecc.inlier_thresh"])
    assert d.type == ParameterType.PARAMETER_DOUBLE and d.description
    assert d.floating_point_range[0].from_value == specs["ecc.inlier_thresh"].low
    d = descriptor(specs["frontend.depth_window"])
    assert d.type == ParameterType.PARAMETER_INTEGER
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (1, 31)
    d = descriptor(specs["qos_reliability"], read_only=True)
    assert d.read_only and "best_effort" in d.additional_constraints
    assert descriptor(specs["frontend.refine"]).type == ParameterType.PARAMETER_BOOL


def test_every_tracker_setting_is_a_ranged_node_parameter():
    specs = {s.name: s for s in all_specs()}
    for spec in [*param_specs(TrackerConfig(), "tracking."), *param_specs(LiveConfig(), "tracking.")]:
        assert specs[spec.name] == spec and spec.description
        d = descriptor(spec)
        if spec.type is float:
            assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (spec.low, spec.high)
        elif spec.type is int:
            assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (spec.low, spec.high)
    assert specs["tracking.publish_tentative"].default is False        # only confirmed/coasting by default
    assert specs["tracking.enabled"].default is True and "tracking.enabled" in READ_ONLY
    assert "tracking.catch_up_frames" in READ_ONLY and specs["tracking.catch_up_frames"].high == 90
    assert descriptor(specs["tracking.enabled"], read_only=True).read_only
    assert (specs["detector_niceness"].low, specs["detector_niceness"].high) == (0, 19)


@pytest.mark.parametrize("name, value, ok", [
    ("ecc.inlier_thresh", 0.02, True),
    ("ecc.inlier_thresh", -1.0, False),
    ("frontend.depth_window", 99, False),
    ("qos_reliability", "sometimes", False),
    ("sync_slop_s", 0.05, True),
    ("no.such_parameter", 1, False),
    ("tracking.smoothing", 0.5, True),
    ("tracking.smoothing", 0.99, False),
    ("tracking.coast_s", -1.0, False),
    ("tracking.icp_points", 10, False),
    ("tracking.publish_tentative", 1, False),
    ("tracking.enabled", False, True),
    ("detector_niceness", 20, False),
])
def test_check_parameters_gives_a_reason(name, value, ok):
    specs = {s.name: s for s in all_specs()}
    reason = check_parameters(specs, [Parameter(name, value=value)])
    assert (reason is None) == ok
    if not ok:
        assert name.split(".")[-1] in reason


@pytest.mark.parametrize("text, expected", [
    ("", None),
    ("[a.npz, /abs/b.npz]", ["a.npz", "/abs/b.npz"]),
    ("a.npz, b.npz", ["a.npz", "b.npz"]),
    ("only.npz", ["only.npz"]),
])
def test_the_launch_file_takes_model_paths_as_a_list_or_comma_separated(text, expected):
    params = launch_model_parameters("one.npz", text)
    assert params["model_path"] == "one.npz"
    assert params.get("model_paths") == expected


@pytest.mark.parametrize("text", ["[a.npz, [b.npz]]", "[a.npz", "[1, 2]"])
def test_the_launch_file_refuses_model_paths_that_are_no_list_of_files(text):
    with pytest.raises(InputError, match="model_paths"):
        launch_model_parameters("", text)
