"""Meshes, models from meshes, symmetries, and the shape front end on an untextured bag."""
import json
import subprocess
import sys

import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.meshes import box_mesh, cylinder_mesh, load_mesh, sample_surface, save_mesh
from multi_instance_reg.metrics import evaluate_scene
from multi_instance_reg.models.mesh_model import build_model_from_mesh
from multi_instance_reg.models.model import load_model, save_model
from multi_instance_reg.symmetry import closest_symmetric_pose, detect_symmetries, parse_symmetry_text

MIREG = [sys.executable, "-m", "multi_instance_reg.tools.cli"]


@pytest.mark.parametrize("suffix", ["ply", "stl", "obj"])
@pytest.mark.parametrize("units", ["m", "mm"])
def test_mesh_round_trip(tmp_path, suffix, units):
    mesh = box_mesh(0.3, 0.2, 0.15)
    path = save_mesh(mesh, tmp_path / f"box.{suffix}", units)
    back = load_mesh(path, units)
    lo, hi = back.bounds
    assert np.allclose(hi - lo, [0.3, 0.2, 0.15], atol=1e-6)
    _, areas = back.face_normals_areas()
    assert areas.sum() == pytest.approx(2 * (0.3 * 0.2 + 0.3 * 0.15 + 0.2 * 0.15), rel=1e-5)


def test_ascii_ply_with_quads_and_wrong_units(tmp_path):
    # A box of six quads, 100 x 50 x 20 mm (a single flat quad is refused: it bounds nothing).
    corners = "".join(f"{x} {y} {z}\n" for z in (0, 20) for y in (0, 50) for x in (0, 100))
    quads = "".join(f"4 {a} {b} {c} {d}\n" for a, b, c, d in
                    [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)])
    text = ("ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 6\nproperty list uchar int vertex_indices\nend_header\n" + corners + quads)
    (tmp_path / "q.ply").write_text(text)
    mesh = load_mesh(tmp_path / "q.ply", "mm")
    assert len(mesh.triangles) == 12 and np.allclose(mesh.bounds[1], [0.1, 0.05, 0.02])
    with pytest.raises(InputError, match="--units mm"):
        load_mesh(tmp_path / "q.ply", "m")     # 100 m across: the units are wrong


def test_broken_meshes_refused(tmp_path):
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 7\n")
    with pytest.raises(InputError, match="broken"):
        load_mesh(tmp_path / "bad.obj")
    (tmp_path / "bad.stl").write_bytes(b"\x00" * 90)
    with pytest.raises(InputError, match="broken"):
        load_mesh(tmp_path / "bad.stl")
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                        "property float y\nproperty float z\nend_header\n")
    with pytest.raises(InputError, match="broken"):
        load_mesh(tmp_path / "empty.ply")
    # From the outside: one line, exit code 2, no traceback.
    run = subprocess.run(MIREG + ["build-model", "--mesh", str(tmp_path / "bad.obj"), "-o", str(tmp_path / "m.npz")],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "broken" in run.stderr and "Traceback" not in run.stderr


def test_symmetries_of_box_and_cylinder():
    pts, _ = sample_surface(box_mesh(0.3, 0.2, 0.15), 0.004)
    box = detect_symmetries(pts, 0.006)
    assert len(box.discrete) == 4 and box.axis is None
    pts, _ = sample_surface(box_mesh(0.1, 0.1, 0.05), 0.0015)
    assert len(detect_symmetries(pts, 0.00225).discrete) == 8           # a square face: quarter turns too
    pts, _ = sample_surface(cylinder_mesh(0.06, 0.1), 0.0012)
    cyl = detect_symmetries(pts, 0.0018)
    assert cyl.axis is not None and abs(abs(cyl.axis[2]) - 1) < 0.01 and len(cyl.discrete) == 2
    # An L-shaped profile has none.
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    pts, _ = sample_surface(object_mesh(get_object("bracket")), 0.0015)
    assert detect_symmetries(pts, 0.00225).is_trivial


def test_metrics_over_symmetries():
    sym = parse_symmetry_text("z:inf,x:2", np.zeros(3))
    T_gt = np.eye(4)
    T_gt[:3, 3] = [0.1, 0.0, 0.8]
    turned = T_gt.copy()
    c, s = np.cos(1.0), np.sin(1.0)
    turned[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])    # a turn about the axis: same look
    plain = evaluate_scene([T_gt], [turned], 5.0, 0.01)
    assert plain.hits == 0
    sym_score = evaluate_scene([T_gt], [turned], 5.0, 0.01, symmetries=sym)
    assert sym_score.hits == 1 and sym_score.rre_deg[0] < 1e-6
    assert np.allclose(closest_symmetric_pose(T_gt, turned, sym), turned, atol=1e-9)
    assert evaluate_scene([T_gt], [turned], 5.0, 0.01, symmetries=parse_symmetry_text("none", np.zeros(3))).hits == 0


