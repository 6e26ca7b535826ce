"""The per-frame pipeline and its parts: lifting, undistortion, matching, bad inputs."""
import cv2
import numpy as np
import pytest
from planar_scene import INTRINSICS, K, card_pose, render_planes, table
from skimage import data

from multi_instance_reg.errors import InputError
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.frontends.sift.features import SiftSettings, extract_sift
from multi_instance_reg.rgbd.lifting import backproject, lookup_depth, undistort_pixels
from multi_instance_reg.frontends.sift.matching import DescriptorMatcher, prepare_descriptors
from multi_instance_reg.transforms import apply_transform, invert_transform


def lifted_on_plane(uv, depth, T_plane, window=5, max_spread=0.02):
    z = lookup_depth(depth, uv, window, 0.1, 4.0, max_spread)
    ok = z > 0
    xyz = backproject(undistort_pixels(uv[ok], INTRINSICS), z[ok], INTRINSICS)
    # Distance of each lifted point from the plane (object z = 0).
    return ok, apply_transform(invert_transform(T_plane), xyz.astype(np.float64))[:, 2]


def test_lifting_accuracy_on_a_rendered_plane():
    T = card_pose(rx=25, ry=-20, rz=30, t=(0.05, 0.02, 0.7))
    rgb, depth = render_planes(data.astronaut(), (0.3, 0.3), [T])
    uv, _ = extract_sift(rgb, SiftSettings())
    assert len(uv) > 100
    ok, off_plane = lifted_on_plane(uv, depth, T)
    assert ok.mean() > 0.9          # only keypoints on the border lose their depth
    assert np.median(np.abs(off_plane)) < 0.0005 and np.percentile(np.abs(off_plane), 95) < 0.002


def test_window_median_survives_missing_pixels_and_noise():
    T = card_pose(rx=20, t=(0.0, 0.0, 0.8))
    rgb, depth = render_planes(data.astronaut(), (0.4, 0.4), [T])
    uv, _ = extract_sift(rgb, SiftSettings())
    rng = np.random.default_rng(0)
    holes = depth.copy()
    holes[rng.random(depth.shape) < 0.3] = 0.0                        # 30 % of pixels missing
    holes = np.where(holes > 0, holes + rng.normal(0, 0.003, depth.shape), 0).astype(np.float32)
    ok1, err1 = lifted_on_plane(uv, holes, T, window=1)              # the centre pixel alone
    ok5, err5 = lifted_on_plane(uv, holes, T, window=5)
    assert ok1.mean() < 0.75 and ok5.mean() > 0.9
    assert np.median(np.abs(err5)) < np.median(np.abs(err1))


def test_depth_edge_keypoints_are_dropped():
    depth = np.full((20, 20), 0.5, np.float32)
    depth[:, 10:] = 0.9
    uv = np.array([[5.0, 5.0], [10.0, 5.0], [15.0, 5.0]], np.float32)
    z = lookup_depth(depth, uv, 5, 0.1, 4.0, max_spread=0.02)
    np.testing.assert_allclose(z, [0.5, 0.0, 0.9])
    z = lookup_depth(depth, uv, 5, 0.1, 4.0, max_spread=0.0)
    assert z[1] in (np.float32(0.5), np.float32(0.9))
    assert lookup_depth(depth, np.array([[-5.0, 3.0]]), 5)[0] == 0       # outside the image


def test_undistortion_inverts_the_distortion_model():
    D = np.array([-0.055, 0.066, 0.0004, -0.0008, -0.021])
    intr = CameraIntrinsics(K=K, width=640, height=480, D=D)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), np.ones(50)])
    ideal = (pts @ K.T)[:, :2]
    distorted, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    assert np.abs(distorted.reshape(-1, 2) - ideal).max() > 1.0       # the distortion is not negligible
    np.testing.assert_allclose(undistort_pixels(distorted.reshape(-1, 2), intr), ideal, atol=0.05)
    no_d = CameraIntrinsics(K=K, width=640, height=480)
    np.testing.assert_array_equal(undistort_pixels(ideal, no_d), ideal)


