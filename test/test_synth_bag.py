"""Synthetic bags are real rosbag2 files: they read back through rosbags' AnyReader with the
realsense-ros topics, types, encodings, frame ids and stamps, and hold what was rendered."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from multi_instance_reg.datasets import bag_writer as bw
from multi_instance_reg.messages import camera_info_to_intrinsics, colour_to_rgb, depth_to_metres
from multi_instance_reg.synthetic.scene import (
    FRAME_RATE_HZ, START_STAMP_NS, generate_capture_bag, generate_scene_bag, make_tabletop_scene)
from multi_instance_reg.datasets.rgbd_bag import read_object_description
from multi_instance_reg.tools import cli
from multi_instance_reg.transforms import pose_to_matrix

TYPES = {
    bw.TOPIC_COLOUR: "sensor_msgs/msg/Image",
    bw.TOPIC_COLOUR_INFO: "sensor_msgs/msg/CameraInfo",
    bw.TOPIC_DEPTH: "sensor_msgs/msg/Image",
    bw.TOPIC_DEPTH_INFO: "sensor_msgs/msg/CameraInfo",
    bw.TOPIC_GT_POSES: "geometry_msgs/msg/PoseArray",
    bw.TOPIC_GT_OBJECT: "std_msgs/msg/String",
    bw.TOPIC_GT_VISIBILITY: "std_msgs/msg/Float32MultiArray",
    bw.ACCEL_TOPIC: "sensor_msgs/msg/Imu",
}
SCENE = dict(object_name="can", instances=3, distractors=2, frames=4, seed=21)


def read_bag(path):
    """topic -> list of (log time, raw bytes, decoded message)."""
    out = {}
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TYPES
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, bytes(raw), reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.fixture(scope="module", params=["sqlite3", "mcap"])
def bag(request, tmp_path_factory):
    path = tmp_path_factory.mktemp(request.param) / "scene"
    summary = generate_scene_bag(path, storage=request.param, **SCENE)
    assert summary.frames == SCENE["frames"] and summary.path == path
    suffix = ".db3" if request.param == "sqlite3" else ".mcap"
    assert any(p.suffix == suffix for p in path.iterdir()) and (path / "metadata.yaml").exists()
    return read_bag(path)


def test_topics_types_encodings_frame_ids_and_stamps(bag):
    n = SCENE["frames"]
    for topic in set(TYPES) - {bw.ACCEL_TOPIC}:
        assert len(bag[topic]) == (1 if topic == bw.TOPIC_GT_OBJECT else n), topic
    expected = [START_STAMP_NS + round(i * 1e9 / FRAME_RATE_HZ) for i in range(n)]
    # The accelerometer at 200 Hz from a frame interval before the first frame to the last,
    # in its own optical frame, about 1 g.
    accel = bag[bw.ACCEL_TOPIC]
    assert len(accel) == round(n * 200 / FRAME_RATE_HZ)
    assert expected[0] - 1e9 / FRAME_RATE_HZ < accel[0][0] and accel[-1][0] <= expected[-1]
    assert all(t2 - t1 == 5_000_000 for (t1, _, _), (t2, _, _) in zip(accel, accel[1:]))
    for t, _, msg in accel:
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == t
        assert msg.header.frame_id == "camera_accel_optical_frame" and msg.orientation_covariance[0] == -1
        a = msg.linear_acceleration
        assert abs(np.linalg.norm([a.x, a.y, a.z]) - 9.81) < 1.0
    for topic in (bw.TOPIC_COLOUR, bw.TOPIC_COLOUR_INFO, bw.TOPIC_DEPTH, bw.TOPIC_DEPTH_INFO, bw.TOPIC_GT_POSES):
        for (t, _, msg), stamp in zip(bag[topic], expected):
            assert t == stamp
            assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == stamp
            assert msg.header.frame_id == "camera_color_optical_frame"
    assert [m.encoding for _, _, m in bag[bw.TOPIC_COLOUR]] == ["rgb8"] * n
    assert [m.encoding for _, _, m in bag[bw.TOPIC_DEPTH]] == ["16UC1"] * n
    assert [t for t, _, _ in bag[bw.TOPIC_GT_VISIBILITY]] == expected
    assert bag[bw.TOPIC_GT_OBJECT][0][0] == expected[0]


def test_camera_info_is_the_undistorted_d455_colour_stream(bag):
    for topic in (bw.TOPIC_COLOUR_INFO, bw.TOPIC_DEPTH_INFO):
        msg = bag[topic][0][2]
        intr = camera_info_to_intrinsics(msg)
        assert (intr.width, intr.height) == (640, 480)
        assert np.allclose(intr.K, [[379.05, 0, 321.89], [0, 378.68, 238.97], [0, 0, 1]])
        assert msg.distortion_model == "plumb_bob" and np.array_equal(msg.d, np.zeros(5))
        assert np.allclose(np.asarray(msg.p).reshape(3, 4)[:, :3], intr.K)


def test_object_description_travels_with_the_bag(bag):
    desc = json.loads(bag[bw.TOPIC_GT_OBJECT][0][2].data)
    assert desc["name"] == "can" and desc["shape"] == "cylinder"
    assert desc["dimensions_m"] == pytest.approx([0.066, 0.066, 0.122])
    assert "geometric centre" in desc["object_frame"] and desc["instances"] == 3
    assert len(desc["distractors"]) == 2 and "can" not in desc["distractors"]


def test_bag_holds_exactly_what_was_rendered(bag):
    scene = make_tabletop_scene(**SCENE)
    for i in (0, SCENE["frames"] - 1):
        f = scene.render_frame(i)
        assert np.array_equal(colour_to_rgb(bag[bw.TOPIC_COLOUR][i][2]), f.rgb)
        assert np.array_equal(depth_to_metres(bag[bw.TOPIC_DEPTH][i][2]), f.depth_mm.astype(np.float32) * np.float32(0.001))
        poses = bag[bw.TOPIC_GT_POSES][i][2].poses
        assert len(poses) == 3
        for T, p in zip(f.poses, poses):
            T_bag = pose_to_matrix([p.position.x, p.position.y, p.position.z],
                                   [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])
            assert np.allclose(T_bag, T, atol=1e-9)
        assert np.allclose(bag[bw.TOPIC_GT_VISIBILITY][i][2].data, f.visibility)


def test_same_seed_gives_identical_messages(tmp_path):
    kw = dict(SCENE, frames=2)
    generate_scene_bag(tmp_path / "a", **kw)
    generate_scene_bag(tmp_path / "b", **kw)
    generate_scene_bag(tmp_path / "c", **dict(kw, seed=22))
    a, b, c = (read_bag(tmp_path / x) for x in "abc")
    for topic in TYPES:
        assert [(t, raw) for t, raw, _ in a[topic]] == [(t, raw) for t, raw, _ in b[topic]], topic
    assert [raw for _, raw, _ in a[bw.TOPIC_COLOUR]] != [raw for _, raw, _ in c[bw.TOPIC_COLOUR]]


def test_capture_bag_and_previews(tmp_path):
    summary = generate_capture_bag(tmp_path / "cap", "cereal_box", seed=1, views=5, storage="mcap",
                                   preview_dir=tmp_path / "png")
    assert summary.frames == 5
    bag = read_bag(tmp_path / "cap")
    assert len(bag[bw.TOPIC_COLOUR]) == 5
    assert all(len(m.poses) == 1 for _, _, m in bag[bw.TOPIC_GT_POSES])
    assert json.loads(bag[bw.TOPIC_GT_OBJECT][0][2].data)["distractors"] == []
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert len(pngs) == 12
    assert all(cv2.imread(str(p)).shape == (480, 640, 3) for p in pngs)


def test_cli_writes_a_bag_and_reports_bad_input(tmp_path, capsys):
    out = tmp_path / "new" / "cli"           # parent folders are made as needed
    assert cli.main(["synth", "scene", "-o", str(out), "--instances", "2", "--distractors", "0",
                     "--frames", "2", "--seed", "3", "--storage", "mcap"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("mireg synth scene: wrote 2 frames") and "frames/s" in line and str(out) in line
    assert len(read_bag(out)[bw.TOPIC_COLOUR]) == 2
    assert cli.main(["synth", "scene", "-o", str(out)]) == 2                     # exists
    assert "already exists" in capsys.readouterr().err
    assert cli.main(["synth", "capture", "-o", str(tmp_path / "x"), "--object", "banana"]) == 2
    assert "unknown object 'banana'" in capsys.readouterr().err
    assert cli.main(["synth", "untextured", "--preset", "cylinders", "-o", str(tmp_path / "y"),
                     "--depth-noise-correlation", "25"]) == 2
    err = capsys.readouterr().err.strip()
    assert "depth noise correlation must be 0" in err and len(err.splitlines()) == 1


def test_correlated_depth_noise_is_recorded_in_the_bag(tmp_path, capsys):
    out = tmp_path / "corr"
    assert cli.main(["synth", "scene", "-o", str(out), "--instances", "2", "--distractors", "0",
                     "--frames", "1", "--seed", "3", "--depth-noise-correlation", "2.5"]) == 0
    assert read_object_description(out)["depth_noise_correlation_px"] == 2.5
    default = make_tabletop_scene(instances=2, distractors=0, frames=1, seed=3)
    assert "depth_noise_correlation_px" not in default.description()       # default bags as they were


def test_compressed_image_transport_holds_the_same_frames(tmp_path, capsys):
    """`--image-transport compressed`: image_transport's topics and types, depth exact (PNG),
    colour within JPEG's loss; the reader finds them without being told the topics."""
    from multi_instance_reg.datasets.rgbd_bag import RGBDBag

    args = ["synth", "scene", "--instances", "2", "--distractors", "1", "--frames", "2", "--seed", "3"]
    assert cli.main([*args, "-o", str(tmp_path / "raw")]) == 0
    assert cli.main([*args, "-o", str(tmp_path / "cmp"), "--image-transport", "compressed"]) == 0
    with AnyReader([tmp_path / "cmp"], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
    images = {bw.TOPIC_COLOUR + "/compressed", bw.TOPIC_DEPTH + "/compressedDepth"}
    assert {t: m for t, m in types.items() if t in images} == dict.fromkeys(images, "sensor_msgs/msg/CompressedImage")
    assert bw.TOPIC_COLOUR not in types and bw.TOPIC_DEPTH not in types
    with RGBDBag(tmp_path / "raw") as raw, RGBDBag(tmp_path / "cmp") as cmp:
        pairs = list(zip(raw, cmp))
        assert cmp.skipped.count == 0
    assert len(pairs) == 2
    for a, b in pairs:
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.gt_poses, b.gt_poses)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        err = np.abs(a.rgb.astype(int) - b.rgb)
        assert err.mean() < 3 and np.percentile(err, 99) < 30, (err.mean(), np.percentile(err, 99))
    with pytest.raises(ValueError, match="image transport"):
        bw.RealSenseBagWriter(tmp_path / "t", transport="theora")


def test_writer_rejects_bad_arrays(tmp_path):
    from multi_instance_reg.synthetic.sensor import d455_intrinsics
    with bw.RealSenseBagWriter(tmp_path / "w") as bag:
        with pytest.raises(ValueError, match="depth must be"):
            bag.write_frame(0, np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5), np.uint16), d455_intrinsics())
    with pytest.raises(ValueError, match="storage"):
        bw.RealSenseBagWriter(tmp_path / "v", storage="bag")
