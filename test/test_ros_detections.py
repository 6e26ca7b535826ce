"""vision_msgs output and namespaces, from the outside: the node as a real process over DDS, the
subscribers in this test process (one ROS_DOMAIN_ID per test).

vision_msgs comes from ``make install`` (interfaces/install_vision_msgs.py) or the user's ROS.
"""
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from multi_instance_reg.ros.detections import ObjectClass, detection_array, label_info
from ros_testing import (POSTER_Z, REPO, CameraPublisher, Probe, live_node, poster_frame, poster_model, ros_env,
                         start, stop, wait_until)
from test_ros_node import UNTRACKED, stamp_ns

BOX_CENTRE = np.array([0.01, -0.02, 0.005])   # model frame: a box not centred on the model origin


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return poster_model(tmp_path_factory.mktemp("model") / "poster.npz")


@pytest.fixture(scope="module")
def unnamed_model(tmp_path_factory):
    """The poster model without a stored name and with an off-centre box."""
    from multi_instance_reg.models.model import load_model, save_model

    folder = tmp_path_factory.mktemp("unnamed")
    m = load_model(poster_model(folder / "poster.npz"))
    m.name, m.box_centre = "", BOX_CENTRE
    return save_model(m, folder / "snack_bar.npz")


def transient_local_subscription(probe, msg_type, topic):
    """A late joiner's subscription that asks for what was published before it existed."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    box = []
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    probe.node.create_subscription(msg_type, topic, box.append, qos)
    return box


def xyz(point):
    return np.array([point.x, point.y, point.z])


def test_detections_from_the_node_reach_another_process_and_match_the_poses(unnamed_model):
    import json

    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String
    from vision_msgs.msg import Detection3DArray, LabelInfo

    from multi_instance_reg.models.model import load_model

    extent = load_model(unnamed_model).extent
    with live_node(93, unnamed_model) as live:
        node, probe = live.proc, live.probe
        poses = probe.subscribe(PoseArray, "/instances/poses")
        detections = probe.subscribe(Detection3DArray, "/instances/detections")
        details = probe.subscribe(String, "/instances/details")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(60, proc=node), stop(node)
        assert probe.wait_for_publishers(["/instances/poses", "/instances/detections", "/instances/details"],
                                         proc=node), stop(node)
        rgb, depth, K = poster_frame()
        sent = []
        # Frame by frame until the tracker has confirmed the poster and published it 3 times.
        # By time, not by a count of frames: in a fresh checkout the detector's first frame
        # compiles kernels for tens of seconds while every frame's (empty) poses go out at once.
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and sum(len(m.poses) == 1 for _, m in poses) < 3:
            time.sleep(0.05)
            sent.append(camera.send(rgb, depth, K))
            assert wait_until(lambda: len(detections) == len(sent) and len(details) == len(sent)
                              and len(poses) == len(sent), 15, proc=node), stop(node)
        found = 0
        for (_, array), (_, pose_array), (_, detail), stamp in zip(detections, poses, details, sent):
            assert stamp_ns(array) == stamp and array.header.frame_id == "camera_color_optical_frame"
            assert len(array.detections) == len(pose_array.poses)   # the same instances, in the same order
            if not array.detections:
                continue
            found += 1
            (det,) = array.detections
            (result,) = det.results
            (instance,) = json.loads(detail.data)["instances"]
            # No stored name: the model file's stem.
            assert result.hypothesis.class_id == "snack_bar"
            assert result.hypothesis.score == pytest.approx(instance["score"], abs=1e-4)
            # The pose is the PoseArray's, exactly.
            (pose,) = pose_array.poses
            assert result.pose.pose == pose
            assert det.header == array.header
            assert det.id == str(instance["track_id"])   # the identity across messages
            # The box: the model's extent, centred on the box centre moved by the pose.
            assert np.allclose(xyz(det.bbox.size), extent)
            assert abs(pose.orientation.w) > 0.999
            assert np.allclose(xyz(det.bbox.center.position), xyz(pose.position) + BOX_CENTRE, atol=2e-3)
            assert det.bbox.center.orientation == pose.orientation
            assert np.allclose(xyz(pose.position), [0, 0, POSTER_Z], atol=0.01)
        assert found >= 3

        # A subscriber joining now still gets the class names (transient local).
        labels = transient_local_subscription(probe, LabelInfo, "/instances/label_info")
        assert wait_until(lambda: len(labels) == 1, 10), "LabelInfo did not reach a late-joining subscriber"
        assert [(c.class_id, c.class_name) for c in labels[0].class_map] == [(0, "snack_bar")]
        # In the root namespace every name is what it was before topics became relative.
        published = {name for name, _ in probe.node.get_publisher_names_and_types_by_node("instance_registration", "/")}
        subscribed = {name for name, _ in probe.node.get_subscriber_names_and_types_by_node("instance_registration", "/")}
    assert {"/instances/poses", "/instances/markers", "/instances/details", "/instances/debug_image",
            "/instances/detections", "/instances/label_info", "/instance_registration/stats"} <= published
    assert {"/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
            "/camera/camera/color/camera_info"} <= subscribed
    assert node.returncode == 0, live.out


def get_parameter(probe, node: str, name: str, timeout: float = 10.0):
    """The node's value of one parameter through its GetParameters service (`ros2 param get`)."""
    from rcl_interfaces.srv import GetParameters
    from rclpy.parameter import parameter_value_to_python

    client = probe.node.create_client(GetParameters, f"{node}/get_parameters")
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"{node}/get_parameters is not available"
        future = client.call_async(GetParameters.Request(names=[name]))
        assert wait_until(future.done, timeout)
        return parameter_value_to_python(future.result().values[0])
    finally:
        probe.node.destroy_client(client)


