"""The workspace (rgbd/workspace.py), the shape path's resolvable depth and its search deadline."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.meshes import sample_surface
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.rgbd.workspace import Workspace, WorkspaceConfig
from multi_instance_reg.transforms import make_transform

INTR = CameraIntrinsics(K=np.array([[380.0, 0, 160], [0, 380.0, 120], [0, 0, 1]]), width=320, height=240)


def _rays():
    K = INTR.K
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)


def test_box_pixels_follow_its_centre_size_and_turn():
    depth = np.full((240, 320), 1.0, np.float32)                 # a wall 1 m away
    depth[:, :10] = 0.0                                          # no depth there
    ws = Workspace.from_config(WorkspaceConfig(centre_x=0.2013, centre_z=1.0, size_x=0.2, size_y=0.1013, size_z=0.1))
    inside = ws.pixels(depth, INTR)
    p = _rays() * depth[..., None]
    expected = (np.abs(p[..., 0] - 0.2013) <= 0.1) & (np.abs(p[..., 1]) <= 0.05065) & (depth > 0)
    assert inside.sum() > 1000 and np.array_equal(inside, expected)
    assert not inside[:, :10].any()
    # Turned a quarter about the optical axis: the box's x side now runs down the image.
    turned = Workspace.from_config(replace(WorkspaceConfig(centre_x=0.2013, centre_z=1.0, size_x=0.2, size_y=0.1013,
                                                           size_z=0.1), yaw_deg=90.0)).pixels(depth, INTR)
    expected = (np.abs(p[..., 0] - 0.2013) <= 0.05065) & (np.abs(p[..., 1]) <= 0.1)
    assert turned.sum() > 1000 and np.array_equal(turned, expected)
    # Nearer than the box: nothing.
    assert not ws.pixels(np.full((240, 320), 0.5, np.float32), INTR).any()


def test_mask_and_bad_workspaces(tmp_path):
    assert Workspace.from_config(WorkspaceConfig()) is None
    with pytest.raises(InputError, match="positive on all three sides"):
        Workspace.from_config(WorkspaceConfig(size_x=0.3, size_y=0.3))
    with pytest.raises(InputError, match="does not exist"):
        Workspace.from_config(WorkspaceConfig(mask=str(tmp_path / "none.png")))
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="not a readable image"):
        Workspace.from_config(WorkspaceConfig(mask=str(tmp_path / "junk.png")))
    mask = np.zeros((240, 320), np.uint8)
    cv2.imwrite(str(tmp_path / "zero.png"), mask)
    with pytest.raises(InputError, match="all zero"):
        Workspace.from_config(WorkspaceConfig(mask=str(tmp_path / "zero.png")))
    mask[50:100, 60:200] = 255
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    ws = Workspace.from_config(WorkspaceConfig(mask=str(tmp_path / "m.png")))
    depth = np.full((240, 320), 1.0, np.float32)
    assert np.array_equal(ws.pixels(depth, INTR), mask > 0)
    with pytest.raises(InputError, match="draw it on a colour image"):
        ws.pixels(np.ones((480, 640), np.float32), INTR)
    img = np.zeros((240, 320, 3), np.uint8)
    ws.draw(img, INTR)
    assert img.any()


def _cylinders_on_a_table(xs, table_z=0.7, mesh=None):
    """Depth of grey cylinders standing at camera x ``xs`` on a table facing the camera at
    ``table_z`` (seen from straight above): (depth, poses, mesh)."""
    from multi_instance_reg.synthetic.objects import get_object, object_mesh

    mesh = mesh or object_mesh(get_object("grey_cylinder"))     # 6 cm across, 10 cm high, axis z
    dense, _ = sample_surface(mesh, 0.001)
    down = np.diag([1.0, -1.0, -1.0])                            # its axis towards the camera
    poses = [make_transform(down, [x, 0.0, table_z - 0.05]) for x in xs]
    depth = np.full((240, 320), table_z, np.float32)
    for T in poses:
        P = dense @ T[:3, :3].T + T[:3, 3]
        u = np.round(380.0 * P[:, 0] / P[:, 2] + 160).astype(int)
        v = np.round(380.0 * P[:, 1] / P[:, 2] + 120).astype(int)
        ok = (u >= 0) & (u < 320) & (v >= 0) & (v < 240)
        np.minimum.at(depth, (v[ok], u[ok]), P[ok, 2].astype(np.float32))
    return depth, poses, mesh


@pytest.fixture(scope="module")
def cylinder_model():
    from multi_instance_reg.models.mesh_model import build_model_from_mesh
    from multi_instance_reg.synthetic.objects import get_object, object_mesh

    return build_model_from_mesh(object_mesh(get_object("grey_cylinder")), "grey_cylinder")


def _found_near(instances, poses, model):
    centres = [i.T[:3, :3] @ model.box_centre + i.T[:3, 3] for i in instances]
    return [any(np.linalg.norm(c - (T[:3, :3] @ model.box_centre + T[:3, 3])) < 0.02 for c in centres) for T in poses]


def test_workspace_keeps_the_search_inside_it(cylinder_model):
    """Two cylinders on a table: with a box around the left one only, only it is found (and
    the table, cut by the box, is still taken for the support it is)."""
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig

    depth, poses, _ = _cylinders_on_a_table([-0.12, 0.12])
    rgb = np.zeros((240, 320, 3), np.uint8)
    config = replace(PipelineConfig(), frontend=replace(PipelineConfig().frontend, shape_deadline_ms=0.0))
    every = InstanceRegistration(cylinder_model, config).register_frame(rgb, depth, INTR)
    assert _found_near(every.instances, poses, cylinder_model) == [True, True]
    box = WorkspaceConfig(centre_x=-0.12, centre_z=0.62, size_x=0.2, size_y=0.2, size_z=0.25)
    reg = InstanceRegistration(cylinder_model, replace(config, workspace=box))
    left = reg.register_frame(rgb, depth, INTR)
    assert _found_near(left.instances, poses, cylinder_model) == [True, False] and len(left.instances) == 1


def test_no_points_beyond_the_resolvable_depth(cylinder_model):
    """The depth check's tolerance (3 sigma of the noise) is at most shape_max_noise_share of
    the object's diameter out to resolvable_depth; the frame's points stop there."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.frontends.shape.frontend import ShapeFrontEnd

    fe = replace(PipelineConfig().frontend, shape_depth_noise=0.002)     # fixed: the frame is noiseless
    shape = ShapeFrontEnd(cylinder_model, fe)
    z = shape.resolvable_depth
    assert 3.0 * fe.shape_depth_noise * z ** 2 == pytest.approx(fe.shape_max_noise_share * shape.diameter)
    assert 1.3 < z < 2.0                                          # the 13 cm cylinder: about 1.65 m
    assert ShapeFrontEnd(cylinder_model, replace(fe, shape_max_noise_share=0.0)).resolvable_depth == np.inf
    depth, _, _ = _cylinders_on_a_table([-0.15, 0.2], table_z=z - 0.2)
    depth[:, 170:] += 0.5                                         # the right one and its table beyond it
    cloud = shape.frame_cloud(depth, INTR, None)
    assert len(cloud.points) > 50 and cloud.points[:, 2].max() <= z
    unlimited = ShapeFrontEnd(cylinder_model, replace(fe, shape_max_noise_share=0.0)).frame_cloud(depth, INTR, None)
    assert np.sum(unlimited.points[:, 2] > z) > 50


