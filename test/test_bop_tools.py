"""`mireg synth ... --bop`, `mireg bop run / model / to-bag` from the outside: a synthetic scene
exported as BOP reads back as its bag does; the commands' files, exit codes and one-line errors."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from multi_instance_reg.datasets.bop import BopDataset, object_name, read_results_csv
from multi_instance_reg.datasets.rgbd_bag import RGBDBag, read_rgbd_frames


def cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def one_line_error(res, *fragments):
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert err.count("\n") == 0, err
    assert err.startswith("mireg bop: error: "), err
    for f in fragments:
        assert f in err, err


def same_frames(a, b):
    """Two RGBDFrames alike: images (depth to the bit), intrinsics, ground truth, stamp."""
    assert a.stamp_ns == b.stamp_ns
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    np.testing.assert_allclose(a.intrinsics.K, b.intrinsics.K)
    assert (a.intrinsics.width, a.intrinsics.height) == (b.intrinsics.width, b.intrinsics.height)
    assert a.gt_poses.shape == b.gt_poses.shape
    np.testing.assert_allclose(a.gt_poses, b.gt_poses, atol=1e-6)
    np.testing.assert_allclose(a.gt_visibility, b.gt_visibility, atol=1e-6)


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory):
    """Two objects, two frames: written as a bag and, in the same pass, as BOP scene 4."""
    from multi_instance_reg.synthetic.scene import make_tabletop_scene, write_scene_bag

    d = tmp_path_factory.mktemp("bop_synth")
    scene = make_tabletop_scene(["snack_box", "can"], instances=2, distractors=1, frames=2, seed=3)
    write_scene_bag(scene, d / "bag", imu=False, bop_dir=d / "bop", bop_scene=4)
    return scene, d / "bag", d / "bop"


def test_synthetic_scene_as_bop_reads_back_as_its_bag(mixed_scene):
    from multi_instance_reg.synthetic.bop_export import catalogue_obj_id

    scene, bag, bop = mixed_scene
    ds = BopDataset(bop)
    assert ds.scene_ids == [4] and ds.scene(4).image_ids == [0, 1]
    bop_frames = list(ds.frames())
    bag_frames = list(read_rgbd_frames(bag))
    assert len(bop_frames) == len(bag_frames) == 2
    for a, b in zip(bop_frames, bag_frames):
        same_frames(a, b)
        assert a.gt_obj_ids.tolist() == [catalogue_obj_id(n) for n in scene.instance_objects]
    # The models: each object's mesh in mm, its box in models_info.json; textured: no symmetries.
    for name, dims in (("snack_box", scene.target.dimensions_m), ("can", scene.more_targets[0].dimensions_m)):
        info = ds.models_info[catalogue_obj_id(name)]
        np.testing.assert_allclose(info.size_mm, np.array(dims) * 1000, atol=1e-3)
        assert info.symmetries() is None
        assert ds.model_path(info.obj_id).is_file()
        # ... with the pictures the scene shows on it, so a model built from it has keypoints.
        from multi_instance_reg.meshes import load_mesh

        assert load_mesh(ds.model_path(info.obj_id), "mm").has_colour


def test_to_bag_gives_the_bop_frames_and_names_the_objects(mixed_scene, tmp_path):
    scene, _, bop = mixed_scene
    res = cli("bop", "to-bag", bop, "--scene", 4, "-o", tmp_path / "conv")
    assert res.returncode == 0, res.stderr
    assert "wrote 2 frame(s) of scene 4" in res.stderr
    with RGBDBag(tmp_path / "conv") as bag:
        frames = list(bag)
        names = bag.instance_objects(len(frames[0].gt_poses))
    for a, b in zip(BopDataset(bop).frames(), frames):
        same_frames(a, b)
    from multi_instance_reg.synthetic.bop_export import catalogue_obj_id
    assert names == [object_name(catalogue_obj_id(n)) for n in scene.instance_objects]
    res = cli("bop", "to-bag", bop, "--scene", 4, "-o", tmp_path / "conv")
    assert res.returncode == 2 and "already exists" in res.stderr
    one_line_error(cli("bop", "to-bag", bop, "--scene", 4, "-o", tmp_path / "conv.bag"), "name it without .bag")


@pytest.fixture(scope="module")
def cylinders_bop(tmp_path_factory):
    """`mireg synth untextured --bop`: three grey cylinders, one frame (symmetric objects)."""
    d = tmp_path_factory.mktemp("bop_cyl")
    res = cli("synth", "untextured", "--preset", "cylinders", "-o", d / "bag", "--frames", 1, "--instances", 3,
              "--distractors", 0, "--no-imu", "--bop", d / "bop", "--bop-scene", 7)
    assert res.returncode == 0, res.stderr
    assert "BOP scene in" in res.stdout
    return d / "bop"


def test_run_writes_csv_summary_and_overlays(cylinders_bop, tmp_path):
    # No budget on the shape search: a process that compiles its kernels inside it on its
    # first frame is cut where the next one, finding them compiled, is not, and the two runs
    # below must find the same poses (what is compared is the saved model).
    params = tmp_path / "no_deadline.yaml"
    params.write_text("instance_registration:\n  ros__parameters:\n    frontend.shape_deadline_ms: 0.0\n")
    out = tmp_path / "run"
    res = cli("bop", "run", cylinders_bop, "-o", out, "--quiet", "--params", params)
    assert res.returncode == 0, res.stderr
    csv_path = out / f"mireg_{cylinders_bop.name}-test.csv"
    rows = read_results_csv(csv_path)
    summary = json.loads((out / "summary.json").read_text())
    (image,) = summary["images"]
    assert (image["scene_id"], image["im_id"]) == (7, 0)
    assert image["poses"] == len(rows) > 0
    assert 0 < image["cpu_seconds"] and summary["cpu_seconds_per_image"]["max"] == pytest.approx(image["cpu_seconds"])
    assert image["gt_instances"] == 3
    assert image["hits"] >= 2, summary            # the pipeline finds these cylinders (3 of 3 when written)
    for r in rows:
        assert (r.scene_id, r.im_id) == (7, 0) and r.time_s == pytest.approx(image["seconds"], abs=1e-3)
        np.testing.assert_allclose(r.R @ r.R.T, np.eye(3), atol=1e-6)
        assert 300 < r.t_mm[2] < 1500                                   # mm, in front of the camera
    assert (out / "overlays" / "000007_000000.png").is_file()
    obj = next(iter(BopDataset(cylinders_bop).models_info))
    model = out / "models" / f"{object_name(obj)}.npz"
    assert model.is_file()
    # The saved model given back with --model gives the same poses.
    res = cli("bop", "run", cylinders_bop, "-o", tmp_path / "again", "--quiet", "--model", f"{obj}={model}",
              "--csv", tmp_path / "again.csv", "--params", params)
    assert res.returncode == 0, res.stderr
    again = read_results_csv(tmp_path / "again.csv")
    assert len(again) == len(rows)
    for a, b in zip(rows, again):
        np.testing.assert_allclose(a.T_m, b.T_m, atol=1e-6)


def test_model_command_takes_the_models_info_symmetries(cylinders_bop, tmp_path):
    from multi_instance_reg.models.model import load_model

    ds = BopDataset(cylinders_bop)
    obj = next(iter(ds.models_info))
    res = cli("bop", "model", cylinders_bop, "--obj", obj, "-o", tmp_path / "m.npz")
    assert res.returncode == 0, res.stderr
    model = load_model(tmp_path / "m.npz")
    want = ds.models_info[obj].symmetries()
    assert model.name == object_name(obj)
    np.testing.assert_allclose(model.symmetries.axis, want.axis)
    np.testing.assert_allclose(model.symmetries.discrete, want.discrete)
    assert model.has_shape


def test_errors_are_one_line(cylinders_bop, tmp_path):
    one_line_error(cli("bop", "run", tmp_path / "nowhere", "-o", tmp_path / "o"), "does not exist")
    one_line_error(cli("bop", "run", cylinders_bop, "-o", tmp_path / "o", "--model", "cup.npz"), "must be ID=MODEL.npz")
    one_line_error(cli("bop", "run", cylinders_bop, "-o", tmp_path / "o", "--objects", "99"),
                   "object id 99 is not in", "models_info.json")
    one_line_error(cli("bop", "run", cylinders_bop, "-o", tmp_path / "o", "--scenes", "3"), "has no scene 3")
    one_line_error(cli("bop", "model", cylinders_bop, "--obj", 10, "-o", tmp_path / "m.txt"), "must end in .npz")
    broken = tmp_path / "broken"
    shutil.copytree(cylinders_bop, broken)
    depth = broken / "test" / "000007" / "depth" / "000000.png"
    import cv2
    cv2.imwrite(str(depth), np.ones((10, 10), np.uint16))
    one_line_error(cli("bop", "run", broken, "-o", tmp_path / "o"), "could be processed", "1 skipped",
                   "000000.png is 10x10")
    (broken / "test" / "000007" / "scene_camera.json").unlink()
    one_line_error(cli("bop", "to-bag", broken, "--scene", 7, "-o", tmp_path / "b"), "000007/scene_camera.json does not exist")


def test_run_skips_and_counts_a_bad_image(mixed_scene, tmp_path):
    """One image of two with a depth PNG of the wrong size: the run goes on (with the tracker
    over the scene's images), the CSV holds the good image only, summary.json counts the bad one."""
    import cv2

    _, _, bop = mixed_scene
    copy = tmp_path / "bop"
    shutil.copytree(bop, copy)
    cv2.imwrite(str(copy / "test" / "000004" / "depth" / "000001.png"), np.ones((4, 4), np.uint16))
    out = tmp_path / "run"
    res = cli("bop", "run", copy, "-o", out, "--quiet", "--tracking", "--csv", tmp_path / "r.csv")
    assert res.returncode == 0, res.stderr
    assert "1 skipped" in res.stderr and "000001.png is 4x4" in res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [(e["scene_id"], e["im_id"]) for e in summary["images"]] == [(4, 0)]
    assert summary["skipped"] == 1 and summary["tracking"] is True
    assert {r.im_id for r in read_results_csv(tmp_path / "r.csv")} <= {0}
    assert len(summary["objects"]) == 2                      # both objects of the ground truth looked for


def test_converted_scene_reads_in_mireg_offline(cylinders_bop, tmp_path):
    """to-bag, then mireg offline with the model `mireg bop model` built: the ground truth
    travels with the bag (objects named as the model) and is scored."""
    ds = BopDataset(cylinders_bop)
    obj = next(iter(ds.models_info))
    assert cli("bop", "model", cylinders_bop, "--obj", obj, "-o", tmp_path / "m.npz").returncode == 0
    assert cli("bop", "to-bag", cylinders_bop, "--scene", 7, "-o", tmp_path / "bag").returncode == 0
    res = cli("offline", tmp_path / "bag", "--model", tmp_path / "m.npz", "--no-tracking", "-o", tmp_path / "off",
              "--quiet")
    assert res.returncode == 0, res.stderr
    metrics = json.loads((tmp_path / "off" / "metrics.json").read_text())
    assert metrics["frames_with_ground_truth"] == 1
    assert metrics["objects"][object_name(obj)]["MHR"] >= 2 / 3, metrics


def test_draw_points_puts_model_points_where_the_pose_projects_them():
    from multi_instance_reg.messages import CameraIntrinsics
    from multi_instance_reg.rgbd.overlay import draw_points

    intr = CameraIntrinsics(K=np.array([[100.0, 0, 20], [0, 100.0, 10], [0, 0, 1]]), width=40, height=30)
    img = np.zeros((30, 40, 3), np.uint8)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.0]
    pts = np.array([[0.0, 0.0, 0.0], [0.05, -0.03, 0.0], [0.0, 0.0, -2.0], [5.0, 0.0, 0.0]])   # centre, off-centre, behind, outside
    assert draw_points(img, T, pts, intr, (1, 2, 3)) == 2
    assert img[10, 20].tolist() == [1, 2, 3] and img[7, 25].tolist() == [1, 2, 3]
    assert int(img.sum()) == 2 * 6


