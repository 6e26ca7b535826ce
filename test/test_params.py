import pytest

from multi_instance_reg.core import ECCConfig
from multi_instance_reg.errors import InputError
from multi_instance_reg.params import flatten, param_specs, read_params_yaml, with_overrides


def test_every_ecc_parameter_has_description_and_range():
    for spec in param_specs(ECCConfig()):
        assert spec.description, spec.name
        if spec.choices is not None:
            assert spec.default in spec.choices, spec.name
        else:
            assert spec.low is not None and spec.high is not None, spec.name
            assert spec.low <= spec.default <= spec.high, spec.name


def test_overrides_are_checked():
    cfg = with_overrides(ECCConfig(), {"inlier_thresh": 0.02, "min_cluster_size": 4})
    assert cfg.inlier_thresh == 0.02 and cfg.min_cluster_size == 4
    with pytest.raises(InputError, match="out of range"):
        with_overrides(ECCConfig(), {"gamma_thresh": 1.5})
    with pytest.raises(InputError, match="integer"):
        with_overrides(ECCConfig(), {"min_cluster_size": 2.5})
    with pytest.raises(InputError, match="unknown parameter"):
        with_overrides(ECCConfig(), {"inlier_treshold": 1})
    assert flatten(ECCConfig())["inlier_thresh"] == 0.3


def test_read_ros_parameter_file(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("instance_registration:\n  ros__parameters:\n    ecc:\n      inlier_thresh: 0.01\n    model_path: m.npz\n")
    assert read_params_yaml(f) == {"ecc.inlier_thresh": 0.01, "model_path": "m.npz"}
    f.write_text("/**:\n  ros__parameters:\n    a: 1\n")
    assert read_params_yaml(f) == {"a": 1}
    f.write_text("/**/instance_registration:\n  ros__parameters:\n    a: 2\n")   # any namespace
    assert read_params_yaml(f) == {"a": 2}
    f.write_text("other_node:\n  ros__parameters:\n    a: 1\n")
    with pytest.raises(InputError, match="no section"):
        read_params_yaml(f)
    f.write_text("a: [1, 2\n")
    with pytest.raises(InputError, match="not valid YAML"):
        read_params_yaml(f)
    with pytest.raises(InputError, match="does not exist"):
        read_params_yaml(tmp_path / "missing.yaml")