def test_a_box_is_looked_for_as_far_as_its_faces_edges_show(cylinder_model):
    """A model placed by its faces' outlines (a carton) is looked for out to where the
    tolerance is half its thinnest extent, the least step at its faces' edges; the diameter's
    share held realistic-sensor cartons at 1.7-2.0 m (k 0.006) out. A model without such faces
    (the cylinder) keeps the diameter's share."""
    from multi_instance_reg.frontends.shape.frontend import FACE_STEP_SHARE, ShapeFrontEnd
    from multi_instance_reg.models.mesh_model import build_model_from_mesh
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.synthetic.objects import get_object, object_mesh

    carton = build_model_from_mesh(object_mesh(get_object("carton")), "carton")
    fe = replace(PipelineConfig().frontend, shape_depth_noise=0.006)
    box = ShapeFrontEnd(carton, fe)
    thinnest = float(np.min(carton.extent))
    assert 3.0 * 0.006 * box.resolvable_depth ** 2 == pytest.approx(FACE_STEP_SHARE * thinnest)
    assert box.resolvable_depth > 1.2 * np.sqrt(fe.shape_max_noise_share * box.diameter / (3.0 * 0.006))
    assert ShapeFrontEnd(carton, replace(fe, shape_faces=False)).resolvable_depth == pytest.approx(
        np.sqrt(fe.shape_max_noise_share * box.diameter / (3.0 * 0.006)))
    round_one = ShapeFrontEnd(cylinder_model, fe)
    assert 3.0 * 0.006 * round_one.resolvable_depth ** 2 == pytest.approx(fe.shape_max_noise_share
                                                                          * round_one.diameter)