def test_ratio_test_ignores_copies_of_the_same_physical_point():
    rng = np.random.default_rng(0)
    base = rng.random((50, 128)).astype(np.float32)
    xyz = rng.uniform(-0.1, 0.1, (50, 3))
    # The model holds every point twice (two views): two noisy copies of a descriptor, 2 mm apart;
    # the scene sees a third copy, as far from either.
    def noisy():
        return base + rng.normal(0, 0.02, base.shape).astype(np.float32)
    model_desc = prepare_descriptors(np.vstack([noisy(), noisy()]))
    model_xyz = np.vstack([xyz, xyz + 0.002])
    scene = prepare_descriptors(noisy())
    s, m, r = DescriptorMatcher(model_desc, model_xyz, ratio=0.8, separation=0.01).match(scene)
    assert len(s) == 50 and np.all(m % 50 == s)
    # The textbook test (separation 0) rejects them: the copy is as close as the original.
    s0, _, _ = DescriptorMatcher(model_desc, model_xyz, ratio=0.8, separation=0.0).match(scene)
    assert len(s0) < 10


def test_one_to_many_matching_maps_several_scene_points_to_one_model_point():
    rng = np.random.default_rng(2)
    model_desc = prepare_descriptors(rng.random((30, 128)).astype(np.float32))
    model_xyz = rng.uniform(-0.1, 0.1, (30, 3))
    scene = np.vstack([model_desc[:10], model_desc[:10]])
    s, m, _ = DescriptorMatcher(model_desc, model_xyz).match(scene)
    assert len(s) == 20 and np.all(m == np.tile(np.arange(10), 2))


@pytest.mark.parametrize("method", ["flann", "brute_force"])
def test_matchers_agree_and_flann_is_deterministic(method):
    rng = np.random.default_rng(3)
    model_desc = prepare_descriptors(rng.random((800, 128)).astype(np.float32))
    model_xyz = rng.uniform(-0.1, 0.1, (800, 3))
    scene = prepare_descriptors(np.vstack([model_desc[:300] + rng.normal(0, 0.01, (300, 128)).astype(np.float32),
                                           rng.random((300, 128)).astype(np.float32)]))  # 2 search threads
    runs = [DescriptorMatcher(model_desc, model_xyz, method=method).match(scene) for _ in range(2)]
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    s, m, _ = runs[0]
    assert len(set(range(300)) - set(s.tolist())) < 5
    assert np.mean(m[s < 300] == s[s < 300]) > 0.99


def test_joint_index_matches_each_model_as_its_own_exact_search_does():
    """One index over three models: (nearly) every match it accepts, the model's own exact
    search accepts too, to the same model point, and it finds nearly all of them; a keypoint that
    two models share (same texture) matches both, and the matches come back per model."""
    from multi_instance_reg.frontends.sift.matching import JointMatcher

    rng = np.random.default_rng(4)
    descs = [prepare_descriptors(rng.random((n, 128)).astype(np.float32)) for n in (900, 300, 1500)]
    xyzs = [rng.uniform(-0.1, 0.1, (len(d), 3)) for d in descs]
    descs[1][:40] = descs[0][:40]                   # the can's label printed on the snack box too
    queries = [d[:200] + rng.normal(0, 0.01, (200, 128)).astype(np.float32) for d in descs]
    scene = prepare_descriptors(np.vstack(queries + [rng.random((300, 128)).astype(np.float32)]))
    joint = JointMatcher(descs, xyzs, ratio=0.8, separation=0.01).match_later(scene)()
    assert len(joint) == 3
    for k, (s, m, r) in enumerate(joint):
        es, em, _ = DescriptorMatcher(descs[k], xyzs[k], method="brute_force").match(scene)
        exact = dict(zip(es.tolist(), em.tolist()))
        agree = [exact.get(a) == b for a, b in zip(s.tolist(), m.tolist())]
        assert np.mean(agree) >= 0.99                # approximate search: a rare second found too far
        assert len(s) >= 0.95 * len(es) and np.all(r < 0.8)
        own = (s >= 200 * k) & (s < 200 * (k + 1))
        assert own.sum() >= 190 and np.all(m[own] == s[own] - 200 * k)
    both, shared = set(joint[0][0].tolist()) & set(joint[1][0].tolist()), set(range(40)) | set(range(200, 240))
    assert len(both & shared) >= 68 and len(both - shared) <= 2
    empty = JointMatcher(descs, xyzs).match_later(np.zeros((0, 128), np.float32))()
    assert [len(s) for s, _, _ in empty] == [0, 0, 0]


