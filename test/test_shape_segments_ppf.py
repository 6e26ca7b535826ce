"""The pieces of the PPF shape front end: support planes cut by piece size, connected
segments, oriented model surface, point-pair voting and its correspondences, damped ICP."""
import cv2
import numpy as np
import pytest

from multi_instance_reg.meshes import box_mesh, sample_surface
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.rgbd.lifting import _depth_to_cloud_numpy, depth_to_cloud
from multi_instance_reg.models.mesh_model import build_model_from_mesh
from multi_instance_reg.rgbd.ppf import PPFModel
from multi_instance_reg.rgbd.segments import connected_segments, support_mask
from multi_instance_reg.rgbd.shape import PointGrid, icp_point_to_plane
from multi_instance_reg.rgbd.shape_frontend import oriented_downsample
from multi_instance_reg.symmetry import closest_symmetric_pose
from multi_instance_reg.transforms import make_transform, rotation_angle_deg


def _intrinsics():
    K = np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])
    return CameraIntrinsics(K=K, width=320, height=240)


def test_support_mask_removes_floor_keeps_small_coplanar_tops():
    depth = np.full((240, 320), 1.5, np.float32)           # a floor facing the camera
    depth[40:80, 40:100] = 1.3                               # two box tops in one plane, apart
    depth[150:190, 200:260] = 1.3
    valid = depth > 0
    # Tops: 60 x 40 px at 1.3 m = 0.195 x 0.13 m = 0.025 m^2 each; the floor ~ 1 m^2.
    mask = support_mask(depth, _intrinsics(), valid, max_area=0.1, thresh=0.01, noise_per_m2=0.0)
    assert mask[200:, :150].all()                            # floor removed
    assert not mask[45:75, 45:95].any() and not mask[155:185, 205:255].any()   # both tops kept


def test_support_mask_keeps_a_thin_plate_on_the_table_and_says_which_way_is_up():
    """A 12 mm plate lying on a table at 0.7 m: within plane_thresh (1 cm) + 3 sigma of the
    table, point by point (``window`` 1), it would be removed with it; at the shape path's
    4 mm it stays."""
    depth = np.full((240, 320), 0.7, np.float32)             # a table facing the camera
    depth[100:140, 100:180] = 0.688                           # the plate's top, 12 mm above it
    valid = depth > 0
    ground = []
    loose = support_mask(depth, _intrinsics(), valid, max_area=0.05, thresh=0.01, noise_per_m2=0.002, window=1)
    tight = support_mask(depth, _intrinsics(), valid, max_area=0.05, thresh=0.004, noise_per_m2=0.002, ground=ground)
    assert loose[105:135, 105:175].all()                     # taken for the table
    assert not tight[105:135, 105:175].any() and tight[200:, :].all()
    assert len(ground) == 2 and ground[0] @ [0.0, 0.0, -1.0] > 0.99   # the table's normal, towards the camera
    assert abs(ground[1] - 0.7) < 0.002                      # and its offset: up . p + 0.7 = 0 on it


def _tilted_table(z0: float, sigma_per_m2: float, noise, raised: float = 0.0) -> np.ndarray:
    """Depth of a table seen 40 deg from straight on (depth z0 at the image centre), with a
    160 x 80 mm plate ``raised`` above it in the middle, plus noise (unit-variance field
    ``noise``) of sigma = sigma_per_m2 z^2."""
    K = _intrinsics().K
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    t = np.radians(40.0)
    n = np.array([0.0, -np.sin(t), -np.cos(t)])                # the table's normal, towards the camera
    d = z0 * np.cos(t)                                          # n . p + d = 0 on it
    depth = -d / (rays @ n)
    if raised > 0:
        p = rays * depth[..., None]
        centre = np.array([0.0, 0.0, z0])
        across = np.array([1.0, 0.0, 0.0])
        along = np.cross(n, across)
        plate = (np.abs((p - centre) @ across) < 0.08) & (np.abs((p - centre) @ along) < 0.04)
        depth = np.where(plate, -(d - raised) / (rays @ n), depth)
    return (depth + sigma_per_m2 * depth ** 2 * noise).astype(np.float32), plate if raised > 0 else None


def test_support_mask_keeps_a_plate_raised_less_than_the_band():
    """An 8 mm plate (a tray's floor, a lid) on a table at 1 m, depth noise sigma 2 mm: the
    band (4 mm + 3 sigma, 10 mm) takes most of it for the table; the mean height of a window
    of its points does not."""
    noise = np.random.default_rng(3).standard_normal((240, 320))
    depth, plate = _tilted_table(1.0, 0.002, noise, raised=0.008)
    valid = depth > 0
    inner = cv2.erode(plate.astype(np.uint8), np.ones((13, 13), np.uint8)) > 0
    table = cv2.dilate(plate.astype(np.uint8), np.ones((13, 13), np.uint8)) == 0
    per_point = support_mask(depth, _intrinsics(), valid, max_area=0.1, thresh=0.004, noise_per_m2=0.002, window=1)
    mask = support_mask(depth, _intrinsics(), valid, max_area=0.1, thresh=0.004, noise_per_m2=0.002)
    assert per_point[inner].mean() > 0.8                     # the plate went with the table
    assert mask[inner].mean() < 0.02                         # now it stays
    assert mask[table].mean() > 0.99 and per_point[table].mean() > 0.99
    # Larger than any face of the object (0.0128 m^2 against 0.005): a support, as the table.
    board = support_mask(depth, _intrinsics(), valid, max_area=0.005, thresh=0.004, noise_per_m2=0.002)
    assert board[inner].mean() > 0.8                        # (the rest: points above the band)


@pytest.mark.parametrize("stride", [2, 3])
def test_support_mask_rest_is_the_cloud_off_the_mask(stride):
    """``rest``: the points lifted once are those ``depth_to_cloud`` gives off the mask, to the bit."""
    noise = np.random.default_rng(3).standard_normal((240, 320))
    depth, _ = _tilted_table(1.0, 0.002, noise, raised=0.008)
    depth[::7, ::5] = 0.0
    valid = depth > 0
    rest = []
    mask = support_mask(depth, _intrinsics(), valid, max_area=0.005, thresh=0.004, noise_per_m2=0.002,
                        stride=stride, rest=rest)
    pts, pix = depth_to_cloud(depth, _intrinsics(), valid & ~mask, stride=stride)
    assert 0 < len(pts) < valid[::stride, ::stride].sum() // 2
    assert rest[0].tobytes() == pts.tobytes() and rest[1].tobytes() == pix.tobytes()


def test_depth_to_cloud_compiled_equals_numpy():
    rng = np.random.default_rng(1)
    depth = rng.uniform(-0.2, 3.0, (61, 83)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = np.nan
    depth[rng.random(depth.shape) < 0.1] = 0.0
    depth[rng.random(depth.shape) < 0.02] = np.inf
    mask = rng.random(depth.shape) < 0.7
    K = np.array([[415.3, 0, 41.7], [0, 414.9, 30.2], [0, 0, 1]])
    intr = CameraIntrinsics(K=K, width=83, height=61)
    for d in (depth, depth.astype(np.float64)):
        for m in (None, mask, mask.astype(np.uint8)):
            for stride in (1, 2, 3):
                pts, pix = depth_to_cloud(d, intr, m, stride)
                ref_pts, ref_pix = _depth_to_cloud_numpy(d, intr, m, stride)
                assert pts.dtype == ref_pts.dtype and pix.dtype == ref_pix.dtype and len(pts) > 0
                assert pts.tobytes() == ref_pts.tobytes() and pix.tobytes() == ref_pix.tobytes()


def test_support_mask_takes_no_table_for_raised_where_the_noise_is_smooth():
    """Stereo depth noise shared by neighbouring pixels (smooth over 3 px) at 2 m (sigma 8 mm):
    a window's mean scatters nearly as much as a point, which the plane's own scatter says;
    the whole table stays a table."""
    from multi_instance_reg.synthetic.sensor import correlated_randn

    depth, _ = _tilted_table(2.0, 0.002, correlated_randn((240, 320), 5, 3.0))
    valid = depth > 0
    mask = support_mask(depth, _intrinsics(), valid, max_area=0.1, thresh=0.004, noise_per_m2=0.002)
    assert mask[valid].mean() > 0.99


def test_graph_components_number_components_as_scipy_does():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from multi_instance_reg.rgbd.segments import graph_components

    rng = np.random.default_rng(5)
    for n, m in ((1, 0), (50, 0), (500, 300), (2000, 2500), (3000, 9000)):
        i, j = rng.integers(0, n, m), rng.integers(0, n, m)
        _, ref = connected_components(coo_matrix((np.ones(m, np.int8), (i, j)), shape=(n, n)), directed=False)
        labels = graph_components(n, i.astype(np.int64), j.astype(np.int64))
        assert labels.dtype == ref.dtype and np.array_equal(labels, ref)


def test_connected_segments_split_and_drop_small():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 0.1, (200, 3))
    b = rng.uniform(0, 0.1, (200, 3)) + [0.5, 0, 0]
    c = np.array([[1.0, 1.0, 1.0], [1.001, 1.0, 1.0]])
    labels = connected_segments(np.vstack([a, b, c]), link=0.03, min_points=5)
    assert len(set(labels[:200])) == 1 and len(set(labels[200:400])) == 1
    assert labels[0] != labels[200] and (labels[400:] == -1).all()


def test_oriented_downsample_keeps_both_sides_of_a_thin_plate():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 0.1, (2000, 2))
    top = np.c_[xy, np.full(2000, 0.004)]
    bottom = np.c_[xy, np.zeros(2000)]
    normals = np.vstack([np.tile([0, 0, 1.0], (2000, 1)), np.tile([0, 0, -1.0], (2000, 1))])
    pts, n = oriented_downsample(np.vstack([top, bottom]), normals, voxel=0.01)
    up = n[:, 2] > 0.99
    down = n[:, 2] < -0.99
    assert up.sum() + down.sum() == len(n) and abs(up.sum() - down.sum()) <= 2
    assert np.allclose(pts[up, 2], 0.004) and np.allclose(pts[down, 2], 0.0)


def _box_model():
    return build_model_from_mesh(box_mesh(0.3, 0.2, 0.15), "box")


def _visible(points, normals, T, noise, seed=0):
    P = points @ T[:3, :3].T + T[:3, 3]
    N = normals @ T[:3, :3].T
    vis = np.einsum("ij,ij->i", N, -P) > 0
    return P[vis] + np.random.default_rng(seed).normal(0, noise, (vis.sum(), 3)), N[vis]


def _box_seen_by_ppf():
    """The box model's point-pair features, a pose, and the points / normals it shows there."""
    model = _box_model()
    surface, normals = oriented_downsample(model.shape_points, model.shape_normals, model.shape_voxel)
    ppf = PPFModel(surface, normals, float(np.linalg.norm(model.extent)), model.shape_voxel, model.symmetries,
                   bucket_cap=1000)
    T = make_transform(np.array([[0.36, -0.48, 0.8], [0.8, 0.6, 0.0], [-0.48, 0.64, 0.6]]), [0.1, -0.05, 1.2])
    P, N = _visible(surface, normals, T, 0.001)
    return model, ppf, T, P, N


def test_ppf_votes_recover_the_pose_and_give_consistent_correspondences():
    model, ppf, T, P, N = _box_seen_by_ppf()
    s, m, poses, share = ppf.vote(P, N, np.zeros(len(P), np.int64), ref_step=2, max_partners=200)
    assert len(s) > 20
    errs = []
    for Tp in poses:
        G = closest_symmetric_pose(T, Tp, model.symmetries)
        dR = np.degrees(np.arccos(np.clip((np.trace(G[:3, :3].T @ Tp[:3, :3]) - 1) / 2, -1, 1)))
        errs.append(np.linalg.norm(G[:3, 3] - Tp[:3, 3]) < 0.02 and dR < 15)
    assert np.mean(errs) > 0.6
    # Canonical poses: the references that are right agree on one symmetric pose, so most
    # correspondences fit one rigid transform.
    src, idx = ppf.correspondences(s, poses, P)
    canon = ppf.canonical_poses(poses)
    G = closest_symmetric_pose(T, canon[int(np.argmax(errs))], model.symmetries)
    resid = np.linalg.norm(src @ G[:3, :3].T + G[:3, 3] - P[idx], axis=1)
    assert np.mean(resid < 2 * model.shape_voxel) > 0.4


def test_icp_does_not_slide_a_box_seen_by_its_top_alone():
    model = _box_model()
    surface, normals = oriented_downsample(model.shape_points, model.shape_normals, model.shape_voxel)
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.5])       # top (+z) facing the camera
    dense, _ = sample_surface(box_mesh(0.3, 0.2, 0.15), 0.004)
    top = dense[dense[:, 2] > 0.074]
    scene = top @ T[:3, :3].T + T[:3, 3] + np.random.default_rng(2).normal(0, 0.004, (len(top), 3))
    scene_n = np.tile([0, 0, -1.0], (len(scene), 1))
    start = T.copy()
    start[:3, 3] += [0.005, -0.004, 0.003]
    out, share = icp_point_to_plane(start, surface, PointGrid(scene, scene_n, 2 * model.shape_voxel),
                                    2 * model.shape_voxel, 15, model_normals=normals)
    assert share > 0.5
    assert np.linalg.norm(out[:3, 3] - start[:3, 3]) < 0.01           # no drift along the face
    assert abs(out[2, 3] - T[2, 3]) < 0.003                            # the depth is corrected


def _face_model():
    """A 0.2 x 0.13 m face (points every cm, normals towards the camera), centred at its origin."""
    g = np.stack(np.meshgrid(np.arange(-0.1, 0.1001, 0.01), np.arange(-0.065, 0.0651, 0.01)), -1).reshape(-1, 2)
    face = np.column_stack([g, np.zeros(len(g))])
    return face, np.tile([0.0, 0.0, -1.0], (len(face), 1))


def _looking_at(K):
    """at(row, col, z): the pose that puts the model's origin on pixel (row, col) at depth z."""
    return lambda row, col, z: make_transform(np.eye(3), z * (np.linalg.inv(K.K) @ [col, row, 1.0]))


def test_outline_continuation_tells_a_box_top_from_a_piece_of_a_larger_surface():
    from multi_instance_reg.rgbd.verify import outline_continuation

    K = _intrinsics()
    face, normals = _face_model()
    at = _looking_at(K)
    depth = np.full((240, 320), 1.5, np.float32)            # floor
    depth[120:220, 160:300] = 1.3                            # a crate top, 0.46 x 0.325 m
    # A box top exactly as big as the model, standing 0.2 m above the floor.
    T_box = at(70, 70, 1.3)
    uv = (K.K @ (face @ T_box[:3, :3].T + T_box[:3, 3]).T).T
    uv = uv[:, :2] / uv[:, 2:]
    c0, r0 = np.floor(uv.min(0)).astype(int)
    c1, r1 = np.ceil(uv.max(0)).astype(int)
    depth[r0:r1 + 1, c0:c1 + 1] = 1.3
    own, n_own = outline_continuation(T_box, face, normals, depth, K, 0.01, 0.01)
    # The same face laid on the crate top's middle, and on the open floor: the surface goes on.
    crate, n_crate = outline_continuation(at(170, 230, 1.3), face, normals, depth, K, 0.01, 0.01)
    floor, _ = outline_continuation(at(200, 60, 1.5), face, normals, depth, K, 0.01, 0.01)
    assert n_own > 50 and n_crate > 50
    assert own < 0.05
    assert crate > 0.9 and floor > 0.9


def test_in_view_share_counts_the_facing_surface_inside_the_image():
    from multi_instance_reg.rgbd.verify import in_view_share

    K = _intrinsics()
    face, normals = _face_model()
    at = _looking_at(K)
    assert in_view_share(at(120, 160, 1.0), face, normals, K) == 1.0
    # Centred on the image's left edge: the left half of the face is outside.
    assert 0.4 < in_view_share(at(120, 0, 1.0), face, normals, K) < 0.6
    assert in_view_share(at(120, -200, 1.0), face, normals, K) == 0.0
    # Turned away from the camera: nothing faces it.
    away = at(120, 160, 1.0)
    away[:3, :3] = np.diag([1.0, -1.0, -1.0])
    assert in_view_share(away, face, normals, K) == 0.0


def test_pose_clusters_rank_agreeing_references_above_scattered_ones():
    from multi_instance_reg.rgbd.ppf import cluster_poses
    from multi_instance_reg.symmetry import _rotation

    rng = np.random.default_rng(0)
    a = make_transform(_rotation(np.array([0.0, 0, 1]), 0.3), [0.1, 0.0, 1.0])
    b = make_transform(_rotation(np.array([1.0, 0, 0]), 1.0), [-0.2, 0.1, 1.2])

    def near(T, k):
        out = []
        for _ in range(k):
            D = make_transform(_rotation(rng.normal(size=3) / 1.0, np.radians(3)), rng.normal(0, 0.003, 3))
            out.append(T @ D)
        return out

    scattered = [make_transform(_rotation(rng.normal(size=3), rng.uniform(0, np.pi)), rng.uniform(-0.5, 0.5, 3) + [0, 0, 1])
                 for _ in range(40)]
    poses = np.stack(near(a, 12) + near(b, 6) + scattered)
    weights = rng.uniform(0.5, 1.0, len(poses))
    top = cluster_poses(poses, weights, 12.0, 0.03, max_clusters=2)
    assert len(top) == 2
    assert np.linalg.norm(top[0][:3, 3] - a[:3, 3]) < 0.02 and np.linalg.norm(top[1][:3, 3] - b[:3, 3]) < 0.02
    # Every pose distinct: each is its own seed, in the order of the weights.
    assert len(cluster_poses(poses[:3], -np.arange(3.0), 1.0, 1e-6, 10, min_members=1)) == 3


