"""Node + `mireg play` + `mireg listen` as three real processes on one DDS domain, over a
rendered scene bag with ground truth: the poses the node publishes are the offline pipeline's,
frame for frame, so the live MHF1 is the offline one."""
import json

import numpy as np

from ros_testing import Probe, output, start, start_logged, stop, wait_until

COLOUR, DEPTH, INFO = ("/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                       "/camera/camera/color/camera_info")


def test_live_replay_matches_offline_quality(scene_bag, object_model, tmp_path):
    from geometry_msgs.msg import PoseArray

    from multi_instance_reg.metrics import evaluate_scene, summarize
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.tools.listen import pose_array_to_matrices
    from multi_instance_reg.tools.offline import estimates_in_object_frame, replay

    model = load_model(object_model)
    offline = replay(scene_bag, model, PipelineConfig(), progress=False, min_visibility=0.25)  # as listen
    by_stamp = {f["stamp_ns"]: f for f in offline.frames}
    last_stamp = offline.frames[-1]["stamp_ns"]

    domain = 48
    # The per-detection path (tracking off): its poses are the offline pipeline's, frame for frame.
    node = start(["multi_instance_reg.ros.node", "--ros-args", "-p", f"model_path:={object_model}",
                  "-p", "tracking.enabled:=false"], domain)
    probe = listen = play = None
    try:
        probe = Probe(domain)
        poses = probe.subscribe(PoseArray, "/instances/poses")
        summary_path = tmp_path / "summary.json"
        listen = start_logged(["multi_instance_reg.tools.cli", "listen", "--ground-truth", str(scene_bag),
                               "--model", str(object_model), "--summary", str(summary_path),
                               "--wait-for-node", "60", "--idle-timeout", "3", "--timeout", "150"],
                              domain, tmp_path / "listen.log")
        assert wait_until(lambda: "listening" in output(listen), 90, proc=listen), output(listen)
        # The listener waits for the node; the probe must be matched too, or the first frame's
        # poses can reach the listener and not the probe (seen once in a fresh-clone run).
        assert probe.wait_for_publishers(["/instances/poses"], proc=node), stop(node)
        play = start(["multi_instance_reg.tools.cli", "play", str(scene_bag), "--rate", "0.25",
                      "--wait-for", COLOUR, DEPTH, INFO], domain)
        assert play.wait(120) == 0, stop(play)
        # The node always gets to the newest frame, however slow this machine is today.
        assert wait_until(lambda: any(stamp_ns(m) == last_stamp for _, m in poses), 60, proc=node), stop(node)
        assert listen.wait(60) == 0, stop(listen)
    finally:
        if probe is not None:
            probe.close()
        outputs = {name: stop(p) for name, p in (("play", play), ("listen", listen), ("node", node)) if p}
    summary = json.loads(summary_path.read_text())

    # Every frame was processed or counted as dropped (newest kept), none lost otherwise.
    processed = [stamp_ns(m) for _, m in poses]
    assert summary["frames"] == len(processed) >= 1, outputs
    assert summary["frames"] + summary["frames_dropped"] == len(offline.frames), summary
    assert summary["node_counters"]["bad"] == 0 and summary["node_counters"]["no_camera_info"] == 0
    # Each processed frame's poses are the offline pipeline's, in the colour image's frame...
    for _, msg in poses:
        expected = by_stamp[stamp_ns(msg)]
        assert msg.header.frame_id == expected["frame_id"]
        np.testing.assert_allclose(pose_array_to_matrices(msg),
                                   np.array([i["T"] for i in expected["instances"]]).reshape(-1, 4, 4), atol=1e-5)
    # ... so the live MHF1 (scored by the listener, a separate process) is the offline one.
    gt = {}
    for index, f in enumerate(offline.frames):
        gt[f["stamp_ns"]] = index
    offline_scores = []
    for _, msg in poses:
        score = offline.scores[gt[stamp_ns(msg)]]
        offline_scores.append(score)
    offline_mhf1 = round(100 * summarize(offline_scores)["MHF1"], 1)
    assert summary["frames_scored"] == len(processed)
    assert summary["MHF1"] == offline_mhf1, (summary, offline_mhf1)
    assert summary["MHF1"] > 50, summary  # a real answer, not two empty ones agreeing
    assert "MHF1" in outputs["listen"]


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
