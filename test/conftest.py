"""Shared, session-scoped test data: small synthetic bags from the generator and a model.

Fixtures (paths): ``capture_bag`` (the object alone, several views), ``scene_bag`` (several
instances plus distractors, with ground truth), ``object_model`` (built from capture_bag).
"""
from __future__ import annotations

import os

import pytest

# Integration tests pick their own ROS_DOMAIN_ID; keep DDS discovery on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

SCENE_OBJECT = None        # the generator's default object
SCENE_FRAMES = 6
SCENE_INSTANCES = 8
CAPTURE_VIEWS = 8


@pytest.fixture(scope="session")
def bag_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bags")


@pytest.fixture(scope="session")
def capture_bag(bag_dir):
    from multi_instance_reg.synthetic.scene import generate_capture_bag

    path = bag_dir / "capture"
    generate_capture_bag(path, seed=0, views=CAPTURE_VIEWS)
    return path


@pytest.fixture(scope="session")
def scene_bag(bag_dir):
    from multi_instance_reg.synthetic.scene import generate_scene_bag

    path = bag_dir / "scene"
    generate_scene_bag(path, instances=SCENE_INSTANCES, distractors=3, frames=SCENE_FRAMES, seed=1)
    return path


@pytest.fixture(scope="session")
def object_model(capture_bag, bag_dir):
    from multi_instance_reg.rgbd.model import BuildSettings, build_model, save_model
    from multi_instance_reg.tools.build_model import register_view_with_ecc, views_from_bag

    views, description = views_from_bag(capture_bag, None, None)
    model = build_model(views, BuildSettings(), name=(description or {}).get("name", ""),
                        register_view=register_view_with_ecc)
    return save_model(model, bag_dir / "model.npz")
