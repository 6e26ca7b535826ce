"""The node tracking instances live at 30 Hz: real node process, camera frames over DDS (one
ROS_DOMAIN_ID per test). Poses come for (nearly) every frame, not only for those the detector
got to; track ids hold across frames, scored against the ground-truth identities of a
rendered bag replayed by `mireg play`."""
import json
import time

import numpy as np
import pytest

from ros_testing import (CameraPublisher, live_node, poster_frame, poster_model, set_parameters, start, stop,
                         wait_until)


@pytest.fixture(scope="module")
def poster(tmp_path_factory):
    return poster_model(tmp_path_factory.mktemp("model") / "poster.npz")


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def send_at_30hz(camera, rgb, depth, K, count):
    start_time, sent = time.monotonic(), []
    for k in range(count):
        sent.append(camera.send(rgb, depth, K))
        time.sleep(max(0.0, start_time + (k + 1) / 30 - time.monotonic()))
    return sent


def test_tracked_poster_at_30hz_has_a_pose_per_frame_one_track_id_and_its_marker_ends_with_it(poster):
    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray

    with live_node(54, poster) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses", depth=200)
        details = probe.subscribe(String, "/instances/details", depth=200)
        markers = probe.subscribe(MarkerArray, "/instances/markers", depth=200)
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(proc=node), stop(node)
        assert probe.wait_for_publishers(["/instances/poses", "/instances/details", "/instances/markers"],
                                         proc=node), stop(node)
        rgb, depth, K = poster_frame()
        sent = send_at_30hz(camera, rgb, depth, K, 75)
        assert wait_until(lambda: poses and stamp_ns(poses[-1][1]) == sent[-1], 20, proc=node), stop(node)
        # A PoseArray for (nearly) every camera frame, in order.
        got = [stamp_ns(m) for _, m in poses]
        assert got == sorted(got) and len(got) >= 0.9 * len(sent), (len(got), len(sent))
        # Once the detector has confirmed the poster, it is in (nearly) every frame's poses.
        counts = [len(m.poses) for _, m in poses]
        first = counts.index(1)
        assert len(counts) - first >= 0.5 * len(sent), counts
        assert sum(c == 1 for c in counts[first:]) >= 0.9 * (len(counts) - first), counts
        assert wait_until(lambda: len(details) == len(poses) and len(markers) == len(poses), 10)
        tracked = [i for _, m in details for i in json.loads(m.data)["instances"]]
        assert {i["track_id"] for i in tracked} == {0}                        # one object, one id throughout
        assert {i["state"] for i in tracked} <= {"tentative", "confirmed"}    # a prediction (coasting) is not published
        info = json.loads(details[-1][1].data)
        detected, processed = info["counters"]["detected"], info["counters"]["processed"]
        # Frames the detector did not see are published from the tracks. How many there are
        # depends on the machine: a fast one detects this small poster in under a frame
        # interval, and then (nearly) every frame is a detection's.
        if detected < 0.8 * processed:      # observed: 54-70 of 75 detected; 65 had tracked ones, 70 none
            assert "tracking" in {i["source"] for i in tracked}, (detected, processed)
        ages = [i["age_s"] for i in tracked]
        assert ages == sorted(ages) and all(i["id"] == 0 and i["inliers"] >= 20 for i in tracked)
        assert detected <= processed
        assert {"tracking", "total"} <= set(info["timings_ms"]) and info["detection"]["stamp_ns"] in sent
        boxes = [mk for _, m in markers for mk in m.markers if mk.type == Marker.CUBE]
        assert boxes and {mk.id for mk in boxes} == {0}                        # marker id = track id

        # Tracking parameters: live ones apply, read-only and out-of-range ones are refused.
        (ok,) = set_parameters(probe, {"tracking.smoothing": 0.5})
        assert ok.successful
        (refused,) = set_parameters(probe, {"tracking.enabled": False})
        assert not refused.successful and "read-only" in refused.reason.lower()
        (refused,) = set_parameters(probe, {"tracking.coast_s": 100.0})
        assert not refused.successful and "coast_s" in refused.reason

        # The poster leaves the view: the track coasts, then ends, and its marker is deleted.
        n = len(markers)
        sent = send_at_30hz(camera, np.full_like(rgb, 90), np.full_like(depth, 1000), K, 75)
        assert wait_until(lambda: poses and stamp_ns(poses[-1][1]) == sent[-1], 20, proc=node), stop(node)
        assert poses[-1][1].poses == []
        assert wait_until(lambda: len(markers) == len(poses), 10)
        deleted = [mk for _, m in markers[n:] for mk in m.markers if mk.action == Marker.DELETE]
        assert {mk.id for mk in deleted} == {0}
    assert "parameters changed: tracking.smoothing=0.5" in live.out


def test_ids_hold_over_a_rendered_pan_played_at_30hz(object_model, tmp_path):
    """`mireg play` at the bag's own 30 Hz: the share of frames with poses, and identity
    (IDF1, switches) against the bag's ground truth, whose instances keep their index."""
    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String

    from multi_instance_reg.datasets.rgbd_bag import RGBDBag
    from multi_instance_reg.metrics import IdentityScore
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.synthetic.scene import generate_scene_bag
    from multi_instance_reg.tools.listen import pose_array_to_matrices
    from multi_instance_reg.tools.offline import estimates_in_object_frame, match_frame

    bag = tmp_path / "pan"
    generate_scene_bag(bag, instances=5, distractors=2, frames=90, seed=7, motion="pan")
    with live_node(55, object_model) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses", depth=200)
        details = probe.subscribe(String, "/instances/details", depth=200)
        assert probe.wait_for_publishers(["/instances/poses", "/instances/details"], proc=node), stop(node)
        play = start(["multi_instance_reg.tools.cli", "play", str(bag), "--quiet", "--wait-for",
                      "/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                      "/camera/camera/color/camera_info", "--wait-timeout", "120"], 55)
        assert play.wait(180) == 0, stop(play)
        with RGBDBag(bag) as reader:
            frames = list(reader)
        last = frames[-1].stamp_ns
        assert wait_until(lambda: poses and stamp_ns(poses[-1][1]) == last, 30, proc=node), stop(node)
        assert wait_until(lambda: len(details) == len(poses), 10)
    model = load_model(object_model)
    by_stamp = {stamp_ns(m): pose_array_to_matrices(m) for _, m in poses}
    tracks = {json.loads(m.data)["stamp_ns"]: [i["track_id"] for i in json.loads(m.data)["instances"]]
              for _, m in details}
    share = sum(f.stamp_ns in by_stamp for f in frames) / len(frames)
    assert share >= 0.9, (share, live.out[-2000:])
    identity = IdentityScore()
    for f in frames[30:]:   # from 1 s on: the detector has had time to find and confirm them
        est = by_stamp.get(f.stamp_ns, np.zeros((0, 4, 4)))
        score, hits = match_frame(f.gt_poses, estimates_in_object_frame(model, est), f.gt_visibility, 0.25)
        identity.add_frame([(g, tracks[f.stamp_ns][e]) for g, e in hits], score.n_gt, score.n_est)
    summary = identity.summary()
    print("live pan at 30 Hz: share with poses", round(share, 3), summary)
    assert summary["id_switches"] <= 1, summary
    assert summary["IDF1"] >= 0.75, summary
