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
    head = f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {len(vertices)}\n"
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
    from multi_instance_reg.symmetry import read_bop_symmetries

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
    assert read_bop_symmetries(path, 9).is_trivial                # no keys: asymmetric (BOP leaves them out)
    with pytest.raises(InputError, match="no object 4"):
        read_bop_symmetries(path, 4)
    bad = models_info(tmp_path, {1: {"symmetries_discrete": [[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}}, "bad.json")
    with pytest.raises(InputError, match="not a rigid transform"):
        read_bop_symmetries(bad, 1)
    short = models_info(tmp_path, {1: {"symmetries_discrete": [[1, 0, 0]]}}, "short.json")
    with pytest.raises(InputError, match="16 finite numbers"):
        read_bop_symmetries(short, 1)


def test_build_model_takes_symmetries_from_models_info(tmp_path):
    from multi_instance_reg.meshes import box_mesh, save_mesh
    from multi_instance_reg.rgbd.model import load_model

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
    # Without the id, and with both sources: one line each.
    for args, says in [(("--models-info", info), "--obj-id"), (("--models-info", info, "--obj-id", 4), "no object 4"),
                       (("--models-info", info, "--obj-id", 8, "--symmetry", "none"), "not both")]:
        run = build(tmp_path, "--mesh", other, "--units", "mm", *args)
        assert run.returncode == 2 and says in run.stderr and len(run.stderr.strip().splitlines()) == 1, run.stderr