def test_work_split_over_threads_comes_back_in_order():
    from multi_instance_reg.threads import map_in_chunks
    rows = np.arange(1000)
    parts = map_in_chunks(lambda chunk: chunk * 2, rows, min_chunk=100)
    assert len(parts) >= 1 and np.array_equal(np.concatenate(parts), rows * 2)
    assert len(map_in_chunks(lambda chunk: chunk, rows[:50], min_chunk=100)) == 1


# --------------------------------------------------------------------------- on rendered frames

@pytest.fixture(scope="module")
def rendered_frame():
    from multi_instance_reg.synthetic.scene import make_tabletop_scene

    scene = make_tabletop_scene(instances=6, distractors=2, frames=1, seed=3)
    return scene, scene.render_frame(0)


def test_lifting_accuracy_on_a_rendered_frame(rendered_frame):
    scene, frame = rendered_frame
    depth = frame.depth_mm.astype(np.float32) / 1000.0        # with the simulated D455 noise and holes
    uv, _ = extract_sift(frame.rgb, SiftSettings())
    truth = frame.depth_true_m[np.clip(np.rint(uv[:, 1]).astype(int), 0, 479), np.clip(np.rint(uv[:, 0]).astype(int), 0, 639)]
    on_objects = frame.instance_mask[np.clip(np.rint(uv[:, 1]).astype(int), 0, 479),
                                     np.clip(np.rint(uv[:, 0]).astype(int), 0, 639)] >= 0
    z5 = lookup_depth(depth, uv, 5, 0.1, 4.0, 0.02)
    z1 = lookup_depth(depth, uv, 1, 0.1, 4.0, 0.0)
    ok5 = (z5 > 0) & (truth > 0) & on_objects
    ok1 = (z1 > 0) & (truth > 0) & on_objects
    err5 = np.abs(z5[ok5] - truth[ok5])
    err1 = np.abs(z1[ok1] - truth[ok1])
    assert ok5.sum() > 200
    assert np.median(err5) < 0.003 and np.percentile(err5, 90) < 0.01
    assert np.median(err5) <= np.median(err1)
    # Back-projected points sit on the true surface: compare with the noise-free depth lifted alike.
    xyz = backproject(undistort_pixels(uv[ok5], scene.intrinsics), z5[ok5], scene.intrinsics)
    xyz_true = backproject(undistort_pixels(uv[ok5], scene.intrinsics), truth[ok5], scene.intrinsics)
    assert np.median(np.linalg.norm(xyz - xyz_true, axis=1)) < 0.003


def test_register_frame_finds_the_instances(rendered_frame, object_model):
    from multi_instance_reg.metrics import evaluate_scene
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import STAGES, InstanceRegistration

    scene, frame = rendered_frame
    model = load_model(object_model)
    reg = InstanceRegistration(model)
    result = reg.register_frame(frame.rgb, frame.depth_mm.astype(np.float32) / 1000.0, scene.intrinsics)
    assert set(result.timings_ms) == set(STAGES)
    assert [i.id for i in result.instances] == list(range(len(result.instances)))
    assert all(a.inliers >= b.inliers for a, b in zip(result.instances, result.instances[1:]))
    assert len(result.labels) == len(result.keypoints_uv) == len(result.model_xyz) == len(result.scene_xyz)
    assert set(np.unique(result.labels)) <= set(range(-1, len(result.instances)))
    visible = frame.visibility >= 0.5
    est = np.array([i.T for i in result.instances]).reshape(-1, 4, 4) @ np.linalg.inv(model.T_object_model)
    score = evaluate_scene(frame.poses[visible], est, 10.0, 0.02)
    assert score.hits >= visible.sum() - 1 and len(result.instances) <= visible.sum() + 1
    assert np.median(score.rte[score.hit]) < 0.005


def test_eight_boxes_lying_flat_are_found_although_their_tops_form_a_plane(object_model):
    # Generated static scene seed 62: eight snack boxes lying flat, their tops a plane of 20 %
    # of the pixels 5 cm above the table. It was removed as a second support plane, and the
    # frame gave 0 instances (the tracker's static sequences of this kind: IDF1 0.57-0.70).
    from multi_instance_reg.metrics import evaluate_scene
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration
    from multi_instance_reg.synthetic.scene import make_tabletop_scene

    model = load_model(object_model)
    scene = make_tabletop_scene(instances=8, distractors=3, frames=1, seed=62, motion="static")
    frame = scene.render_frame(0)
    depth = frame.depth_mm.astype(np.float32) / 1000.0
    reg = InstanceRegistration(model)
    present = frame.visibility >= 0.5
    for reach, least_hits in ((0.0, 0), (reg.object_reach, present.sum() - 1)):
        reg.object_reach = reach        # 0: any parallel plane counts, as before
        result = reg.register_frame(frame.rgb, depth, scene.intrinsics)
        est = np.array([i.T for i in result.instances]).reshape(-1, 4, 4) @ np.linalg.inv(model.T_object_model)
        hits = evaluate_scene(frame.poses[present], est, 10.0, 0.02).hits
        if reach == 0.0:
            assert hits <= present.sum() // 2
        else:
            assert hits >= least_hits and len(result.instances) <= present.sum() + 1


