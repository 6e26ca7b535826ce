"""`mireg offline` and `mireg build-model` as a user runs them: real bags, real processes, the
files they write, and clear one-line errors with a non-zero exit for bad input."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# Its module fixture (replay) runs `mireg offline`: one pytest-xdist worker takes the whole module, so
# that it runs once.
pytestmark = pytest.mark.xdist_group("test_offline_cli")

COLOUR, DEPTH, INFO = ("/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                       "/camera/camera/color/camera_info")


def cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def one_line_error(res, command, *fragments):
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip()
    assert err.count("\n") == 0, err
    assert err.startswith(f"mireg {command}: error: "), err
    for f in fragments:
        assert f in err, err


def write_bag(path, frames, topics=(COLOUR, DEPTH, INFO), storage="sqlite3"):
    """A small rosbag2 of (colour array, colour encoding, depth array, depth encoding) frames."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    K = np.array([379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1.0])
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(Path(path), version=9, storage_plugin=plugin) as w:
        conns = [w.add_connection(topics[0], "sensor_msgs/msg/Image", typestore=ts),
                 w.add_connection(topics[1], "sensor_msgs/msg/Image", typestore=ts),
                 w.add_connection(topics[2], "sensor_msgs/msg/CameraInfo", typestore=ts)]
        for k, (colour, colour_enc, depth, depth_enc) in enumerate(frames):
            t = 10**9 + k * 33_000_000
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                           frame_id="camera_color_optical_frame")
            info = T["sensor_msgs/msg/CameraInfo"](
                header=hdr, height=colour.shape[0], width=colour.shape[1], distortion_model="plumb_bob", d=np.zeros(5),
                k=K, r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            Image = T["sensor_msgs/msg/Image"]
            w.write(conns[2], t, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            w.write(conns[0], t, ts.serialize_cdr(Image(header=hdr, **image_fields(colour, colour_enc)),
                                                  "sensor_msgs/msg/Image"))
            w.write(conns[1], t, ts.serialize_cdr(Image(header=hdr, **image_fields(depth, depth_enc)),
                                                  "sensor_msgs/msg/Image"))
    return path


def image_fields(arr, encoding):
    """Image fields of arr; encodings the package does not know (yuv422) are packed by hand."""
    from multi_instance_reg.messages import array_to_image_fields

    if encoding == "yuv422":
        h, w = arr.shape[:2]
        return {"height": h, "width": w, "encoding": encoding, "is_bigendian": 0, "step": w * 2,
                "data": np.ascontiguousarray(arr[:, :, :2]).reshape(-1)}
    return array_to_image_fields(arr, encoding)


def noise_frame(h=480, w=640, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8), np.full((h, w), 800, np.uint16)


@pytest.fixture(scope="module")
def replay(scene_bag, object_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("offline") / "out"
    # The benchmark bag strings independent scenes together: each frame is solved alone.
    res = cli("offline", scene_bag, "--model", object_model, "-o", out, "--no-tracking")
    return res, out


def test_offline_writes_the_poses_contract(replay):
    res, out = replay
    assert res.returncode == 0, res.stderr
    poses = json.loads((out / "poses.json").read_text())
    assert set(poses) == {"frames"} and len(poses["frames"]) >= 5
    stamps = [f["stamp_ns"] for f in poses["frames"]]
    assert stamps == sorted(stamps)
    for f in poses["frames"]:
        assert set(f) == {"stamp_ns", "frame_id", "latency_ms", "instances"}
        assert isinstance(f["stamp_ns"], int) and f["frame_id"] == "camera_color_optical_frame"
        assert f["latency_ms"] > 0
        for inst in f["instances"]:
            # "object" (the model's name) extends the contract: nothing else is new.
            assert set(inst) == {"id", "object", "T", "inliers", "score"} and inst["object"] == "snack_box"
            T = np.array(inst["T"])
            assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
            assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5)
            assert inst["inliers"] > 0 and 0 <= inst["score"] <= 1
    assert sum(len(f["instances"]) for f in poses["frames"]) > 0


def test_offline_reaches_the_quality_targets(replay):
    res, out = replay
    assert res.returncode == 0, res.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["max_rre_deg"] == 10.0 and m["max_rte"] == 0.02
    print("offline replay metrics:", {k: m[k] for k in ("MHF1", "MHR", "MHP", "MF", "median_rte", "median_rre_deg")})
    assert m["MHF1"] >= 0.95, m
    assert m["median_rte"] <= 0.005 and m["median_rre_deg"] <= 2.0, m
    assert set(m["latency_ms"]) >= {"sift", "matching", "lifting", "ecc", "refinement", "total"}
    assert list(out.glob("overlay_*.png")) and (out / "found_vs_present.png").is_file()


def test_offline_reads_a_bag_of_compressed_images_as_well_as_the_raw_one(replay, scene_bag, object_model, tmp_path):
    """A bag recorded with image_transport's compressed topics only (colour JPEG, depth PNG):
    found on its own (no --topics) and scored as the raw bag is, give or take the JPEG."""
    from multi_instance_reg.datasets.bag_writer import RealSenseBagWriter
    from multi_instance_reg.datasets.rgbd_bag import RGBDBag

    compressed = tmp_path / "compressed"
    with RGBDBag(scene_bag) as raw, RealSenseBagWriter(compressed, transport="compressed") as out:
        out.write_object_description(1, raw.object_description)
        for f in raw:
            out.write_frame(f.stamp_ns, f.rgb, np.round(f.depth_m * 1000).astype(np.uint16), f.intrinsics,
                            poses=f.gt_poses, visibility=f.gt_visibility)
    res = cli("offline", compressed, "--model", object_model, "-o", tmp_path / "out", "--no-tracking")
    assert res.returncode == 0, res.stderr
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    raw_m = json.loads((replay[1] / "metrics.json").read_text())
    assert m["frames"] == raw_m["frames"] and m["skipped_frames"] == 0, res.stderr
    print("compressed / raw MHF1:", m["MHF1"], raw_m["MHF1"])
    assert m["MHF1"] >= raw_m["MHF1"] - 0.05 and m["MHF1"] >= 0.9, (m, raw_m)


def test_offline_reads_a_bare_db3(scene_bag, object_model, tmp_path):
    db3 = next(Path(scene_bag).glob("*.db3"))
    bare = shutil.copy(db3, tmp_path / "bare.db3")
    res = cli("offline", bare, "--model", object_model, "-o", tmp_path / "out", "--max-frames", 1, "--quiet")
    assert res.returncode == 0, res.stderr
    assert len(json.loads((tmp_path / "out" / "poses.json").read_text())["frames"]) == 1


def test_offline_reads_a_bare_mcap_with_custom_topics_and_no_ground_truth(object_model, tmp_path):
    topics = ("/cam/rgb", "/cam/depth", "/cam/info")
    rgb, depth = noise_frame()
    bag = write_bag(tmp_path / "custom", [(rgb, "bgr8", depth, "16UC1")] * 2, topics, storage="mcap")
    bare = shutil.copy(next(bag.glob("*.mcap")), tmp_path / "bare.mcap")
    res = cli("offline", bare, "--model", object_model, "-o", tmp_path / "out", "--topics", *topics, "--quiet")
    assert res.returncode == 0, res.stderr
    frames = json.loads((tmp_path / "out" / "poses.json").read_text())["frames"]
    assert len(frames) == 2 and not (tmp_path / "out" / "metrics.json").exists()   # no ground truth


def test_missing_topics_are_named(object_model, tmp_path):
    rgb, depth = noise_frame()
    bag = write_bag(tmp_path / "other", [(rgb, "rgb8", depth, "16UC1")], ("/a/rgb", "/a/depth", "/a/info"))
    res = cli("offline", bag, "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", COLOUR, "topics present: /a/depth, /a/info, /a/rgb")
    # A topic of another type given as an image (here the camera_info) is named, not a traceback.
    res = cli("offline", bag, "--model", object_model, "-o", tmp_path / "out", "--topics", "/a/rgb", "/a/info", "/a/info")
    one_line_error(res, "offline", "topic /a/info holds sensor_msgs/msg/CameraInfo, not sensor_msgs/msg/Image or")


def test_unknown_encoding_fails_clearly(object_model, tmp_path):
    rgb, depth = noise_frame()
    bag = write_bag(tmp_path / "yuv", [(rgb, "yuv422", depth, "16UC1")])
    res = cli("offline", bag, "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", "no frame", "unsupported image encoding 'yuv422'")


def test_colour_and_depth_of_different_sizes_fail_clearly(object_model, tmp_path):
    rgb, _ = noise_frame()
    bag = write_bag(tmp_path / "sizes", [(rgb, "rgb8", np.full((240, 320), 800, np.uint16), "16UC1")])
    res = cli("offline", bag, "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", "depth image is 320x240 but colour is 640x480")


def test_all_zero_depth_fails_clearly(object_model, tmp_path):
    rgb, depth = noise_frame()
    bag = write_bag(tmp_path / "zero", [(rgb, "rgb8", np.zeros_like(depth), "16UC1")] * 2)
    res = cli("offline", bag, "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", "2 x depth image has no valid pixel")


def test_bad_models_fail_clearly(object_model, scene_bag, tmp_path):
    with np.load(object_model, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    missing = {k: v for k, v in arrays.items() if k != "keypoints_xyz"}
    np.savez(tmp_path / "missing.npz", **missing)
    res = cli("offline", scene_bag, "--model", tmp_path / "missing.npz", "-o", tmp_path / "out")
    one_line_error(res, "offline", "lacks keypoints_xyz")
    empty = dict(arrays, keypoints_xyz=np.zeros((0, 3), np.float32), descriptors=np.zeros((0, 128), np.float32))
    np.savez(tmp_path / "empty.npz", **empty)
    res = cli("offline", scene_bag, "--model", tmp_path / "empty.npz", "-o", tmp_path / "out")
    one_line_error(res, "offline", "0 keypoints")


def test_not_a_bag_fails_clearly(object_model, tmp_path):
    res = cli("offline", tmp_path / "nothing", "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", "does not exist")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file")
    res = cli("offline", tmp_path / "junk.mcap", "--model", object_model, "-o", tmp_path / "out")
    one_line_error(res, "offline", "cannot read bag")


def test_build_model_from_the_capture_bag(capture_bag, tmp_path):
    out = tmp_path / "m.npz"
    res = cli("build-model", capture_bag, "-o", out, "--frames", "0:4")
    assert res.returncode == 0, res.stderr
    from multi_instance_reg.models.model import load_model

    model = load_model(out)
    assert model.num_keypoints > 100 and model.T_object_model is not None and model.name
    res = cli("build-model", capture_bag, "-o", tmp_path / "x.npz", "--frames", "500")
    one_line_error(res, "build-model", "outside the bag")
    res = cli("build-model", capture_bag, "-o", tmp_path / "x.npz", "--topics", "/x", "/y", "/z")
    one_line_error(res, "build-model", "has no topic /x, /y, /z")


def test_offline_reads_the_node_parameter_file(scene_bag, object_model, tmp_path):
    good = tmp_path / "params.yaml"
    good.write_text("instance_registration:\n  ros__parameters:\n    model_path: ''\n    sync_slop_s: 0.02\n"
                    "    frontend:\n      ratio: 0.75\n    ecc:\n      inlier_thresh: 0.012\n")
    res = cli("offline", scene_bag, "--model", object_model, "-o", tmp_path / "out", "--params", good, "--max-frames", 1)
    assert res.returncode == 0, res.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("instance_registration:\n  ros__parameters:\n    frontend:\n      ratio: 5.0\n")
    res = cli("offline", scene_bag, "--model", object_model, "-o", tmp_path / "out2", "--params", bad)
    one_line_error(res, "offline", "frontend.ratio=5.0 is out of range")
    typo = tmp_path / "typo.yaml"
    typo.write_text("instance_registration:\n  ros__parameters:\n    frontend:\n      ratoi: 0.7\n")
    res = cli("offline", scene_bag, "--model", object_model, "-o", tmp_path / "out3", "--params", typo)
    one_line_error(res, "offline", "unknown parameter(s) frontend.ratoi")