def _face_and_depth():
    """A 0.2 x 0.13 m model face (normals towards the camera) and a camera looking down at it."""
    K = _intrinsics()
    g = np.stack(np.meshgrid(np.arange(-0.1, 0.1001, 0.01), np.arange(-0.065, 0.0651, 0.01)), -1).reshape(-1, 2)
    face = np.column_stack([g, np.zeros(len(g))])
    return K, face, np.tile([0.0, 0.0, -1.0], (len(face), 1))


def _face_pixels(K, face, T):
    uv = (K.K @ (face @ T[:3, :3].T + T[:3, 3]).T).T
    uv = uv[:, :2] / uv[:, 2:]
    c0, r0 = np.floor(uv.min(0)).astype(int)
    c1, r1 = np.ceil(uv.max(0)).astype(int)
    return slice(r0, r1 + 1), slice(c0, c1 + 1)


def _box_top_and_neighbour(gap_px: int):
    """A box top 1.3 m below the camera on a pallet at 1.5 m, and a neighbour's top in the
    same plane ``gap_px`` pixels to its right (0: flush with it)."""
    K, face, normals = _face_and_depth()
    T = make_transform(np.eye(3), [0.0, 0.0, 1.3])
    rows, cols = _face_pixels(K, face, T)
    depth = np.full((240, 320), 1.5, np.float32)
    depth[rows, cols] = 1.3
    neighbour = (rows, slice(cols.stop + gap_px, cols.stop + 60))
    depth[neighbour] = 1.3
    return K, face, normals, T, rows, cols, depth, neighbour


def test_outline_continuation_ignores_a_neighbour_past_a_gap_and_what_lies_below():
    from multi_instance_reg.rgbd.verify import outline_continuation

    # Pallet grid: the neighbour 1 cm (3 px) away, past a gap down to the pallet; the band
    # (0.5 to 1.5 voxels of 1 cm) reaches it.
    K, face, normals, T, rows, cols, depth, _ = _box_top_and_neighbour(3)
    share, n = outline_continuation(T, face, normals, depth, K, 0.01, 0.01)
    assert n > 50 and share < 0.05
    # Without the gap the same plane goes on from the outline: a piece of a larger surface.
    depth[rows, cols.stop:cols.stop + 60] = 1.3
    share, _ = outline_continuation(T, face, normals, depth, K, 0.01, 0.01)
    assert share > 0.15
    # A wall face seen head-on, standing on a floor flush with its lower edge (a carton on
    # a carton of its size): the surface below the object's lowest point is its support.
    depth = np.full((240, 320), 2.5, np.float32)
    depth[rows, cols] = 1.3
    depth[rows.stop:, cols] = 1.3                             # the same plane goes on below (+y: down)
    below, _ = outline_continuation(T, face, normals, depth, K, 0.01, 0.01)
    up = np.array([0.0, -1.0, 0.0])                           # camera y points down
    with_up, _ = outline_continuation(T, face, normals, depth, K, 0.01, 0.01, up=up)
    assert below > 0.1 and with_up < 0.02


def test_outline_shift_moves_a_face_onto_the_patch_its_outline_bounds():
    from multi_instance_reg.rgbd.verify import outline_shift

    K, face, normals = _face_and_depth()
    T = make_transform(np.eye(3), [0.0, 0.0, 1.3])
    rows, cols = _face_pixels(K, face, T)
    # The box top, a neighbour's top past a 3 px gap on the pallet's grid, pallet below.
    depth = np.full((240, 320), 1.5, np.float32)
    depth[rows, cols] = 1.3
    depth[rows, cols.stop + 3:cols.stop + 60] = 1.3
    off = T.copy()
    off[:3, 3] += [0.025, -0.015, 0.0]                        # 2.9 cm off along the face
    shift = outline_shift(off, face, normals, depth, K, 0.01, 0.01, reach=0.04)
    assert shift is not None and abs(shift[2]) < 1e-9
    assert np.linalg.norm(off[:3, 3] + shift - T[:3, 3]) < 0.006
    # At the right pose nothing to move.
    assert np.linalg.norm(outline_shift(T, face, normals, depth, K, 0.01, 0.01, reach=0.04)) < 0.003
    # Turned in its plane (about the line of sight, through its centre): the turn back.
    c, sn = np.cos(np.radians(7.0)), np.sin(np.radians(7.0))
    turned = T.copy()
    turned[:3, :3] = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ T[:3, :3]
    _, turn = outline_shift(turned, face, normals, depth, K, 0.01, 0.01, reach=0.04, with_turn=True)
    assert abs(np.degrees(turn) + 7.0) < 1.5
    # On a piece of a larger surface (no gap: the plane goes on beyond reach) no patch bounds it.
    depth[rows, cols.stop:cols.stop + 60] = 1.3
    assert outline_shift(off, face, normals, depth, K, 0.01, 0.01, reach=0.04) is None

def test_ppf_partners_stay_within_the_objects_reach_in_a_joined_segment():
    """A segment that joins the object with a wide surface far away (touching objects, a
    pallet's layer): the references still vote with partners on their own object."""
    model, ppf, T, P, N = _box_seen_by_ppf()
    g = np.stack(np.meshgrid(np.arange(0.6, 2.6, 0.012), np.arange(-1.0, 1.0, 0.012)), -1).reshape(-1, 2)
    far = np.column_stack([g, np.full(len(g), 1.4)])          # 28,000 points, all beyond the object's reach
    pts = np.vstack([P, far])
    nrm = np.vstack([N, np.tile([0.0, 0.0, -1.0], (len(far), 1))])
    s, m, poses, share = ppf.vote(pts, nrm, np.zeros(len(pts), np.int64), ref_step=1, max_partners=60)
    own = s < len(P)
    right = []
    for Tp in poses[own]:
        G = closest_symmetric_pose(T, Tp, model.symmetries)
        dR = np.degrees(np.arccos(np.clip((np.trace(G[:3, :3].T @ Tp[:3, :3]) - 1) / 2, -1, 1)))
        right.append(np.linalg.norm(G[:3, 3] - Tp[:3, 3]) < 0.02 and dR < 15)
    assert own.sum() == len(P) and np.mean(right) > 0.5


def test_texture_agreement_picks_the_symmetric_pose_the_matches_agree_with():
    """both: a shape pose showing textured faces is judged by the SIFT matches there."""
    from multi_instance_reg.rgbd.verify import texture_agreement

    model = _box_model()                                      # 0.3 x 0.2 x 0.15, 4 symmetric poses
    rng = np.random.default_rng(3)
    # Texture on the top (+z) face only: 40 keypoints; the bottom is plain.
    kp = np.column_stack([rng.uniform(-0.14, 0.14, 40), rng.uniform(-0.09, 0.09, 40), np.full(40, 0.075)])
    kp_normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    K = _intrinsics()
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.0])      # top towards the camera
    depth = np.full((240, 320), 1.0 - 0.075, np.float32)                 # the top face's depth
    S = next(D for D in model.symmetries.discrete if D[2, 2] > 0.99 and D[0, 0] < -0.99)    # 180 deg about z
    shape_pose = T @ S                                        # what shape gives: the other symmetric pose
    scene = kp[:12] @ T[:3, :3].T + T[:3, 3]                  # 12 matches on the true pose, 8 outliers
    model_xyz = np.vstack([kp[:12], kp[12:20]])
    scene_xyz = np.vstack([scene, rng.uniform(-0.2, 0.2, (8, 3)) + [0, 0, 1.0]])
    best, agree, shown = texture_agreement(shape_pose, kp, kp_normals, model.symmetries, model_xyz, scene_xyz,
                                           depth, K, 0.01, 0.01)
    assert agree == 12 and shown == 40
    assert np.allclose(best, T, atol=1e-9)                    # the texture chose the pose
    # The same pose with matches that agree with none of its symmetric poses (a distractor).
    _, agree, shown = texture_agreement(shape_pose, kp, kp_normals, model.symmetries, model_xyz,
                                        scene_xyz + [0.3, 0.0, 0.0], depth, K, 0.01, 0.01)
    assert agree == 0 and shown == 40
    # Turned over, the textured top faces away: nothing to agree with.
    flipped = make_transform(np.eye(3), [0.0, 0.0, 1.0 + 0.075])
    _, _, shown = texture_agreement(flipped, kp, kp_normals, None, model_xyz, scene_xyz, depth, K, 0.01, 0.01)
    assert shown == 0


@pytest.mark.parametrize("association", ["nearest", "projective"])
def test_refinement_corrects_a_box_pose_with_either_icp_association(association):
    from dataclasses import replace

    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    model = _box_model()
    intr = _intrinsics()
    K = intr.K
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.5])       # top (+z) at 1.425 m, facing the camera
    # Depth image: the box's top over a floor at the box's bottom (1.575 m).
    v, u = np.mgrid[0:240, 0:320]
    depth = np.full((240, 320), 1.575, np.float32)
    x, y = (u - K[0, 2]) / K[0, 0] * 1.425, (v - K[1, 2]) / K[1, 1] * 1.425
    depth[(np.abs(x) < 0.15) & (np.abs(y) < 0.1)] = 1.425
    shape = ShapeFrontEnd(model, replace(FrontEndConfig(), shape_icp_association=association))
    cloud = shape.frame_cloud(depth, intr, None)
    # Tilted 6 deg and 6 mm too far: the top's ends are off by more than the depth check's
    # tolerance, so only a refined pose is supported better than the start.
    a = np.radians(6.0)
    start = T @ make_transform(np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]), [0, 0, 0])
    start[:3, 3] += [0.004, -0.003, 0.006]
    kept = shape.refine_and_check([start], cloud, depth, intr)
    assert len(kept) == 1
    out = kept[0][0]
    assert rotation_angle_deg(out[:3, :3].T @ T[:3, :3]) < 2.0
    assert abs(out[2, 3] - T[2, 3]) < 0.002                            # the depth is corrected
    # A face seen alone does not fix the pose along it: the top's centre slides no further
    # from where it is than where it started.
    top = np.array([0.0, 0.0, 0.075, 1.0])
    assert np.linalg.norm((out @ top - T @ top)[:2]) < np.linalg.norm((start @ top - T @ top)[:2]) + 0.002


def test_the_warm_up_frame_shows_the_object_where_it_was_drawn():
    # warm_up runs the shape path on a made-up frame so that its compiled kernels are built
    # before the first real frame; that frame must be one the path works through, up to a pose.
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.symmetry import closest_symmetric_pose

    model = _box_model()
    reg = InstanceRegistration(model, PipelineConfig())
    depth, intr, T = reg._shape.warm_up_frame()
    assert depth.shape == (intr.height, intr.width) and np.all(depth > 0)
    found = reg.register_frame(np.zeros(depth.shape + (3,), np.uint8), depth, intr).instances
    assert len(found) == 1
    Ts = closest_symmetric_pose(found[0].T, T, model.symmetries)
    assert rotation_angle_deg(Ts[:3, :3].T @ T[:3, :3]) < 3.0 and np.linalg.norm(Ts[:3, 3] - T[:3, 3]) < 0.01
    reg.warm_up()


def test_depth_points_and_normals_are_the_central_differences_of_the_depth_image():
    # The outline checks' compiled per-pixel points and normals against the same central
    # differences written with whole arrays: a tilted plane with holes, pixels at the border.
    from multi_instance_reg.rgbd.verify import _points_and_normals

    K = _intrinsics().K
    rng = np.random.default_rng(3)
    rows_all, cols_all = np.mgrid[0:240, 0:320]
    depth = (1.2 + 0.001 * cols_all + 0.0005 * rows_all + rng.normal(0, 0.002, (240, 320))).astype(np.float32)
    depth[rng.random((240, 320)) < 0.05] = 0.0
    rows, cols = rng.integers(0, 240, 3000), rng.integers(0, 320, 3000)
    P, n, ok = _points_and_normals(depth, K, rows, cols, step=2)

    def xyz(r, c):
        z = depth[r, c].astype(np.float64)
        return np.stack([z * (c - K[0, 2]) / K[0, 0], z * (r - K[1, 2]) / K[1, 1], z], axis=1)

    inside = (rows >= 2) & (rows < 238) & (cols >= 2) & (cols < 318)
    r, c = np.clip(rows, 2, 237), np.clip(cols, 2, 317)
    centre, right, left, down, up = (xyz(r + dr, c + dc) for dr, dc in ((0, 0), (0, 2), (0, -2), (2, 0), (-2, 0)))
    expect_ok = inside & (centre[:, 2] > 0) & (right[:, 2] > 0) & (left[:, 2] > 0) & (down[:, 2] > 0) & (up[:, 2] > 0)
    assert np.array_equal(ok, expect_ok) and 0 < ok.sum() < len(ok)
    m = np.cross(right - left, down - up)[expect_ok]
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    m *= np.where(np.einsum("ij,ij->i", m, centre[expect_ok]) > 0, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(P, centre[expect_ok], rtol=0, atol=1e-12)
    np.testing.assert_allclose(n, m, rtol=0, atol=1e-9)
    assert (np.einsum("ij,ij->i", n, P) < 0).all()           # towards the camera


def test_votes_split_over_threads_give_the_peaks_of_one_call(monkeypatch):
    import multi_instance_reg.rgbd.ppf as ppf_module

    model, ppf, T, P, N = _box_seen_by_ppf()
    labels = np.zeros(len(P), np.int64)
    split = ppf.vote(P, N, labels, ref_step=1, max_partners=200)
    assert len(split[0]) >= 128          # enough references for two parts
    monkeypatch.setattr(ppf_module, "map_in_chunks", lambda function, rows, min_chunk=0: [function(rows)])
    whole = ppf.vote(P, N, labels, ref_step=1, max_partners=200)
    for a, b in zip(split, whole):
        assert np.array_equal(a, b)


def _box_top_on_floor():
    """The box model's pose seen from above, 1.5 m away, and a depth image of its top (the
    0.3 x 0.2 m face, 1.425 m away) on a floor 1.575 m away; and the intrinsics."""
    intr = _intrinsics()
    K = intr.K
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 1.5])
    v, u = np.mgrid[0:240, 0:320]
    depth = np.full((240, 320), 1.575, np.float32)
    x, y = (u - K[0, 2]) / K[0, 0] * 1.425, (v - K[1, 2]) / K[1, 1] * 1.425
    depth[(np.abs(x) < 0.15) & (np.abs(y) < 0.1)] = 1.425
    return T, depth, intr


def test_refinement_in_the_thread_pool_gives_the_serial_results():
    """Hypotheses refined two at a time, and some of them started early (``start_refining``,
    as the pipeline does during ECC), give exactly what one at a time gives, in the same order."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.symmetry import _rotation

    model = _box_model()
    T, depth, intr = _box_top_on_floor()
    shape = ShapeFrontEnd(model, FrontEndConfig())
    cloud = shape.frame_cloud(depth, intr, None)
    rng = np.random.default_rng(3)
    hypotheses = [T @ make_transform(_rotation(rng.normal(size=3), np.radians(rng.uniform(0, 40))),
                                     rng.normal(0, 0.03, 3)) for _ in range(12)]
    hypotheses += [hypotheses[2].copy(), T.copy()]          # a duplicate, and the true pose
    order = shape.distinct(hypotheses)
    assert 2 < len(order) < len(hypotheses)                  # the duplicate is refined once
    firsts = [shape.refine_one(np.array(hypotheses[k]), cloud, depth, intr) for k in order]
    serial = [r for r in firsts if r is not None]
    failed = [k for k, r in zip(order, firsts) if r is None]
    assert len(serial) >= 1 and len(failed) >= 1
    for early in (None, 4):
        # The groups whose first failed, tried again from their next (``_next_of_failed``),
        # go to ``second`` (only where no instance is).
        again = [shape.refine_one(np.array(hypotheses[k]), cloud, depth, intr)
                 for k in shape._next_of_failed(hypotheses, order, failed, early or 0)]
        again = [r for r in again if r is not None]
        started = None
        if early is not None:
            started = shape.start_refining(hypotheses[early:], cloud, depth, intr)
        second = []
        pooled = shape.refine_and_check(hypotheses, cloud, depth, intr, started, early or 0, second=second)
        assert len(again) >= 1 and len(pooled) == len(serial) and len(second) == len(again)
        for a, b in zip(pooled + second, serial + again):
            assert np.array_equal(a[0], b[0]) and a[1:] == b[1:]


def _near_places(Ps, poses=None):
    """An ``overlaps`` for ``refine_and_check``: poses whose origins lie within 10 cm share a place."""
    poses = Ps if poses is None else poses
    return np.array([[np.linalg.norm(P[:3, 3] - Q[:3, 3]) < 0.1 for Q in poses] for P in Ps], bool
                    ).reshape(len(Ps), len(poses))


def test_a_rejected_pose_where_one_is_kept_gets_no_further_tries():
    """``refine_and_check(overlaps=)``: every hypothesis is judged first; a rejected one that
    takes a kept one's place gets no further tries (``_rescue``: moved onto its outline's
    patch, looked at again), one clear of every kept pose does."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd, _Plain

    T, depth, intr = _box_top_on_floor()
    shape = ShapeFrontEnd(_box_model(), FrontEndConfig())
    cloud = shape.frame_cloud(depth, intr, None)
    off = T.copy()
    off[0, 3] += 0.06                                         # along the top: overhangs the floor
    tried = []
    rescue = shape._rescue
    shape._rescue = lambda plain, *a: tried.append(plain) or rescue(plain, *a)
    never = lambda Ps, poses=None: np.zeros((len(Ps), len(Ps if poses is None else poses)), bool)
    plain = [shape._refine_plain(H, cloud, depth, intr) for H in (T, off)]
    assert isinstance(plain[0], _Plain) and plain[0].kept is not None        # the true pose: kept as judged
    assert shape.wants_rescue(plain[1])                   # the shifted one: rejected, though the depth supports it
    for overlaps, expected in ((None, 1), (never, 1), (_near_places, 0)):
        tried.clear()
        shape.refine_and_check([T, off], cloud, depth, intr, overlaps=overlaps)
        assert len(tried) == expected
        assert all(np.array_equal(t.T, plain[1].T) for t in tried)


