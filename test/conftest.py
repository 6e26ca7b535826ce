"""Shared, session-scoped test data: small synthetic bags from the generator and a model.

Fixtures (paths): ``capture_bag`` (the object alone, several views), ``capture_bags`` (that
and three more, the object resting on its top and long sides), ``scene_bag`` (several
instances plus distractors, with ground truth), ``object_model`` (built from capture_bags).

Each is built once per test run, also when pytest-xdist runs the tests in several worker
processes (``make test``): the first worker to ask builds it under a file lock in the run's
folder and the others read what it built (``built_once``); ``make test``'s two pytest runs
share one folder (MIREG_TEST_SHARED).
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
from pathlib import Path

import pytest

# Integration tests pick their own ROS_DOMAIN_ID; keep DDS discovery on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

SCENES = 3
SCENE_FRAMES = 2
CAPTURE_VIEWS = 8


@pytest.fixture(scope="session")
def built_once(tmp_path_factory):
    """``built_once(name, build)``: ``build(folder)``'s result (a Path or a list of Paths in
    ``folder``), built by one process of the run and shared by all of its workers."""
    if os.environ.get("MIREG_TEST_SHARED"):   # `make test`: shared by its two pytest runs
        root = Path(os.environ["MIREG_TEST_SHARED"])
    else:
        root = tmp_path_factory.getbasetemp()
        if os.environ.get("PYTEST_XDIST_WORKER"):
            root = root.parent   # pytest-N/, above each worker's popen-gwK/
    root = root / "built_once"
    root.mkdir(parents=True, exist_ok=True)

    def once(name: str, build):
        record = root / f"{name}.json"
        with open(root / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)   # the others wait here while one builds
            if not record.exists():
                folder = root / name
                shutil.rmtree(folder, ignore_errors=True)   # what a failed build left
                folder.mkdir()
                value = build(folder)
                many = isinstance(value, (list, tuple))
                record.write_text(json.dumps({"many": many, "paths": [str(v) for v in (value if many else [value])]}))
        saved = json.loads(record.read_text())
        paths = [Path(v) for v in saved["paths"]]
        return paths if saved["many"] else paths[0]
    return once


@pytest.fixture(scope="session")
def capture_bags(built_once):
    from multi_instance_reg.tools.bench.scenes import generate_capture_bags

    return built_once("capture_bags", lambda folder: generate_capture_bags(folder, seed=0, views=CAPTURE_VIEWS))


@pytest.fixture(scope="session")
def capture_bag(capture_bags):
    return capture_bags[0]      # the generator's own capture: the object upright


@pytest.fixture(scope="session")
def scene_bag(built_once):
    """The benchmark's first scenes (4, 12 and 6 instances, 3 distractors each), 2 frames each."""
    from multi_instance_reg.tools.bench.scenes import generate_benchmark_bag

    return built_once("scene_bag", lambda folder: generate_benchmark_bag(folder / "scene", scenes=SCENES,
                                                                          frames=SCENE_FRAMES, seed=0))


@pytest.fixture(scope="session")
def object_model(capture_bags, built_once):
    from multi_instance_reg.models.model import save_model
    from multi_instance_reg.tools.bench.scenes import model_from_captures

    return built_once("object_model", lambda folder: save_model(model_from_captures(capture_bags), folder / "model.npz"))
