"""Node + `mireg play` + `mireg listen` as three real processes on one DDS domain, over a
rendered scene bag with ground truth: the poses the node publishes are the offline pipeline's,
frame for frame, so the live MHF1 is the offline one."""
import json

import numpy as np

from ros_testing import Probe, start, stop, wait_until

COLOUR, DEPTH, INFO = ("/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                       "/camera/camera/color/camera_info")


def test_live_replay_matches_offline_quality(scene_bag, object_model, tmp_path):
    from geometry_msgs.msg import PoseArray

    from multi_instance_reg.metrics import summarize
    from multi_instance_reg.rgbd.model import load_model
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.tools.listen import pose_array_to_matrices
    from multi_instance_reg.tools.offline import replay

    model = load_model(object_model)
    offline = replay(scene_bag, model, PipelineConfig(), progress=False)
    n_frames = len(offline.frames)

    domain = 48
    node = start(["multi_instance_reg.ros.node", "--ros-args", "-p", f"model_path:={object_model}"], domain)
    probe = listen = play = None
    try:
        probe = Probe(domain)
        poses = probe.subscribe(PoseArray, "/instances/poses")
        summary_path = tmp_path / "summary.json"
        listen = start(["multi_instance_reg.tools.cli", "listen", "--ground-truth", str(scene_bag),
                        "--model", str(object_model), "--summary", str(summary_path), "--frames", str(n_frames),
                        "--wait-for-node", "60", "--timeout", "120"], domain)
        # Slow enough that the node processes every frame (the pipeline takes ~0.1-0.3 s here).
        play = start(["multi_instance_reg.tools.cli", "play", str(scene_bag), "--rate", "0.1",
                      "--wait-for", COLOUR, DEPTH, INFO], domain)
        assert play.wait(120) == 0, stop(play)
        assert listen.wait(60) == 0, stop(listen)
        assert wait_until(lambda: len(poses) == n_frames, 10)
    finally:
        if probe is not None:
            probe.close()
        outputs = {name: stop(p) for name, p in (("play", play), ("listen", listen), ("node", node)) if p}
    summary = json.loads(summary_path.read_text())

    # Every frame processed, none dropped, and each frame's poses are the offline ones.
    assert summary["frames"] == n_frames and summary["frames_dropped"] == 0, outputs
    by_stamp = {f["stamp_ns"]: f for f in offline.frames}
    for _, msg in poses:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        expected = np.array([i["T"] for i in by_stamp[stamp]["instances"]]).reshape(-1, 4, 4)
        assert msg.header.frame_id == by_stamp[stamp]["frame_id"]
        np.testing.assert_allclose(pose_array_to_matrices(msg), expected, atol=1e-5)
    # ... so the live MHF1 (scored by the listener, a separate process) is the offline MHF1.
    offline_mhf1 = round(100 * summarize(offline.scores)["MHF1"], 1)
    assert summary["frames_scored"] == n_frames
    assert summary["MHF1"] == offline_mhf1, (summary, offline_mhf1)
    assert summary["MHF1"] > 50  # and that quality is real, not two empty answers agreeing
    assert "MHF1" in outputs["listen"]
