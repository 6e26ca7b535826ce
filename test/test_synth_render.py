"""The synthetic renderer's pixels agree with its ground truth, and its sensor model does what
it says (no bag involved here; see test_synth_bag.py for that)."""
import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.synthetic import sensor
from multi_instance_reg.synthetic.objects import OBJECTS, get_object, object_textures
from multi_instance_reg.synthetic.preview import box_corners
from multi_instance_reg.synthetic.scene import (
    LABEL_DISTRACTOR, _lowest_z, _obb_overlap, make_capture_scene, make_tabletop_scene)
from multi_instance_reg.transforms import invert_transform


@pytest.fixture(scope="module", params=["snack_box", "can"])
def scene(request):
    # Boxes and cylinders have their own rasterisers: check both against the truth.
    return make_tabletop_scene(request.param, instances=6, distractors=4, frames=40, seed=5)


@pytest.fixture(scope="module")
def frames(scene):
    return [scene.render_frame(i) for i in (0, 20, 39)]


def surface_distance(spec, points):
    """Signed distance (m) of object-frame points to the object's surface."""
    h = spec.half_extents
    if spec.shape == "box":
        q = np.abs(points) - h
    else:
        q = np.stack([np.hypot(points[:, 0], points[:, 1]) - h[0], np.abs(points[:, 2]) - h[2]], axis=1)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def back_project(depth_m, K, mask):
    v, u = np.nonzero(mask)
    z = depth_m[v, u]
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


def object_points(frame, k, depth_m):
    mask = (frame.instance_mask == k) & (depth_m > 0)
    pts = back_project(depth_m, frame.K, mask)
    T_obj_cam = invert_transform(frame.poses[k])
    return pts @ T_obj_cam[:3, :3].T + T_obj_cam[:3, 3], pts[:, 2]


def test_noise_free_depth_lies_on_the_object_surface(scene, frames):
    spec = scene.target
    checked = 0
    for f in frames:
        for k in range(len(f.poses)):
            p, _ = object_points(f, k, f.depth_true_m)
            if len(p) == 0:
                continue
            checked += 1
            assert np.abs(surface_distance(spec, p)).max() < 5e-4, f"frame {f.index} instance {k}"
    assert checked >= 8


def test_sensor_depth_lies_on_the_surface_within_the_noise(scene, frames):
    spec = scene.target
    for f in frames:
        depth = f.depth_mm.astype(np.float64) / 1000.0
        for k in range(len(f.poses)):
            p, z = object_points(f, k, depth)
            if len(p) < 50:
                continue
            sigma = sensor.DEPTH_NOISE_PER_M * z ** 2
            err = np.abs(surface_distance(spec, p))
            # Quantisation to 1 mm adds up to 0.5 mm on top of the Gaussian noise.
            assert np.mean(err < 3 * sigma + 6e-4) > 0.98
            assert np.all(err < 6 * sigma + 1e-3)


def test_projected_ground_truth_boxes_enclose_the_object_pixels(scene, frames):
    corners = box_corners(scene.target.dimensions_m)
    for f in frames:
        for k, T in enumerate(f.poses):
            v, u = np.nonzero(f.instance_mask == k)
            if len(u) == 0:
                continue
            pc = corners @ T[:3, :3].T + T[:3, 3]
            assert np.all(pc[:, 2] > 0.2)
            uv = pc @ f.K.T
            uv = uv[:, :2] / uv[:, 2:3]
            assert u.min() >= np.floor(uv[:, 0].min()) - 1 and u.max() <= np.ceil(uv[:, 0].max()) + 1
            assert v.min() >= np.floor(uv[:, 1].min()) - 1 and v.max() <= np.ceil(uv[:, 1].max()) + 1


