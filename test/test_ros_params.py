"""The node's parameters: config/params.yaml equals the code's defaults; descriptors carry ranges."""
from pathlib import Path

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from multi_instance_reg.params import flatten, param_specs, read_params_yaml
from multi_instance_reg.rgbd.pipeline import PipelineConfig
from multi_instance_reg.ros.parameters import (NodeSettings, check_parameters, default_params_yaml, descriptor,
                                               node_specs)

PARAMS_FILE = Path(__file__).resolve().parents[1] / "config" / "params.yaml"


def test_params_file_holds_every_default_and_nothing_else():
    expected = {**flatten(NodeSettings()), **flatten(PipelineConfig())}
    assert read_params_yaml(PARAMS_FILE) == expected
    # Types too: a float written as "1" would be declared as an integer by ROS and then refused.
    for name, value in read_params_yaml(PARAMS_FILE).items():
        assert type(value) is type(expected[name]), name


def test_params_file_is_the_generated_one():
    assert PARAMS_FILE.read_text() == default_params_yaml(), \
        "regenerate: python -m multi_instance_reg.ros.parameters > config/params.yaml"


def test_descriptors_carry_type_description_and_range():
    specs = {s.name: s for s in [*node_specs(), *param_specs(PipelineConfig())]}
    d = descriptor(specs["ecc.inlier_thresh"])
    assert d.type == ParameterType.PARAMETER_DOUBLE and d.description
    assert d.floating_point_range[0].from_value == specs["ecc.inlier_thresh"].low
    d = descriptor(specs["frontend.depth_window"])
    assert d.type == ParameterType.PARAMETER_INTEGER
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (1, 31)
    d = descriptor(specs["qos_reliability"], read_only=True)
    assert d.read_only and "best_effort" in d.additional_constraints
    assert descriptor(specs["frontend.refine"]).type == ParameterType.PARAMETER_BOOL


@pytest.mark.parametrize("name, value, ok", [
    ("ecc.inlier_thresh", 0.02, True),
    ("ecc.inlier_thresh", -1.0, False),
    ("frontend.depth_window", 99, False),
    ("qos_reliability", "sometimes", False),
    ("sync_slop_s", 0.05, True),
    ("no.such_parameter", 1, False),
])
def test_check_parameters_gives_a_reason(name, value, ok):
    specs = {s.name: s for s in [*node_specs(), *param_specs(PipelineConfig())]}
    reason = check_parameters(specs, [Parameter(name, value=value)])
    assert (reason is None) == ok
    if not ok:
        assert name.split(".")[-1] in reason