def test_no_instance_in_a_scene_without_the_object(object_model):
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration
    from multi_instance_reg.synthetic.scene import make_tabletop_scene

    reg = InstanceRegistration(load_model(object_model))
    # Another object's instances, and distractors that do not include ours (seed chosen so).
    scene = make_tabletop_scene("cereal_box", instances=6, distractors=3, frames=2, seed=7)
    assert "snack_box" not in scene.description()["distractors"]
    for frame in scene.frames():
        result = reg.register_frame(frame.rgb, frame.depth_mm.astype(np.float32) / 1000.0, scene.intrinsics)
        assert result.instances == []


def test_bad_frames_and_models_raise_clear_errors(object_model):
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration

    model = load_model(object_model)
    reg = InstanceRegistration(model)
    rgb = np.zeros((480, 640, 3), np.uint8)
    depth = np.full((480, 640), 0.8, np.float32)
    with pytest.raises(InputError, match="depth image is 320x240 but colour is 640x480"):
        reg.register_frame(rgb, depth[:240, :320], INTRINSICS)
    with pytest.raises(InputError, match="no valid pixel"):
        reg.register_frame(rgb, np.zeros_like(depth), INTRINSICS)
    with pytest.raises(InputError, match="colour image must be"):
        reg.register_frame(rgb[:, :, 0], depth, INTRINSICS)
    with pytest.raises(InputError, match="camera_info is for"):
        reg.register_frame(rgb, depth, CameraIntrinsics(K=K, width=1280, height=720))
    import dataclasses
    empty = dataclasses.replace(model, keypoints_xyz=np.zeros((0, 3), np.float32), descriptors=np.zeros((0, 128), np.float32))
    with pytest.raises(InputError, match="0 keypoints"):
        InstanceRegistration(empty)
    result = reg.register_frame(rgb, depth, INTRINSICS)     # a blank frame is fine: nothing found
    assert result.instances == [] and result.timings_ms["total"] > 0


def test_the_shared_pool_shortens_the_gil_switch_interval(monkeypatch):
    """Kernels returning to a GIL held by Python in the other thread wait up to the switch
    interval: the pool sets it to GIL_SWITCH_INTERVAL, and never lengthens a shorter one."""
    import sys

    from multi_instance_reg import threads

    before = sys.getswitchinterval()
    try:
        for start, expected in ((0.005, threads.GIL_SWITCH_INTERVAL), (0.0002, 0.0002)):
            sys.setswitchinterval(start)
            monkeypatch.setattr(threads, "_POOL", None)
            monkeypatch.setattr(threads.os, "cpu_count", lambda: 2)
            pool = threads.shared_pool()
            assert pool is not None and abs(sys.getswitchinterval() - expected) < 1e-9
            pool.shutdown()
    finally:
        sys.setswitchinterval(before)


def test_blas_thread_limit_reaches_the_loaded_libraries():
    import scipy.linalg  # noqa: F401  (scipy brings its own OpenBLAS)

    from multi_instance_reg.threads import limit_blas_threads, loaded_openblas_libraries

    libs = loaded_openblas_libraries()
    assert libs, "numpy's OpenBLAS should be mapped into the process"
    assert limit_blas_threads(1) == len(libs)


def test_box_overlaps_of_instances():
    from multi_instance_reg.rgbd.pipeline import box_grid, box_overlaps

    class Model:
        extent = np.array([0.2, 0.1, 0.05])
    same, shifted, far = np.eye(4), np.eye(4), np.eye(4)
    shifted[0, 3] = 0.1      # half a box length along x
    far[0, 3] = 1.0
    O = box_overlaps(Model, [same, shifted, far], box_grid(Model.extent))
    assert O.shape == (3, 3) and np.allclose(np.diag(O), 1.0)
    assert 0.3 < O[0, 1] < 0.7 and O[0, 2] == 0.0 and O[2, 0] == 0.0
    assert box_overlaps(Model, [], box_grid(Model.extent)).shape == (0, 0)


