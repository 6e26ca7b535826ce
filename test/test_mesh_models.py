"""Models from BOP-style meshes: loading defects (issue 38), symmetries from models_info.json,
vertex colours and textures, rendered views of a coloured mesh and the SIFT keypoints they give."""
import subprocess
import sys

import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.meshes import load_mesh

MIREG = [sys.executable, "-m", "multi_instance_reg.tools.cli"]

PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"


def build(tmp_path, *args):
    return subprocess.run(MIREG + ["build-model", *map(str, args), "-o", str(tmp_path / "m.npz")],
                          capture_output=True, text=True)


# --------------------------------------------------------------------------- issue 38

def test_unknown_ply_property_type_is_one_line(tmp_path):
    path = tmp_path / "odd.ply"
    path.write_text(PLY_HEAD.format(n=3) + "property float128 w\nelement face 1\n"
                    "property list uchar int vertex_indices\nend_header\n0 0 0 1\n0.1 0 0 1\n0 0.1 0 1\n3 0 1 2\n")
    with pytest.raises(InputError, match="float128"):
        load_mesh(path)
    run = build(tmp_path, "--mesh", path)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
    assert str(path) in run.stderr and "float128" in run.stderr


def test_single_open_triangle_is_refused(tmp_path):
    path = tmp_path / "tri.ply"
    path.write_text(PLY_HEAD.format(n=3) + "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n0.1 0 0\n0 0.1 0\n3 0 1 2\n")
    with pytest.raises(InputError, match="triangle"):
        load_mesh(path)
    run = build(tmp_path, "--mesh", path)
    assert run.returncode == 2 and "Traceback" not in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "m.npz").exists()


def test_flat_sheet_is_refused(tmp_path):
    # Many triangles, all in one (tilted) plane: no solid to find by shape, no box.
    rng = np.random.default_rng(0)
    uv = rng.random((40, 2)) * 0.1
    v = np.column_stack([uv[:, 0], uv[:, 1], 0.5 * uv[:, 0]])
    faces = "".join(f"3 {i} {i + 1} {i + 2}\n" for i in range(38))
    path = tmp_path / "sheet.ply"
    path.write_text(PLY_HEAD.format(n=40) + "element face 38\nproperty list uchar int vertex_indices\nend_header\n"
                    + "".join(f"{a} {b} {c}\n" for a, b, c in v) + faces)
    with pytest.raises(InputError, match="flat"):
        load_mesh(path)


# --------------------------------------------------------------------------- colours

PYRAMID = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0], [0.05, 0.05, 0.08]])
PYRAMID_FACES = [[0, 3, 2, 1], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]     # a quad base and 4 triangles
PYRAMID_RGB = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30], [200, 100, 50]], np.uint8)


def write_ply(path, vertices, faces, fmt, colours=None, colour_type="uchar"):
    """A PLY as writers lay it out: x y z [red green blue] per vertex, one index list per face."""
    head = f"ply\nformat {fmt} 1.0\ncomment\ncomment test\nelement vertex {len(vertices)}\n"
    head += "property float x\nproperty float y\nproperty float z\n"
    if colours is not None:
        head += "".join(f"property {colour_type} {c}\n" for c in ("red", "green", "blue"))
    head += f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    scale = 1 / 255 if colour_type == "float" else 1
    if fmt == "ascii":
        rows = [" ".join(map(str, list(v) + ([] if colours is None else list(np.asarray(c) * scale))))
                for v, c in zip(vertices, colours if colours is not None else [None] * len(vertices))]
        body = "\n".join(rows + [" ".join(map(str, [len(f)] + list(f))) for f in faces]) + "\n"
        path.write_text(head + body)
        return
    order = "<" if fmt == "binary_little_endian" else ">"
    cdt = {"uchar": "u1", "float": "f4"}[colour_type]
    fields = [("xyz", order + "f4", 3)] + ([] if colours is None else [("rgb", order + cdt, 3)])
    rec = np.zeros(len(vertices), np.dtype(fields))
    rec["xyz"] = vertices
    if colours is not None:
        rec["rgb"] = np.asarray(colours) * scale
    body = rec.tobytes() + b"".join(np.array([len(f)], "u1").tobytes() + np.array(f, order + "i4").tobytes()
                                    for f in faces)
    path.write_bytes(head.encode() + body)


@pytest.mark.parametrize("fmt,colour_type", [("ascii", "uchar"), ("ascii", "float"),
                                             ("binary_little_endian", "uchar"), ("binary_big_endian", "float")])
