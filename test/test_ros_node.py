"""The instance_registration node as a real process over DDS (one ROS_DOMAIN_ID per test).

A test process publishes camera frames like realsense-ros and reads what the node publishes.
The scene is the small poster of ros_testing (one instance ~0.6 m ahead); the ground-truth
quality over a rendered bag replayed with `mireg play` is in test_ros_replay.py, the tracking
at 30 Hz in test_ros_tracking.py. Tests of what the detector publishes frame by frame run
with tracking off (``tracking.enabled:=false``, the behaviour before tracking existed).
"""
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from ros_testing import (POSTER_Z, CameraPublisher, live_node, poster_frame, poster_model, ros_env, set_parameters,
                         stop, wait_until)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return poster_model(tmp_path_factory.mktemp("model") / "poster.npz")


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def last_stats(box):
    return json.loads(box[-1][1].data) if box else {}


def test_missing_or_broken_model_stops_the_node_with_one_clear_line(tmp_path):
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a model")
    cases = [(["-p", f"model_path:={tmp_path / 'absent.npz'}"], "does not exist"),
             (["-p", f"model_path:={broken}"], "broken.npz"),
             ([], "no model"),
             (["-p", "ecc.inlier_thresh:=-1.0", "-p", f"model_path:={broken}"], "inlier_thresh")]
    for params, message in cases:
        done = subprocess.run([sys.executable, "-m", "multi_instance_reg.ros.node", "--ros-args", *params],
                              env=ros_env(43), capture_output=True, text=True, timeout=60)
        assert done.returncode == 1, done
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1, done.stderr
        assert lines[0].startswith("instance_registration: error:") and message in lines[0], lines[0]
    # Malformed --ros-args: rcl logs its own line first, then ours; no traceback.
    done = subprocess.run([sys.executable, "-m", "multi_instance_reg.ros.node", "--ros-args", "-p", "model_path:="],
                          env=ros_env(43), capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("instance_registration: error: cannot parse the --ros-args")


UNTRACKED = "tracking.enabled:=false"


def test_poses_markers_details_and_debug_image_for_a_live_stream_without_tracking(model):
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray

    with live_node(44, model, UNTRACKED) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        markers = probe.subscribe(MarkerArray, "/instances/markers")
        details = probe.subscribe(String, "/instances/details")
        debug = probe.subscribe(Image, "/instances/debug_image")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()
        sent = []
        for _ in range(6):
            sent.append(camera.send(rgb, depth, K))
            wait_until(lambda: len(poses) == len(sent), 15, proc=node)
        assert len(poses) == 6, stop(node)
        # Header = the colour image's stamp and frame id; one pose, the poster 0.6 m ahead.
        assert [stamp_ns(m) for _, m in poses] == sent
        for _, msg in poses:
            assert msg.header.frame_id == "camera_color_optical_frame"
            assert len(msg.poses) == 1
            p = msg.poses[0]
            assert np.allclose([p.position.x, p.position.y, p.position.z], [0, 0, POSTER_Z], atol=0.01)
            assert abs(p.orientation.w) > 0.999  # identity rotation
        assert wait_until(lambda: len(details) == 6 and len(markers) == 6, 15)
        info = json.loads(details[-1][1].data)
        assert info["stamp_ns"] == sent[-1] and info["frame_id"] == "camera_color_optical_frame"
        assert info["latency_ms"] > 0 and info["counters"]["processed"] == 6
        (inst,) = info["instances"]
        assert inst["id"] == 0 and inst["inliers"] >= 20 and 0 <= inst["score"] <= 1
        assert "track_id" not in inst and info["timings_ms"]["total"] > 0   # the old layout
        boxes = [m for m in markers[-1][1].markers if m.type == Marker.CUBE]
        assert len(boxes) == 1 and boxes[0].action == Marker.ADD and boxes[0].scale.x == pytest.approx(0.3166, abs=1e-3)
        # The debug image is drawn because someone subscribed: same size, something drawn.
        assert wait_until(lambda: len(debug) >= 1, 15)
        overlay = debug[-1][1]
        assert (overlay.width, overlay.height, overlay.encoding) == (640, 480, "rgb8")
        assert (np.frombuffer(bytes(overlay.data), np.uint8).reshape(480, 640, 3) != rgb).any()

        # The poster leaves the view: no pose, and its markers are deleted.
        empty = np.full_like(rgb, 90)
        sent.append(camera.send(empty, np.full_like(depth, 1000), K))
        assert wait_until(lambda: len(poses) == 7, 15, proc=node)
        assert poses[-1][1].poses == []
        assert wait_until(lambda: len(markers) == 7, 15)
        gone = markers[-1][1].markers
        assert gone and all(m.action == Marker.DELETE and m.id == 0 for m in gone)
    out = live.out
    assert node.returncode == 0, out


def test_parameter_changes_apply_on_the_next_frame_and_bad_ones_are_refused(model):
    from geometry_msgs.msg import PoseArray

    with live_node(45, model, UNTRACKED) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()

        def frame():
            n = len(poses)
            camera.send(rgb, depth, K)
            assert wait_until(lambda: len(poses) > n, 15, proc=node), stop(node)
            return len(poses[-1][1].poses)

        assert frame() == 1
        # Only depth up to 0.3 m: the poster (0.6 m) is out of range, nothing is found.
        (result,) = set_parameters(probe, {"frontend.depth_max": 0.3})
        assert result.successful
        assert frame() == 0
        # Out of range, wrong type, read-only: refused with the reason; the node keeps going.
        (result,) = set_parameters(probe, {"ecc.inlier_thresh": -1.0})
        assert not result.successful and "inlier_thresh" in result.reason
        (result,) = set_parameters(probe, {"frontend.depth_window": 100})
        assert not result.successful and "depth_window" in result.reason
        (result,) = set_parameters(probe, {"model_path": "/elsewhere.npz"})
        assert not result.successful and "read-only" in result.reason.lower()
        (result,) = set_parameters(probe, {"frontend.depth_max": 4.0})
        assert result.successful
        assert frame() == 1
        assert node.poll() is None
    out = live.out
    assert "parameters changed: frontend.depth_max=0.3" in out


@pytest.mark.parametrize("tracking", [True, False])
def test_malformed_images_and_missing_camera_info_are_skipped_and_counted(model, tracking):
    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String

    with live_node(46 if tracking else 53, model, f"tracking.enabled:={str(tracking).lower()}") as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        stats = probe.subscribe(String, "/instance_registration/stats")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()
        # No camera_info yet: a warning, the frame skipped, no crash.
        camera.send(rgb, depth, K, with_info=False)
        assert wait_until(lambda: last_stats(stats).get("no_camera_info") == 1, 15, proc=node), stop(node)

        def bad(**kw):  # one at a time: frames sent faster than processed would be dropped instead
            n = last_stats(stats).get("bad", 0)
            camera.send(rgb, depth, K, **kw)
            assert wait_until(lambda: last_stats(stats).get("bad", 0) == n + 1, 15, proc=node), stop(node)

        bad(colour_msg=camera.image(rgb, "rgb8", overrides={"step": 100}))                # step < width * 3
        bad(colour_msg=camera.image(rgb, "rgb8", overrides={"encoding": "yuv422_yuy2"}))  # unknown encoding
        bad(depth_msg=camera.image(depth[:240, :320], "16UC1"))                           # sizes differ
        bad(colour_msg=camera.image(rgb, "rgb8", overrides={"data": rgb.tobytes()[:1000]}))  # truncated
        assert poses == [] and last_stats(stats)["dropped"] == 0
        # ... and the next good frame goes through.
        camera.send(rgb, depth, K)
        assert wait_until(lambda: len(poses) == 1, 15, proc=node), stop(node)
        # Tracked: published at once, before any detection made a track; else the detection.
        assert len(poses[0][1].poses) == (0 if tracking else 1)
        assert node.poll() is None
        assert wait_until(lambda: last_stats(stats)["processed"] == 1, 15)
        assert last_stats(stats)["failed"] == 0 and last_stats(stats)["bad"] == 4
    out = live.out
    assert "no camera_info received" in out
    assert "skipping a malformed frame" in out


def test_compressed_image_transport_is_subscribed_decoded_and_bad_data_counted(model):
    """``image_transport:=compressed``: the node takes image_transport's compressed topics
    (colour JPEG, depth PNG), finds the poster as from raw images, and counts undecodable data."""
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import String

    from multi_instance_reg.messages import compressed_colour_fields, compressed_depth_fields

    with live_node(56, model, UNTRACKED, "image_transport:=compressed") as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        stats = probe.subscribe(String, "/instance_registration/stats")
        camera = CameraPublisher(probe)
        camera.colour = probe.publisher(CompressedImage, "/camera/camera/color/image_raw/compressed")
        camera.depth = probe.publisher(CompressedImage, "/camera/camera/aligned_depth_to_color/image_raw/compressedDepth")
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()

        def compressed(fields):
            return CompressedImage(format=fields["format"], data=fields["data"].tobytes())

        for _ in range(3):
            camera.send(rgb, depth, K, colour_msg=compressed(compressed_colour_fields(rgb)),
                        depth_msg=compressed(compressed_depth_fields(depth)))
            wait_until(lambda: len(poses) == _ + 1, 15, proc=node)
        assert len(poses) == 3, stop(node)
        for _, msg in poses:
            (p,) = msg.poses
            assert np.allclose([p.position.x, p.position.y, p.position.z], [0, 0, POSTER_Z], atol=0.01)
        camera.send(rgb, depth, K, colour_msg=CompressedImage(format="jpeg", data=b"\xff\xd8 cut short"),
                    depth_msg=compressed(compressed_depth_fields(depth)))
        assert wait_until(lambda: last_stats(stats).get("bad") == 1, 15, proc=node), stop(node)
        assert node.poll() is None and len(poses) == 3
    assert "image_raw/compressed" in live.out and "does not decode" in live.out


def test_two_pipeline_processes_publish_in_order(model):
    from geometry_msgs.msg import PoseArray

    with live_node(47, model, "pipeline_processes:=2", UNTRACKED) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()
        sent = []
        for _ in range(12):
            sent.append(camera.send(rgb, depth, K))
            time.sleep(0.03)
        assert wait_until(lambda: poses and stamp_ns(poses[-1][1]) == sent[-1], 20, proc=node), stop(node)
    out = live.out
    got = [stamp_ns(m) for _, m in poses]
    assert got == sorted(got) and set(got) <= set(sent), out
    assert all(len(m.poses) == 1 for _, m in poses)


def test_a_dead_pipeline_process_is_restarted_and_the_stream_goes_on(model):
    import os
    import signal
    from pathlib import Path

    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String

    with live_node(49, model, UNTRACKED) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        stats = probe.subscribe(String, "/instance_registration/stats")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        rgb, depth, K = poster_frame()
        camera.send(rgb, depth, K)
        assert wait_until(lambda: len(poses) == 1, 15, proc=node), stop(node)
        children = [int(c) for task in Path(f"/proc/{node.pid}/task").iterdir()
                    for c in (task / "children").read_text().split()]
        # The pipeline process (multiprocessing also starts its resource tracker).
        (pipeline,) = [c for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
        os.kill(pipeline, signal.SIGKILL)
        time.sleep(0.5)
        camera.send(rgb, depth, K)   # lost with the process: counted as failed
        assert wait_until(lambda: last_stats(stats).get("failed") == 1, 30, proc=node), stop(node)
        camera.send(rgb, depth, K)   # the restarted process takes it
        assert wait_until(lambda: len(poses) == 2, 30, proc=node), stop(node)
        assert len(poses[-1][1].poses) == 1 and node.poll() is None
    out = live.out
    assert "the pipeline process died" in out


def test_a_reliable_30hz_camera_loses_no_frame_and_the_newest_is_always_processed(model):
    """Faster than the pipeline: every image arrives, every pair is processed or counted as
    dropped (the newest kept), and the last frame's poses come out."""
    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String

    with live_node(52, model) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        stats = probe.subscribe(String, "/instance_registration/stats")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        assert probe.wait_for_publishers(["/instances/poses"], proc=node), stop(node)   # every frame counted
        rgb, depth, K = poster_frame()
        start_time, sent = time.monotonic(), []
        for k in range(60):
            sent.append(camera.send(rgb, depth, K))
            time.sleep(max(0.0, start_time + (k + 1) / 30 - time.monotonic()))
        assert wait_until(lambda: poses and stamp_ns(poses[-1][1]) == sent[-1], 20, proc=node), stop(node)
        assert wait_until(lambda: last_stats(stats).get("processed") == len(poses), 5)
        counts = last_stats(stats)
    assert counts["colour_received"] == 60 and counts["depth_received"] == 60, counts
    assert counts["processed"] + counts["dropped"] == 60 and counts["unmatched"] == 0, counts


def test_gravity_from_the_accelerometer_goes_with_each_frame_and_its_absence_is_no_error(model):
    """realsense-ros' accel/sample (sensor_msgs/Imu): the samples of the 0.1 s before a frame's
    stamp give it the direction of gravity (counted in ~/stats); without samples, with stale
    ones (another clock) or with ``gravity_source`` none a frame goes without, and is processed."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import Imu
    from std_msgs.msg import String

    with live_node(87, model, UNTRACKED) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        stats = probe.subscribe(String, "/instance_registration/stats")
        accel = probe.publisher(Imu, "/camera/camera/accel/sample", depth=100)
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        assert wait_until(lambda: accel.get_subscription_count() > 0, 30, proc=node), stop(node)
        rgb, depth, K = poster_frame()

        def samples(start_ns):
            """40 samples 5 ms apart from ``start_ns``: a level camera at rest (y points down)."""
            for k in range(40):
                ns = start_ns + k * 5_000_000
                msg = Imu()
                msg.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
                msg.header.frame_id = "camera_accel_optical_frame"
                msg.linear_acceleration.y = -9.81
                accel.publish(msg)

        def frame(expected_with_gravity):
            n = len(poses)
            camera.send(rgb, depth, K)
            assert wait_until(lambda: len(poses) > n, 15, proc=node), stop(node)
            assert len(poses[-1][1].poses) == 1
            assert wait_until(lambda: last_stats(stats).get("processed") == n + 1, 15, proc=node), stop(node)
            assert last_stats(stats)["with_gravity"] == expected_with_gravity, json.dumps(last_stats(stats))

        frame(0)                                      # no IMU at all: as before
        samples(time.time_ns() + 100_000_000)         # the frame will be stamped ~0.25 s from now
        time.sleep(0.25)
        frame(1)
        assert last_stats(stats)["accel_received"] >= 20          # best effort: a burst may lose a few
        samples(time.time_ns() - 10_000_000_000)      # on another clock: stale for the frame
        time.sleep(0.25)
        frame(1)
        (result,) = set_parameters(probe, {"gravity_source": "none"})
        assert result.successful
        samples(time.time_ns() + 100_000_000)
        time.sleep(0.25)
        frame(1)                                      # asked not to use it
        (result,) = set_parameters(probe, {"gravity_source": "compass"})
        assert not result.successful and "gravity_source" in result.reason
        assert last_stats(stats)["failed"] == 0 and node.poll() is None
    assert "none within 0.1 s before a frame's stamp" in live.out
