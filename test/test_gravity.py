"""The direction of gravity from the camera's accelerometer: averaged per frame, carried by
bags (synthetic ones hold it, readers find it), and used by the shape front end to take the
support below the objects along it rather than the frame's largest plane (a wall)."""
import numpy as np
import pytest

from multi_instance_reg.datasets.bag_writer import RealSenseBagWriter
from multi_instance_reg.datasets.rgbd_bag import RGBDBag
from multi_instance_reg.errors import InputError
from multi_instance_reg.gravity import IMU_TOPIC, AccelWindow, up_from_samples
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.frontends.shape.segments import support_mask


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def test_accel_window_averages_the_samples_just_before_a_frame():
    w = AccelWindow(window_ns=100_000_000)
    rng = np.random.default_rng(0)
    up = np.array([0.0, -0.8, -0.6])                      # a camera looking down at 37 deg
    for k in range(100):                                   # 0.5 s at 200 Hz
        w.add(k * 5_000_000, 9.81 * up + rng.normal(0.0, 0.05, 3))
    assert _angle_deg(w.up_at(400_000_000), up) < 0.5
    assert np.isclose(np.linalg.norm(w.up_at(400_000_000)), 1.0)
    assert w.up_at(2_000_000_000) is None                 # stale: nothing in the window before it
    assert w.up_at(-1) is None                            # before the first sample
    # Knocked or swung hard: the mean is far from 1 g, no gravity reading.
    assert up_from_samples([[0.0, -3.0, 0.0]]) is None and up_from_samples([]) is None
    assert _angle_deg(up_from_samples([[0.0, -9.5, 0.3]]), [0.0, -1.0, 0.0]) < 2.0


def _floor_and_larger_wall():
    """A camera 1 m above a floor, looking 20 deg down at a wall 1.4 m ahead: the wall fills
    most of the image, the floor the lower part. Returns depth, intrinsics and the true up
    (camera frame)."""
    intr = CameraIntrinsics(K=np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]]), width=320, height=240)
    pitch = np.radians(20.0)
    # Camera axes in the world (x right, y forward, z up): optical z forward and 20 deg down, y down.
    z = np.array([0.0, np.cos(pitch), -np.sin(pitch)])
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])                         # camera -> world
    v, u = np.mgrid[0:240, 0:320]
    rays = np.stack([(u - 160) / 300.0, (v - 120) / 300.0, np.ones_like(u, float)], -1) @ R.T
    with np.errstate(divide="ignore"):
        t_floor = np.where(rays[..., 2] < 0, -1.0 / rays[..., 2], np.inf)     # floor z = -1 (camera at 0)
        t_wall = np.where(rays[..., 1] > 0, 1.4 / rays[..., 1], np.inf)       # wall y = 1.4
    depth = np.minimum(t_floor, t_wall).astype(np.float32)
    depth[~np.isfinite(depth)] = 0.0
    return depth, intr, R.T @ np.array([0.0, 0.0, 1.0])


def test_support_below_follows_gravity_not_the_larger_wall():
    depth, intr, up = _floor_and_larger_wall()
    valid = depth > 0
    planes, ground = [], []
    support_mask(depth, intr, valid, 0.2, 0.004, 0.002, ground=ground, planes=planes)
    assert len(planes) == 2
    wall_normal = ground[0]
    assert _angle_deg(wall_normal, up) > 80                # without gravity: the largest plane, the wall
    level = []
    tilted = up + np.array([0.15, 0.0, 0.0])               # a hand-held IMU reading ~9 deg off
    support_mask(depth, intr, valid, 0.2, 0.004, 0.002, ground=level, up=tilted / np.linalg.norm(tilted))
    assert _angle_deg(level[0], up) < 1.0                  # the floor's own normal, not the IMU's
    assert abs(level[1] - 1.0) < 0.02                      # and its offset: 1 m below the camera
    # No removed plane within the tolerance of "up" (30 deg off the floor, 60 off the wall):
    # the largest, as without gravity.
    off = np.cos(np.radians(30)) * up + np.sin(np.radians(30)) * wall_normal
    fallback = []
    support_mask(depth, intr, valid, 0.2, 0.004, 0.002, ground=fallback, up=off / np.linalg.norm(off))
    assert np.allclose(fallback[0], wall_normal)