def test_box_overlaps_skipping_pairs_apart_gives_every_share():
    """The kernel skips pairs whose boxes lie apart; every entry is still the share the
    grid points give, counted point by point (poses packed close, some touching, turned)."""
    from multi_instance_reg.rgbd.pipeline import box_grid, box_overlaps
    from multi_instance_reg.symmetry import _rotation

    class Model:
        extent = np.array([0.2, 0.1, 0.05])
        box_centre = np.array([0.01, -0.02, 0.005])
    rng = np.random.default_rng(4)
    poses = []
    for _ in range(40):
        axis = rng.normal(size=3)
        T = np.eye(4)
        T[:3, :3] = _rotation(axis / np.linalg.norm(axis), rng.uniform(0, np.pi))
        T[:3, 3] = rng.uniform(-0.25, 0.25, 3)
        poses.append(T)
    # The pipeline's grid (about the box centre): a grid point exactly on a box face would be
    # in or out by the last bit of the relative pose, which the kernel and numpy round apart.
    grid = box_grid(Model.extent) + Model.box_centre
    O = box_overlaps(Model, poses, grid)
    half = Model.extent / 2.0
    ref = np.zeros_like(O)
    for a, A in enumerate(poses):
        for b, B in enumerate(poses):
            R = A[:3, :3].T @ B[:3, :3]
            t = A[:3, :3].T @ (B[:3, 3] - A[:3, 3])
            x, y, z = grid[:, 0], grid[:, 1], grid[:, 2]
            inside = np.ones(len(grid), bool)
            for i in range(3):
                inside &= np.abs(x * R[i, 0] + y * R[i, 1] + z * R[i, 2] + t[i] - Model.box_centre[i]) <= half[i]
            ref[a, b] = inside.sum() / len(grid)
    assert np.array_equal(O, ref)
    assert 0 < (O > 0).sum() - 40 and (O == 0).sum() > 100      # both kinds of pairs


def _box_cloud(extent, step=0.004):
    """Dense points on the surface of a box centred at the origin."""
    h = np.asarray(extent) / 2.0
    axes = [np.arange(-hi, hi + 1e-9, step) for hi in h]
    pts = []
    for a in range(3):
        b, c = [i for i in range(3) if i != a]
        B, C = np.meshgrid(axes[b], axes[c], indexing="ij")
        for sign in (-1.0, 1.0):
            p = np.zeros((B.size, 3))
            p[:, a], p[:, b], p[:, c] = sign * h[a], B.ravel(), C.ravel()
            pts.append(p)
    return np.concatenate(pts)


def test_free_space_share_tells_a_box_on_the_depth_from_one_in_empty_space():
    from multi_instance_reg.rgbd.verify import free_space_share, surface_samples

    extent = np.array([0.18, 0.12, 0.05])
    pts, normals = surface_samples(_box_cloud(extent), extent)
    assert len(pts) > 100 and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    # Outward: along the offset from the centre on the faces (z: top and bottom faces).
    top = pts[:, 2] > extent[2] / 2 - 1e-6
    assert top.sum() > 20 and (normals[top, 2] > 0.5).all() and np.median(normals[top, 2]) > 0.95

    def pose(z_top, x=0.0, tilt_deg=0.0):
        """Camera looking down +z at a table; the box's top face (its +z face) towards the
        camera, at depth z_top; tilted about the y axis through its -x end."""
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])              # box +z -> camera -z (towards it)
        a = np.radians(tilt_deg)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        T[:3, :3] = R @ T[:3, :3]
        end = np.array([-extent[0] / 2, 0.0, z_top])
        T[:3, 3] = end - R @ (end - np.array([0.0, 0.0, z_top + extent[2] / 2]))
        T[0, 3] += x
        return T

    flat = np.full((480, 640), 0.8, np.float32)
    pivot_at = lambda T: T[:3, :3] @ np.array([-extent[0] / 2 + 0.01, 0.0, extent[2] / 2]) + T[:3, 3]
    slope = np.tan(np.radians(10.0))

    def share(T, depth, slope=slope):
        s, m = free_space_share(T, pts, normals, depth, INTRINSICS, pivot_at(T), 0.008, slope)
        assert m > 50
        return s

    # On the depth: nothing in empty space. Floating 8 cm in front of it: all of it.
    assert share(pose(0.8), flat) == 0.0
    assert share(pose(0.72), flat) > 0.95
    # Hidden behind something nearer: no evidence against it.
    assert share(pose(0.8), np.full((480, 640), 0.7, np.float32)) == 0.0
    # Slid half off a raised surface onto a table 5 cm lower (a fit to repeated texture on a
    # real box, shifted along it): the overhanging half fills empty space.
    step = flat.copy()
    step[:, 320:] = 0.85
    assert 0.3 < share(pose(0.8, x=0.0), step) < 0.7
    # Tilted by 5 deg about the end its inliers are at: within the tilt allowed, not without.
    assert share(pose(0.8, tilt_deg=5.0), flat) < 0.05
    assert share(pose(0.8, tilt_deg=5.0), flat, slope=0.0) > 0.3