def test_vertex_colours_read_with_mixed_polygons(tmp_path, fmt, colour_type):
    path = tmp_path / "pyramid.ply"
    write_ply(path, PYRAMID, PYRAMID_FACES, fmt, PYRAMID_RGB, colour_type)
    mesh = load_mesh(path)
    assert len(mesh.triangles) == 6 and np.allclose(mesh.vertices, PYRAMID, atol=1e-6)
    assert mesh.has_colour and mesh.corner_uv is None
    assert np.array_equal(mesh.vertex_colours, PYRAMID_RGB)
    # Without colours: none made up.
    write_ply(path, PYRAMID, PYRAMID_FACES, fmt)
    assert load_mesh(path).vertex_colours is None and not load_mesh(path).has_colour


# --------------------------------------------------------------------------- symmetries from models_info.json

FLIP_X_MM = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 20, 0, 0, 0, 1]      # 180 deg about x through z = 10 mm
HALF_Z = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


def models_info(tmp_path, entries, name="models_info.json"):
    import json

    base = {"diameter": 100.0, "min_x": -50, "min_y": -50, "min_z": -50, "size_x": 100, "size_y": 100, "size_z": 100}
    path = tmp_path / name
    path.write_text(json.dumps({str(k): {**base, **v} for k, v in entries.items()}, indent=1))
    return path