def test_the_pipeline_takes_gravity_per_frame_and_checks_it():
    from multi_instance_reg.meshes import box_mesh
    from multi_instance_reg.models.mesh_model import build_model_from_mesh
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig, unit_up

    depth, intr, up = _floor_and_larger_wall()
    depth[150:200, 130:190] *= 0.9                         # something off the planes, for the frame to have points
    reg = InstanceRegistration(build_model_from_mesh(box_mesh(0.2, 0.15, 0.1), "box"), PipelineConfig())
    clouds = []
    original = reg._shape.frame_cloud
    reg._shape.frame_cloud = lambda *a: clouds.append(original(*a)) or clouds[-1]
    rgb = np.zeros(depth.shape + (3,), np.uint8)
    reg.register_frame(rgb, depth, intr)
    reg.register_frame(rgb, depth, intr, gravity=9.81 * up)     # any length: the accelerometer's reading
    assert _angle_deg(clouds[0].up, up) > 80 and _angle_deg(clouds[1].up, up) < 1.0
    assert unit_up(None) is None and np.allclose(unit_up([0.0, -2.0, 0.0]), [0.0, -1.0, 0.0])
    for bad in ([0.0, 0.0, 0.0], [1.0, np.nan, 0.0], [1.0, 0.0]):
        with pytest.raises(InputError, match="gravity"):
            reg.register_frame(rgb, depth, intr, gravity=bad)


def test_a_carton_fitted_into_a_crates_corner_is_rejected_with_gravity():
    """Held-out pallet seed 269 (scene 521, distractor-only): a crate's wall is the frame's
    largest plane, and a carton fitted into the crate's front corner passed the outline check
    with "below the object" taken from that wall. Given the direction of gravity, the support
    below is the floor, and the carton is rejected."""
    from multi_instance_reg.models.mesh_model import build_model_from_mesh
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.untextured import make_untextured_scene

    scene = make_untextured_scene("pallet", 0, 3, 1, 521)
    frame = scene.render_frame(0)
    depth = frame.depth_mm.astype(np.float32) / 1000.0
    up = frame.T_world_camera[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    reg = InstanceRegistration(build_model_from_mesh(object_mesh(get_object("carton")), "carton"), PipelineConfig())
    clouds = []
    original = reg._shape.frame_cloud
    reg._shape.frame_cloud = lambda *a: clouds.append(original(*a)) or clouds[-1]
    reg.register_frame(frame.rgb, depth, scene.intrinsics)
    with_gravity = reg.register_frame(frame.rgb, depth, scene.intrinsics, gravity=up)
    assert _angle_deg(clouds[0].up, up) > 60               # the wall, without gravity
    assert _angle_deg(clouds[1].up, up) < 5                # the floor, with it
    assert with_gravity.instances == []                    # no carton on a distractor-only frame


@pytest.mark.parametrize("imu", [True, False])
def test_synthetic_bags_carry_gravity_and_readers_find_it(tmp_path, imu):
    from multi_instance_reg.synthetic.scene import generate_scene_bag, make_tabletop_scene

    generate_scene_bag(tmp_path / "bag", instances=2, distractors=1, frames=3, seed=4, imu=imu)
    truth = make_tabletop_scene(instances=2, distractors=1, frames=3, seed=4).camera_poses
    with RGBDBag(tmp_path / "bag") as bag:
        frames = list(bag)
    assert len(frames) == 3
    for f, T in zip(frames, truth):
        if imu:
            # Hand-held: the sweep's own acceleration tilts the reading by a few degrees.
            assert _angle_deg(f.gravity, T[:3, :3].T @ [0.0, 0.0, 1.0]) < 12.0
        else:
            assert f.gravity is None
    if imu:
        with RGBDBag(tmp_path / "bag", accel_topic=None) as bag:      # ignored on request (A/B)
            assert all(f.gravity is None for f in bag)


def test_a_bag_with_the_united_imu_topic_only_is_read_too(tmp_path):
    """realsense-ros with unite_imu_method: accel and gyro on one topic, /camera/camera/imu."""
    intr = CameraIntrinsics(K=np.array([[300.0, 0, 32], [0, 300.0, 24], [0, 0, 1]]), width=64, height=48)
    up = np.array([0.0, -0.6, -0.8])
    with RealSenseBagWriter(tmp_path / "bag") as bag:
        bag.write_accel_samples(1_000_000_000, np.arange(-19, 1) * 5_000_000, np.tile(9.81 * up, (20, 1)),
                                topic=IMU_TOPIC)
        bag.write_frame(1_000_000_000, np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 800, np.uint16), intr)
    with RGBDBag(tmp_path / "bag") as reader:
        assert reader.accel_topic == IMU_TOPIC
        (frame,) = list(reader)
    assert _angle_deg(frame.gravity, up) < 1e-6