def test_warm_up_compiles_every_kernel_a_real_frame_uses(rendered_frame, object_model):
    """A new checkout has no compiled kernels on disk: what warm_up leaves uncompiled, the
    first frame compiles (1.8 s; a live node's detector fell behind a short stream)."""
    from multi_instance_reg.rgbd import lifting, verify
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration

    scene, frame = rendered_frame
    reg = InstanceRegistration(load_model(object_model))
    reg.warm_up()
    kernels = [lifting._window_medians, verify._free_space_share]
    compiled = [len(k.signatures) for k in kernels]
    assert all(compiled)
    result = reg.register_frame(frame.rgb, frame.depth_mm.astype(np.float32) / 1000.0, scene.intrinsics)
    assert len(result.instances) >= 3                        # the free-space check ran on them
    assert [len(k.signatures) for k in kernels] == compiled  # nothing new compiled



def _tabletop_depth(tops_share: float = 0.0, top_height: float = 0.05, floor_rows: int = 0):
    """Depth of a table seen from 45 deg, 0.6 m away at the image centre, with a grid of
    object tops ``top_height`` above it covering ``tops_share`` of the image, and the floor
    0.7 m below the table in the top ``floor_rows`` rows. Returns (depth, table normal, table d)."""
    n = np.array([0.0, -np.sqrt(0.5), -np.sqrt(0.5)])       # towards the camera
    u, v = np.meshgrid((np.arange(640) - K[0, 2]) / K[0, 0], (np.arange(480) - K[1, 2]) / K[1, 1])
    along = n[0] * u + n[1] * v + n[2]
    d_table = 0.6 * np.sqrt(0.5)
    offset = np.zeros((480, 640))
    side = int(round(80 * np.sqrt(tops_share)))             # one top per 80 x 80 pixel cell
    offset[((np.arange(480) % 80) < side)[:, None] & ((np.arange(640) % 80) < side)[None, :]] = top_height
    offset[:floor_rows] = -0.7
    return ((d_table - offset) / -along).astype(np.float32), n, d_table


@pytest.mark.parametrize("tops_share", [0.3, 0.6])
def test_the_tops_of_many_objects_are_not_taken_for_the_table(tops_share):
    # Ten snack bars lying flat: their tops are a plane of their own, parallel to the table and
    # one object height nearer. Removing it (the second "plane") removed the objects; with
    # the tops covering more than the table, they were even taken for the table.
    from multi_instance_reg.rgbd.lifting import support_planes
    depth, n, d_table = _tabletop_depth(tops_share)
    old = support_planes(depth, INTRINSICS, count=2, thresh=0.01, min_share=0.2)
    assert sorted(round(d - d_table, 3) for _, d in old) == [-0.05, 0.0]
    planes = support_planes(depth, INTRINSICS, count=2, thresh=0.01, min_share=0.2, object_reach=0.2)
    assert len(planes) == 1
    assert planes[0][0] @ n > 0.999 and abs(planes[0][1] - d_table) < 0.002


def test_a_table_and_the_floor_below_it_are_both_supports():
    from multi_instance_reg.rgbd.lifting import support_planes
    depth, n, d_table = _tabletop_depth(floor_rows=200)
    planes = support_planes(depth, INTRINSICS, count=2, thresh=0.01, min_share=0.2, object_reach=0.2)
    assert sorted(round(d - d_table, 2) for _, d in planes) == [0.0, 0.7]