def test_symmetries_read_from_models_info(tmp_path):
    from multi_instance_reg.datasets.bop import read_models_info

    def read_bop_symmetries(path, obj_id):
        return read_models_info(path)[obj_id].symmetries()

    path = models_info(tmp_path, {3: {"symmetries_discrete": [FLIP_X_MM, HALF_Z]},
                                  7: {"symmetries_continuous": [{"axis": [0, 0, 2], "offset": [1, 2, 3]}],
                                      "symmetries_discrete": [FLIP_X_MM]},
                                  9: {}})
    box = read_bop_symmetries(path, 3)
    assert len(box.discrete) == 3 and np.allclose(box.discrete[0], np.eye(4)) and box.axis is None
    flip = box.discrete[1]
    assert np.allclose(flip[:3, 3], [0, 0, 0.02])              # mm -> m
    assert np.allclose(flip @ [0.01, 0.02, 0.01, 1], [0.01, -0.02, 0.01, 1])   # a point on the axis' plane
    cyl = read_bop_symmetries(path, 7)
    assert np.allclose(cyl.axis, [0, 0, 1]) and np.allclose(cyl.point, [0.001, 0.002, 0.003])
    assert len(cyl.discrete) == 2
    assert read_bop_symmetries(path, 9) is None                   # no keys: asymmetric (BOP leaves them out)
    bad = models_info(tmp_path, {1: {"symmetries_discrete": [[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}}, "bad.json")
    with pytest.raises(InputError, match="not a rigid transform"):
        read_bop_symmetries(bad, 1)
    short = models_info(tmp_path, {1: {"symmetries_discrete": [[1, 0, 0]]}}, "short.json")
    with pytest.raises(InputError, match="must be 16 finite numbers"):
        read_bop_symmetries(short, 1)


def test_build_model_takes_symmetries_from_models_info(tmp_path):
    from multi_instance_reg.meshes import box_mesh, save_mesh
    from multi_instance_reg.models.model import load_model

    mesh = save_mesh(box_mesh(0.06, 0.04, 0.03), tmp_path / "obj_000003.ply", "mm")
    models_info(tmp_path, {3: {"symmetries_continuous": [{"axis": [0, 1, 0], "offset": [0, 0, 5]}]}})
    # Found beside the mesh, the id from BOP's file name: BOP's word over the shape's (a box has 4 discrete).
    run = build(tmp_path, "--mesh", mesh, "--units", "mm")
    assert run.returncode == 0, run.stderr
    sym = load_model(tmp_path / "m.npz").symmetries
    assert np.allclose(sym.axis, [0, 1, 0]) and np.allclose(sym.point, [0, 0, 0.005]) and len(sym.discrete) == 1
    assert "models_info.json, object 3" in run.stderr
    # Given, for a mesh named otherwise, with its id.
    other = save_mesh(box_mesh(0.06, 0.04, 0.03), tmp_path / "sub" / "carton.ply", "mm")
    info = models_info(tmp_path, {8: {"symmetries_discrete": [HALF_Z]}}, "info8.json")
    run = build(tmp_path, "--mesh", other, "--units", "mm", "--models-info", info, "--obj-id", 8)
    assert run.returncode == 0, run.stderr
    sym = load_model(tmp_path / "m.npz").symmetries
    assert sym.axis is None and len(sym.discrete) == 2 and np.allclose(sym.discrete[1], np.reshape(HALF_Z, (4, 4)))
    # Without the id, with an id it does not list, with both sources, an id and no file: refused.
    from multi_instance_reg.tools.build_model import mesh_symmetry

    for args, says in [((info, None), "--obj-id"), ((info, 4), "no object 4"), ((None, 8), "none beside")]:
        with pytest.raises(InputError, match=says):
            mesh_symmetry(other, "auto", *args)
    run = build(tmp_path, "--mesh", other, "--units", "mm", "--models-info", info, "--obj-id", 8, "--symmetry", "none")
    assert run.returncode == 2 and "not both" in run.stderr and len(run.stderr.strip().splitlines()) == 1, run.stderr


# --------------------------------------------------------------------------- rendering coloured meshes

BOX = np.array([0.10, 0.08, 0.06])
# Each face of a box: its outward axis, and its 4 corners counter-clockwise seen from outside.
FACES = {"+x": [(1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1)], "-x": [(-1, 1, -1), (-1, -1, -1), (-1, -1, 1), (-1, 1, 1)],
         "+y": [(1, 1, -1), (-1, 1, -1), (-1, 1, 1), (1, 1, 1)], "-y": [(-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1)],
         "+z": [(-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)], "-z": [(-1, 1, -1), (1, 1, -1), (1, -1, -1), (-1, -1, -1)]}
RED, BLUE = (220, 30, 20), (20, 40, 200)


def box_faces(size=BOX):
    """24 vertices (4 a face, so that each face has its own colour or texture corners) and 12 triangles."""
    verts = np.array([c for corners in FACES.values() for c in corners], np.float64) * size / 2
    tris = [[4 * f, 4 * f + 1, 4 * f + 2] for f in range(6)] + [[4 * f, 4 * f + 2, 4 * f + 3] for f in range(6)]
    return verts, tris


def write_two_coloured_box(path):
    verts, tris = box_faces()
    colours = [RED if name == "+z" else BLUE for name in FACES for _ in range(4)]
    write_ply(path, verts, tris, "binary_little_endian", colours)


def photo_texture(size=384):
    """A photograph that ships with scikit-image (astronaut): the detail SIFT needs."""
    import cv2
    from skimage import data

    return cv2.resize(data.astronaut(), (size, size), interpolation=cv2.INTER_AREA)


def write_textured_box(path, texture, per_corner: bool, scale: float = 1.0):
    """Each face maps to its own cell of a 3 x 2 grid over the picture: per vertex (texture_u/v)
    or per face corner (a face 'texcoord' list, as MeshLab writes); coordinates x ``scale``."""
    import cv2

    verts, tris = box_faces()
    verts = verts * scale
    cell = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) * [1 / 3, 1 / 2] * 0.96 + 0.02 / 3
    uv = np.concatenate([cell + [f % 3 / 3, f // 3 / 2] for f in range(6)])
    cv2.imwrite(str(path.parent / "box_texture.png"), texture[:, :, ::-1])
    head = f"ply\nformat ascii 1.0\ncomment TextureFile box_texture.png\nelement vertex {len(verts)}\n"
    head += "property float x\nproperty float y\nproperty float z\n"
    if not per_corner:
        head += "property float texture_u\nproperty float texture_v\n"
    head += f"element face {len(tris)}\nproperty list uchar int vertex_indices\n"
    if per_corner:
        head += "property list uchar float texcoord\n"
    head += "end_header\n"
    rows = [" ".join(map(str, list(v) + ([] if per_corner else list(t)))) for v, t in zip(verts, uv)]
    for t in tris:
        row = f"3 {t[0]} {t[1]} {t[2]}"
        if per_corner:
            row += " 6 " + " ".join(str(x) for k in t for x in uv[k])
        rows.append(row)
    path.write_text(head + "\n".join(rows) + "\n")
    return uv


def camera(width=320, height=240, f=300.0):
    from multi_instance_reg.messages import CameraIntrinsics

    return CameraIntrinsics(np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]]), width, height)


def pixel_of(T, K, point):
    p = T[:3, :3] @ point + T[:3, 3]
    return int(round(K[0, 0] * p[0] / p[2] + K[0, 2])), int(round(K[1, 1] * p[1] / p[2] + K[1, 2])), p[2]


def depth_on_face(T, K, u, v, normal, offset):
    """Camera z where the ray of pixel (u, v) meets the plane normal . x = offset (mesh frame)."""
    ray = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])     # camera frame, z = 1
    centre = -T[:3, :3].T @ T[:3, 3]                                            # the camera, mesh frame
    return (offset - normal @ centre) / ((T[:3, :3] @ normal) @ ray)