def test_each_image_is_searched_for_the_objects_its_targets_name(mixed_scene, tmp_path):
    """With a targets file (BOP's localisation task gives each image's objects) an image is
    searched only for the objects its targets name; --all-objects searches every object in
    every image."""
    _, _, bop = mixed_scene
    copy = tmp_path / "bop"
    shutil.copytree(bop, copy)
    ds = BopDataset(copy)
    first, second = sorted(ds.models_info)
    (copy / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 4, "im_id": 0, "obj_id": first, "inst_count": 2},
         {"scene_id": 4, "im_id": 1, "obj_id": first, "inst_count": 2},
         {"scene_id": 4, "im_id": 1, "obj_id": second, "inst_count": 2}]))
    params = tmp_path / "no_deadline.yaml"
    params.write_text("instance_registration:\n  ros__parameters:\n    frontend.shape_deadline_ms: 0.0\n")
    out = tmp_path / "run"
    res = cli("bop", "run", copy, "-o", out, "--quiet", "--params", params)
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["objects"] == [first, second] and summary["objects_per_image"] == "targets"
    by_image = {e["im_id"]: e["poses_by_object"] for e in summary["images"]}
    assert set(by_image[0]) == {str(first)}
    assert set(by_image[1]) == {str(first), str(second)}
    models = [f"{o}={out / 'models' / f'{object_name(o)}.npz'}" for o in (first, second)]
    res = cli("bop", "run", copy, "-o", tmp_path / "all", "--quiet", "--params", params, "--all-objects",
              "--images", "0", *[a for m in models for a in ("--model", m)])
    assert res.returncode == 0, res.stderr
    summary = json.loads((tmp_path / "all" / "summary.json").read_text())
    assert summary["objects_per_image"] == "all"
    assert set(summary["images"][0]["poses_by_object"]) == {str(first), str(second)}
