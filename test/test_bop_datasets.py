"""The BOP reader, writer and results CSV (datasets/bop.py) on tiny datasets laid out by hand
in tmp dirs: known values in, the same values out; the error cases name the file."""
import json

import cv2
import numpy as np
import pytest

from multi_instance_reg.datasets.bop import (BopDataset, BopEstimate, BopFrame, BopWriter, bop_stamp_ns,
                                             gt_info_from_mask, models_info_entry, read_models_info,
                                             read_results_csv, write_results_csv)
from multi_instance_reg.datasets.rgbd_bag import RGBDFrame, SkipCounter
from multi_instance_reg.errors import InputError

W, H = 64, 48
K = [500.0, 0.0, 31.5, 0.0, 510.0, 23.5, 0.0, 0.0, 1.0]
R_A = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])     # 90 deg about z
T_A_MM = [10.0, -20.0, 700.0]
FLIP_X_MM = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]            # 180 deg about x


def dump(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def lay_out(root, depth_scale=0.1, gray=False, jpg=False, obj_ids=(1, 2)):
    """A BOP dataset by hand: objects 1 (symmetric by a flip about x) and 2; scene 3 with
    images 0 and 5; image 5 shows object obj_ids[0] at (R_A, T_A_MM) and obj_ids[1] at identity."""
    dump(root / "camera.json", {"cx": 31.5, "cy": 23.5, "fx": 500.0, "fy": 510.0, "width": W, "height": H,
                                "depth_scale": depth_scale})
    dump(root / "models" / "models_info.json", {
        "1": {"diameter": 100.0, "min_x": -30, "min_y": -20, "min_z": -10, "size_x": 60, "size_y": 40, "size_z": 20,
              "symmetries_discrete": [FLIP_X_MM]},
        "2": {"diameter": 50.0, "min_x": -10, "min_y": -10, "min_z": -20, "size_x": 20, "size_y": 20, "size_z": 40,
              "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 5.0]}]}})
    scene = root / "test" / "000003"
    for im in (0, 5):
        bgr = np.zeros((H, W, 3), np.uint8)
        bgr[:, :, 2] = 200          # red in BGR
        bgr[0, 0] = (im, 0, 200)
        kind, suffix = ("gray", ".png") if gray else ("rgb", ".jpg" if jpg else ".png")
        (scene / kind).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(scene / kind / f"{im:06d}{suffix}"), bgr[:, :, 2] if gray else bgr)
        depth = np.full((H, W), 7000 + im, np.uint16)
        depth[1, 1] = 0
        (scene / "depth").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(scene / "depth" / f"{im:06d}.png"), depth)
    dump(scene / "scene_camera.json", {str(im): {"cam_K": K, "depth_scale": depth_scale} for im in (0, 5)})
    dump(scene / "scene_gt.json", {
        "0": [],
        "5": [{"cam_R_m2c": R_A.reshape(-1).tolist(), "cam_t_m2c": T_A_MM, "obj_id": obj_ids[0]},
              {"cam_R_m2c": np.eye(3).reshape(-1).tolist(), "cam_t_m2c": [0, 0, 500], "obj_id": obj_ids[1]}]})
    dump(scene / "scene_gt_info.json", {"0": [], "5": [{"visib_fract": 0.75}, {"visib_fract": 0.05}]})
    dump(root / "test_targets_bop19.json", [{"scene_id": 3, "im_id": 5, "obj_id": 1, "inst_count": 1}])
    return root


def test_reader_gives_known_frames(tmp_path):
    ds = BopDataset(lay_out(tmp_path / "ds"))
    assert ds.scene_ids == [3]
    assert ds.images() == [(3, 0), (3, 5)]
    assert ds.images(targets_only=True) == [(3, 5)]
    assert ds.images(images=[0]) == [(3, 0)]
    assert [(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in ds.targets] == [(3, 5, 1, 1)]
    f = ds.read_frame(3, 5)
    assert isinstance(f, BopFrame) and isinstance(f, RGBDFrame)
    assert (f.scene_id, f.im_id, f.stamp_ns) == (3, 5, bop_stamp_ns(5))
    assert f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
    assert f.rgb[5, 5].tolist() == [200, 0, 0] and f.rgb[0, 0].tolist() == [200, 0, 5]   # RGB order
    assert f.depth_m.dtype == np.float32
    assert f.depth_m[2, 2] == pytest.approx(7005 * 0.1 / 1000, rel=1e-6)                     # value x depth_scale = mm
    assert f.depth_m[1, 1] == 0
    np.testing.assert_allclose(f.intrinsics.K, np.array(K).reshape(3, 3))
    assert (f.intrinsics.width, f.intrinsics.height) == (W, H)
    assert f.gt_poses.shape == (2, 4, 4)
    np.testing.assert_allclose(f.gt_poses[0][:3, :3], R_A)
    np.testing.assert_allclose(f.gt_poses[0][:3, 3], np.array(T_A_MM) / 1000)
    np.testing.assert_allclose(f.gt_poses[1][:3, 3], [0, 0, 0.5])
    assert f.gt_obj_ids.tolist() == [1, 2]
    np.testing.assert_allclose(f.gt_visibility, [0.75, 0.05])
    empty = ds.read_frame(3, 0)
    assert empty.gt_poses.shape == (0, 4, 4) and empty.gt_obj_ids.tolist() == []


def test_models_info_symmetries(tmp_path):
    info = read_models_info(lay_out(tmp_path / "ds") / "models" / "models_info.json")
    assert sorted(info) == [1, 2] and info[1].diameter_mm == 100.0
    np.testing.assert_allclose(info[1].size_mm, [60, 40, 20])
    s1 = info[1].symmetries()
    assert len(s1.discrete) == 2 and s1.axis is None                         # the identity and the flip
    np.testing.assert_allclose(s1.discrete[1], np.array(FLIP_X_MM, float).reshape(4, 4))
    s2 = info[2].symmetries()
    np.testing.assert_allclose(s2.axis, [0, 0, 1])
    np.testing.assert_allclose(s2.point, [0, 0, 0.005])                      # mm -> m


def test_gray_and_jpeg_images(tmp_path):
    f = BopDataset(lay_out(tmp_path / "g", gray=True)).read_frame(3, 5)
    assert f.rgb.shape == (H, W, 3) and f.rgb[5, 5].tolist() == [200, 200, 200]
    f = BopDataset(lay_out(tmp_path / "j", jpg=True)).read_frame(3, 0)
    assert abs(int(f.rgb[20, 20, 0]) - 200) <= 3 and f.rgb[20, 20, 2] <= 3


def test_missing_scene_camera_stops_naming_it(tmp_path):
    root = lay_out(tmp_path / "ds")
    (root / "test" / "000003" / "scene_camera.json").unlink()
    ds = BopDataset(root)
    with pytest.raises(InputError, match="000003/scene_camera.json does not exist"):
        list(ds.frames())


def test_unknown_object_id_stops_naming_scene_gt(tmp_path):
    ds = BopDataset(lay_out(tmp_path / "ds", obj_ids=(1, 9)))
    with pytest.raises(InputError, match=r"scene_gt.json: image 5 names object id 9.*models_info.json"):
        ds.read_frame(3, 0)
    with pytest.raises(InputError, match="object id 9 is not in"):
        ds.model_path(9)


def test_wrong_size_depth_raises_and_a_run_skips_and_counts_it(tmp_path):
    root = lay_out(tmp_path / "ds")
    bad = root / "test" / "000003" / "depth" / "000005.png"
    cv2.imwrite(str(bad), np.ones((H // 2, W // 2), np.uint16))
    ds = BopDataset(root)
    with pytest.raises(InputError, match=r"depth image .*000005.png is 32x24 but the colour image is 64x48"):
        ds.read_frame(3, 5)
    skipped = SkipCounter()
    frames = list(ds.frames(skipped=skipped))
    assert [f.im_id for f in frames] == [0]
    assert skipped.count == 1 and "000005.png" in skipped.summary()


def test_missing_split_and_bad_json_name_the_problem(tmp_path):
    root = lay_out(tmp_path / "ds")
    with pytest.raises(InputError, match="has no split 'val'.*test"):
        BopDataset(root, "val")
    (root / "test" / "000003" / "scene_gt_info.json").write_text("{not json")
    with pytest.raises(InputError, match="scene_gt_info.json is not valid JSON"):
        BopDataset(root).read_frame(3, 5)


def test_results_csv_round_trip_and_format(tmp_path):
    T = np.eye(4)
    T[:3, :3] = R_A
    T[:3, 3] = [0.01, -0.02, 0.7]
    rows = [BopEstimate.from_pose(3, 5, 1, 0.9, T, 0.25), BopEstimate.from_pose(3, 5, 2, 0.4, np.eye(4), 0.25),
            BopEstimate.from_pose(3, 6, 1, 0.1, T, -1)]
    path = write_results_csv(tmp_path / "r.csv", rows)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    fields = lines[1].split(",")
    assert fields[:3] == ["3", "5", "1"] and float(fields[3]) == pytest.approx(0.9)
    assert [float(v) for v in fields[4].split()] == pytest.approx(R_A.reshape(-1).tolist())       # row-major, spaces
    assert [float(v) for v in fields[5].split()] == pytest.approx([10.0, -20.0, 700.0])          # mm
    assert float(fields[6]) == pytest.approx(0.25)
    back = read_results_csv(path)
    assert [(r.scene_id, r.im_id, r.obj_id) for r in back] == [(3, 5, 1), (3, 5, 2), (3, 6, 1)]
    np.testing.assert_allclose(back[0].T_m, T, atol=1e-9)
    assert back[2].time_s == -1


def test_results_csv_errors_name_the_line(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,2,0.5,1 0 0 0 1 0 0 0 1,0 0 500,0.1\n"
                    "1,0,2,0.5,1 0 0 0 1 0 0 0,0 0 500,0.1\n")
    with pytest.raises(InputError, match="r.csv line 3: R has 8 numbers"):
        read_results_csv(path)
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,2,0.5,1 0 0 0 1 0 0 0 1,0 0 500,0.1\n"
                    "1,0,3,0.5,1 0 0 0 1 0 0 0 1,0 0 500,0.2\n")
    with pytest.raises(InputError, match="the same on each of its rows"):
        read_results_csv(path)
    path.write_text("scene,im,obj\n")
    with pytest.raises(InputError, match="line 1 must be the header"):
        read_results_csv(path)
    with pytest.raises(InputError, match="the same on each of its rows"):
        write_results_csv(tmp_path / "w.csv", [BopEstimate.from_pose(1, 0, 2, 1, np.eye(4), 0.1),
                                               BopEstimate.from_pose(1, 0, 2, 1, np.eye(4), 0.3)])


def test_writer_round_trip(tmp_path):
    from multi_instance_reg.meshes import box_mesh, load_mesh
    from multi_instance_reg.symmetry import parse_symmetry_text

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.integers(0, 3000, (H, W)).astype(np.uint16)
    mask = np.zeros((H, W), bool)
    mask[10:20, 30:35] = True
    T = np.eye(4)
    T[:3, :3] = R_A
    T[:3, 3] = [0.0123456, -0.02, 0.7]
    Kmat = np.array(K).reshape(3, 3)
    writer = BopWriter(tmp_path / "out")
    mesh = box_mesh(0.06, 0.04, 0.02)
    writer.add_model(4, mesh, parse_symmetry_text("x:2,y:2", np.zeros(3)))
    with writer.scene(7) as scene:
        scene.add_image(0, rgb, depth, Kmat, gt=[(4, T)], gt_info=[gt_info_from_mask(mask, depth, 0.5)])
        scene.add_image(1, rgb, depth, Kmat, gt=[], gt_info=[])
    with pytest.raises(InputError, match="already exists"):
        writer.scene(7)
    ds = BopDataset(tmp_path / "out")
    assert ds.camera["width"] == W and ds.camera["fx"] == 500.0
    f = ds.read_frame(7, 0)
    np.testing.assert_array_equal(f.rgb, rgb)
    np.testing.assert_array_equal(np.round(f.depth_m * 1000).astype(np.uint16), depth)
    np.testing.assert_allclose(f.gt_poses[0], T, atol=1e-12)
    assert f.gt_obj_ids.tolist() == [4] and f.gt_visibility.tolist() == [0.5]
    info = json.loads((tmp_path / "out" / "test" / "000007" / "scene_gt_info.json").read_text())["0"][0]
    assert info["bbox_visib"] == [30, 10, 5, 10] and info["px_count_visib"] == 50
    m = ds.models_info[4]
    assert m.diameter_mm == pytest.approx(np.linalg.norm([60, 40, 20]))
    np.testing.assert_allclose(m.min_mm, [-30, -20, -10], atol=1e-6)
    assert len(m.symmetries().discrete) == 4                                  # a box: identity and three flips
    back = load_mesh(ds.model_path(4), "mm")
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-7)


def test_models_info_entry_continuous(tmp_path):
    from multi_instance_reg.meshes import cylinder_mesh
    from multi_instance_reg.symmetry import parse_symmetry_text

    entry = models_info_entry(cylinder_mesh(0.05, 0.1), parse_symmetry_text("z:inf,x:2", np.array([0, 0, 0.001])))
    assert entry["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 1.0]}]
    assert len(entry["symmetries_discrete"]) == 1                            # the flip, not the identity
    assert entry["diameter"] == pytest.approx(np.hypot(50, 100), rel=1e-3)


def test_unreadable_or_missing_images_are_skipped_and_named(tmp_path):
    root = lay_out(tmp_path / "ds")
    scene = root / "test" / "000003"
    (scene / "rgb" / "000000.png").write_bytes(b"not a png")
    (scene / "depth" / "000005.png").unlink()
    skipped = SkipCounter()
    assert list(BopDataset(root).frames(skipped=skipped)) == []
    assert skipped.count == 2
    text = skipped.summary()
    assert "cannot read image" in text and "rgb/000000.png" in text
    assert "has no image 000005" in text and "depth" in text