def test_rendered_two_coloured_box_has_its_colours_where_expected(tmp_path):
    from multi_instance_reg.models.mesh_render import BACKGROUND_RGB, look_at, render_mesh

    path = tmp_path / "box.ply"
    write_two_coloured_box(path)
    mesh = load_mesh(path)
    intr = camera()
    T = look_at(np.zeros(3), [0.6, -0.5, 0.8], 0.5)          # sees +z (red), +x and -y (blue)
    r = render_mesh(mesh, T, intr)
    h = BOX / 2
    for point, colour, axis in [((0, 0, h[2]), RED, 2), ((0.02, -0.01, h[2]), RED, 2), ((h[0], 0, 0), BLUE, 0),
                                ((0.01, -h[1], -0.01), BLUE, 1)]:
        u, v, _ = pixel_of(T, intr.K, np.array(point, np.float64))
        assert tuple(r.rgb[v, u]) == colour, (point, r.rgb[v, u])
        normal = np.sign(point[axis]) * np.eye(3)[axis]
        assert r.depth_m[v, u] == pytest.approx(depth_on_face(T, intr.K, u, v, normal, h[axis]), abs=2e-5)
    # The z-buffer: the bottom's centre (blue) is hidden behind the top (red), nearer.
    u, v, z_bottom = pixel_of(T, intr.K, np.array([0, 0, -h[2]]))
    assert tuple(r.rgb[v, u]) == RED and r.depth_m[v, u] < z_bottom - 0.03
    assert tuple(r.rgb[0, 0]) == BACKGROUND_RGB and r.depth_m[0, 0] == 0 and r.triangle[0, 0] == -1
    # Colours blend inside a face only between its own corners: no red on the blue sides.
    side = r.mask & (np.abs(r.rgb.astype(int) - BLUE).sum(axis=2) < 6)
    top = r.mask & (np.abs(r.rgb.astype(int) - RED).sum(axis=2) < 6)
    assert side.sum() > 1000 and top.sum() > 1000 and (side | top).sum() > 0.97 * r.mask.sum()


@pytest.mark.parametrize("per_corner", [False, True])
def test_textured_box_read_and_rendered(tmp_path, per_corner):
    from multi_instance_reg.models.mesh_render import look_at, render_mesh

    texture = np.zeros((64, 96, 3), np.uint8)
    cells = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 255, 255), (255, 0, 255)]
    for f, c in enumerate(cells):       # cell f: columns f % 3, rows from the bottom f // 3 (v up)
        col, row = f % 3, 1 - f // 3
        texture[row * 32:(row + 1) * 32, col * 32:(col + 1) * 32] = c
    write_textured_box(tmp_path / "box.ply", texture, per_corner)
    mesh = load_mesh(tmp_path / "box.ply")
    assert mesh.has_colour and mesh.texture.shape == (64, 96, 3) and mesh.corner_uv.shape == (12, 3, 2)
    intr = camera()
    for f, (name, direction) in enumerate([("+x", (1, 0, 0)), ("-x", (-1, 0, 0)), ("+y", (0, 1, 0)),
                                           ("-y", (0, -1, 0)), ("+z", (0, 0, 1)), ("-z", (0, 0, -1))]):
        d = np.array(direction, np.float64)
        T = look_at(np.zeros(3), d + [0.2, 0.1, 0.15], 0.5)
        r = render_mesh(mesh, T, intr)
        u, v, _ = pixel_of(T, intr.K, d * BOX / 2)
        assert tuple(r.rgb[v, u]) == cells[f], (name, r.rgb[v, u])
    # Coordinates without a picture named, or the other way round: read without colour.
    text = (tmp_path / "box.ply").read_text()
    (tmp_path / "no_name.ply").write_text(text.replace("comment TextureFile box_texture.png\n", ""))
    (tmp_path / "no_uv.ply").write_text(text.replace("texture_u", "quality_u").replace(" texcoord", " quality"))
    for name in ("no_name.ply", "no_uv.ply"):
        assert not load_mesh(tmp_path / name).has_colour and load_mesh(tmp_path / name).corner_uv is None
    # The picture it names must be there: one line naming it.
    (tmp_path / "box_texture.png").unlink()
    with pytest.raises(InputError, match="box_texture.png"):
        load_mesh(tmp_path / "box.ply")