def test_the_support_is_found_beyond_the_resolvable_depth(cylinder_model):
    """Objects nearer than the resolvable depth may stand on a support past it: the supports
    are sought up to an object's size farther, so the table is found (and removed) though no
    point of it is kept; sought only as far as the points, it was not there at all."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.frontends.shape.frontend import ShapeFrontEnd

    fe = replace(PipelineConfig().frontend, shape_depth_noise=0.002)
    shape = ShapeFrontEnd(cylinder_model, fe)
    z = shape.resolvable_depth
    table = z + 0.04                                             # the cylinders' tops 6 cm nearer than z
    depth, _, _ = _cylinders_on_a_table([-0.15, 0.0, 0.15], table_z=table)
    cloud = shape.frame_cloud(depth, INTR, None)
    assert cloud.up is not None and cloud.up_offset == pytest.approx(table, abs=0.01)
    assert len(cloud.points) > 50 and cloud.points[:, 2].max() <= z


def test_measured_noise_sets_the_resolvable_depth(cylinder_model):
    """shape_depth_noise 0: k is measured on each frame, and the frame's points stop where 3
    sigma at that k reaches shape_max_noise_share of the diameter; a fixed k is kept as given."""
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.frontends.shape.frontend import ShapeFrontEnd

    fe = PipelineConfig().frontend
    assert fe.shape_depth_noise == 0.0
    depth, _, _ = _cylinders_on_a_table([-0.15, 0.2], table_z=1.2)
    depth[:, 170:] += 0.5
    rng = np.random.default_rng(3)
    found = {}
    for k in (0.002, 0.006):
        noisy = (depth + rng.standard_normal(depth.shape) * k * depth ** 2).astype(np.float32)
        shape = ShapeFrontEnd(cylinder_model, fe)
        cloud = shape.frame_cloud(noisy, INTR, None)
        assert shape.depth_noise == pytest.approx(k, rel=0.15)
        z = shape.resolvable_depth
        assert 3.0 * k * z ** 2 == pytest.approx(fe.shape_max_noise_share * shape.diameter, rel=0.35)
        assert np.all(cloud.points[:, 2] <= z)
        found[k] = len(cloud.points)
        fixed = ShapeFrontEnd(cylinder_model, replace(fe, shape_depth_noise=0.002))
        assert len(fixed.frame_cloud(noisy, INTR, None).points) > 50 and fixed.depth_noise == 0.002
    # k 0.002: out to about 1.65 m, the table (1.2 m) and the cylinders on it are searched;
    # k 0.006: about 0.95 m, nothing of the scene can be told apart from a surface.
    assert found[0.002] > 50 and found[0.006] == 0


def test_search_deadline_stops_refining_and_says_so(cylinder_model):
    from multi_instance_reg.rgbd.pipeline import InstanceRegistration, PipelineConfig

    depth, poses, _ = _cylinders_on_a_table([-0.12, 0.0, 0.12])
    rgb = np.zeros((240, 320, 3), np.uint8)
    fe = PipelineConfig().frontend
    free = InstanceRegistration(cylinder_model, replace(PipelineConfig(), frontend=replace(fe, shape_deadline_ms=0.0)))
    result = free.register_frame(rgb, depth, INTR)
    assert not result.deadline_cut and all(_found_near(result.instances, poses, cylinder_model))
    spent = InstanceRegistration(cylinder_model, replace(PipelineConfig(), frontend=replace(fe, shape_deadline_ms=1e-6)))
    cut = spent.register_frame(rgb, depth, INTR)
    assert cut.deadline_cut and len(cut.instances) < len(result.instances)


def test_offline_reads_the_workspace_draws_it_and_counts_deadline_cuts(tmp_path):
    """`mireg offline` as a user runs it: the workspace from the parameter file (a box where
    no cylinder stands: nothing found, the box drawn in the overlay), and a spent deadline
    counted in metrics.json and on the summary line."""
    import json
    import subprocess
    import sys

    mireg = [sys.executable, "-m", "multi_instance_reg.tools.cli"]
    bag, mesh, model = tmp_path / "cyl", tmp_path / "cyl.ply", tmp_path / "cyl.npz"
    for args in (["synth", "untextured", "-o", bag, "--preset", "cylinders", "--instances", "4", "--frames", "2",
                  "--seed", "3", "--mesh", mesh], ["build-model", "--mesh", mesh, "-o", model]):
        run = subprocess.run(mireg + [str(a) for a in args], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr

    def offline(name, params):
        (tmp_path / f"{name}.yaml").write_text("instance_registration:\n  ros__parameters:\n" + params)
        run = subprocess.run(mireg + ["offline", str(bag), "--model", str(model), "-o", str(tmp_path / name),
                                      "--no-tracking", "--quiet", "--overlays", "1",
                                      "--params", str(tmp_path / f"{name}.yaml")], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        return json.loads((tmp_path / name / "metrics.json").read_text()), run.stderr

    # A box in the air 40 cm in front of the camera: no object in it.
    metrics, _ = offline("box", "    workspace:\n      centre_x: 0.05\n      centre_z: 0.4\n"
                                "      size_x: 0.1\n      size_y: 0.1\n      size_z: 0.1\n")
    assert metrics["gt"] > 0 and metrics["est"] == 0 and metrics["deadline_cut_frames"] == 0
    overlay = cv2.imread(str(next((tmp_path / "box").glob("overlay_*.png"))))
    b, g, r = (overlay[..., k].astype(int) for k in range(3))
    assert np.sum((r > 200) & (g > 100) & (g < 180) & (b < 80)) > 100    # the box's orange edges
    metrics, line = offline("spent", "    frontend:\n      shape_deadline_ms: 0.000001\n")
    assert metrics["deadline_cut_frames"] == 2 and "cut 2 of them" in line
    bad, _ = tmp_path / "bad.yaml", None
    bad.write_text("instance_registration:\n  ros__parameters:\n    workspace:\n      mask: /nonexistent/m.png\n")
    run = subprocess.run(mireg + ["offline", str(bag), "--model", str(model), "-o", str(tmp_path / "bad"),
                                  "--params", str(bad)], capture_output=True, text=True)
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0 and "workspace mask" in run.stderr