def test_of_the_rejected_poses_on_one_place_only_the_best_fits_get_further_tries():
    """``shape_rescues_per_place``: rejected poses on one place (``overlaps``) get the further
    tries only as many as that, the best fits (support - free) first; those on other places
    their own; 0 tries them all."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd, _Plain

    T, depth, intr = _box_top_on_floor()
    offs = []
    for dx, dy in ((0.06, 0.0), (0.02, 0.05), (-0.07, -0.03)):     # two overhanging on one side, one on the other
        off = T.copy()
        off[0, 3] += dx
        off[1, 3] += dy
        offs.append(off)
    for per_place, expected in ((1, 2), (2, 3), (0, 3)):
        shape = ShapeFrontEnd(_box_model(), FrontEndConfig(shape_rescues_per_place=per_place))
        cloud = shape.frame_cloud(depth, intr, None)
        plain = [shape._refine_plain(H, cloud, depth, intr) for H in offs]
        assert all(isinstance(p, _Plain) and shape.wants_rescue(p) for p in plain)
        places = _near_places([p.T for p in plain])
        assert places[0, 1] and not places[0, 2] and not places[1, 2]
        tried = []
        rescue = shape._rescue
        shape._rescue = lambda p, *a, rescue=rescue: tried.append(p) or rescue(p, *a)
        shape.refine_and_check(offs, cloud, depth, intr, overlaps=_near_places)
        assert len(tried) == expected
        if per_place == 1:
            first = max(plain[:2], key=lambda p: p.support - p.free)
            assert any(np.array_equal(t.T, first.T) for t in tried)
            assert any(np.array_equal(t.T, plain[2].T) for t in tried)


def test_overhanging_and_flush_rejected_poses_on_one_place_each_get_their_own_tries():
    """Only a pose overhanging space seen empty gets the second look and turned starts: with
    ``shape_rescues_per_place`` 1, the best overhanging pose on a place is tried beside the best
    flush one, though a better flush one is left out."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd, _Plain

    T, depth, intr = _box_top_on_floor()
    shape = ShapeFrontEnd(_box_model(), FrontEndConfig(shape_rescues_per_place=1))
    cloud = shape.frame_cloud(depth, intr, None)
    figures = {0.0: (0.95, 0.0), 0.05: (0.9, 0.0), -0.05: (0.8, 0.1)}     # shift: support, free
    poses = []
    for dx in figures:
        P = T.copy()
        P[0, 3] += dx
        poses.append(P)
    shape._refine_plain = lambda T0, *a: _Plain(None, T0, *figures[round(T0[0, 3], 3)], T0, (0.0, 0.0, 0.0, 0))
    tried = []
    shape._rescue = lambda p, *a: tried.append(round(p.T[0, 3], 3)) or (None, p.T, p.support, None)
    shape.refine_and_check(poses, cloud, depth, intr, overlaps=_near_places)
    assert sorted(tried) == [-0.05, 0.0]


def test_best_per_place_keeps_a_pose_unless_as_many_better_ones_taken_overlap_it():
    from types import SimpleNamespace

    from multi_instance_reg.rgbd.shape_frontend import best_per_place

    poses = [SimpleNamespace(support=s + 0.1, free=0.1, name=i) for i, s in enumerate((0.5, 0.9, 0.7, 0.8, 0.6, 0.55))]
    overlap = np.eye(6, dtype=bool)
    overlap[0, 1] = overlap[2, 1] = overlap[0, 2] = True        # 0, 1, 2 one place (either way)
    overlap[4, 3] = True                                        # 3, 4 another
    overlap[5, 4] = True                                        # 5 overlaps 4 alone (left out): taken
    assert [p.name for p in best_per_place(poses, overlap, 1)] == [1, 3, 5]
    assert [p.name for p in best_per_place(poses, overlap, 2)] == [1, 2, 3, 4, 5]
    assert [p.name for p in best_per_place(poses, overlap, 3)] == [0, 1, 2, 3, 4, 5]


def test_a_group_whose_first_fails_is_tried_again_from_its_next_vote_pose():
    """``distinct`` refines the first of each group of near-identical hypotheses; where that
    one fails, ``_next_of_failed`` names the group's next one at or after ``offset`` (the vote
    poses, after ECC's), one a group; groups whose first passed, and ECC's own duplicates
    before ``offset``, are not tried again."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.symmetry import _rotation

    shape = ShapeFrontEnd(_box_model(), FrontEndConfig())
    A = make_transform(np.eye(3), [0.0, 0.0, 1.5])
    B = make_transform(_rotation(np.array([0.0, 1.0, 0.0]), np.radians(90.0)), [0.3, 0.0, 1.5])
    near = make_transform(_rotation(np.array([1.0, 0.0, 0.0]), np.radians(5.0)), [0.002, 0.0, 0.0])
    # ECC: A, B, A again; votes (offset 3): B, A, A, B.
    hypotheses = [A, B, A @ near, B @ near, A @ near @ near, A, B]
    order = shape.distinct(hypotheses)
    assert sorted(order) == [0, 1]
    assert shape._next_of_failed(hypotheses, order, [0], 3) == [4]
    assert shape._next_of_failed(hypotheses, order, [0, 1], 3) == [3, 4]
    assert shape._next_of_failed(hypotheses, order, [1], 3) == [3]
    assert shape._next_of_failed(hypotheses, order, [], 3) == []
    assert shape._next_of_failed(hypotheses, order, [0], 7) == []


def test_thread_pool_helpers_keep_order_and_raise_errors():
    from multi_instance_reg.rgbd.shape_frontend import Prefetch
    from multi_instance_reg.threads import map_each, submit_each

    assert map_each(lambda x: x * x, range(20)) == [x * x for x in range(20)]
    task = submit_each(lambda x: 1 // x, [0])[0]
    with pytest.raises(ZeroDivisionError):
        task.result()
    done = Prefetch(lambda x: x + 100, list(range(10)), range(9, -1, -1))
    claimed = done.stop()
    assert claimed <= set(range(10))
    assert all(done.result(k) == k + 100 for k in claimed)


def _depth_of(points, T, intr):
    """A depth image of dense surface points at pose T: the nearest per pixel (a z-buffer)."""
    P = points @ T[:3, :3].T + T[:3, 3]
    K = intr.K
    u = np.round(K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]).astype(int)
    ok = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    depth = np.full((intr.height, intr.width), np.inf)
    np.minimum.at(depth, (v[ok], u[ok]), P[ok, 2])
    depth[np.isinf(depth)] = 0.0
    return depth.astype(np.float32)


def _bracket_before_a_wall():
    """A bracket seen from above at 0.6 m, a wall 0.3 m behind it: (intrinsics, its pose,
    its mesh, the depth image)."""
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([0.3, -0.3, 0.4]), np.zeros(3)))
    mesh = object_mesh(get_object("bracket"))
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    return intr, T, mesh, np.where(depth > 0, depth, np.float32(T[2, 3] + 0.3))


def _two_brackets_side_by_side():
    """(bracket mesh, intrinsics, T1, T2, depth): two brackets side by side, the second turned
    90 deg about the first's z and touching it (one segment in the frame cloud)."""
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T1 = invert_transform(look_at(np.array([0.35, -0.25, 0.4]), np.zeros(3)))
    T2 = T1 @ make_transform(rotation_z(90.0), [0.02, 0.09, 0.0])
    dense, _ = sample_surface(mesh, 0.001)
    first, second = _depth_of(dense, T1, intr), _depth_of(dense, T2, intr)
    depth = np.where((first > 0) & ((second == 0) | (first < second)), first, second)
    return mesh, intr, T1, T2, depth


def test_depth_support_leaves_out_what_a_bracket_hides_of_itself():
    from multi_instance_reg.rgbd.shape import depth_support, is_convex
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    surface, normals = shape._surface, shape._surface_normals
    assert not is_convex(surface, normals, shape.voxel) and shape._self_hiding > 0
    for solid in (box_mesh(0.3, 0.2, 0.15), box_mesh(0.08, 0.07, 0.05)):
        box = build_model_from_mesh(solid, "box")
        assert ShapeFrontEnd(box, PipelineConfig().frontend)._self_hiding == 0.0
    # Seen from behind its upright plate (at -x) and above: the base plate's top faces the
    # camera, and the upright hides the part of it next to the corner.
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([-0.5, 0.1, 0.35]), np.zeros(3)))      # object -> camera
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    tol = 0.008
    plain = depth_support(T, surface, normals, depth, intr, tol)
    seen = depth_support(T, surface, normals, depth, intr, tol, shape._self_hiding)
    assert plain[0] < 0.85                          # the hidden part counted against the true pose
    assert seen[0] > 0.95 and seen[1] < 0.03 and seen[2] < plain[2]
    # What the model hides of itself is only left out, never counted for a pose: moved 2-3 cm,
    # support - free stays short of the evidence the depth check asks for (0.8; along the
    # plates' extrusion 0.73 at 2 cm, 0.50 without the self-hiding).
    for shift in ([0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.03], [0.0, 0.02, 0.0], [0.0, 0.0, 0.02]):
        support, free, _ = depth_support(T @ make_transform(np.eye(3), shift), surface, normals, depth, intr, tol,
                                         shape._self_hiding)
        assert support - free < 0.78


def test_a_box_half_hidden_by_an_instance_found_is_judged_by_what_is_in_view():
    _, shape, intr, front, back, depth = _front_and_back_boxes()
    cloud = shape.frame_cloud(depth, intr, None)
    assert shape.refine_one(front, cloud, depth, intr) is not None
    assert shape.refine_one(back, cloud, depth, intr) is None          # its hidden part counted against it
    rejected = []
    kept = shape.refine_and_check([front, back], cloud, depth, intr, rejected=rejected)
    assert len(kept) == 1 and len(rejected) == 1                       # the back box, for too little support
    assert np.linalg.norm(rejected[0][:3, 3] - back[:3, 3]) < 0.01
    occluders = shape.instance_pixels([front], depth, intr)
    again = shape.judge_behind(back, cloud, depth, intr, occluders, [front])
    assert again is not None and np.allclose(again[0], back) and again[1] > 0.95
    # Hidden behind the front box's face, but inside its box: not explained by it.
    inside = front @ make_transform(np.eye(3), [0.0, 0.0, 0.02])
    assert shape.judge_behind(inside, cloud, depth, intr, occluders, [front]) is None



def test_instance_pixels_kept_for_the_frame_equal_a_fresh_drawing():
    _, shape, intr, front, back, depth = _front_and_back_boxes()
    fresh = shape.instance_pixels([front, back], depth, intr)
    assert fresh.any() and shape.instance_pixels([front, back], depth, intr) is not fresh   # nothing kept
    shape.keep_frame(depth, intr)
    first = shape.instance_pixels([front, back], depth, intr)
    assert np.array_equal(first, fresh) and not first.flags.writeable                 # shared: read-only
    assert shape.instance_pixels([front, back], depth, intr) is first                 # kept, by the poses
    alone = shape.instance_pixels([front], depth, intr)                                # other poses: drawn
    assert np.array_equal(alone, shape._instance_pixels([front], depth, intr)) and not np.array_equal(alone, first)
    # Another depth image is drawn, not taken from the one kept.
    other = np.zeros_like(depth)
    assert not shape.instance_pixels([front, back], other, intr).any()
    shape.keep_frame(None)
    assert shape.instance_pixels([front, back], depth, intr) is not first


def test_depth_checks_kept_for_the_frame_equal_fresh_ones(monkeypatch):
    from multi_instance_reg.rgbd import shape_frontend

    _, shape, intr, front, back, depth = _front_and_back_boxes()
    calls = []
    kernel = shape_frontend.depth_support
    monkeypatch.setattr(shape_frontend, "depth_support", lambda *a: calls.append(a[-1]) or kernel(*a))
    occluders = shape.instance_pixels([front], depth, intr)
    fresh = [shape.depth_check(back, depth, intr), shape.depth_check(back, depth, intr, occluders)]
    assert fresh[0] != fresh[1] and len(calls) == 2                         # the front box hides some
    shape.keep_frame(depth, intr)
    kept = [shape.depth_check(back, depth, intr), shape.depth_check(back, depth, intr, shape.instance_pixels([front], depth, intr))]
    assert kept == fresh and len(calls) == 4
    assert shape.depth_check(back.copy(), depth, intr) == fresh[0] and len(calls) == 4     # by the pose's bytes
    assert shape.depth_check(front, depth, intr) != fresh[0] and len(calls) == 5           # another pose: checked
    # Occluders that can change (writeable) are checked each time, not taken from the kept.
    mine = np.zeros(depth.shape, np.uint8)
    assert shape.depth_check(back, depth, intr, mine) == fresh[0] and len(calls) == 6
    mine[:] = 1
    assert shape.depth_check(back, depth, intr, mine) != fresh[0] and len(calls) == 7
    every = shape.depth_check(back, depth, intr, shape.every_pixel(depth))
    assert every == shape.depth_check(back, depth, intr, mine) and len(calls) == 9
    assert shape.depth_check(back, depth, intr, shape.every_pixel(depth)) == every and len(calls) == 9   # read-only: kept
    shape.keep_frame(None)
    shape.depth_check(back, depth, intr)
    assert len(calls) == 10

