"""The generated inputs the benchmarks share (and the demo and the tests): capture bags of an
object in several resting poses, tabletop scene bags with ground truth, and the model that
``mireg build-model`` makes of the capture bags."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError

INSTANCES_PER_SCENE = (4, 12, 6, 10, 8, 5, 11, 7, 9)

# Rotation (object frame) that turns the upright object's "up" axis (+z) into another.
_TO_UP = {
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "+y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "-y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}
CAPTURE_POSES = ("+z", "-z", "+y", "-y")


def capture_scene_resting_on(up: str, object_name=None, seed: int = 0, views: int = 8):
    """The generator's capture scene with the object resting so that its ``up`` axis points
    up (the generator itself scans it upright): scanning an object in several resting poses
    is how its model gets to see every face."""
    from ...synthetic.scene import (DEFAULT_OBJECT, Placement, SyntheticScene, capture_viewpoints,
                                   make_capture_scene)

    base = make_capture_scene(object_name or DEFAULT_OBJECT, seed, views)
    if up == "+z":
        return base
    upright = base.placements[0]
    pose = upright.pose.copy()
    pose[:3, :3] = pose[:3, :3] @ _TO_UP[up].T
    pose[2, 3] = float(np.sum(np.abs(pose[2, :3]) * upright.spec.half_extents))   # lowest point on the table
    placement = Placement(upright.spec, pose, 0, "free")
    cameras = capture_viewpoints(placement, views, np.random.default_rng([seed, 5, CAPTURE_POSES.index(up)]))
    return SyntheticScene("capture", upright.spec, [placement], cameras, base.intrinsics, seed)


def generate_capture_bags(workdir: Path, object_name=None, seed: int = 0, views: int = 8,
                          poses=CAPTURE_POSES) -> list[Path]:
    """Capture bags of the object in several resting poses (default: on its bottom, top and
    both long sides)."""
    from ...synthetic.scene import write_scene_bag

    paths = []
    for up in poses:
        path = Path(workdir) / f"capture_{'pos' if up[0] == '+' else 'neg'}{up[1]}_up"
        write_scene_bag(capture_scene_resting_on(up, object_name, seed, views), path)
        paths.append(path)
    return paths


def generate_benchmark_bag(path: Path, object_name=None, scenes: int = 6, frames: int = 5, seed: int = 0,
                           instances_each: int = 0, depth_noise_correlation_px: float = 0.0) -> Path:
    """One bag holding ``scenes`` tabletop scenes (4 to 12 instances of the object, 3
    distractors each; seeds seed+100, seed+101, ...), ``frames`` consecutive frames of each,
    with ground truth: the benchmark's (and the tests') scene set. With a list of objects
    (mixed scenes), ``instances_each`` of each in every scene, so that the bag's one
    /ground_truth/object names every scene's instances. ``depth_noise_correlation_px``: see
    ``sensor.simulate_depth``."""
    from ...synthetic.scene import DEFAULT_OBJECT, make_tabletop_scene

    def scene(k):
        count = instances_each or INSTANCES_PER_SCENE[k % len(INSTANCES_PER_SCENE)]
        return make_tabletop_scene(object_name or DEFAULT_OBJECT, count, distractors=3, frames=frames, seed=seed + 100 + k)
    return write_scenes_bag(path, (scene(k) for k in range(scenes)), depth_noise_correlation_px)


def write_scenes_bag(path: Path, scenes, depth_noise_correlation_px: float = 0.0) -> Path:
    """Generated scenes one after the other in one bag at 30 Hz, with ground truth and the
    accelerometer; the first scene's object description stands for all."""
    from ...datasets.bag_writer import RealSenseBagWriter

    frame_period_ns = 33_333_333
    stamp = 1_700_000_000_000_000_000
    with RealSenseBagWriter(path) as bag:
        for k, scene in enumerate(scenes):
            scene.set_depth_noise_correlation(depth_noise_correlation_px)
            if k == 0:
                bag.write_object_description(stamp, scene.description())
            for frame in scene.frames():
                bag.write_accel_samples(stamp, *scene.accel_samples(frame.index))
                bag.write_frame(stamp, frame.rgb, frame.depth_mm, scene.intrinsics, poses=frame.poses,
                                visibility=frame.visibility)
                stamp += frame_period_ns
    return Path(path)


def model_from_captures(captures, ignore_ground_truth: bool = False) -> "object":
    """What ``build-model`` makes of the capture bags; ``ignore_ground_truth``: as of a real
    capture (views registered by texture), the first view's ground truth then giving the
    model's object frame for scoring only."""
    from ...models.model import BuildSettings, CaptureView, build_model
    from ...transforms import invert_transform
    from ..build_model import register_view_with_ecc, views_from_bag

    views, description = [], None
    for bag in captures:
        more, desc = views_from_bag(bag, None, None)
        views += more
        description = description or desc
    if not ignore_ground_truth:
        return build_model(views, BuildSettings(), name=(description or {}).get("name", ""),
                           register_view=register_view_with_ecc)
    if views[0].T_camera_object is None:
        raise InputError("--ignore-ground-truth scores the model against the captures' ground truth; these capture "
                         "bags have none")
    model = build_model([CaptureView(v.rgb, v.depth_m, v.intrinsics) for v in views], BuildSettings(),
                        name=(description or {}).get("name", ""), register_view=register_view_with_ecc)
    # The capture frame is the first placed view's (the first view's unless it was left out).
    model.T_object_model = invert_transform(views[model.capture_view].T_camera_object) @ model.T_capture_model
    return model
