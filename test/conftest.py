"""Shared, session-scoped test data: small synthetic bags from the generator and a model.

Fixtures (paths): ``capture_bag`` (the object alone, several views), ``capture_bags`` (that
and three more, the object resting on its top and long sides), ``scene_bag`` (several
instances plus distractors, with ground truth), ``object_model`` (built from capture_bags).
"""
from __future__ import annotations

import os

import pytest

# Integration tests pick their own ROS_DOMAIN_ID; keep DDS discovery on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

SCENES = 3
SCENE_FRAMES = 2
CAPTURE_VIEWS = 8


@pytest.fixture(scope="session")
def bag_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bags")


@pytest.fixture(scope="session")
def capture_bags(bag_dir):
    from multi_instance_reg.tools.bench_frames import generate_capture_bags

    return generate_capture_bags(bag_dir, seed=0, views=CAPTURE_VIEWS)


@pytest.fixture(scope="session")
def capture_bag(capture_bags):
    return capture_bags[0]      # the generator's own capture: the object upright


@pytest.fixture(scope="session")
def scene_bag(bag_dir):
    """The benchmark's first scenes (4, 12 and 6 instances, 3 distractors each), 2 frames each."""
    from multi_instance_reg.tools.bench_frames import generate_benchmark_bag

    return generate_benchmark_bag(bag_dir / "scene", scenes=SCENES, frames=SCENE_FRAMES, seed=0)


@pytest.fixture(scope="session")
def object_model(capture_bags, bag_dir):
    from multi_instance_reg.rgbd.model import save_model
    from multi_instance_reg.tools.bench_frames import model_from_captures

    return save_model(model_from_captures(capture_bags), bag_dir / "model.npz")