def _front_and_back_boxes():
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    solid = box_mesh(0.08, 0.07, 0.05)
    model = build_model_from_mesh(solid, "block")
    shape = ShapeFrontEnd(model, PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    turn = np.array([[1.0, 0, 0], [0, -0.8, -0.6], [0, 0.6, -0.8]])     # top and a side towards the camera
    front = make_transform(turn, [0.0, 0.0, 0.6])
    back = make_transform(turn, [0.06, 0.0, 0.7])                     # its left part behind the front box
    dense, _ = sample_surface(solid, 0.001)
    depth = np.maximum(_depth_of(dense, front, intr), 0)
    behind = _depth_of(dense, back, intr)
    depth = np.where((depth == 0) | ((behind > 0) & (behind < depth)), behind, depth)
    return model, shape, intr, front, back, depth


def test_two_rejected_poses_are_judged_as_a_pair_each_with_the_other_found():
    from multi_instance_reg.rgbd.pipeline import box_grid, box_overlaps

    model, shape, intr, front, back, depth = _front_and_back_boxes()
    cloud = shape.frame_cloud(depth, intr, None)
    grid = box_grid(model.extent) + np.asarray(model.box_centre, np.float64)
    none = np.zeros(depth.shape, np.uint8)
    assert shape.judge_behind(back, cloud, depth, intr, none, []) is None      # alone: what is hidden counts
    poses = [back, front]
    overlap = box_overlaps(model, poses, grid)
    assert shape.judge_pairs(poses, overlap, 0.3, cloud, depth, intr, none, []) == []   # convex: not judged so
    # Judged as a non-convex model's poses are (a box never hides itself: the same checks).
    shape._self_hiding = 0.75 * shape.voxel
    pairs = shape.judge_pairs(poses, overlap, 0.3, cloud, depth, intr, none, [])
    assert [(i, j) for i, j, _, _ in pairs] == [(0, 1)]
    assert pairs[0][2][1] > 0.95 and np.allclose(pairs[0][2][0], back)
    # A pose sunk into the front box is hidden by the front box, not by the other pose.
    sunk = front @ make_transform(np.eye(3), [0.0, 0.0, 0.02])
    poses = [back, sunk]
    assert shape.judge_pairs(poses, box_overlaps(model, poses, grid), 0.3, cloud, depth, intr, none, []) == []


def test_a_pair_passes_with_a_member_as_its_second_look_places_it(monkeypatch):
    """Two rejected poses that pass as a pair at their true poses, one of them left tilted by
    the refinement (as nearest-point ICP left a channel lying flush beside another 2 deg
    off, its outline running past the neighbour: channel seed 2187 frames 6 / 7): judged as
    refined the pair fails; with that member as its projective look places it (stubbed:
    onto the truth), it passes, and the pose the pair returns is the look's."""
    from multi_instance_reg.rgbd.pipeline import box_grid, box_overlaps
    from multi_instance_reg.rgbd.shape import apply_twist

    model, shape, intr, front, back, depth = _front_and_back_boxes()
    cloud = shape.frame_cloud(depth, intr, None)
    grid = box_grid(model.extent) + np.asarray(model.box_centre, np.float64)
    none = np.zeros(depth.shape, np.uint8)
    shape._self_hiding = 0.75 * shape.voxel            # judged as a non-convex model's poses
    tilted = apply_twist(front, np.array([np.radians(8.0), 0.0, 0.0, 0.0, 0.0, 0.0]),
                         shape._visible_surface(front).mean(axis=0))
    poses = [back, tilted]
    overlap = box_overlaps(model, poses, grid)
    still = lambda T, depth_m, intrinsics: (np.array(T), None)
    monkeypatch.setattr(shape, "_projective_look", still)
    assert shape.judge_pairs(poses, overlap, 0.3, cloud, depth, intr, none, []) == []
    onto_front = lambda T, depth_m, intrinsics: (front.copy() if np.allclose(T, tilted) else np.array(T), None)
    monkeypatch.setattr(shape, "_projective_look", onto_front)
    pairs = shape.judge_pairs(poses, overlap, 0.3, cloud, depth, intr, none, [])
    assert [(i, j) for i, j, _, _ in pairs] == [(0, 1)]
    assert np.allclose(pairs[0][2][0], back) and np.allclose(pairs[0][3][0], front)


def test_a_pose_behind_a_nearer_surface_is_judged_by_what_is_in_view_where_the_depth_steps_in_front(monkeypatch):
    import multi_instance_reg.rgbd.shape_frontend as shape_frontend

    model, shape, intr, front, back, depth = _front_and_back_boxes()
    cloud = shape.frame_cloud(depth, intr, None)
    # The front box not found (a distractor): the back one passes with what it hides left out.
    again = shape.judge_hidden(back, cloud, depth, intr, None)
    assert again is not None and np.allclose(again[0], back) and again[1] > 0.95
    assert shape.judge_hidden(back, cloud, depth, intr, None, [front]) is not None   # nothing of it in that box
    # A box sunk 1 cm into the front one (rendered so): its hidden part goes on into the front
    # box's surface, no step in front of it.
    solid = box_mesh(0.08, 0.07, 0.05)
    dense, _ = sample_surface(solid, 0.001)
    sunk = make_transform(front[:3, :3], [0.06, 0.0, 0.61])
    depth = np.maximum(_depth_of(dense, front, intr), 0)
    other = _depth_of(dense, sunk, intr)
    depth = np.where((depth == 0) | ((other > 0) & (other < depth)), other, depth)
    cloud = shape.frame_cloud(depth, intr, None)
    assert shape.judge_hidden(sunk, cloud, depth, intr, None) is None
    monkeypatch.setattr(shape_frontend, "HIDDEN_STEP", 0.0)
    assert shape.judge_hidden(sunk, cloud, depth, intr, None) is not None
    # ... and with the front box found, its points inside that box count against it anyway.
    assert shape.judge_hidden(sunk, cloud, depth, intr, None, [front]) is None


def test_the_step_in_front_of_a_hidden_part_is_measured_across_a_band_with_no_depth():
    """The depth lost along the front box's edge (the spread and the stereo shadow there: 4-8
    px, 1.5-3 voxels) lies between the back box's hidden and agreeing points, so none is next
    to the other: the agreeing points' depth is carried across the band, and the back box
    passes as where none is lost. A box sunk into the front one still does not."""
    model, shape, intr, front, back, depth = _front_and_back_boxes()
    solid = box_mesh(0.08, 0.07, 0.05)
    dense, _ = sample_surface(solid, 0.001)
    mine = _depth_of(dense, front, intr) > 0
    sunk = make_transform(front[:3, :3], [0.06, 0.0, 0.61])
    other = _depth_of(dense, sunk, intr)
    into = np.where(~mine | ((other > 0) & (other < depth)), other, depth)
    for r in (4, 8):
        band = (cv2.dilate(mine.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0) & ~mine
        lost = np.where(band, 0, depth).astype(np.float32)
        again = shape.judge_hidden(back, shape.frame_cloud(lost, intr, None), lost, intr, None)
        assert again is not None and np.allclose(again[0], back) and again[1] > 0.95
        lost = np.where(band, 0, into).astype(np.float32)
        assert shape.judge_hidden(sunk, shape.frame_cloud(lost, intr, None), lost, intr, None) is None


def test_a_bracket_split_by_a_depth_step_is_voted_as_one_pair_of_segments():
    """Seen from behind, a bracket's upright plate and its base plate past the depth step
    form two segments; each alone votes hardly a right pose, the pair voted together does."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.segments import pairs_across_steps
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([-0.5, 0.1, 0.35]), np.zeros(3)))
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    # A block beside it in the image (not across a step from it), and a wall behind both,
    # larger than the bracket's reach: neither is paired.
    block = _depth_of(sample_surface(box_mesh(0.04, 0.04, 0.04), 0.001)[0], T @ make_transform(np.eye(3), [0, 0.2, 0]),
                      intr)
    depth = np.where(block > 0, block, depth)
    depth[:60, :] = np.where(depth[:60, :] > 0, depth[:60, :], 0.9)
    cloud = shape.frame_cloud(depth, intr, None)

    def right(P, deg=15.0, metres=0.03):
        return rotation_angle_deg(P[:3, :3].T @ T[:3, :3]) < deg and np.linalg.norm(P[:3, 3] - T[:3, 3]) < metres

    on = np.flatnonzero(np.linalg.norm(cloud.points - T[:3, 3], axis=1) < 0.08)
    ids = np.unique(cloud.segments[on])
    assert len(ids) == 2 and np.all(ids >= 0)                     # the two plates
    pairs = pairs_across_steps(cloud.points, cloud.segments, shape.diameter,
                               shape.fe.shape_segment_link * shape.voxel)
    assert pairs == [tuple(ids)]
    _, _, own, _ = shape._ppf.vote(cloud.points, cloud.normals, cloud.segments, 5, 60)
    assert sum(right(P, 10.0, 0.02) for P in own) <= 3
    joined = shape.joined_poses(cloud)
    assert 1 <= len(joined) <= shape.fe.shape_joined_clusters and any(right(P) for P in joined)
    refined = [shape.refine_one(P, cloud, depth, intr) for P in joined]
    assert any(r is not None and right(r[0], 2.0, 0.005) for r in refined)


def test_vote_groups_in_one_call_give_each_groups_own_votes():
    model, ppf, T, P, N = _box_seen_by_ppf()
    third = len(P) // 3
    groups = [np.arange(0, 2 * third), np.arange(third, len(P))]           # overlapping
    together = ppf.vote_groups(P, N, groups, ref_step=3, max_partners=40)
    assert np.array_equal(np.unique(together[4]), [0, 1])
    for k, group in enumerate(groups):
        alone = ppf.vote_groups(P, N, [group], ref_step=3, max_partners=40)
        mine = together[4] == k
        for x, y in zip(together[:4], alone[:4]):
            assert np.array_equal(x[mine], y)
    # One group of one segment: the segment's votes.
    labels = np.zeros(len(P), np.int64)
    for x, y in zip(ppf.vote(P, N, labels, 3, 40), ppf.vote_groups(P, N, [np.arange(len(P))], 3, 40)):
        assert np.array_equal(x, y)


def test_outline_continuation_leaves_out_a_flush_neighbour_found_as_an_instance():
    from multi_instance_reg.rgbd.verify import outline_continuation

    K, face, normals, T, rows, cols, depth, neighbour = _box_top_and_neighbour(0)   # flush, no gap
    share, n = outline_continuation(T, face, normals, depth, K, 0.01, 0.01)
    assert share > 0.15
    found = np.zeros(depth.shape, np.uint8)
    found[neighbour] = 1                                       # ... found as an instance
    share, m = outline_continuation(T, face, normals, depth, K, 0.01, 0.01, explained=found)
    assert share < 0.02 and 0 < m < n


def test_a_box_flush_with_an_instance_found_is_judged_by_its_outline_without_it():
    from dataclasses import replace

    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    solid = box_mesh(0.08, 0.07, 0.05)
    fe = PipelineConfig().frontend
    shape = ShapeFrontEnd(build_model_from_mesh(solid, "block"), fe)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    turn = np.array([[1.0, 0, 0], [0, -0.8, -0.6], [0, 0.6, -0.8]])
    left, right = make_transform(turn, [-0.04, 0.0, 0.6]), make_transform(turn, [0.04, 0.0, 0.6])   # side by side, touching
    dense, _ = sample_surface(solid, 0.001)
    a, b = _depth_of(dense, left, intr), _depth_of(dense, right, intr)
    depth = np.where(a == 0, b, np.where(b == 0, a, np.minimum(a, b)))
    cloud = shape.frame_cloud(depth, intr, None)
    # Each box's faces go on into the other's: alone, each looks like a piece of a larger surface.
    rejected = []
    assert shape.refine_and_check([left, right], cloud, depth, intr, rejected=rejected) == []
    assert len(rejected) == 2
    occluders = shape.instance_pixels([left], depth, intr)
    again = shape.judge_behind(right, cloud, depth, intr, occluders, [left])
    assert again is not None and np.allclose(again[0], right) and again[1] > 0.95
    off = ShapeFrontEnd(build_model_from_mesh(solid, "block"), replace(fe, shape_outline_by_instances=False))
    assert off.judge_behind(right, cloud, depth, intr, occluders, [left]) is None


def test_a_bracket_pose_left_off_by_icp_gets_a_second_look_by_projective_icp(monkeypatch):
    """Where a bracket's plates meet, nearest-point ICP can stop a few degrees off (its pairs
    cross to the other plate); the pose then overhangs empty space and is rejected. The
    second look aligns it by projective ICP and returns it apart (``second``); a convex
    model, or the option off, gets none."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([0.3, -0.3, 0.4]), np.zeros(3)))
    off = apply_twist(T, np.array([0.0, np.radians(5.0), np.radians(2.0), 0.004, -0.003, 0.0]), T[:3, 3])
    for name, mesh in (("bracket", object_mesh(get_object("bracket"))), ("block", box_mesh(0.12, 0.06, 0.08))):
        dense, _ = sample_surface(mesh, 0.001)
        depth = _depth_of(dense, T, intr)
        depth = np.where(depth > 0, depth, np.float32(T[2, 3] + 0.3))      # a wall behind
        for on in (True, False):
            fe = replace(PipelineConfig().frontend, shape_second_look=on)
            shape = ShapeFrontEnd(build_model_from_mesh(mesh, name), fe)
            # The nearest-point ICP stopped where it started (as it does on a crowded table).
            monkeypatch.setattr(shape, "_icp", lambda T0, *a, **k: T0)
            cloud = shape.frame_cloud(depth, intr, None)
            second = []
            assert shape.refine_and_check([off], cloud, depth, intr, second=second) == []
            if name == "bracket" and on:
                assert len(second) == 1
                P = second[0][0]
                assert rotation_angle_deg(P[:3, :3].T @ T[:3, :3]) < 1.0
                assert np.linalg.norm(P[:3, 3] - T[:3, 3]) < 0.002 and second[0][1] > 0.95
            else:
                assert second == []


def test_a_pose_reaching_through_the_table_is_rejected():
    """A bracket on the table, and the same bracket turned over (180 deg about its long
    axis) and lowered so that its base plate lies where the true one's does: its upright
    plate is sunk into the table, which the depth check counts as hidden, and it passes
    there (support 0.88). The support plane rejects it; the true pose stays."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, 0.0, 0.4]), np.zeros(3))               # camera -> world, table z = 0
    T = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, 0.04])      # base plate's underside on it
    over = invert_transform(cam) @ make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, -0.028])
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    # The table: the plane z = 0 wherever the bracket is not.
    rays = _world_rays(cam, intr)
    table = (-cam[2, 3] / rays[..., 2]).astype(np.float32)              # depth: the rays have z = 1 in the camera
    depth = np.where((depth > 0) & (depth < table), depth, table)
    for on in (True, False):
        fe = replace(PipelineConfig().frontend, shape_reject_through_support=on)
        shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), fe)
        cloud = shape.frame_cloud(depth, intr, None)
        assert cloud.up is not None and float(cloud.up @ cam[2, :3]) > 0.99     # world z, in the camera frame
        assert not shape.pierces(T, cloud, depth, intr) and shape.pierces(over, cloud, depth, intr)
        assert shape.refine_one(T, cloud, depth, intr) is not None
        assert (shape.refine_one(over, cloud, depth, intr) is None) == on


def test_a_standing_bracket_below_a_plane_of_its_own_base_plates_top_does_not_reach_through_it():
    """Brackets standing flush on one table: their base plates' tops make a plane one plate
    (12 mm) above the table (here a board of that thickness around one bracket, its base
    plate's top flush with it), found as a support plane. The true pose's base plate lies
    below that plane by its thickness, but the rays onto it show the bracket's own top face
    in the plane, not a support in front of it (bracket seed 701 frame 4: 9 true poses of
    10 rejected). A pose turned over, its upright plate sunk into the table, still is; so is
    one sunk into the table (the plane it stands on), its base plate's top 4 mm under it:
    nothing stands below the table, so its own face there is no object top."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import BRACKET_THICKNESS_M, get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, 0.0, 0.4]), np.zeros(3))               # camera -> world, table z = 0
    T = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, 0.04])      # base plate's underside on it
    over = invert_transform(cam) @ make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, -0.028])
    sunk = invert_transform(cam) @ make_transform(np.eye(3), [-0.05, -0.17, 0.04 - BRACKET_THICKNESS_M - 0.004])
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    seen = _depth_of(dense, sunk, intr)
    depth = np.where((seen > 0) & ((depth == 0) | (seen < depth)), seen, depth)
    rays = _world_rays(cam, intr)
    table = (-cam[2, 3] / rays[..., 2]).astype(np.float32)
    # The plane fitted over many plates' tops lay a few mm above this one's (seed 701: its
    # base plate's underside 14-16 mm below it, beyond the 2 voxels).
    top = BRACKET_THICKNESS_M + 0.004
    board = ((top - cam[2, 3]) / rays[..., 2]).astype(np.float32)
    x, y = cam[0, 3] + board * rays[..., 0], cam[1, 3] + board * rays[..., 1]
    ground = np.where((np.abs(x) <= 0.15) & (np.abs(y) <= 0.1), board, table)
    depth = np.where((depth > 0) & (depth < ground), depth, ground)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None)
    level = [(up, o) for up, o in cloud.planes if float(cam[:3, :3] @ up @ [0, 0, 1]) > 0.99]
    board_plane = [(up, o) for up, o in level if abs(o - (cam[2, 3] - top)) < 0.003]
    assert len(board_plane) == 1 and abs(cloud.up_offset - cam[2, 3]) < 0.003     # the table is the support
    up, offset = board_plane[0]
    pts = shape._surface @ T[:3, :3].T + T[:3, 3]
    below = pts[pts @ up + offset < -2 * shape.voxel]                      # its base plate, under the board's plane
    assert len(below) > 0 and shape._pierces_plane(below, up, offset, depth, intr)   # without its own face: through
    assert not shape.pierces(T, cloud, depth, intr)
    assert shape.pierces(over, cloud, depth, intr)
    assert shape.pierces(sunk, cloud, depth, intr)