def test_mesh_model_file_round_trip_and_old_files(tmp_path):
    mesh_path = save_mesh(box_mesh(0.3, 0.2, 0.15), tmp_path / "carton.stl", "mm")
    run = subprocess.run(MIREG + ["build-model", "--mesh", str(mesh_path), "--units", "mm", "-o", str(tmp_path / "c.npz")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    model = load_model(tmp_path / "c.npz")
    assert model.has_shape and model.num_keypoints == 0 and len(model.symmetries.discrete) == 4
    assert model.shape_descriptors.shape[1] == 33 and np.allclose(model.extent, [0.3, 0.2, 0.15], atol=1e-6)
    # Symmetries given on the command line instead.
    run = subprocess.run(MIREG + ["build-model", "--mesh", str(mesh_path), "--units", "mm", "--symmetry", "none",
                                  "-o", str(tmp_path / "n.npz")], capture_output=True, text=True)
    assert run.returncode == 0 and load_model(tmp_path / "n.npz").symmetries is None
    # A model file of the old schema (no shape arrays) still loads and keeps no shape data.
    old = dict(np.load(tmp_path / "c.npz"))
    for k in [k for k in old if k.startswith(("shape_", "symmetry_", "box_centre"))]:
        del old[k]
    old["keypoints_xyz"] = np.zeros((5, 3), np.float32)
    old["descriptors"] = np.zeros((5, 128), np.float32)
    np.savez(tmp_path / "old.npz", **old)
    m_old = load_model(tmp_path / "old.npz")
    assert not m_old.has_shape and m_old.symmetries is None
    save_model(m_old, tmp_path / "old2.npz")
    assert set(np.load(tmp_path / "old2.npz").files) == set(old)
    # A mesh without colour gives no grey; one with vertex colours, its grey per shape point.
    assert model.shape_grey is None and "shape_grey" not in np.load(tmp_path / "c.npz").files
    coloured = box_mesh(0.3, 0.2, 0.15)
    coloured.vertex_colours = np.where(coloured.vertices[:, 2:] > 0, 250, 20).repeat(3, axis=1).astype(np.uint8)
    save_model(build_model_from_mesh(coloured, "carton"), tmp_path / "g.npz")
    grey = load_model(tmp_path / "g.npz")
    top = grey.shape_points[:, 2] > 0.074
    assert grey.shape_grey.shape == (len(grey.shape_points),) and grey.shape_grey[top].min() > 240


def test_untextured_offline_replay(tmp_path):
    """mesh -> model -> bag -> poses on generated grey cylinders, from the outside."""
    bag = tmp_path / "cyl"
    run = subprocess.run(MIREG + ["synth", "untextured", "-o", str(bag), "--preset", "cylinders", "--instances", "5",
                                  "--frames", "2", "--seed", "0", "--mesh", str(tmp_path / "cyl.ply")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    run = subprocess.run(MIREG + ["build-model", "--mesh", str(tmp_path / "cyl.ply"), "-o", str(tmp_path / "cyl.npz")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    run = subprocess.run(MIREG + ["offline", str(bag), "--model", str(tmp_path / "cyl.npz"), "-o", str(tmp_path / "out"), "--no-tracking",
                                  "--quiet", "--overlays", "0"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert len(poses["frames"]) == 2
    # PPF per segment with the outline check reaches MHF1 0.75 on these two frames (3 of 5
    # instances each, no false one; before PPF: 4 hits of 10); the MHF1 >= 0.90 is
    # not met here (docs/frontends.md, the shape path); a margin below.
    assert metrics["MHF1"] >= 0.65
    assert metrics["median_rte"] <= 0.01 and metrics["median_rre_deg"] <= 3.0


@pytest.mark.parametrize("preset", ["channel", "stairs", "tee"])
def test_profile_objects_mesh_matches_render_and_symmetry(preset):
    """The catalogue's profile objects (session 12): the mesh a model is built from is the
    surface the renderer draws from the object's boxes, at the ground-truth poses, and the
    symmetries found from it are the object's (a half turn about z for the U channel and the
    T, none for the steps)."""
    import cv2
    from scipy.spatial import cKDTree

    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.untextured import PRESETS, make_untextured_scene

    spec = get_object(PRESETS[preset])
    mesh = object_mesh(spec)
    lo, hi = mesh.bounds
    assert np.allclose(hi - lo, spec.dimensions_m, atol=1e-9)
    # Closed and consistently wound: every edge used once each way, the volume the boxes' volume.
    edges = np.concatenate([mesh.triangles[:, [0, 1]], mesh.triangles[:, [1, 2]], mesh.triangles[:, [2, 0]]])
    assert len({tuple(e) for e in edges}) == len(edges) and {tuple(e[::-1]) for e in edges} == {tuple(e) for e in edges}
    v = mesh.vertices[mesh.triangles]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    assert volume == pytest.approx(sum(np.prod(d) for _, d in spec.parts), rel=1e-9)
    pts, normals = sample_surface(mesh, 0.001)
    tree = cKDTree(pts)
    on_mesh, in_front = [], []
    for seed in (0, 1, 2):                       # both ways the object rests, several views
        scene = make_untextured_scene(preset, 2, 0, 2, seed)
        K = scene.intrinsics.K
        for frame in scene.frames():
            for label, T in enumerate(frame.poses):
                # Each pixel drawn for the instance lies on the mesh ...
                v_, u_ = np.nonzero(frame.instance_mask == label)
                z = frame.depth_true_m[v_, u_]
                cam = np.column_stack([(u_ - K[0, 2]) * z / K[0, 0], (v_ - K[1, 2]) * z / K[1, 1], z])
                d, _ = tree.query((cam - T[:3, 3]) @ T[:3, :3])
                on_mesh.append(d)
                # ... and no mesh point facing the camera is in front of what was drawn there.
                p = pts @ T[:3, :3].T + T[:3, 3]
                facing = np.einsum("ij,ij->i", normals @ T[:3, :3].T, p) < 0
                p = p[facing]
                u = np.rint(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(int)
                w = np.rint(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(int)
                ok = (u >= 0) & (u < frame.depth_true_m.shape[1]) & (w >= 0) & (w < frame.depth_true_m.shape[0])
                # (the nearest depth of the 3 x 3 pixels around: a point at the silhouette's
                # edge may round to the pixel beside it)
                near = cv2.erode(np.where(frame.depth_true_m > 0, frame.depth_true_m, np.inf).astype(np.float32),
                                 np.ones((3, 3), np.uint8))
                in_front.append(p[ok, 2] < near[w[ok], u[ok]] - 0.003)
    on_mesh, in_front = np.concatenate(on_mesh), np.concatenate(in_front)
    assert len(on_mesh) > 2000 and np.quantile(on_mesh, 0.99) < 0.001
    assert in_front.mean() < 0.01        # pixels at the silhouette's edge only
    sym = detect_symmetries(*sample_surface(mesh, 0.0015)[:1], 0.00225)
    if preset == "stairs":
        assert sym.is_trivial
    else:
        assert sym.axis is None and len(sym.discrete) == 2
        assert np.allclose(sym.discrete[1][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-6)


def test_flush_cartons_form_one_plane_in_depth_and_show_their_seams_in_colour():
    """The ``flush`` preset: cartons packed with hairline gaps, their tops within a few
    millimetres of one plane, and the line where two meet darker than their tops (a real
    carton's worn edges), so the outlines are in the colour image and not in the depth."""
    import cv2

    from multi_instance_reg.synthetic.untextured import make_untextured_scene

    scene = make_untextured_scene("flush", 10, 0, 1, 3)
    cartons = [p for p in scene.placements if p.spec.name == "carton"]
    assert len(cartons) == 10
    xy = np.array([p.pose[:2, 3] for p in cartons])
    apart = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy))
    assert 0.2 <= apart.min() <= 0.2025                    # neighbours along the short side: hairline gaps
    tops = np.array([p.pose[2, 3] for p in cartons])
    assert np.ptp(tops) < 0.005
    frame = next(iter(scene.frames()))
    grey = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    seam, inside = [], []
    for k in range(len(cartons)):
        mine = (frame.instance_mask == k).astype(np.uint8)
        others = ((frame.instance_mask >= 0) & (frame.instance_mask != k)).astype(np.uint8)
        seam.append(grey[(mine > 0) & (cv2.dilate(others, np.ones((3, 3), np.uint8)) > 0)])
        inside.append(grey[cv2.erode(mine, np.ones((9, 9), np.uint8)) > 0])
    seam, inside = np.concatenate(seam), np.concatenate(inside)
    assert len(seam) > 100 and seam.mean() < 0.9 * inside.mean()


def test_size_error_makes_the_objects_another_size_than_their_mesh(tmp_path):
    """``size_error``: every instance of one scene the same size, off the mesh's by at most
    the share along each axis, packed by that size; the scene's object, the ground truth's
    frame and the mesh written stay the nominal ones. Out of range: a one-line error."""
    from multi_instance_reg.synthetic.objects import get_object, scaled
    from multi_instance_reg.synthetic.untextured import generate_untextured_bag, make_untextured_scene

    nominal = np.array(get_object("carton").dimensions_m)
    scene = make_untextured_scene("flush", 6, 0, 1, 7, size_error=0.03)
    sizes = {p.spec.dimensions_m for p in scene.placements if p.spec.name == "carton"}
    assert len(sizes) == 1
    share = np.array(sizes.pop()) / nominal
    assert np.all(np.abs(share - 1.0) <= 0.03) and np.abs(share - 1.0).max() > 0.005
    assert scene.target.dimensions_m == get_object("carton").dimensions_m
    assert make_untextured_scene("flush", 6, 0, 1, 7).placements[1].spec.dimensions_m == tuple(nominal)
    bracket = scaled(get_object("bracket"), (1.1, 1.0, 0.9))
    (c0, d0), (c1, d1) = get_object("bracket").parts[0], bracket.parts[0]
    assert np.allclose(d1, np.array(d0) * (1.1, 1.0, 0.9)) and np.allclose(c1, np.array(c0) * (1.1, 1.0, 0.9))
    assert scaled(get_object("grey_cylinder"), (1.1, 0.9, 1.0)).dimensions_m[0] == pytest.approx(
        get_object("grey_cylinder").dimensions_m[0])
    generate_untextured_bag(tmp_path / "bag", "flush", 3, 0, 1, seed=7, mesh_path=tmp_path / "m.stl", size_error=0.03)
    assert np.allclose(np.ptp(load_mesh(tmp_path / "m.stl").vertices, axis=0), nominal)
    with pytest.raises(InputError, match="size error"):
        make_untextured_scene("flush", 6, 0, 1, 7, size_error=0.5)


def test_flush_cartons_are_found_one_by_one_on_generated_pallets():
    """Cartons packed flush (one plane in depth, taped tops, dark seams): each is found and
    placed within 2 cm and 10 deg, the patches cut at the seams and kept on them in their
    plane after ICP (which slides a face seen alone there). Two seeds' frames, no deadline:
    without the seams 2 of 20 are found, without the patches after ICP 17 and 5 poses off,
    without shrunk patches matching (SIDE_SHORT 1) 20 and 2 off."""
    from dataclasses import replace

    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh
    from multi_instance_reg.synthetic.untextured import make_untextured_scene

    model = build_model_from_mesh(object_mesh(get_object("carton")), "carton")
    config = PipelineConfig()
    reg = InstanceRegistration(model, replace(config, frontend=replace(config.frontend, shape_deadline_ms=0)))
    present = hits = wrong = 0
    for seed in (4, 5):
        scene = make_untextured_scene("flush", 10, 0, 1, seed)
        frame = scene.render_frame(0)
        up = frame.T_world_camera[:3, :3].T @ [0.0, 0.0, 1.0]
        found = [i.T for i in reg.register_frame(frame.rgb, frame.depth_mm / 1000.0, scene.intrinsics, up).instances]
        seen = frame.visibility >= 0.5
        present += int(seen.sum())
        hits += evaluate_scene(frame.poses[seen], found, 10.0, 0.02, symmetries=model.symmetries).hits
        wrong += len(found) - evaluate_scene(frame.poses, found, 10.0, 0.02, symmetries=model.symmetries).hits
    # The wrong ones are cartons "sunk" into the pallet in an empty slot among them (its top
    # the exposed pallet top, carton-sized and as high as a carton above the floor): known,
    # 3 on seed 4.
    assert present == 20 and hits >= 19 and wrong <= 3