def test_two_nodes_in_two_namespaces_each_follow_their_own_camera(model, tmp_path):
    """One node per camera: -r __ns:=/left and /right with one parameter file, each fed its own
    stream; mireg listen finds the right one with --namespace."""
    from geometry_msgs.msg import PoseArray
    from vision_msgs.msg import Detection3DArray

    domain = 94
    params = tmp_path / "params.yaml"
    text = (REPO / "config" / "params.yaml").read_text()
    assert "    sync_slop_s: 0.02\n" in text
    params.write_text(text.replace("    sync_slop_s: 0.02\n", "    sync_slop_s: 0.031\n"))
    # Untracked: every frame's poses come from the detector, one instance each.
    nodes = {ns: start(["multi_instance_reg.ros.node", "--ros-args", "-r", f"__ns:={ns}",
                        "--params-file", str(params), "-p", f"model_path:={model}", "-p", UNTRACKED], domain)
             for ns in ("/left", "/right")}
    probe = Probe(domain)
    listen = None
    try:
        poses = {ns: probe.subscribe(PoseArray, f"{ns}/instances/poses") for ns in nodes}
        detections = {ns: probe.subscribe(Detection3DArray, f"{ns}/instances/detections") for ns in nodes}
        root_poses = probe.subscribe(PoseArray, "/instances/poses")
        cameras = {ns: CameraPublisher(probe, ns) for ns in nodes}
        for ns, camera in cameras.items():
            assert camera.wait_for_subscribers(60, proc=nodes[ns]), stop(nodes[ns])
        listen = start(["multi_instance_reg.tools.cli", "listen", "--namespace", "right", "--frames", "2",
                        "--wait-for-node", "60", "--timeout", "120"], domain)
        rgb, depth, K = poster_frame()
        # The right camera sees the poster 60 px further right: each node's pose says which stream it read.
        shift = 60
        streams = {"/left": (rgb, depth, 0.0),
                   "/right": (np.roll(rgb, shift, axis=1), np.roll(depth, shift, axis=1), shift * POSTER_Z / K[0, 0])}
        for _ in range(2):
            for ns, camera in cameras.items():
                n = len(poses[ns])
                camera.send(streams[ns][0], streams[ns][1], K)
                assert wait_until(lambda: len(poses[ns]) > n, 15, proc=nodes[ns]), stop(nodes[ns])
        for ns in nodes:
            assert wait_until(lambda: len(detections[ns]) == 2, 10)
            for _, msg in poses[ns]:
                (pose,) = msg.poses
                assert pose.position.x == pytest.approx(streams[ns][2], abs=0.01), (ns, pose.position)
                assert pose.position.z == pytest.approx(POSTER_Z, abs=0.01), (ns, pose.position)
        assert root_poses == []   # nothing left in the root namespace
        # mireg listen --namespace right hears the right node: more right frames until it has two
        # (it may have joined after the first ones; discovery is slow on a busy machine).
        for _ in range(30):
            if listen.poll() is not None:
                break
            n = len(poses["/right"])
            cameras["/right"].send(*streams["/right"][:2], K)
            assert wait_until(lambda: len(poses["/right"]) > n, 15, proc=nodes["/right"]), stop(nodes["/right"])
            wait_until(lambda: listen.poll() is not None, 1.0)
        assert listen.wait(10) == 0
        heard = stop(listen)
        assert "frames received: 2" in heard, heard
        # The parameter file reaches a namespaced node too (it names the node /**/instance_registration).
        for ns, proc in nodes.items():
            assert get_parameter(probe, f"{ns}/instance_registration", "sync_slop_s") == pytest.approx(0.031)
            assert proc.poll() is None, stop(proc)
    finally:
        probe.close()
        outs = {ns: stop(proc) for ns, proc in nodes.items()}
        if listen is not None:
            stop(listen)
    for ns, out in outs.items():
        assert f"listening on {ns}/camera/camera/color/image_raw" in out, out