def test_an_object_beyond_the_tables_edge_and_lower_does_not_reach_through_it():
    """The table (the largest plane) ends at world x = -0.22 and the floor lies 5 cm lower
    beyond it: a bracket standing on the floor there is mostly below the table's plane, but
    the depth on its rays reaches past that plane. Only the plane where it is there counts."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.15, 0.0, 0.4]), np.array([-0.1, 0.0, 0.0]))     # camera -> world, table z = 0
    on_floor = invert_transform(cam) @ make_transform(np.eye(3), [-0.32, 0.0, -0.05 + 0.04])   # floor z = -0.05
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, on_floor, intr)
    rays = _world_rays(cam, intr)
    table = (-cam[2, 3] / rays[..., 2]).astype(np.float32)
    floor = ((-0.05 - cam[2, 3]) / rays[..., 2]).astype(np.float32)
    on_table = cam[0, 3] + table * rays[..., 0] > -0.22
    ground = np.where(on_table, table, floor)
    assert ((depth > 0) & (depth < ground)).sum() > 1000                  # the bracket in view
    depth = np.where((depth > 0) & (depth < ground), depth, ground)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None)
    assert cloud.up is not None and float(cloud.up @ cam[2, :3]) > 0.99
    assert abs(cloud.up_offset - 0.4) < 0.01                              # the table, not the floor
    heights = (dense @ on_floor[:3, :3].T + on_floor[:3, 3]) @ cloud.up + cloud.up_offset
    assert np.mean(heights < -2 * shape.voxel) > 0.3                      # the plane without bound would cut it
    assert not shape.pierces(on_floor, cloud, depth, intr)
    assert shape.refine_one(on_floor, cloud, depth, intr) is not None


def test_touching_objects_whose_tops_are_found_as_a_plane_do_not_reach_through_it():
    """Six channels open side down, side by side on the table: their flush tops (5 cm up,
    larger together than three of the object's faces) are found as a support plane, and
    each true pose reaches 5 cm below it, where on many rays the depth stops at it (the
    channel's own top, or the neighbour's in front). None reaches through it: nothing of
    them lies above it. Raised 2 cm, each would (channel seeds 9 / 503: every true pose
    below such tops was rejected). (With shape_keep_object_tops, as by default, the tops
    are not taken for a plane at all: they stand at the channel's height above the table,
    nothing on them.)"""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.45, 0.0, 0.65]), np.zeros(3))       # camera -> world, table z = 0
    down = np.diag([1.0, -1.0, -1.0])                             # open side down
    poses = [invert_transform(cam) @ make_transform(down, [x, y, 0.025])
             for x in (-0.1, 0.0, 0.1) for y in (-0.08, 0.08)]
    depth = _meshes_on_table(mesh, poses, cam, intr)
    model = build_model_from_mesh(mesh, "channel")
    up = cam[:3, :3].T @ [0.0, 0.0, 1.0]                          # world z in the camera frame

    def tops_plane(cloud):
        return [o for n, o in cloud.planes if float(n @ up) > 0.99 and abs(o - (cam[2, 3] - 0.05)) < 0.005]

    kept = ShapeFrontEnd(model, PipelineConfig().frontend).frame_cloud(depth, intr, None, up)
    assert tops_plane(kept) == [] and np.sum(kept.points @ up + cam[2, 3] > 0.045) > 1000
    shape = ShapeFrontEnd(model, replace(PipelineConfig().frontend, shape_keep_object_tops=False))
    cloud = shape.frame_cloud(depth, intr, None, up)
    assert abs(cloud.up_offset - cam[2, 3]) < 0.005               # the table
    assert len(tops_plane(cloud)) == 1                            # and the tops, as a plane 5 cm above it
    assert np.sum(cloud.points @ up + cam[2, 3] > 0.045) < 100
    assert not any(shape.pierces(T, cloud, depth, intr) for T in poses)
    raised = [invert_transform(cam) @ make_transform(down, [x, y, 0.045]) for x in (-0.1, 0.0) for y in (-0.08, 0.08)]
    assert all(shape.pierces(T, cloud, depth, intr) for T in raised)


def test_a_row_of_three_flush_channels_passes_as_a_group_not_in_pairs():
    """Three channels open side down, side by side, their tops flush: each one's outline band
    runs onto its neighbours' tops. With the evidence asked for set at 0.9 (between what
    one neighbour found leaves the middle one and what both leave it), each is rejected
    alone and the middle one passes only with both neighbours taken as found, so no pair
    passes both ways (channel seed 307 frame 9 at the usual 0.75). Judged as a group (each
    with the other two as found) all three pass; a pose between two of them (half on each),
    added to the rejected ones, is not taken with them."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig, box_grid, box_overlaps
    from multi_instance_reg.rgbd.shape import depth_support
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.0, -0.45, 0.55]), np.zeros(3))      # camera -> world, table z = 0
    down = np.diag([1.0, -1.0, -1.0])
    poses = [invert_transform(cam) @ make_transform(down, [x, 0.0, 0.025]) for x in (-0.1, 0.0, 0.1)]
    depth = _meshes_on_table(mesh, poses, cam, intr)
    model = build_model_from_mesh(mesh, "channel")
    fe = replace(PipelineConfig().frontend, shape_min_evidence=0.9)
    shape = ShapeFrontEnd(model, fe)
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    for T in poses:
        support, free, n = depth_support(T, shape._surface, shape._surface_normals, depth, intr,
                                         shape.tolerance_at(T), shape._self_hiding)
        assert support > 0.95 and shape._judge(T, support, free, n, cloud, depth, intr) is None
    between = invert_transform(cam) @ make_transform(down, [0.05, 0.0, 0.025])
    rejected = poses + [between]
    overlap = box_overlaps(model, rejected, box_grid(model.extent) + np.asarray(model.box_centre))
    none = np.zeros(depth.shape, np.uint8)
    assert shape.judge_pairs(rejected, overlap, fe.max_overlap, cloud, depth, intr, none, []) == []
    groups = shape.judge_groups(rejected, overlap, fe.max_overlap, cloud, depth, intr, none, [])
    assert len(groups) == 3
    for T in poses:
        assert sum(np.allclose(g[0], T) for g in groups) == 1


def test_a_carton_sunk_through_the_pallets_top_is_rejected_though_the_floor_is_the_largest_plane():
    """Floor, a pallet top 0.144 m above it and a tray 8 cm tall on the pallet. A carton whose
    top face lies in the tray's top reaches 7 cm through the pallet's top, where the tray on
    it is seen; the depth check passes it (its hidden body is behind the tray's top), and
    the largest plane, the floor, does not cut it. Every support plane does; a carton
    standing on the pallet beside the tray reaches through none."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import depth_support
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    intr = CameraIntrinsics(K=np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.1, 0.0, 1.5]), np.array([-0.15, 0.0, 0.0]))     # camera -> world, floor z = 0
    rays = _world_rays(cam, intr)

    def level(height, half_x, half_y, cx=0.0):
        """Depth of the horizontal plane at ``height`` on each ray, and where it is inside the box."""
        t = (height - cam[2, 3]) / rays[..., 2]
        x, y = cam[0, 3] + t * rays[..., 0], cam[1, 3] + t * rays[..., 1]
        return t, (np.abs(x - cx) <= half_x) & (np.abs(y) <= half_y)

    floor, _ = level(0.0, 9.0, 9.0)
    pallet, on_pallet = level(0.144, 0.6, 0.4)
    tray, on_tray = level(0.224, 0.2, 0.15, cx=-0.2)
    depth = np.where(on_tray, tray, np.where(on_pallet, pallet, floor)).astype(np.float32)
    mesh = object_mesh(get_object("carton"))                                 # 0.30 x 0.20 x 0.15, centred
    half_h = float(mesh.vertices[:, 2].max())
    sunk = invert_transform(cam) @ make_transform(np.eye(3), [-0.2, 0.0, 0.224 - half_h])
    standing = invert_transform(cam) @ make_transform(np.eye(3), [0.3, 0.0, 0.144 + half_h])
    model = build_model_from_mesh(mesh, "carton")
    for every in (True, False):
        shape = ShapeFrontEnd(model, replace(PipelineConfig().frontend, shape_pierce_every_plane=every))
        cloud = shape.frame_cloud(depth, intr, None)
        assert abs(cloud.up_offset - 1.5) < 0.01                            # the largest plane: the floor
        assert len(cloud.planes) == 2 and sorted(round(o, 2) for _, o in cloud.planes) == [1.36, 1.5]
        support, free, _ = depth_support(sunk, shape._surface, shape._surface_normals, depth, intr,
                                         shape.tolerance_at(sunk))
        assert support > 0.95 and free == 0.0
        assert shape.pierces(sunk, cloud, depth, intr) == every
        assert not shape.pierces(standing, cloud, depth, intr)


def test_noise_agreement_tells_a_cylinder_from_a_square_bar_it_fits_in():
    """A lying cylinder (6 cm across) and a square bar whose faces touch it, an edge towards
    the camera, both 0.45 m away. Moved 5 mm towards the bar's edge, the cylinder's side
    agrees with the bar everywhere within the 8 mm tolerance (support 1.0), but within the
    depth noise (2 mm) only where it nears the faces; on itself, everywhere."""
    from multi_instance_reg.rgbd.shape import depth_support, noise_agreement

    K = _intrinsics()
    r, length, zc = 0.03, 0.10, 0.45
    xs = np.arange(-length / 2, length / 2 + 1e-9, 0.004)
    X, A = np.meshgrid(xs, np.arange(0, 2 * np.pi, 0.004 / r))
    side = np.stack([r * np.cos(A).ravel(), r * np.sin(A).ravel(), X.ravel()], 1)    # the model's axis: z
    normals = np.stack([np.cos(A).ravel(), np.sin(A).ravel(), np.zeros(A.size)], 1)

    def at(z):
        """The cylinder lying along the camera's x axis, its axis z metres away."""
        return make_transform(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), [0.0, 0.0, z])

    v, u = np.mgrid[0:240, 0:320]
    dx, dy = (u - K.K[0, 2]) / K.K[0, 0], (v - K.K[1, 2]) / K.K[1, 1]
    a = dy ** 2 + 1
    disc = zc ** 2 - a * (zc ** 2 - r ** 2)
    t = (zc - np.sqrt(np.maximum(disc, 0))) / a
    cylinder = np.where((disc >= 0) & (np.abs(t * dx) <= length / 2), t, 0.8).astype(np.float32)
    # The bar: two faces at 45 deg to the line of sight, r from the axis, meeting in an edge
    # r sqrt(2) in front of it; 16 cm long, so it goes on past the cylinder's ends.
    t = np.maximum((zc - r * np.sqrt(2)) / (1 + dy), (zc - r * np.sqrt(2)) / (1 - dy))
    bar = np.where((np.abs(t * dy) <= r * np.sqrt(2)) & (np.abs(t * dx) <= 0.08), t, 0.8).astype(np.float32)

    own = noise_agreement(at(zc), side, normals, cylinder, K, 0.008, 0.002)
    support, free, n = depth_support(at(zc - 0.005), side, normals, bar, K, 0.008)
    fitted = noise_agreement(at(zc - 0.005), side, normals, bar, K, 0.008, 0.002)
    assert n > 300 and support == 1.0 and free == 0.0
    assert own == 1.0 and fitted < 0.35
    # Nothing agrees: nothing to judge.
    assert noise_agreement(at(zc), side, normals, np.zeros_like(bar), K, 0.008, 0.002) == 1.0


def test_two_small_segments_larger_together_are_paired_once():
    """A standing bracket seen from above: its base plate, and past a depth step its
    upright's top edge, which touches a second bracket's (one segment across both). Each is
    within the object's reach, both together are not: paired anyway, once, the one with more
    points first (the joined vote takes of the other only its points within reach of it); a
    segment elsewhere is not."""
    from multi_instance_reg.rgbd.segments import pairs_across_steps

    g = np.arange(0.0, 1.0, 0.1)
    plate = np.array([[x, y, 0.60] for x in 0.09 * g for y in 0.06 * g])              # a: 9 x 6 cm
    edge = np.array([[0.075 + 0.01 * x, y, 0.53] for x in g for y in -0.07 + 0.14 * g])  # b: 1 x 14 cm
    far = np.array([[0.5 + 0.3 * x, 0.3 * y, 0.60] for x in g for y in g])            # c: 30 cm, elsewhere
    points = np.concatenate([plate, edge, far])
    labels = np.repeat([0, 1, 2], [len(plate), len(edge), len(far)])
    reach = 0.15
    from scipy.spatial.distance import pdist
    assert pdist(plate).max() < reach and pdist(edge).max() < reach < pdist(np.concatenate([plate, edge])).max()
    pairs = pairs_across_steps(points, labels, reach, 0.02)
    assert pairs == [(0, 1)]
    # The same with the edge holding more points than the plate: the edge first.
    dense_edge = np.repeat(edge, 3, axis=0)
    points = np.concatenate([plate, dense_edge, far])
    labels = np.repeat([0, 1, 2], [len(plate), len(dense_edge), len(far)])
    assert pairs_across_steps(points, labels, reach, 0.02) == [(1, 0)]


def test_segments_within_reach_are_those_within_reach_one_by_one():
    """``segments_within_reach`` (one sort) names the segments ``within_reach`` names one by
    one (labels shuffled, some -1); given to ``pairs_across_steps`` it finds the same pairs."""
    from multi_instance_reg.rgbd.segments import pairs_across_steps, segments_within_reach, within_reach

    rng = np.random.default_rng(2)
    sizes = rng.uniform(0.02, 0.3, 30)
    points = np.concatenate([rng.uniform(0, s, (40, 3)) + [0.2 * k, 0.0, 0.8] for k, s in enumerate(sizes)])
    labels = np.repeat(np.arange(30), 40)
    labels[rng.random(len(labels)) < 0.1] = -1
    perm = rng.permutation(len(points))
    points, labels = points[perm], labels[perm]
    compact = segments_within_reach(points, labels, 0.25)
    assert compact.tolist() == [s for s in range(30) if within_reach(points[labels == s], 0.25)]
    assert 0 < len(compact) < 30
    assert pairs_across_steps(points, labels, 0.25, 0.02, small=compact) == pairs_across_steps(points, labels, 0.25, 0.02)


def test_densest_pose_clusters_are_seeded_at_the_mode_not_at_the_strongest_vote():
    """References spread about the right pose (a plate's votes, blurred in its plane) with
    the strongest of them 22 deg off: strongest first, that one seeds the cluster and is
    the hypothesis; densest first, the pose most of them agree with is."""
    from multi_instance_reg.rgbd.ppf import cluster_poses

    def yaw(deg, x=0.0):
        a = np.radians(deg)
        return make_transform(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]),
                              [x, 0.0, 0.5])

    poses = np.stack([yaw(22.0)] + [yaw(d, 0.001 * d) for d in (-4, -2, 0, 2, 4)] + [yaw(170.0, 0.05)])
    weights = np.array([1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.9])
    strongest = cluster_poses(poses, weights, 24.0, 0.015, 1, min_members=1)
    assert rotation_angle_deg(strongest[0][:3, :3]) > 20.0
    densest = cluster_poses(poses, weights, 24.0, 0.015, 2, min_members=1, densest=True)
    assert rotation_angle_deg(densest[0][:3, :3]) < 3.0
    assert rotation_angle_deg(densest[1][:3, :3]) > 160.0        # the lone pose: its own cluster, second


def test_each_segment_keeps_its_own_best_pose_clusters():
    """A large segment's many references fill the frame's best clusters; a small segment's
    one agreeing pair ranks below them all. Its own best cluster is still a hypothesis
    (``segment_poses``), and a segment's cluster the frame already has is not repeated."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.ppf import ANGLE_BINS, cluster_poses
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    shape = ShapeFrontEnd(build_model_from_mesh(box_mesh(0.12, 0.06, 0.08), "block"),
                          replace(PipelineConfig().frontend, shape_segment_clusters=1))
    # Segment 0: four poses 0.3 m apart, each voted by five references; segment 1: one pose,
    # two references of lower share.
    big = [make_transform(np.eye(3), [0.3 * k, 0.0, 1.0]) for k in range(4) for _ in range(5)]
    small = [make_transform(np.eye(3), [0.0, 0.5, 1.0])] * 2
    poses = np.stack(big + small)
    share = np.concatenate([np.ones(20), [0.5, 0.5]])
    labels = np.array([0] * 20 + [1, 1])
    taken = cluster_poses(poses, share, 360.0 / ANGLE_BINS, 0.1 * shape.diameter, 3)
    assert not any(np.allclose(T[:3, 3], small[0][:3, 3]) for T in taken)
    added = shape.segment_poses(poses, share, labels, taken)
    assert len(added) == 1 and np.allclose(added[0][:3, 3], small[0][:3, 3])
    assert len(shape.segment_poses(poses, share, labels, cluster_poses(
        poses, share, 360.0 / ANGLE_BINS, 0.1 * shape.diameter, 5))) == 0


def test_a_bracket_pose_a_turn_away_from_icps_basin_is_started_again_turned(monkeypatch):
    """A bracket pose 10 deg off about one of the model's axes, where neither ICP moves it
    (stubbed: each returns its start unless within 2 deg of the true pose, then the true
    pose): rejected, and its second look by projective ICP gets nowhere. Started again turned
    both ways about each model axis, one start lies in the basin and is kept (``second``);
    with ``shape_turned_starts`` 0 nothing is."""
    from dataclasses import replace
    from multi_instance_reg.rgbd import shape_frontend as sf
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist

    intr, T, mesh, depth = _bracket_before_a_wall()

    def basin(T0, *a, **k):
        near = rotation_angle_deg(T0[:3, :3].T @ T[:3, :3]) < 2.0 and np.linalg.norm(T0[:3, 3] - T[:3, 3]) < 0.01
        return T.copy() if near else np.array(T0)

    monkeypatch.setattr(sf, "align_projective", lambda T0, *a, **k: np.array(basin(T0)).T)
    for degrees in (10.0, 0.0):
        shape = sf.ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"),
                                 replace(PipelineConfig().frontend, shape_turned_starts=degrees))
        monkeypatch.setattr(shape, "_icp", basin)
        centre = shape._visible_surface(T).mean(axis=0)
        off = apply_twist(T, np.concatenate([np.radians(10.0) * T[:3, 0], np.zeros(3)]), centre)
        cloud = shape.frame_cloud(depth, intr, None)
        second = []
        assert shape.refine_and_check([off], cloud, depth, intr, second=second) == []
        if degrees:
            assert len(second) == 1 and rotation_angle_deg(second[0][0][:3, :3].T @ T[:3, :3]) < 0.5
        else:
            assert second == []


def test_a_turned_start_icp_slides_off_is_judged_as_it_starts(monkeypatch):
    """A bracket pose 10 deg off, rejected, and one of its turned starts lies on the true
    pose, where ICP does not keep it (stubbed: it slides a start near the truth 10 deg off
    again, as nearest-point ICP turned and slid an open-side-down channel onto its flush
    neighbour: channel seed 2187 frame 4, a start 0.3 deg / 18 mm off went to 9 deg / 23 mm
    and fitted worse). The start competes with what ICP makes of it (as in
    ``_refine_plain``), so the true pose is kept (``second``); ranked after ICP alone, no
    start beat the rejected pose and nothing was."""
    from multi_instance_reg.rgbd import shape_frontend as sf
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist

    intr, T, mesh, depth = _bracket_before_a_wall()
    shape = sf.ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    centre = shape._visible_surface(T).mean(axis=0)
    off = apply_twist(T, np.concatenate([np.radians(10.0) * T[:3, 0], np.zeros(3)]), centre)

    def slides_off(T0, *a, **k):
        near = rotation_angle_deg(T0[:3, :3].T @ T[:3, :3]) < 2.0 and np.linalg.norm(T0[:3, 3] - T[:3, 3]) < 0.01
        return off.copy() if near else np.array(T0)

    monkeypatch.setattr(sf, "align_projective", lambda T0, *a, **k: np.array(T0).T)
    monkeypatch.setattr(shape, "_icp", slides_off)
    cloud = shape.frame_cloud(depth, intr, None)
    second = []
    assert shape.refine_and_check([off], cloud, depth, intr, second=second) == []
    assert len(second) == 1 and rotation_angle_deg(second[0][0][:3, :3].T @ T[:3, :3]) < 0.5
    assert np.linalg.norm(second[0][0][:3, 3] - T[:3, 3]) < 0.002


def test_a_pose_icp_could_not_better_gets_the_second_look_however_far_it_overhangs(monkeypatch):
    """A bracket pose 11 deg / 8 mm off, overhanging (support - free 0.45: under the second
    look's ``SECOND_LOOK_MIN``): where no ICP round bettered its start (ICP stubbed to stop
    there, as it did on a crowded table: bracket seed 2462, four brackets 4-24 deg off at
    support - free 0.21-0.58), the projective look is tried all the same and sets it right;
    where ICP moved it (to a pose as far along, still rejected), it gets no look."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.rgbd.shape_frontend import SECOND_LOOK_MIN, ShapeFrontEnd

    intr, T, mesh, depth = _bracket_before_a_wall()
    off = apply_twist(T, np.array([0.0, np.radians(10.0), np.radians(5.0), 0.006, -0.005, 0.0]), T[:3, 3])
    moved = apply_twist(T, np.array([0.0, np.radians(9.0), np.radians(4.5), 0.0055, -0.0045, 0.0]), T[:3, 3])
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None)
    for P in (off, moved):
        fit, support, free, _ = shape._fit(P, depth, intr)
        assert free > 0.1 and fit < SECOND_LOOK_MIN
    assert shape._fit(moved, depth, intr)[0] > shape._fit(off, depth, intr)[0]
    for icp, looked in ((lambda T0, *a, **k: T0, True), (lambda T0, *a, **k: moved.copy(), False)):
        monkeypatch.setattr(shape, "_icp", icp)
        second = []
        assert shape.refine_and_check([off], cloud, depth, intr, second=second) == []
        if looked:
            assert len(second) == 1
            P = second[0][0]
            assert rotation_angle_deg(P[:3, :3].T @ T[:3, :3]) < 1.0 and np.linalg.norm(P[:3, 3] - T[:3, 3]) < 0.002
        else:
            assert second == []


