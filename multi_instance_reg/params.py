"""Declarative parameters: one dataclass field = one tunable setting, with its range.

The same declarations feed the ROS node (declare_parameter with a descriptor and a range),
the YAML file (``config/params.yaml``, read by both the node and ``mireg offline``) and the
command line (``mireg register --inlier-thresh 0.02``). Nested dataclasses become dotted
names: ``ecc.inlier_thresh``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from .errors import InputError


def param(default, description: str, low=None, high=None, choices: tuple | None = None):
    """A dataclass field carrying a description and an allowed range (inclusive)."""
    return field(default=default, metadata={
        "description": description, "low": low, "high": high, "choices": choices})


@dataclass(frozen=True)
class ParamSpec:
    name: str          # dotted name, e.g. "ecc.inlier_thresh"
    default: Any
    type: type
    description: str
    low: Any = None
    high: Any = None
    choices: tuple | None = None

    def check(self, value):
        """Return value converted to the declared type, or raise InputError saying why."""
        if self.type is bool:
            if not isinstance(value, bool):
                raise InputError(f"parameter {self.name} must be true or false, got {value!r}")
        elif self.type is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise InputError(f"parameter {self.name} must be an integer, got {value!r}")
        elif self.type is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise InputError(f"parameter {self.name} must be a number, got {value!r}")
            value = float(value)
        elif self.type is str:
            if not isinstance(value, str):
                raise InputError(f"parameter {self.name} must be a string, got {value!r}")
        elif self.type is tuple:   # a list of strings (a ROS string array)
            if value is None:      # an empty array in a ROS parameter file arrives unset
                value = ()
            if isinstance(value, str) or not all(isinstance(v, str) for v in value):
                raise InputError(f"parameter {self.name} must be a list of strings, got {value!r}")
            return tuple(value)
        if self.low is not None and value < self.low or self.high is not None and value > self.high:
            raise InputError(
                f"parameter {self.name}={value!r} is out of range [{self.low}, {self.high}]")
        if self.choices is not None and value not in self.choices:
            raise InputError(f"parameter {self.name}={value!r} must be one of {list(self.choices)}")
        return value


def param_specs(config, prefix: str = "") -> Iterator[ParamSpec]:
    """Every leaf setting of a (nested) parameter dataclass, in declaration order."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        name = prefix + f.name
        if dataclasses.is_dataclass(value):
            yield from param_specs(value, name + ".")
            continue
        meta = f.metadata
        yield ParamSpec(name, value, type(value), meta.get("description", ""),
                        meta.get("low"), meta.get("high"), meta.get("choices"))


def flatten(config, prefix: str = "") -> dict[str, Any]:
    return {spec.name: spec.default for spec in param_specs(config, prefix)}


def with_overrides(config, overrides: dict[str, Any]):
    """A copy of ``config`` with dotted-name overrides applied, each checked against its spec."""
    specs = {s.name: s for s in param_specs(config)}
    unknown = sorted(set(overrides) - set(specs))
    if unknown:
        raise InputError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(specs)}")
    grouped: dict[str, dict[str, Any]] = {}
    leaves: dict[str, Any] = {}
    for name, value in overrides.items():
        value = specs[name].check(value)
        head, _, rest = name.partition(".")
        if rest:
            grouped.setdefault(head, {})[rest] = value
        else:
            leaves[head] = value
    for head, sub in grouped.items():
        leaves[head] = with_overrides(getattr(config, head), sub)
    return dataclasses.replace(config, **leaves)


def _flatten_mapping(mapping: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for key, value in mapping.items():
        if isinstance(value, dict):
            out.update(_flatten_mapping(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def read_params_yaml(path, node_name: str = "instance_registration") -> dict[str, Any]:
    """Dotted-name parameters from a ROS 2 parameter file (``node: ros__parameters: ...``).

    Accepts the node's own name, ``/**/name`` (the node in any namespace), ``/**`` (every
    node) or a bare mapping of parameters.
    """
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise InputError(f"parameter file {path} does not exist") from None
    except yaml.YAMLError as exc:
        raise InputError(f"parameter file {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"parameter file {path} must hold a mapping of parameters")
    for key in (node_name, "/" + node_name, "/**/" + node_name, "/**"):
        if isinstance(data.get(key), dict) and "ros__parameters" in data[key]:
            return _flatten_mapping(data[key]["ros__parameters"] or {})
    if any(isinstance(v, dict) and "ros__parameters" in v for v in data.values()):
        raise InputError(f"parameter file {path} has no section for node '{node_name}' or '/**'")
    return _flatten_mapping(data)