def run_without_detections(env, domain: int, model) -> str:
    """The node in ``env``: it must publish poses but no detections; returns its output."""
    from geometry_msgs.msg import PoseArray

    proc = subprocess.Popen([sys.executable, "-m", "multi_instance_reg.ros.node", "--ros-args",
                             "-p", f"model_path:={model}", "-p", UNTRACKED], env=env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    probe = Probe(domain)
    try:
        poses = probe.subscribe(PoseArray, "/instances/poses")
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(60, proc=proc), stop(proc)
        rgb, depth, K = poster_frame()
        for k in range(2):
            camera.send(rgb, depth, K)
            assert wait_until(lambda: len(poses) == k + 1, 15, proc=proc), stop(proc)
        assert len(poses[-1][1].poses) == 1
        assert probe.node.count_publishers("/instances/detections") == 0
    finally:
        probe.close()
        out = stop(proc)
    assert "Traceback" not in out, out
    return out


def test_without_vision_msgs_the_node_runs_and_says_once_why_detections_are_off(tmp_path, model):
    # A vision_msgs that fails to import, first on the path: as on a machine without it.
    (tmp_path / "vision_msgs").mkdir()
    (tmp_path / "vision_msgs" / "__init__.py").write_text("raise ImportError('hidden by the test')\n")
    env = ros_env(95)
    env["PYTHONPATH"] = str(tmp_path) + os.pathsep + env["PYTHONPATH"]
    out = run_without_detections(env, 95, model)
    assert out.count("instances/detections is off: vision_msgs is not installed (hidden by the test)") == 1, out


def test_when_vision_msgs_type_support_cannot_load_the_node_runs_and_says_once_why(tmp_path, model):
    """vision_msgs' Python package imports but its C libraries are not found: the node started
    from a program whose LD_LIBRARY_PATH names another ROS's libraries (here: this venv's without
    vision_msgs), which the ROS wheels' bootstrap then leaves as it is."""
    other_ros = tmp_path / "other_ros_lib"
    other_ros.mkdir()
    venv_lib = Path(sys.prefix) / "lib"
    for lib in venv_lib.glob("lib*.so*"):
        if not lib.name.startswith("libvision_msgs"):
            (other_ros / lib.name).symlink_to(lib)
    env = ros_env(96)
    env["LD_LIBRARY_PATH"] = os.pathsep.join(str(other_ros) if part == str(venv_lib) else part
                                             for part in env.get("LD_LIBRARY_PATH", "").split(os.pathsep))
    env["_ROS_WHEELS_BOOTSTRAP_COMPLETE"] = "1"
    out = run_without_detections(env, 96, model)
    lines = [line for line in out.splitlines() if "instances/detections is off" in line]
    assert len(lines) == 1 and "type support" in lines[0] and "LD_LIBRARY_PATH" in lines[0], out


# ---- the message contents without DDS --------------------------------------------------------

@dataclass
class _Instance:
    id: int
    T: np.ndarray
    inliers: int
    score: float


@dataclass
class _Tracked(_Instance):
    track_id: int
    object: str


def test_detection_array_names_boxes_and_track_ids():
    from std_msgs.msg import Header

    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # 90 deg about z
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.1, 0.2, 0.7]
    objects = {"bar": ObjectClass("bar", np.array([0.02, 0.0, 0.0]), np.array([0.1, 0.04, 0.03])),
               "can": ObjectClass("can", np.zeros(3), np.array([0.066, 0.066, 0.12]))}
    header = Header(frame_id="cam")
    header.stamp.sec = 12
    msg = detection_array([_Instance(0, T, 30, 0.9), _Tracked(1, T, 20, 0.5, track_id=7, object="can")],
                          header, objects)
    assert msg.header == header and len(msg.detections) == 2
    plain, tracked = msg.detections
    assert plain.results[0].hypothesis.class_id == "bar" and plain.id == ""
    assert plain.results[0].hypothesis.score == pytest.approx(0.9)
    # The box centre (0.02, 0, 0) in the model frame, turned by 90 deg about z: (0, 0.02, 0) added.
    assert np.allclose(xyz(plain.bbox.center.position), [0.1, 0.22, 0.7])
    assert np.allclose(xyz(plain.bbox.size), [0.1, 0.04, 0.03])
    assert np.allclose(xyz(plain.results[0].pose.pose.position), [0.1, 0.2, 0.7])
    assert tracked.results[0].hypothesis.class_id == "can" and tracked.id == "7"
    assert np.allclose(xyz(tracked.bbox.size), [0.066, 0.066, 0.12])
    labels = label_info(["bar", "can"])
    assert [(c.class_id, c.class_name) for c in labels.class_map] == [(0, "bar"), (1, "can")]


def test_object_class_is_the_stored_name_else_the_file_stem(tmp_path):
    from multi_instance_reg.models.model import load_model

    named = load_model(poster_model(tmp_path / "whatever.npz"))
    assert ObjectClass.of_model(named, tmp_path / "whatever.npz").name == "poster"
    named.name = ""
    kind = ObjectClass.of_model(named, Path("models/snack_bar.npz"))
    assert kind.name == "snack_bar" and np.allclose(kind.box_size, named.extent)