def test_a_pose_still_rejected_after_its_second_look_is_handed_on_as_the_pose_the_depth_agrees_with_best(monkeypatch):
    """The second look moves a bracket pose 5 deg off onto the depth, and the checks still
    reject it (stubbed: as a bracket half behind a distractor is, by its hidden points):
    the later passes, which judge it with points hidden, are given that pose, not the one
    ICP left (bracket seed 5 frame 7: ICP 11.5 deg off, the second look 0.3 deg; the pose
    ICP left passed with its points hidden)."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    intr, T, mesh, depth = _bracket_before_a_wall()
    off = apply_twist(T, np.array([0.0, np.radians(5.0), np.radians(2.0), 0.004, -0.003, 0.0]), T[:3, 3])
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    monkeypatch.setattr(shape, "_icp", lambda T0, *a, **k: T0)
    monkeypatch.setattr(shape, "_judge", lambda *a, **k: None)
    cloud = shape.frame_cloud(depth, intr, None)
    rejected, second = [], []
    assert shape.refine_and_check([off], cloud, depth, intr, rejected=rejected, second=second) == []
    assert second == [] and len(rejected) == 1
    assert rotation_angle_deg(rejected[0][:3, :3].T @ T[:3, :3]) < 1.0
    assert np.linalg.norm(rejected[0][:3, 3] - T[:3, 3]) < 0.002


def test_central_radius_is_the_smallest_ball_about_a_surface_point_holding_the_box():
    """A 0.3 x 0.2 x 0.15 box: about the middle of a largest face, the far corners lie
    sqrt(0.15^2 + 0.1^2 + 0.15^2) away; about any other surface point, something lies farther."""
    from multi_instance_reg.rgbd.shape_frontend import central_radius

    pts, _ = sample_surface(box_mesh(0.3, 0.2, 0.15), 0.005, seed=0)
    assert abs(central_radius(pts) - np.sqrt(0.15 ** 2 + 0.1 ** 2 + 0.15 ** 2)) < 0.006


def _cartons_in_a_row(model, surface, normals, count=3):
    """``count`` boxes side by side, their tops flush, seen tilted from above: (points,
    normals, which box each point is of, the boxes' poses)."""
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.5), -np.sin(0.5)], [0.0, np.sin(0.5), np.cos(0.5)]])
    top_up = np.diag([1.0, -1.0, -1.0])
    poses = [make_transform(tilt @ top_up, tilt @ np.array([0.0, 0.2 * k, 0.0]) + [0.0, 0.0, 1.0]) for k in range(count)]
    seen = [_visible(surface, normals, T, 0.001, seed=k) for k, T in enumerate(poses)]
    which = np.concatenate([np.full(len(p), k) for k, (p, _) in enumerate(seen)])
    return np.vstack([p for p, _ in seen]), np.vstack([n for _, n in seen]), which, poses


def test_references_in_a_segment_of_touching_boxes_vote_right_more_often_within_the_central_reach():
    """Touching boxes with flush tops are one segment: partners over the whole diameter lie
    mostly on the neighbours; within the central radius mostly on the reference's own box."""
    from multi_instance_reg.rgbd.shape_frontend import central_radius

    model = _box_model()
    surface, normals = oriented_downsample(model.shape_points.astype(np.float64), model.shape_normals,
                                           model.shape_voxel)
    ppf = PPFModel(surface, normals, float(np.linalg.norm(model.extent)), model.shape_voxel, model.symmetries,
                   bucket_cap=50)
    P, N, which, poses = _cartons_in_a_row(model, surface, normals)
    right = {}
    for name, reach in (("diameter", None), ("central", np.full(len(P), central_radius(surface)))):
        s, _, found, _ = ppf.vote(P, N, np.zeros(len(P), np.int64), ref_step=1, max_partners=60, reach=reach)
        ok = []
        for k, Tp in zip(s, found):
            G = closest_symmetric_pose(poses[which[k]], Tp, model.symmetries)
            ok.append(np.linalg.norm(G[:3, 3] - Tp[:3, 3]) < 0.02 and rotation_angle_deg(G[:3, :3].T @ Tp[:3, :3]) < 10)
        right[name] = float(np.mean(ok))
    assert right["central"] > right["diameter"] + 0.05


def test_partner_reach_is_short_only_in_segments_larger_than_the_object():
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import FrameCloud, ShapeFrontEnd

    model = _box_model()
    shape = ShapeFrontEnd(model, FrontEndConfig())
    surface, normals = shape._surface, shape._surface_normals
    P, N, which, _ = _cartons_in_a_row(model, surface, normals)
    alone = P[which == 0] + [1.0, 0.0, 0.0]          # a box of its own, far to the side
    pts = np.vstack([P, alone])
    labels = np.concatenate([np.zeros(len(P), np.int64), np.ones(len(alone), np.int64)])
    cloud = FrameCloud(pts, np.vstack([N, N[which == 0]]), np.zeros(0, np.int64), np.zeros((0, 33)), None, labels)
    reach = shape.partner_reach(cloud)
    assert np.allclose(reach[labels == 0], shape.central_reach) and np.all(np.isinf(reach[labels == 1]))
    assert 0.5 * shape.diameter < shape.central_reach < 0.65 * shape.diameter
    single = FrameCloud(alone, N[which == 0], np.zeros(0, np.int64), np.zeros((0, 33)), None,
                        np.zeros(len(alone), np.int64))
    assert shape.partner_reach(single) is None


def test_central_radius_of_a_flat_patch_falls_back_to_every_point():
    """Points in one plane have no convex hull in 3-D: the farthest points are then sought
    among all of them (a square of side 0.2: about its centre, the corners 0.1 * sqrt(2) away)."""
    from multi_instance_reg.rgbd.shape_frontend import central_radius

    g = np.stack(np.meshgrid(np.linspace(0, 0.2, 21), np.linspace(0, 0.2, 21)), -1).reshape(-1, 2)
    assert abs(central_radius(np.column_stack([g, np.zeros(len(g))])) - 0.1 * np.sqrt(2.0)) < 1e-9


def test_the_segments_an_instance_found_touches_are_voted_again_without_its_points():
    """Two brackets side by side are one segment; with the first found, what it leaves of
    the segment is voted again (``residual_poses``) and gives the second its pose. Nothing
    found: nothing voted again."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    mesh, intr, T1, T2, depth = _two_brackets_side_by_side()
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    assert shape.non_convex
    cloud = shape.frame_cloud(depth, intr, None)

    def on(T):
        surf = shape._surface @ T[:3, :3].T + T[:3, 3]
        return np.min(np.linalg.norm(cloud.points[:, None] - surf[None], axis=2), axis=1) < shape.voxel

    def right(P, deg=15.0, metres=0.03):
        return rotation_angle_deg(P[:3, :3].T @ T2[:3, :3]) < deg and np.linalg.norm(P[:3, 3] - T2[:3, 3]) < metres

    ids = np.unique(cloud.segments[on(T1) | on(T2)])
    assert len(ids) == 1 and ids[0] >= 0                        # one segment holds both
    assert len(shape.residual_poses(cloud, [], np.zeros((0, 4, 4)))) == 0
    again = shape.residual_poses(cloud, [T1], np.zeros((0, 4, 4)))
    assert 1 <= len(again) and any(right(P) for P in again)
    refined = [shape.refine_one(P, cloud, depth, intr) for P in again]
    assert any(r is not None and right(r[0], 2.0, 0.005) for r in refined)
    # A hypothesis already refined is not given again.
    assert not any(right(P) for P in shape.residual_poses(cloud, [T1], np.stack([T2])))


def test_the_points_of_a_supported_rejected_pose_are_left_out_of_the_residual_votes_too():
    """Two brackets side by side in one segment, neither found: with the first's pose
    rejected but supported by the depth (``supported``), what it leaves of the segment is
    voted again and gives the second its pose (session 22: a channel whose flush
    neighbours were all rejected on their outlines onto it had no hypothesis). Its evidence
    (``supported_evidence``) ranks the right pose above one slid off it, which takes in
    points of the neighbour."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    mesh, intr, T1, T2, depth = _two_brackets_side_by_side()
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None)

    def right(P, deg=15.0, metres=0.03):
        return rotation_angle_deg(P[:3, :3].T @ T2[:3, :3]) < deg and np.linalg.norm(P[:3, 3] - T2[:3, 3]) < metres

    none = np.zeros((0, 4, 4))
    assert len(shape.residual_poses(cloud, [], none)) == 0
    again = shape.residual_poses(cloud, [], none, supported=[T1])
    assert 1 <= len(again) and any(right(P) for P in again)
    slid = T1.copy()
    slid[:3, 3] += 0.5 * (T2[:3, 3] - T1[:3, 3])
    at_truth = shape.supported_evidence(T1, cloud, depth, intr)
    assert at_truth is not None
    off = shape.supported_evidence(slid, cloud, depth, intr)
    assert off is None or off < at_truth


def test_the_pieces_a_bracket_found_in_front_cuts_another_into_are_voted_together():
    """A bracket found lying across another in front of it (6 cm above) cuts what is seen of
    the other into two segments, its upright end and its base plate's far end; no instance
    found touches either, so the residual votes leave them. Voted together
    (``bridged_poses``), they give its pose, which refined passes behind the one found."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    world = invert_transform(look_at(np.array([0.05, -0.12, 0.5]), np.zeros(3)))
    under = world @ make_transform(np.eye(3), [0.0, 0.0, 0.04])
    across = world @ make_transform(rotation_z(90.0), [0.0, 0.0, 0.11])
    dense, _ = sample_surface(mesh, 0.001)
    a, b = _depth_of(dense, across, intr), _depth_of(dense, under, intr)
    depth = np.where((a > 0) & ((b == 0) | (a < b)), a, b)
    cloud = shape.frame_cloud(depth, intr, None)

    def right(P, deg=15.0, metres=0.03):
        return rotation_angle_deg(P[:3, :3].T @ under[:3, :3]) < deg and np.linalg.norm(P[:3, 3] - under[:3, 3]) < metres

    surf = shape._surface @ under[:3, :3].T + under[:3, 3]
    on = np.min(np.linalg.norm(cloud.points[:, None] - surf[None], axis=2), axis=1) < shape.voxel
    assert len(np.unique(cloud.segments[on & (cloud.segments >= 0)])) == 2     # two pieces
    none = np.zeros((0, 4, 4))
    assert len(shape.residual_poses(cloud, [across], none)) == 0               # without the frame: no bridging
    bridged = shape.residual_poses(cloud, [across], none, depth, intr)
    assert 1 <= len(bridged) and any(right(P) for P in bridged)
    rejected = []
    shape.refine_and_check(list(bridged), cloud, depth, intr, rejected=rejected)
    occluders = shape.instance_pixels([across], depth, intr)
    behind = [shape.judge_behind(R, cloud, depth, intr, occluders, [across]) for R in rejected]
    assert any(r is not None and right(r[0], 2.0, 0.005) for r in behind)
    # Already refined: not given again.
    assert not any(right(P) for P in shape.residual_poses(cloud, [across], np.stack([under]), depth, intr))


def rotation_z(degrees):
    a = np.radians(degrees)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _vote_reference(p, n, refs, lo, hi, reach, max_partners, bucket_start, entry_first, entry_alpha, n_model,
                    d_step, a_step, n_dist):
    """``ppf._vote`` written plainly: a dict accumulator per reference, the peak the
    first-voted of the largest cells. Also returns the most votes one reference cast."""
    import math

    from multi_instance_reg.rgbd.ppf import TURN_BINS, _align_to_x, _feature

    out, most = [], 0
    for r, i in enumerate(refs):
        d2 = ((p[lo[r]:hi[r]] - p[i]) ** 2).sum(axis=1)
        step = max(1, int((d2 < reach[r] ** 2).sum()) // max_partners)
        R = _align_to_x(n[i, 0], n[i, 1], n[i, 2])
        acc, seen, partners, cast = {}, -1, 0, 0
        for j in range(lo[r], hi[r]):
            if j == i or d2[j - lo[r]] >= reach[r] ** 2:
                continue
            seen += 1
            if seen % step:
                continue
            key, a_s = _feature(p, n, i, j, R, d_step, a_step, n_dist)
            if key < 0:
                continue
            partners += 1
            for e in range(bucket_start[key], bucket_start[key + 1]):
                turn = a_s - entry_alpha[e]
                turn = turn + 2.0 * math.pi if turn < 0 else turn
                tb = int(turn / (2.0 * math.pi) * TURN_BINS)
                cell = entry_first[e] * TURN_BINS + (0 if tb >= TURN_BINS else tb)
                acc[cell] = acc.get(cell, 0.0) + 1.0      # dicts keep the order of first votes
                cast += 1
        best, cell = 0.0, -1
        for c, v in acc.items():
            if v > best:
                best, cell = v, c
        out.append((cell // TURN_BINS if cell >= 0 else -1, cell % TURN_BINS if cell >= 0 else 0, best, partners))
        most = max(most, cast)
    return out, most


@pytest.mark.parametrize("layout", ["random", "plane"])
def test_vote_kernel_gives_the_peaks_of_a_plain_accumulator(layout):
    """Known answer for ``_vote``'s accumulator (every vote listed, repeats too): the same
    peaks as a dict per reference. "plane": three coplanar model points and a flat scene,
    whose every partner votes for all the model's pairs: a reference casts more votes than
    the accumulator has cells, and the list of votes is grown."""
    from multi_instance_reg.rgbd.ppf import TURN_BINS, _vote

    rng = np.random.default_rng(4)
    if layout == "random":
        mp = rng.uniform(-0.05, 0.05, (300, 3))
        mn = rng.normal(size=(300, 3))
        sp = rng.uniform(-0.08, 0.08, (400, 3))
        sn = rng.normal(size=(400, 3))
    else:
        mp = np.array([[0.0, 0.0, 0.0], [0.025, 0.0, 0.0], [0.0, 0.025, 0.0]])
        mn = np.tile([0.0, 0.0, 1.0], (3, 1))
        sp = np.column_stack([rng.uniform(-0.08, 0.08, (400, 2)), np.zeros(400)])
        sn = np.tile([0.0, 0.0, 1.0], (400, 1))
    mn = mn / np.linalg.norm(mn, axis=1, keepdims=True)
    sn = sn / np.linalg.norm(sn, axis=1, keepdims=True)
    model = PPFModel(mp, mn, 0.15, 0.01)
    refs = np.arange(0, 400, 7, dtype=np.int64)
    lo = np.where(refs < 200, 0, 200).astype(np.int64)
    hi = lo + 200
    reach = np.full(len(refs), 0.12)
    args = (sp, sn, refs, lo, hi, reach, 150, model._start, model._first, model._alpha, len(model.points),
            model.d_step, model.a_step, model.n_dist)
    m, turn, votes, partners = _vote(*args)
    expected, most = _vote_reference(*args)
    assert [tuple(x) for x in zip(m.tolist(), turn.tolist(), votes.tolist(), partners.tolist())] == expected
    assert (m >= 0).sum() > len(refs) // 2
    if layout == "plane":
        assert most > len(model.points) * TURN_BINS


@pytest.mark.parametrize("order", ["raster", "random"])
def test_nearest_model_points_of_the_outline_checks_are_those_of_a_full_sort(order):
    """Known answer for ``verify._nearest`` (grid cells scanned within the previous query's
    bound): each query's k nearest as a full sort of the distances gives them, and a tie
    flagged exactly where the (k+1)-th is as near as the k-th (coincident model points,
    queries on a lattice)."""
    from multi_instance_reg.rgbd.verify import _nearest

    rng = np.random.default_rng(11)
    p = rng.uniform(-0.05, 0.05, (300, 3))
    p[:, 2] *= 0.1                                       # a flat-ish model, as a face seen alone
    p = np.concatenate([p, p[:20]])                      # coincident samples: exact ties
    u, v = np.meshgrid(np.linspace(-0.09, 0.09, 40), np.linspace(-0.09, 0.09, 30))
    P = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, 0.01)])
    P = np.concatenate([P, p[:25] + 1e-4, p[300:305]])   # some on the model, some on a duplicate
    if order == "random":
        P = P[rng.permutation(len(P))]
    k = 8
    j, tied = _nearest(P, p, k)
    d = ((P[:, None, :] - p[None]) ** 2).sum(axis=2)
    ranked = np.sort(d, axis=1)
    want_tied = ranked[:, k] <= ranked[:, k - 1] * (1.0 + 1e-12)
    assert np.array_equal(tied, want_tied)
    assert want_tied.any() and not want_tied.all()
    for i in np.flatnonzero(~tied):
        assert set(j[i].tolist()) == set(np.argsort(d[i], kind="stable")[:k].tolist())
    # Tied rows still hold k points as near as the k nearest.
    assert np.allclose(np.sort(np.take_along_axis(d, j, axis=1), axis=1)[tied], ranked[tied, :k])


def _board_on_table(cam, intr, half_x, half_y, height):
    """Depth of the table (z = 0) with a board on it (|x| <= half_x, |y| <= half_y, 0 <= z <=
    height; world frame, ``cam`` camera -> world): its top and the two sides facing a camera
    at +x, +y."""
    rays = _world_rays(cam, intr)
    depth = -cam[2, 3] / rays[..., 2]                                   # the table
    for axis, value, other, half in ((0, half_x, 1, half_y), (1, half_y, 0, half_x), (2, height, None, None)):
        t = (value - cam[axis, 3]) / rays[..., axis]
        p = cam[:3, 3] + t[..., None] * rays
        if other is None:
            inside = (np.abs(p[..., 0]) <= half_x) & (np.abs(p[..., 1]) <= half_y)
        else:
            inside = (np.abs(p[..., other]) <= half) & (p[..., 2] >= 0) & (p[..., 2] <= height)
        depth = np.where(inside & (t > 0) & (t < depth), t, depth)
    return depth.astype(np.float32)


def test_a_pose_sunk_whole_into_a_board_its_top_flush_with_the_boards_is_rejected():
    """A board 40 x 40 cm, 8 cm thick, on the table, and a tee (10 x 12 x 7 cm) sunk whole
    into it, its top flush with the board's top: its top agrees with the board, the rest
    lies behind the board's surface and counts as hidden (support 0.87, nothing free).
    Nothing of it is above a support plane, so ``pierces`` passes it (a plane of object
    tops is no support it goes through); the outline must reject it: the board's top goes
    on past it. The same tee standing on the board is kept."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import depth_support
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("tee"))
    top = float(mesh.vertices[:, 2].max())
    height = float(np.ptp(mesh.vertices[:, 2])) + 0.01
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.35, 0.1, 0.6]), np.zeros(3))               # camera -> world, table z = 0
    board = _board_on_table(cam, intr, 0.2, 0.2, height)
    sunk = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, height - top])
    standing = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, height + top])
    dense, _ = sample_surface(mesh, 0.001)
    tee = _depth_of(dense, standing, intr)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "tee"), PipelineConfig().frontend)
    up = cam[:3, :3].T @ [0.0, 0.0, 1.0]                                 # world z in the camera frame
    cloud = shape.frame_cloud(board, intr, None, up)
    assert any(abs(o - (cam[2, 3] - height)) < 0.005 for _, o in cloud.planes)   # the board's top is a plane
    support, free, n = depth_support(sunk, shape._surface, shape._surface_normals, board, intr,
                                     shape.tolerance_at(sunk), shape._self_hiding)
    assert support > shape.fe.shape_min_support and free == 0.0           # the depth alone would take it
    assert not shape.pierces(sunk, cloud, board, intr)
    assert shape._judge(sunk, support, free, n, cloud, board, intr) is None
    assert shape.refine_one(sunk, cloud, board, intr) is None
    assert shape.judge_hidden(sunk, cloud, board, intr, None) is None
    # Standing on the board, the tee is kept.
    scene = np.where((tee > 0) & (tee < board), tee, board)
    cloud = shape.frame_cloud(scene, intr, None, up)
    kept = shape.refine_one(standing, cloud, scene, intr)
    assert kept is not None and np.linalg.norm(kept[0][:3, 3] - standing[:3, 3]) < 0.005