def test_frames_hold_what_the_api_promises(scene, frames):
    f = frames[0]
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
    assert f.depth_mm.shape == (480, 640) and f.depth_mm.dtype == np.uint16
    assert f.instance_mask.dtype == np.int16 and f.poses.shape == (6, 4, 4)
    assert set(np.unique(f.instance_mask)) <= set(range(6)) | {-1, LABEL_DISTRACTOR}
    assert np.allclose(f.K, sensor.d455_intrinsics("640x480").K)
    # Poses are proper rigid transforms, instances 0.3-1.6 m in front of the camera.
    for T in f.poses:
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    assert np.all((f.poses[:, 2, 3] > 0.3) & (f.poses[:, 2, 3] < 1.6))
    # Most instances are mostly visible in the default kind of scene.
    vis = np.stack([fr.visibility for fr in frames])
    assert np.all((vis >= 0) & (vis <= 1)) and np.mean(vis > 0.5) >= 0.6
    # The colour image has texture and noise, not flat fills.
    assert f.rgb.std() > 12 and len(np.unique(f.rgb.reshape(-1, 3), axis=0)) > 5000


def test_capture_sees_the_lone_object_from_all_sides_with_true_poses():
    cap = make_capture_scene("snack_box", seed=2, views=6)
    up = []
    for i in range(cap.num_frames):
        f = cap.render_frame(i)
        assert f.visibility.shape == (1,)
        assert f.visibility[0] > 0.98, (i, f.visibility)
        assert set(np.unique(f.instance_mask)) == {-1, 0}
        p, _ = object_points(f, 0, f.depth_true_m)
        assert len(p) > 500 and np.abs(surface_distance(cap.target, p)).max() < 5e-4
        up.append((f.T_world_camera @ f.poses[0])[2, 2])       # object z in world z
    # Turned over half way: first the +z face is up, then the -z face.
    assert np.allclose(up, [1, 1, 1, -1, -1, -1], atol=1e-9)


def test_same_seed_same_frames_other_seed_other_frames():
    a = make_tabletop_scene("can", instances=3, distractors=2, frames=5, seed=11).render_frame(4)
    b = make_tabletop_scene("can", instances=3, distractors=2, frames=5, seed=11).render_frame(4)
    c = make_tabletop_scene("can", instances=3, distractors=2, frames=5, seed=12).render_frame(4)
    for name in ("rgb", "depth_mm", "instance_mask", "poses", "visibility"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.rgb, c.rgb) and not np.allclose(a.poses, c.poses)


def test_placement_is_plausible_and_varied():
    kinds = set()
    for seed in range(4):
        sc = make_tabletop_scene("snack_bar", instances=12, distractors=5, frames=2, seed=seed)
        placed = sc.placements
        assert sum(p.is_instance for p in placed) == 12 and len(placed) == 17
        for i, a in enumerate(placed):
            assert _lowest_z(a.pose, a.spec.half_extents) > -1e-6       # nothing sinks into the table
            for b in placed[i + 1:]:
                assert not _obb_overlap(a.pose, a.spec.half_extents, b.pose, b.spec.half_extents, margin=-2e-4)
            if a.arrangement == "stacked":                              # rests on something
                assert _lowest_z(a.pose, a.spec.half_extents) > 0.005
        kinds |= {p.arrangement for p in placed}
        # Camera 0.4-1.5 m from the table centre, looking at it.
        for T_wc in sc.camera_poses:
            assert 0.4 <= np.linalg.norm(T_wc[:3, 3] - [0, 0, 0]) <= 1.5
    assert kinds == {"free", "touching", "stacked", "leaning"}


def test_instances_are_identical_and_faces_differ():
    tex = object_textures("snack_box")
    assert len(tex) == 6 and not np.array_equal(tex["+z"], tex["-z"])
    assert object_textures("snack_box") is tex                          # same pictures every time
    for spec in OBJECTS.values():
        assert spec.shape in ("box", "cylinder") and all(d > 0 for d in spec.dimensions_m)
        assert set(object_textures(spec.name)) == {f for f, _ in spec.faces}
    assert {"snack_box", "cereal_box", "snack_bar", "can"} <= set(OBJECTS)