def box_surface_distance(p, size=BOX):
    """Distance of points from the surface of a box centred at the origin."""
    q = np.abs(p) - size / 2
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return np.abs(outside + inside)


def test_keypoints_of_a_textured_mesh_sit_at_their_3d_places(tmp_path):
    from multi_instance_reg.models.mesh_render import look_at, render_mesh
    from multi_instance_reg.frontends.sift.features import extract_sift
    from multi_instance_reg.frontends.sift.matching import DescriptorMatcher, prepare_descriptors
    from multi_instance_reg.models.mesh_model import add_rendered_keypoints, build_model_from_mesh, view_directions
    from multi_instance_reg.models.model import BuildSettings

    write_textured_box(tmp_path / "box.ply", photo_texture(), per_corner=False)
    mesh = load_mesh(tmp_path / "box.ply")
    model = build_model_from_mesh(mesh, "box", "none", views=6)
    model, per_view = add_rendered_keypoints(model, mesh, BuildSettings(tilts=()), count=10, distance=0.45)
    assert len(per_view) == 10 and model.num_keypoints == sum(per_view) and min(per_view) >= 20
    # Every keypoint lies on the box's surface (lifted by the rendered depth, in the mesh frame).
    d = box_surface_distance(model.keypoints_xyz.astype(np.float64))
    assert np.percentile(d, 95) < 0.0015 and d.max() < 0.01
    # A view it was not built from (12 deg and 5 cm away from one: SIFT bears about 30 deg):
    # SIFT there, matched to the model; the matched model points project back onto the
    # keypoints' pixels.
    intr = camera(640, 480, 550.0)
    d = view_directions(10)[3]
    turned = d + 0.21 * np.cross(d, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(d, [0.0, 0.0, 1.0]))
    T = look_at(np.zeros(3), turned, 0.5)
    r = render_mesh(mesh, T, intr)
    uv, desc = extract_sift(r.rgb, BuildSettings().sift, r.mask)
    # The pipeline's matcher: a point seen in several views is one point to the ratio test.
    matcher = DescriptorMatcher(prepare_descriptors(model.descriptors), model.keypoints_xyz, ratio=0.8, separation=0.01)
    s_idx, m_idx, _ = matcher.match(prepare_descriptors(desc))
    assert len(s_idx) >= 15
    xyz = model.keypoints_xyz[m_idx].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    proj = xyz[:, :2] / xyz[:, 2:] * [intr.K[0, 0], intr.K[1, 1]] + intr.K[:2, 2]
    err = np.linalg.norm(proj - uv[s_idx], axis=1)
    assert np.mean(err < 2.0) > 0.85, np.percentile(err, [50, 80, 95])


def test_build_model_from_coloured_mesh_takes_the_sift_path(tmp_path):
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.frontends.shape.frontend import resolve_correspondences

    write_textured_box(tmp_path / "box.ply", photo_texture(), per_corner=True)
    run = build(tmp_path, "--mesh", tmp_path / "box.ply", "--render-views", 6, "--symmetry", "none")
    assert run.returncode == 0, run.stderr
    assert "rendered from its texture" in run.stderr
    model = load_model(tmp_path / "m.npz")
    assert model.num_keypoints > 100 and model.has_shape
    assert resolve_correspondences("auto", model) == "both" and resolve_correspondences("sift", model) == "sift"
    run = build(tmp_path, "--mesh", tmp_path / "box.ply", "--render-views", 0, "--symmetry", "none")
    assert run.returncode == 0 and load_model(tmp_path / "m.npz").num_keypoints == 0


def test_bop_model_of_a_coloured_mesh_has_keypoints_and_the_listed_symmetries(tmp_path):
    from multi_instance_reg.datasets.bop import BopDataset
    from multi_instance_reg.tools.bop import model_from_bop_mesh

    (tmp_path / "test").mkdir()
    (tmp_path / "models").mkdir()
    write_textured_box(tmp_path / "models" / "obj_000001.ply", photo_texture(), per_corner=False, scale=1000.0)
    models_info(tmp_path / "models", {1: {"symmetries_discrete": [HALF_Z]}})
    model = model_from_bop_mesh(BopDataset(tmp_path), 1)
    assert model.num_keypoints > 300 and model.has_shape and np.allclose(model.extent, BOX)
    assert len(model.symmetries.discrete) == 2 and np.allclose(model.symmetries.discrete[1], np.reshape(HALF_Z, (4, 4)))