def test_found_share_is_the_share_of_agreeing_points_on_a_found_instances_surface():
    """A bracket seen alone: judged against itself as found, all its agreeing points are that
    instance's (1.0); against a bracket 20 cm away, none (0.0); nothing found, 0.0."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([0.35, -0.25, 0.4]), np.zeros(3)))
    dense, _ = sample_surface(mesh, 0.001)
    depth = _depth_of(dense, T, intr)
    far = T @ make_transform(np.eye(3), [0.2, 0.0, 0.0])
    assert shape.found_shares([T], [T], depth, intr)[0] > 0.99
    assert shape.found_shares([T], [far], depth, intr)[0] == 0.0
    assert shape.found_shares([T], [], depth, intr)[0] == 0.0


def test_the_first_choice_drops_a_pose_whose_evidence_lies_on_a_stronger_instance():
    """A bracket turned over about its base plate (the plate on the true one's, the upright
    below it; its box clear of the true one's) agrees with the depth only on the true one's
    plate: found second, it took the place of a bracket below whose box it overlaps (bracket
    seed 5 frame 2). The first choice drops it, and keeps the one below."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig, box_overlaps
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))          # base plate z -0.04..-0.028, upright at -x
    reg = InstanceRegistration(build_model_from_mesh(mesh, "bracket"), PipelineConfig())
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    T = invert_transform(look_at(np.array([0.35, -0.25, 0.4]), np.zeros(3)))
    over = T @ make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, -0.068])   # turned about the plate
    below = T @ make_transform(np.eye(3), [0.0, 0.0, -0.085])
    dense, _ = sample_surface(mesh, 0.001)
    near, far = _depth_of(dense, T, intr), _depth_of(dense, below, intr)
    depth = np.where((near > 0) & ((far == 0) | (near < far)), near, far)
    overlap = box_overlaps(reg.model, [T, over, below], reg._box_grid)
    limit = reg.config.frontend.max_overlap
    assert overlap[0, 1] <= limit and overlap[1, 0] <= limit and overlap[0, 2] == 0.0 and overlap[1, 2] > limit
    assert reg._shape.found_shares([over], [T], depth, intr)[0] > 0.8
    checked = [(T, 1.0, 300, 300.0), (below, 0.9, 100, 90.0), (over, 1.0, 200, 200.0)]
    alone = reg._one_per_box(checked)                  # by the boxes alone: the one turned over kept
    assert len(alone) == 2 and alone[0][0] is T and alone[1][0] is over
    chosen = reg._one_per_box(checked, frame=(depth, intr))
    assert len(chosen) == 2 and chosen[0][0] is T and chosen[1][0] is below


def _meshes_on_table(mesh, poses, cam, intr):
    """Depth of the mesh at each pose (camera frame) on a table at world z = 0 (``cam``:
    camera -> world), the nearest surface on each ray."""
    dense, _ = sample_surface(mesh, 0.001)
    depth = np.zeros((intr.height, intr.width), np.float32)
    for T in poses:
        d = _depth_of(dense, T, intr)
        depth = np.where((d > 0) & ((depth == 0) | (d < depth)), d, depth)
    rays = _world_rays(cam, intr)
    table = (-cam[2, 3] / rays[..., 2]).astype(np.float32)
    return np.where((depth > 0) & (depth < table), depth, table)


def _world_rays(cam, intr):
    """(H, W, 3): each pixel's ray (z = 1 in the camera) in the world frame (``cam``: camera -> world)."""
    K = intr.K
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1) @ cam[:3, :3].T


def test_an_open_channel_behind_a_distractor_passes_judged_behind_anything():
    """An open-side-up channel seen at a slant, a block in front hiding its near end: its
    walls' rims and inner faces lie just past the tolerance behind its own nearer faces (the
    depth check leaves those within the self-hiding margin to count against it); at them the
    depth steps a few mm, and measured with them the step in front of the hidden part was
    too small (channel seed 617: 5-8 mm median, 28-58 mm at the points hidden clearly). Here
    8 mm with them, 71 mm without (16 needed): the true pose passes."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import depth_support
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.45, 0.0, 0.40]), np.zeros(3))       # camera -> world, table z = 0; across the walls
    world = invert_transform(cam)
    T = world @ make_transform(np.eye(3), [0.0, 0.0, 0.025])     # open side up, on the table
    block = box_mesh(0.05, 0.08, 0.08)
    B = world @ make_transform(np.eye(3), [0.10, 0.03, 0.04])     # in front of its near wall's end
    dense, _ = sample_surface(mesh, 0.001)
    rays = _world_rays(cam, intr)
    table = (-cam[2, 3] / rays[..., 2]).astype(np.float32)
    depth = table
    for pts, P in ((dense, T), (sample_surface(block, 0.001)[0], B)):
        d = _depth_of(pts, P, intr)
        depth = np.where((d > 0) & (d < depth), d, depth)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "channel"), PipelineConfig().frontend)
    up = cam[:3, :3].T @ [0.0, 0.0, 1.0]
    cloud = shape.frame_cloud(depth, intr, None, up)
    support, _, _ = depth_support(T, shape._surface, shape._surface_normals, depth, intr, shape.tolerance_at(T),
                                  shape._self_hiding)
    assert support < shape.fe.shape_min_support                  # hidden by the block, not found
    again = shape.judge_hidden(T, cloud, depth, intr, None)
    assert again is not None and np.allclose(again[0], T)


def test_a_plane_just_off_the_table_is_not_pierced_by_what_stands_on_the_table():
    """A channel standing open side down on the table and a support plane tilted 1.5 deg off
    it, 17.5 mm above it under the channel (channel seed 631: such a plane, fitted among
    the table's remains, rejected channels standing on the table). The hidden bottoms of the
    far wall lie 2 voxels below it, and on their rays the depth stops at the channel's own
    top: "through" it, unless points on the table are left out. Sunk into a plane 4 cm up,
    its bottom 2 cm above the table, it still reaches through."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.4, 0.1, 0.4]), np.zeros(3))         # camera -> world, table z = 0
    down = np.diag([1.0, -1.0, -1.0])
    T = invert_transform(cam) @ make_transform(down, [0.0, 0.0, 0.025])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "channel"), PipelineConfig().frontend)
    up = cam[:3, :3].T @ [0.0, 0.0, 1.0]
    cloud = shape.frame_cloud(depth, intr, None, up)
    assert abs(cloud.up_offset - cam[2, 3]) < 0.005               # the table
    a = np.radians(1.5)
    normal = np.array([-np.sin(a), 0.0, np.cos(a)])               # world: normal . x = 0.0175 cos a
    tilted = (cam[:3, :3].T @ normal, float(normal @ cam[:3, 3]) - 0.0175 * np.cos(a))
    cloud.planes = tuple(cloud.planes) + (tilted,)
    pts = shape._surface @ T[:3, :3].T + T[:3, 3]
    assert np.sum(pts @ tilted[0] + tilted[1] < -2 * shape.voxel) > 20      # below it by 2 voxels
    assert not shape.pierces(T, cloud, depth, intr)
    # The plane 4 cm up, the channel raised 2 cm (sunk into a board, its bottom 2 cm over
    # the table): it still reaches through.
    cloud.planes = tuple(cloud.planes[:-1]) + ((tilted[0], tilted[1] - 0.0225 * np.cos(a)),)
    raised = invert_transform(cam) @ make_transform(down, [0.0, 0.0, 0.045])
    assert shape.pierces(raised, cloud, _meshes_on_table(mesh, [raised], cam, intr), intr)


def test_on_found_kept_for_the_same_instances_is_the_same_test():
    """``_on_found`` keeps its last tree: asked again for the same poses it answers as a
    fresh one; for other poses it is built anew (a kept tree would answer for the old ones)."""
    from multi_instance_reg.rgbd.pipeline import FrontEndConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd

    shape = ShapeFrontEnd(_box_model(), FrontEndConfig())
    A = make_transform(np.eye(3), [0.0, 0.0, 1.5])
    B = make_transform(np.eye(3), [0.4, 0.0, 1.5])
    points = np.random.default_rng(0).uniform([-0.3, -0.2, 1.3], [0.7, 0.2, 1.7], (3000, 3))
    fresh = ShapeFrontEnd(_box_model(), FrontEndConfig())._on_found([A])(points)
    assert 0 < fresh.sum() < len(points)
    assert np.array_equal(shape._on_found([A])(points), fresh)
    assert np.array_equal(shape._on_found([A.copy()])(points), fresh)      # kept (by the poses' values)
    assert np.array_equal(shape._on_found([B])(points),
                          ShapeFrontEnd(_box_model(), FrontEndConfig())._on_found([B])(points))
    assert not np.array_equal(shape._on_found([B])(points), fresh)
    assert np.array_equal(shape._on_found([A])(points[:100]), fresh[:100])  # one thread for few points


def test_a_channel_seen_turned_over_is_found_from_its_fit_open_side_up():
    """A channel lying open side down on the table shows a flat top; the votes fit its inner
    floor to it, open side up and 42 mm too high, its walls and rims then standing in front of
    the depth (channel seeds 631 / 1607: the only fits near such channels). That pose is
    rejected and does not refine onto the channel; turned over it is a start that refines and
    passes at the true pose. The true pose open side up gives no start (nothing of it in front
    of the depth)."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import depth_support
    from multi_instance_reg.rgbd.shape_frontend import TURNED_OVER_MIN, ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, -0.2, 0.5]), np.zeros(3))        # camera -> world, table z = 0
    world = invert_transform(cam)
    down = np.diag([1.0, -1.0, -1.0])
    T = world @ make_transform(down, [0.0, 0.0, 0.025])          # open side down, on the table
    fitted = world @ make_transform(np.eye(3), [0.0, 0.0, 0.067])  # its inner floor in the channel's top
    depth = _meshes_on_table(mesh, [T], cam, intr)
    model = build_model_from_mesh(mesh, "channel")
    shape = ShapeFrontEnd(model, PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    support, free, _ = depth_support(fitted, shape._surface, shape._surface_normals, depth, intr,
                                     shape.tolerance_at(fitted), shape._self_hiding)
    assert support < shape.fe.shape_min_support and free >= TURNED_OVER_MIN
    assert shape.refine_one(fitted, cloud, depth, intr) is None
    starts = shape.turned_over_starts(fitted, cloud, depth, intr)
    assert len(starts) == 1                                      # the turn about y is the one about x
    turned = shape.refine_one(starts[0], cloud, depth, intr)
    assert turned is not None
    # Right up to the channel's half turn about z.
    flipped = T @ np.diag([-1.0, -1.0, 1.0, 1.0])
    assert min(np.linalg.norm(turned[0][:3, :3] - P[:3, :3]) for P in (T, flipped)) < 0.1
    assert np.linalg.norm(turned[0][:3, 3] - T[:3, 3]) < 0.005
    # Open side up on the table, it is kept as it is and not turned over.
    up = world @ make_transform(np.eye(3), [0.0, 0.0, 0.025])
    depth = _meshes_on_table(mesh, [up], cam, intr)
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    assert shape.refine_one(up, cloud, depth, intr) is not None
    assert shape.turned_over_starts(up, cloud, depth, intr) == []


def test_near_twins_are_the_half_turns_that_map_most_of_the_model_onto_itself():
    """The L bracket's one near symmetry is the swap of its plates: half a turn about the
    bisector of its corner (xz), the long plate onto the short one. The channel's is its turn
    over (about x; the one about y is the same under its half turn about z, itself a
    symmetry, not a twin). A box (convex) has none looked for."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh

    fe = PipelineConfig().frontend
    bracket = ShapeFrontEnd(build_model_from_mesh(object_mesh(get_object("bracket")), "bracket"), fe)
    T = make_transform(np.eye(3), [0.1, -0.05, 0.6])
    twins = bracket.near_twins(T)
    assert len(twins) == 1
    R = twins[0][:3, :3]
    assert rotation_angle_deg(R) > 179.0
    axis = np.linalg.eigh(R + np.eye(3))[1][:, -1]                # the turn's axis: R a = a
    assert abs(abs(axis[0]) - np.sqrt(0.5)) < 1e-6 and abs(axis[1]) < 1e-6
    assert np.linalg.norm(twins[0][:3, 3] - T[:3, 3]) < 0.03      # shifted onto itself, not far
    channel = ShapeFrontEnd(build_model_from_mesh(object_mesh(get_object("channel")), "channel"), fe)
    twins = channel.near_twins(T)
    assert len(twins) == 1 and abs(twins[0][0, 0] - 1.0) < 1e-9 and abs(twins[0][2, 2] + 1.0) < 1e-9
    assert ShapeFrontEnd(_box_model(), fe).near_twins(T) == []


