"""The node reading depth recorded unaligned (realsense-ros without align_depth.enable), played
from a rendered bag by `mireg play`: it registers the depth with the extrinsics it receives
(latched) and publishes the offline pipeline's poses on the same bag, frame for frame."""
import numpy as np

from ros_testing import Probe, start, stop, wait_until

COLOUR, INFO = "/camera/camera/color/image_raw", "/camera/camera/color/camera_info"
DEPTH, DEPTH_INFO = "/camera/camera/depth/image_rect_raw", "/camera/camera/depth/camera_info"
EXTRINSICS = "/camera/camera/extrinsics/depth_to_color"


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_node_registers_unaligned_depth_as_offline_does(object_model, tmp_path):
    from geometry_msgs.msg import PoseArray

    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.synthetic.scene import generate_scene_bag
    from multi_instance_reg.tools.listen import pose_array_to_matrices
    from multi_instance_reg.tools.offline import replay

    bag = tmp_path / "unaligned"
    generate_scene_bag(bag, frames=2, seed=3, recording="unaligned", imu=False)
    offline = replay(bag, load_model(object_model), PipelineConfig(), progress=False)
    by_stamp = {f["stamp_ns"]: f for f in offline.frames}
    assert sum(len(f["instances"]) for f in offline.frames) >= 4

    domain = 210
    # depth_registration auto (the default): only the unaligned depth arrives, so it is read.
    node = start(["multi_instance_reg.ros.node", "--ros-args", "-p", f"model_path:={object_model}",
                  "-p", "tracking.enabled:=false"], domain)
    probe = play = None
    try:
        probe = Probe(domain)
        poses = probe.subscribe(PoseArray, "/instances/poses")
        assert probe.wait_for_publishers(["/instances/poses"], proc=node), stop(node)
        play = start(["multi_instance_reg.tools.cli", "play", str(bag), "--rate", "0.1",
                      "--wait-for", COLOUR, INFO, DEPTH, DEPTH_INFO, EXTRINSICS], domain)
        assert play.wait(120) == 0, stop(play)
        last = offline.frames[-1]["stamp_ns"]
        assert wait_until(lambda: any(stamp_ns(m) == last for _, m in poses), 60, proc=node), stop(node)
    finally:
        if probe is not None:
            probe.close()
        outputs = {name: stop(p) for name, p in (("play", play), ("node", node)) if p}
    assert "skipping" not in outputs["node"], outputs["node"]   # no frame waited for the extrinsics
    assert poses
    for _, msg in poses:
        expected = np.array([i["T"] for i in by_stamp[stamp_ns(msg)]["instances"]]).reshape(-1, 4, 4)
        np.testing.assert_allclose(pose_array_to_matrices(msg), expected, atol=1e-5)