def test_depth_model_range_noise_edges_and_shadow():
    h, w = 200, 300
    fx = 379.05
    # A ramp over the range: nothing below 0.3 m or above 6 m.
    ramp = np.tile(np.linspace(0.1, 7.0, w, dtype=np.float32), (h, 1))
    d = sensor.simulate_depth(ramp, fx, seed=1)
    assert np.all(d[:, ramp[0] < sensor.MIN_RANGE_M - 0.01] == 0)
    assert np.all(d[:, ramp[0] > sensor.MAX_RANGE_M + 0.05] == 0)
    # Flat wall at 1.5 m: noise sigma = k z^2, some dropouts, nothing else missing.
    flat = np.full((h, w), 1.5, np.float32)
    d = sensor.simulate_depth(flat, fx, seed=2)
    valid = d > 0
    assert 0.005 < 1 - valid.mean() < 0.06
    sigma = (d[valid] / 1000.0 - 1.5).std()
    assert abs(sigma / (sensor.DEPTH_NOISE_PER_M * 1.5 ** 2) - 1) < 0.1
    # A box at 0.6 m in front of a wall at 1.0 m: its edges are invalid, and so is a band
    # left of it as wide as the disparity difference (occlusion shadow); right of it is fine.
    step = np.full((h, w), 1.0, np.float32)
    step[50:150, 150:250] = 0.6
    d = sensor.simulate_depth(step, fx, seed=3)
    band = int(fx * sensor.STEREO_BASELINE_M * (1 / 0.6 - 1 / 1.0))
    assert np.all(d[60:140, 150 - band + 1:151] == 0)
    assert np.all(d[60:140, 149] == 0) and np.all(d[60:140, 250] == 0)
    assert np.mean(d[60:140, 255:290] > 0) > 0.9 and np.mean(d[60:140, 100:150 - band - 2] > 0) > 0.9


def test_correlated_depth_noise_keeps_its_sigma_and_is_shared_by_neighbours():
    h, w = 240, 320
    fx = 379.05
    flat = np.full((h, w), 1.5, np.float32)
    sigma_z = sensor.DEPTH_NOISE_PER_M * 1.5 ** 2
    white = sensor.simulate_depth(flat, fx, seed=2)
    smooth = sensor.simulate_depth(flat, fx, seed=2, correlation_px=3.0)
    assert np.array_equal(white, sensor.simulate_depth(flat, fx, seed=2, correlation_px=0.0))   # the default
    for d, lag1 in ((white, (-0.1, 0.1)), (smooth, (0.9, 1.0))):
        err = np.where(d > 0, d / 1000.0 - 1.5, np.nan)
        valid = np.isfinite(err)
        assert abs(np.std(err[valid]) / sigma_z - 1) < 0.15                  # the same noise per pixel
        both = valid[:, :-1] & valid[:, 1:]
        r = np.corrcoef(err[:, :-1][both], err[:, 1:][both])[0, 1]          # neighbours share it, or not
        assert lag1[0] < r < lag1[1]
    # Far apart, the smooth noise is independent again.
    n = sensor.correlated_randn((h, w), 5, 3.0)
    assert abs(n.std() - 1) < 0.05
    assert abs(np.corrcoef(n[:, :-20].ravel(), n[:, 20:].ravel())[0, 1]) < 0.1


def test_intrinsics_and_bad_input():
    k640 = sensor.d455_intrinsics("640x480")
    assert (k640.width, k640.height) == (640, 480) and k640.K[0, 0] == pytest.approx(379.05)
    k720 = sensor.d455_intrinsics("1280x720")
    assert (k720.width, k720.height) == (1280, 720)
    assert k720.K[0, 2] == pytest.approx(643.78) and k720.K[1, 2] == pytest.approx(357.94)
    assert k640.distortion_model == "plumb_bob" and not k640.has_distortion
    with pytest.raises(InputError, match="resolution"):
        sensor.d455_intrinsics("800x600")
    with pytest.raises(InputError, match="unknown object"):
        get_object("banana")
    with pytest.raises(InputError, match="instances"):
        make_tabletop_scene(instances=0)
    with pytest.raises(InputError, match="instances"):
        make_tabletop_scene(instances=21)