def test_a_turned_pose_gives_way_to_its_twin_the_depth_agrees_with_better():
    """A bracket lying on its short plate, its long one standing: the same bracket with its
    plates swapped (its near-symmetric twin, 178 deg off, 2-3 cm; bracket seed 1213 frame 6)
    is what the turned-over pass placed there. Of the pose and its twin refined, the one the
    depth agrees with better is kept: the true one."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))          # base plate 0.12 along x, upright 0.08 at -x
    reg = InstanceRegistration(build_model_from_mesh(mesh, "bracket"), PipelineConfig())
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, -0.25, 0.45]), np.zeros(3))
    on_short = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])    # model +x up: the upright lies
    T = invert_transform(cam) @ make_transform(on_short, [0.0, 0.0, 0.06])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    cloud = reg._shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    swap = reg._shape.near_twins(np.eye(4))[0]
    wrong = T @ np.linalg.inv(swap) @ make_transform(np.eye(3), [0.004, 0.0, -0.003])
    assert rotation_angle_deg(wrong[:3, :3].T @ T[:3, :3]) > 170.0
    kept = reg._better_twin((wrong, 0.9, 150, 120.0), cloud, depth, intr)
    assert rotation_angle_deg(kept[0][:3, :3].T @ T[:3, :3]) < 3.0
    assert np.linalg.norm(kept[0][:3, 3] - T[:3, 3]) < 0.005 and kept[3] > 120.0
    # A pose the depth agrees with better than with its twin stays.
    right = (T, 1.0, 200, 1000.0)
    assert reg._better_twin(right, cloud, depth, intr) is right


def test_a_turned_pose_left_a_few_degrees_off_is_kept_at_its_second_look():
    """A pose the turned-over pass accepts 10 deg off a standing bracket (turned about the
    vertical; bracket seed 1917 frame 2: 10.4 deg, evidence 171.5) is kept at its second look
    (projective ICP) when the depth agrees with that better (1.0 deg, 213)."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    reg = InstanceRegistration(build_model_from_mesh(mesh, "bracket"), PipelineConfig())
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, -0.25, 0.45]), np.zeros(3))
    T = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, 0.04])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    cloud = reg._shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    twist = np.zeros(6)
    twist[:3] = np.radians(10.0) * T[:3, 2]
    off = apply_twist(T, twist, reg._shape._visible_surface(T).mean(axis=0))
    kept = reg._better_twin((off, 0.9, 150, 100.0), cloud, depth, intr)
    assert rotation_angle_deg(kept[0][:3, :3].T @ T[:3, :3]) < 2.0 and kept[3] > 100.0


def test_icp_does_not_slide_an_open_side_down_channel_along_its_length():
    """A U channel lying open side down, seen from above: its top and slivers of its walls,
    its length held by its thin end faces alone. From its true pose tilted 6 deg, ICP slid
    it 4-7 mm along its length (10-20 mm on channel seed 1607's frames), and the refined pose
    lost to the tilted start and was rejected. Refined again with ICP's move along what the
    visible surface does not hold dropped (``_held_look``), it is right (returned apart, as
    a second look's pose)."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.rgbd.shape_frontend import ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.15, -0.1, 0.6]), np.zeros(3))       # camera -> world, table z = 0
    T = invert_transform(cam) @ make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.025])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    depth = (depth + np.random.default_rng(0).normal(0, 0.001, depth.shape)).astype(np.float32)
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "channel"), PipelineConfig().frontend)
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    flipped = T @ np.diag([-1.0, -1.0, 1.0, 1.0])               # the channel's half turn about z
    for axis in range(3):
        twist = np.zeros(6)
        twist[:3] = np.radians(6.0) * T[:3, axis]
        first, _, _, second = shape._refine(apply_twist(T, twist, T[:3, 3]), cloud, depth, intr)
        kept = first if first is not None else second
        assert kept is not None
        assert min(rotation_angle_deg(kept[0][:3, :3].T @ P[:3, :3]) for P in (T, flipped)) < 2.0
        assert np.linalg.norm(kept[0][:3, 3] - T[:3, 3]) < 0.003


def test_the_second_look_reaches_a_standing_bracket_turned_30_deg_about_its_upright_axis():
    """The second look's projective ICP narrows its pairing distance over its rounds: from a
    standing bracket turned 30 deg about the vertical, 10 rounds stop 11 deg off, its rounds
    (``SECOND_LOOK_ITERATIONS``) reach the pose (bracket seed 1947: 29 deg -> 0.1 deg)."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.rgbd.shape_frontend import SECOND_LOOK_ITERATIONS, ShapeFrontEnd
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.tracking.icp import align_projective
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, -0.25, 0.45]), np.zeros(3))
    T = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, 0.04])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    twist = np.zeros(6)
    twist[:3] = np.radians(30.0) * T[:3, 2]
    start = apply_twist(T, twist, shape._visible_surface(T).mean(axis=0))
    v = shape.voxel

    def looked(rounds):
        R = align_projective(start, shape._surface, shape._surface_normals, depth, intr, rounds, 1.5 * v, 0.75 * v).T
        return rotation_angle_deg(R[:3, :3].T @ T[:3, :3]), np.linalg.norm(R[:3, 3] - T[:3, 3])

    assert looked(10)[0] > 5.0
    angle, shift = looked(SECOND_LOOK_ITERATIONS)
    assert angle < 1.0 and shift < 0.002


def test_a_pose_passed_only_with_points_hidden_gives_way_to_a_better_residual_pose_on_its_place():
    """A pose ``_accept_hidden`` passed (points taken as hidden behind whatever is in front)
    does not hide its points from the residual votes, and a pose voted there with more
    evidence on its place takes it (bracket seed 157 frame 9: a bracket 180 deg about the
    vertical off the one there, on its upright plate with its base taken as hidden, evidence
    219, held the place of that bracket's right pose, 243). With more evidence it stays."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig

    mesh, intr, T1, T2, depth = _two_brackets_side_by_side()
    reg = InstanceRegistration(build_model_from_mesh(mesh, "bracket"), PipelineConfig())
    cloud = reg._shape.frame_cloud(depth, intr, None)
    wrong = T2 @ make_transform(rotation_z(180.0), [0.02, 0.0, 0.0])
    assert reg._overlaps_any([wrong], [T2])[0]

    def right(P):
        return rotation_angle_deg(P[:3, :3].T @ T2[:3, :3]) < 2.0 and np.linalg.norm(P[:3, 3] - T2[:3, 3]) < 0.005

    found, hidden = (T1, 1.0, 300, 300.0), (wrong, 1.0, 150, 50.0)
    kept = reg._accept_residual([found, hidden], [], cloud, depth, intr, provisional=[hidden])
    assert kept[0] is found and not any(c is hidden for c in kept) and any(right(c[0]) for c in kept)
    # Taken as found (not passed with points hidden), or with more evidence, it stays.
    as_found = reg._accept_residual([found, hidden], [], cloud, depth, intr)
    assert as_found[1] is hidden and not any(right(c[0]) for c in as_found)
    strong = (wrong, 1.0, 150, 1e4)
    assert any(c is strong for c in reg._accept_residual([found, strong], [], cloud, depth, intr, provisional=[strong]))


def test_the_second_look_keeps_the_better_fit_of_its_short_and_long_rounds(monkeypatch):
    """The second look's pairing distance narrows over its rounds: from a near start the long
    run can carry a pose past the fit the short one reached (channel seed 5 frame 9: support -
    free 0.85 after 10 rounds, 0.74 after 30, then rejected). Of the two, the pose the depth
    agrees with better is kept."""
    from types import SimpleNamespace

    import multi_instance_reg.rgbd.shape_frontend as sf
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))
    shape = sf.ShapeFrontEnd(build_model_from_mesh(mesh, "bracket"), PipelineConfig().frontend)
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.3, -0.25, 0.45]), np.zeros(3))
    T = invert_transform(cam) @ make_transform(np.eye(3), [0.0, 0.0, 0.04])
    depth = _meshes_on_table(mesh, [T], cam, intr)
    past = T @ make_transform(np.eye(3), [0.015, 0.0, 0.0])
    assert sf.SECOND_LOOK_SHORT < sf.SECOND_LOOK_ITERATIONS
    for short, long_ in ((T, past), (past, T)):
        looks = {sf.SECOND_LOOK_SHORT: short, sf.SECOND_LOOK_ITERATIONS: long_}
        monkeypatch.setattr(sf, "align_projective", lambda T0, *a: SimpleNamespace(T=looks[a[4]]))
        assert np.allclose(shape._projective_look(past, depth, intr)[0], T)


def _table_with_raised(raised, on_top=None):
    """Depth of a table 1 m below the camera, straight on, with ``raised`` (pixel slices) 5 cm
    above it and ``on_top`` 5 cm above those."""
    depth = np.full((240, 320), 1.0, np.float32)
    for rows, cols in raised:
        depth[rows, cols] = 0.95
    for rows, cols in on_top or ():
        depth[rows, cols] = 0.90
    return depth


def test_support_mask_keeps_flush_object_tops_but_not_a_raised_support():
    """Two objects 5 cm high lying flush side by side on a table: their tops, one plane piece
    0.041 m^2, are larger than the support area (0.03; each alone 0.020), so without the objects' face heights
    they go as a support (channel seed 2251: two channels open side down, no hypothesis for
    either). They stand at a face height above the larger table, nothing on them: they stay.
    A platform as high, carrying a box (a pallet's top, as high as a carton), stays a support."""
    intr = _intrinsics()
    tops = [(slice(60, 120), slice(100, 160)), (slice(60, 120), slice(160, 220))]
    depth = _table_with_raised(tops)
    valid = depth > 0
    kw = dict(max_area=0.03, thresh=0.004, noise_per_m2=0.002)
    table = np.ones((240, 320), bool)
    table[55:125, 95:225] = False
    inner = np.zeros((240, 320), bool)
    inner[65:115, 105:215] = True
    assert support_mask(depth, intr, valid, **kw)[inner].all()          # taken for a support
    planes = []
    mask = support_mask(depth, intr, valid, face_heights=np.array([0.008, 0.05, 0.1]), planes=planes, **kw)
    assert not mask[inner].any() and mask[table].all()
    assert len(planes) == 1                                              # the table alone
    # Not at a face height (7 cm): a support.
    assert support_mask(depth, intr, valid, face_heights=np.array([0.02, 0.07]), **kw)[inner].all()
    # A platform at 5 cm with a box on it: the box stands on it, so it is a support.
    platform = _table_with_raised([(slice(40, 200), slice(60, 260))], on_top=[(slice(100, 140), slice(140, 180))])
    mask = support_mask(platform, intr, platform > 0, face_heights=np.array([0.05]), **kw)
    assert mask[45:95, 65:255].all() and not mask[105:135, 145:175].any()


def test_object_face_heights_of_a_box_are_its_sides():
    from multi_instance_reg.rgbd.shape_frontend import object_face_heights

    points, normals = sample_surface(box_mesh(0.16, 0.10, 0.05), 0.004, seed=1)
    heights = object_face_heights(points, normals, 0.008)
    assert np.allclose(heights, [0.05, 0.10, 0.16], atol=0.003)


def test_a_rejected_pose_is_judged_again_with_the_instances_the_later_passes_find(monkeypatch):
    """Three channels open side down in a row, their tops flush; at the evidence asked for
    0.9 the middle one passes only with both neighbours found (its outline runs onto their
    tops). One neighbour is found first, the other only by the residual votes (here: the
    pass made to add it), after the middle one was judged: it is judged again with both
    and passes (channel seed 2251 frames 7 / 8)."""
    from dataclasses import replace
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.0, -0.45, 0.55]), np.zeros(3))
    down = np.diag([1.0, -1.0, -1.0])
    left, middle, right = (invert_transform(cam) @ make_transform(down, [x, 0.0, 0.025]) for x in (-0.1, 0.0, 0.1))
    depth = _meshes_on_table(mesh, [left, middle, right], cam, intr)
    config = PipelineConfig()
    config = replace(config, frontend=replace(config.frontend, shape_min_evidence=0.9))
    reg = InstanceRegistration(build_model_from_mesh(mesh, "channel"), config)
    cloud = reg._shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    late = (right, 1.0, 400, 400.0)
    monkeypatch.setattr(InstanceRegistration, "_accept_residual",
                        lambda self, chosen, *a, **k: chosen + [late])
    found = (left, 1.0, 400, 400.0)
    chosen = reg._accept_rejected([found], [middle], [], cloud, depth, intr)
    assert chosen[:2] == [found, late] and len(chosen) == 3
    assert rotation_angle_deg(chosen[2][0][:3, :3].T @ middle[:3, :3]) < 2.0
    assert np.linalg.norm(chosen[2][0][:3, 3] - middle[:3, 3]) < 0.005


def test_a_channel_half_hidden_by_its_flush_neighbour_is_climbed_onto_its_pose_and_passes_in_a_pair():
    """Two channels open side down, flush side by side (3 mm apart), the nearer one hiding a
    third of the other: the farther one's fit turned 10 deg about its top's normal stays off
    (nearest-point ICP cannot turn a top seen alone in its plane, and slides it along its
    length: 16 mm here, as channel seed 2141 frames 0-2), and the pair fails there. Climbed by
    turned starts with the nearer one's pixels hiding it (``climbed``) it reaches its pose,
    and ``_accept_climbed_pairs`` adds the pair (the nearer one given as a supported rejected
    pose, the turned fit as the residual votes' rejected one), which fails as given; not
    with the nearer one slid along its length, overhanging space seen empty (channel seed
    2404 frame 11: such a pair passed, one member 27 mm off)."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.rgbd.shape import apply_twist
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("channel"))                    # 0.10 x 0.16 x 0.05, open towards +z
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([0.6, -0.1, 0.45]), np.array([0.05, 0.0, 0.0]))    # camera -> world, table z = 0
    down = np.diag([1.0, -1.0, -1.0])
    near, far = [invert_transform(cam) @ make_transform(down, [x, 0.0, 0.025]) for x in (0.103, 0.0)]
    depth = _meshes_on_table(mesh, [near, far], cam, intr)
    reg = InstanceRegistration(build_model_from_mesh(mesh, "channel"), PipelineConfig())
    shape = reg._shape
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    turned = apply_twist(far, np.concatenate([np.radians(10.0) * far[:3, 2], np.zeros(3)]),
                         shape._visible_surface(far).mean(axis=0))

    def right(P, deg=3.0, metres=0.003):
        return rotation_angle_deg(P[:3, :3].T @ far[:3, :3]) < deg and np.linalg.norm(P[:3, 3] - far[:3, 3]) < metres

    refined = shape._refine(turned, cloud, depth, intr)
    assert refined[0] is None and not right(refined[1], 8.0, 0.01)
    hiding = shape.instance_pixels([near], depth, intr)
    assert shape._fit(far, depth, intr, hiding)[3] < shape._fit(far, depth, intr)[3]     # near hides some of it
    assert shape.climb_fit(turned, hiding, depth, intr) is not None
    assert right(shape.climbed(turned, hiding, cloud, depth, intr))
    added = reg._accept_climbed_pairs([], [near], [turned], cloud, depth, intr)
    assert len(added) == 2 and np.allclose(added[0][0], near) and right(added[1][0])
    # As the residual votes gave it, the pair fails.
    assert reg._accept_pairs([], [near, turned], cloud, depth, intr) == []
    # The nearer one slid 1 cm along its length overhangs space seen empty: not rejected for
    # what a neighbour explains, it is not paired (it passed with the far one climbed).
    slid = near @ make_transform(np.eye(3), [0.0, 0.01, 0.0])
    assert shape.overhangs(slid, depth, intr) and not shape.overhangs(near, depth, intr)
    assert reg._accept_climbed_pairs([], [slid], [turned], cloud, depth, intr) == []


def test_a_pose_overhanging_open_space_gives_way_to_one_on_its_surface_hidden_behind_a_block():
    """An L bracket lying on its short plate, its long plate standing, a block in front hiding
    most of the lying plate (support 0.78 at the truth: rejected). The same bracket turned half
    about the vertical through its standing plate, its lying plate behind that plate on the
    open table, agrees with the standing plate as well and passes (support 0.88, free 0.07:
    it overhangs space seen empty; bracket seed 2465 frames 3 / 5). The truth passes judged
    with the block hiding it and claims the same seen points with more evidence: it takes the
    place of the overhanging pose, which alone kept it off its place before."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.scene import look_at
    from multi_instance_reg.transforms import invert_transform

    mesh = object_mesh(get_object("bracket"))                    # 0.12 x 0.06 x 0.08, 12 mm plates
    intr = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)
    cam = look_at(np.array([-0.35, -0.12, 0.45]), np.array([0.0, 0.0, 0.03]))
    world = invert_transform(cam)
    lying = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])   # model x up
    T = world @ make_transform(lying, [0.0, 0.0, 0.06])          # standing plate at world x 0.028-0.04
    turned = world @ make_transform(rotation_z(180.0) @ lying, [0.068, 0.0, 0.06])   # same standing plate
    block = box_mesh(0.04, 0.14, 0.10)
    depth = _meshes_on_table(mesh, [T], cam, intr)
    d = _depth_of(sample_surface(block, 0.001)[0], world @ make_transform(np.eye(3), [-0.10, 0.0, 0.05]), intr)
    depth = np.where((d > 0) & (d < depth), d, depth)
    reg = InstanceRegistration(build_model_from_mesh(mesh, "bracket"), PipelineConfig())
    shape = reg._shape
    cloud = shape.frame_cloud(depth, intr, None, cam[:3, :3].T @ [0.0, 0.0, 1.0])
    assert shape._judge(T, *shape.depth_check(T, depth, intr), cloud, depth, intr) is None
    wrong = shape._judge(turned, *shape.depth_check(turned, depth, intr), cloud, depth, intr)
    assert wrong is not None and shape.overhangs(turned, depth, intr)
    kept = reg._accept_hidden([wrong], [T], cloud, depth, intr)
    assert len(kept) == 1 and np.allclose(kept[0][0], T)