def test_a_plain_coloured_mesh_gets_no_keypoints_from_its_outline():
    # One colour all over: its renders have nothing but the outline, which a real scene does
    # not show against the same background; the model stays shape only.
    from multi_instance_reg.meshes import cylinder_mesh
    from multi_instance_reg.models.mesh_model import add_rendered_keypoints, build_model_from_mesh
    from multi_instance_reg.models.model import BuildSettings

    mesh = cylinder_mesh(0.08, 0.12)
    mesh.vertex_colours = np.full((len(mesh.vertices), 3), 200, np.uint8)
    model = build_model_from_mesh(mesh, "can", "none", views=4)
    model, per_view = add_rendered_keypoints(model, mesh, BuildSettings(tilts=()), count=8)
    assert sum(per_view) == 0 and model.num_keypoints == 0


def test_coloured_meshes_written_and_read_back(tmp_path):
    from multi_instance_reg.meshes import save_mesh

    write_ply(tmp_path / "p.ply", PYRAMID, PYRAMID_FACES, "ascii", PYRAMID_RGB)
    pyramid = load_mesh(tmp_path / "p.ply")
    back = load_mesh(save_mesh(pyramid, tmp_path / "p2.ply", "mm"), "mm")
    assert np.array_equal(back.vertex_colours, PYRAMID_RGB) and np.allclose(back.vertices, pyramid.vertices, atol=1e-7)
    write_textured_box(tmp_path / "box.ply", photo_texture(), per_corner=False)
    box = load_mesh(tmp_path / "box.ply")
    back = load_mesh(save_mesh(box, tmp_path / "out" / "box2.ply"))
    assert (tmp_path / "out" / "box2_texture.png").is_file()
    assert np.array_equal(back.texture, box.texture) and np.allclose(back.corner_uv, box.corner_uv, atol=1e-7)


@pytest.mark.parametrize("name", ["snack_box", "can"])
def test_mesh_render_agrees_with_the_synthetic_renderer(name):
    # The object as a textured mesh (its pictures in one atlas) and as the synthetic scenes
    # draw it (textured quads; a cylinder's side by ray casting): the same depth and outline,
    # the same picture but for the synthetic renderer's lighting. The can's mesh is a 64-gon
    # prism, so its outline and depth agree to within the polygon's sagitta (0.04 mm).
    import cv2

    from multi_instance_reg.models.mesh_render import look_at, render_mesh
    from multi_instance_reg.synthetic.objects import get_object, textured_object_mesh
    from multi_instance_reg.synthetic.render import Renderer
    from multi_instance_reg.synthetic.scene import Placement, object_primitives

    spec = get_object(name)
    mesh = textured_object_mesh(spec)
    assert mesh.has_colour
    intr = camera(640, 480, 550.0)
    for direction in ([0.5, -0.8, 0.9], [-0.7, 0.3, -0.6]):
        T = look_at(np.zeros(3), direction, 0.5)
        ours = render_mesh(mesh, T, intr)
        theirs = Renderer(intr.K, 640, 480).render(object_primitives(Placement(spec, np.eye(4), 0)), T)
        seen = np.isfinite(theirs.depth_m)
        both = ours.mask & seen
        assert (ours.mask ^ seen).sum() <= (0 if name == "snack_box" else 0.01 * seen.sum()) and seen.sum() > 5000
        gap = np.abs(ours.depth_m[both] - theirs.depth_m[both])
        # (the can at grazing rims excepted)
        assert gap.max() < 1e-5 if name == "snack_box" else np.percentile(gap, 99) < 1e-3
        seen = both
        grey = [cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)[seen].astype(float) for img in
                (ours.rgb, np.clip(theirs.radiance * 255, 0, 255).astype(np.uint8))]
        # The can's side is lit by a cosine the mesh renderer leaves out: 0.80-0.88 against
        # 0.06 / -0.54 for the same mesh with its picture mirrored.
        assert np.corrcoef(*grey)[0, 1] > (0.85 if name == "snack_box" else 0.7)
