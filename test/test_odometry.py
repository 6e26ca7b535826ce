"""The camera's motion from one frame to the next (tracking/odometry.py), on rendered frames
whose camera poses are known."""
import numpy as np
import pytest

from multi_instance_reg.synthetic.scene import make_tabletop_scene
from multi_instance_reg.tracking.odometry import CameraOdometry
from multi_instance_reg.transforms import invert_transform, make_transform, rotation_angle_deg


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def scene():
    """A still tabletop view, then the camera turned 6 deg about the table's vertical through
    a point 0.7 m ahead and shaken by 3 mm: a jump no ICP from the last pose reaches."""
    sc = make_tabletop_scene(instances=4, distractors=2, frames=3, seed=11, motion="static")
    P0 = sc.camera_poses[0]
    centre = P0[:3, 3] + 0.7 * P0[:3, 2]
    turn = make_transform(rot_z(6.0), centre - rot_z(6.0) @ centre)
    shake = make_transform(np.eye(3), [0.003, -0.001, 0.0])
    sc.camera_poses = [P0, turn @ P0 @ shake, P0]
    return sc


def truth(sc, a, b):
    """X_b = D X_a for camera optical frames a -> b."""
    return invert_transform(sc.camera_poses[b]) @ sc.camera_poses[a]


def test_a_jump_of_six_degrees_is_measured_well_within_the_icps_reach(scene):
    odo = CameraOdometry()
    frames = [scene.render_frame(k) for k in range(3)]
    assert odo.step(frames[0].rgb, frames[0].depth_mm / 1000.0, scene.intrinsics, frames[0].stamp_ns) is None
    for k in (1, 2):
        D = odo.step(frames[k].rgb, frames[k].depth_mm / 1000.0, scene.intrinsics, frames[k].stamp_ns)
        E = D @ invert_transform(truth(scene, k - 1, k))
        assert rotation_angle_deg(truth(scene, k - 1, k)[:3, :3]) > 5.9
        assert rotation_angle_deg(E[:3, :3]) < 0.3 and np.linalg.norm(E[:3, 3]) < 0.003
        assert odo.inliers >= 50


def test_no_motion_where_it_cannot_be_told(scene):
    frame = scene.render_frame(0)
    depth = frame.depth_mm / 1000.0
    odo = CameraOdometry()
    # No texture: nothing to match.
    grey = np.full_like(frame.rgb, 128)
    odo.step(grey, depth, scene.intrinsics, 0)
    assert odo.step(grey, depth, scene.intrinsics, 1) is None
    # No colour, or no depth where the features are.
    assert odo.step(None, depth, scene.intrinsics, 2) is None
    odo.step(frame.rgb, np.zeros_like(depth), scene.intrinsics, 3)
    assert odo.step(frame.rgb, np.zeros_like(depth), scene.intrinsics, 4) is None
    # The stamps went back: the frame before is not this stream's past.
    odo.step(frame.rgb, depth, scene.intrinsics, 10)
    assert odo.step(frame.rgb, depth, scene.intrinsics, 5) is None
    D = odo.step(frame.rgb, depth, scene.intrinsics, 6)
    assert D is not None and rotation_angle_deg(D[:3, :3]) < 0.05 and np.linalg.norm(D[:3, 3]) < 0.001
