"""Flat faces placed by their outline (frontends/shape/faces.py): the model's faces, a frame's flat
patches, and the poses they give."""
import numpy as np

from multi_instance_reg.meshes import box_mesh, cylinder_mesh, sample_surface
from multi_instance_reg.frontends.shape.faces import frame_patches, matches, model_faces, nearest_face_pose, patch_poses
from multi_instance_reg.models.mesh_model import build_model_from_mesh
from multi_instance_reg.frontends.shape.geometry import voxel_downsample
from multi_instance_reg.frontends.shape.frontend import oriented_downsample
from multi_instance_reg.symmetry import closest_symmetric_pose
from multi_instance_reg.transforms import make_transform, rotation_angle_deg


def _surface(mesh, name):
    model = build_model_from_mesh(mesh, name)
    p, n = oriented_downsample(model.shape_points, model.shape_normals, model.shape_voxel)
    return model, p, n


def _yaw(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _top_seen_from_above(keep=None, yaw=20.0, seed=0):
    """A 0.3 x 0.2 x 0.15 m box, top (+z) towards a camera 1.5 m above, turned ``yaw`` deg;
    its top's points (voxel-downsampled, 2 mm noise), ``keep`` (a filter on the top's model
    x, y) for a partly hidden one. Returns model, surface, normals, true pose, points, normals."""
    model, surface, normals = _surface(box_mesh(0.3, 0.2, 0.15), "box")
    T = make_transform(np.diag([1.0, -1.0, -1.0]) @ _yaw(yaw), [0.05, -0.03, 1.5])
    dense, _ = sample_surface(box_mesh(0.3, 0.2, 0.15), 0.004)
    top = dense[dense[:, 2] > 0.074]
    if keep is not None:
        top = top[keep(top)]
    scene = top @ T[:3, :3].T + T[:3, 3] + np.random.default_rng(seed).normal(0, 0.002, (len(top), 3))
    scene = voxel_downsample(scene, model.shape_voxel)
    return model, surface, normals, T, scene, np.tile([0, 0, -1.0], (len(scene), 1))


def _errors(model, T_true, T):
    G = closest_symmetric_pose(T_true, T, model.symmetries)
    return rotation_angle_deg(G[:3, :3].T @ T[:3, :3]), float(np.linalg.norm(G[:3, 3] - T[:3, 3]))


def test_model_faces_of_a_box_and_none_of_a_cylinder():
    model, surface, normals = _surface(box_mesh(0.3, 0.2, 0.15), "box")
    faces = model_faces(surface, normals, model.shape_voxel)
    assert len(faces) == 6
    # Within a voxel of the box's sides (the voxel means at the edges lie inside them).
    sides = sorted(map(tuple, np.round(faces.sides * 20) / 20))
    want = sorted([(0.3, 0.2)] * 2 + [(0.3, 0.15)] * 2 + [(0.2, 0.15)] * 2)
    assert np.allclose(sides, want) and np.all(np.abs(faces.sides - np.round(faces.sides * 20) / 20) < 0.016)
    # A cylinder's caps have no long axis and its side no flat face.
    model, surface, normals = _surface(cylinder_mesh(0.06, 0.1), "cyl")
    assert len(model_faces(surface, normals, model.shape_voxel)) == 0


def test_a_top_seen_whole_gives_its_pose_and_a_pose_off_in_yaw_is_moved_onto_it():
    model, surface, normals, T, P, N = _top_seen_from_above()
    faces = model_faces(surface, normals, model.shape_voxel)
    diameter = float(np.linalg.norm(model.extent))
    patches = frame_patches(P, N, np.zeros(len(P), np.int64), diameter, 2 * model.shape_voxel, lambda z: 0.01)
    assert len(patches) == 1 and not patches.joined.any()      # delimited by the depth
    fits = matches(faces, patches, model.shape_voxel)
    poses = patch_poses(faces, patches, fits)
    assert len(poses) >= 2                                      # the top, on either sign of its axis
    best = min((_errors(model, T, Q) for Q in poses), key=lambda e: e[0])
    assert best[0] < 2.0 and best[1] < 0.01                    # within a voxel (1.6 cm here)
    # A pose 12 deg off in yaw and 3 cm off along the top (where ICP on the top alone holds
    # nothing) is placed by the patch.
    off = T.copy()
    off[:3, :3] = T[:3, :3] @ _yaw(12.0)
    off[:3, 3] += [0.02, 0.02, 0.0]
    moved = nearest_face_pose(faces, patches, fits, off, 0.1 * diameter + model.shape_voxel)
    assert moved is not None
    rre, rte = _errors(model, T, moved)
    assert rre < 2.0 and rte < 0.01


def test_a_partly_hidden_top_gives_no_pose():
    # A third of the top hidden (by a carton lying over it): its outline is not the top's.
    model, surface, normals, T, P, N = _top_seen_from_above(keep=lambda q: q[:, 0] < 0.05)
    faces = model_faces(surface, normals, model.shape_voxel)
    diameter = float(np.linalg.norm(model.extent))
    patches = frame_patches(P, N, np.zeros(len(P), np.int64), diameter, 2 * model.shape_voxel, lambda z: 0.01)
    poses = patch_poses(faces, patches, matches(faces, patches, model.shape_voxel))
    # 0.2 x 0.2 left: no face of the box has those sides (nor a long axis).
    assert len(poses) == 0


def test_two_tops_in_one_segment_are_cut_apart():
    model, surface, normals, T, P, N = _top_seen_from_above(yaw=0.0)
    other = P + [0.0, 0.25, 0.0]                                # a neighbour 5 cm past its long side
    bridge = np.array([[0.05, -0.03 + 0.125, 1.5 + 0.3]])       # joined below by what lies between
    Q = np.vstack([P, other, bridge])
    NQ = np.vstack([N, N, [[0, 0, -1.0]]])
    faces = model_faces(surface, normals, model.shape_voxel)
    diameter = float(np.linalg.norm(model.extent))
    patches = frame_patches(Q, NQ, np.zeros(len(Q), np.int64), diameter, 2 * model.shape_voxel, lambda z: 0.01)
    assert len(patches) == 2
    assert len(patch_poses(faces, patches, matches(faces, patches, model.shape_voxel))) >= 4


def test_flush_tops_are_cut_apart_along_the_dark_seam_between_them_and_not_along_tape():
    from multi_instance_reg.frontends.shape.explain import FrameView
    from multi_instance_reg.messages import CameraIntrinsics

    model, surface, normals, T, P, N = _top_seen_from_above(yaw=0.0)
    # Its neighbour packed flush past its long side: one plane in depth, 0.3 x 0.4 m.
    Q, NQ = np.vstack([P, P + [0.0, 0.2, 0.0]]), np.vstack([N, N])
    faces = model_faces(surface, normals, model.shape_voxel)
    diameter = float(np.linalg.norm(model.extent))
    cut = lambda **k: frame_patches(Q, NQ, np.zeros(len(Q), np.int64), diameter, 2 * model.shape_voxel,
                                    lambda z: 0.01, **k)
    assert not matches(faces, cut(), model.shape_voxel).any()      # depth alone: no face of the box
    # In colour, a band of lighter tape along the middle of each top (a step, not a line)
    # and a dark seam, 3 pixels wide, where the two tops meet (y = 0.07 m at 1.5 m).
    K = np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])
    row = lambda y: int(round(K[1, 1] * y / 1.5 + K[1, 2]))
    rgb = np.full((240, 320, 3), 150, np.uint8)
    for middle in (-0.03, 0.17):
        rgb[row(middle - 0.024):row(middle + 0.024)] = 175
    taped = FrameView.of(np.full((240, 320), 1.5, np.float32), CameraIntrinsics(K=K, width=320, height=240), rgb)
    assert not matches(faces, cut(across_seams=taped.across_seams), model.shape_voxel).any()
    seam = row(0.07)
    rgb[seam - 1:seam + 2] = 70
    view = FrameView.of(np.full((240, 320), 1.5, np.float32), CameraIntrinsics(K=K, width=320, height=240), rgb)
    patches = cut(across_seams=view.across_seams)
    fits = matches(faces, patches, model.shape_voxel)
    assert len(patches) == 2 and fits.any(axis=1).all() and patches.joined.all()   # by their outline
    best = min((_errors(model, T, Q_) for Q_ in patch_poses(faces, patches, fits)), key=lambda e: e[0] + 100 * e[1])
    assert best[0] < 2.0 and best[1] < 0.015
