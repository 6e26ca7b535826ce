"""Helpers for the ROS integration tests: isolated DDS domains, real processes, a probe node.

Every test gets a ROS_DOMAIN_ID of its own and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so
tests (and other people's ROS processes on the machine) never see each other.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from multi_instance_reg.ros.background import BackgroundNode

REPO = Path(__file__).resolve().parents[1]


def ros_env(domain_id: int) -> dict:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def start(args: list[str], domain_id: int, **kwargs) -> subprocess.Popen:
    """A Python module as a real process in the test's domain (output captured)."""
    return subprocess.Popen([sys.executable, "-m", *args], env=ros_env(domain_id), cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)


def start_logged(args: list[str], domain_id: int, log: Path) -> subprocess.Popen:
    """Like start(), with the output going to ``log`` (readable while it runs)."""
    proc = subprocess.Popen([sys.executable, "-m", *args], env=ros_env(domain_id), cwd=REPO,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT, text=True)
    proc.log = Path(log)
    return proc


def output(proc: subprocess.Popen) -> str:
    return proc.log.read_text() if hasattr(proc, "log") else ""


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> str:
    """Terminate (SIGTERM, then SIGKILL) and return everything it printed."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if hasattr(proc, "log"):
        return output(proc)
    return proc.stdout.read() if proc.stdout else ""


class Probe(BackgroundNode):
    """An rclpy node in this test process, on its own context and domain, spun in a thread."""

    def __init__(self, domain_id: int, name: str = "test_probe"):
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        super().__init__(name, domain_id)
        self.received: dict[str, list] = {}
        self._subscriptions: list = []
        self._lock = threading.Lock()
        self.start()

    def subscribe(self, msg_type, topic: str, depth: int = 50) -> list:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        box = self.received.setdefault(topic, [])

        def keep(msg):
            with self._lock:
                box.append((time.monotonic(), msg))
        self._subscriptions.append(self.node.create_subscription(msg_type, topic, keep, qos))
        return box

    def wait_for_publishers(self, topics, timeout: float = 30.0, proc=None) -> bool:
        """Until this probe's subscriptions to ``topics`` are matched with a publisher: what a
        node publishes before that is lost to them (seen in full-suite runs: a third of a
        30 Hz stream missing at its start)."""
        subs = [s for s in self._subscriptions if s.topic_name in set(topics)]
        ok = wait_until(lambda: all(s.get_publisher_count() > 0 for s in subs), timeout, proc=proc)
        time.sleep(0.3)
        return ok

    def publisher(self, msg_type, topic: str, depth: int = 10):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        return self.node.create_publisher(msg_type, topic, qos)


def start_node(domain_id, model, *params):
    """The node with ``model`` (a file: model_path; a list of files: model_paths)."""
    models = (["-p", f"model_paths:=[{', '.join(map(str, model))}]"] if isinstance(model, (list, tuple))
              else ["-p", f"model_path:={model}"])
    args = ["multi_instance_reg.ros.node", "--ros-args", *models, "-p", "stats_log_period_s:=0.3"]
    for p in params:
        args += ["-p", p]
    return start(args, domain_id)


class live_node:
    """``with live_node(domain_id, model, *params) as live``: the node as a process
    (``live.proc``) and a probe on its domain (``live.probe``); both are closed when the block
    ends, and ``live.out`` then holds the node's log."""

    def __init__(self, domain_id, model, *params):
        self.proc = start_node(domain_id, model, *params)
        self.probe = Probe(domain_id)
        self.out = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.probe.close()
        self.out = stop(self.proc)
        return False


def wait_until(predicate, timeout: float, interval: float = 0.05, proc: subprocess.Popen | None = None) -> bool:
    """Poll ``predicate`` until it holds or ``timeout`` passes (or ``proc`` exits)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        if proc is not None and proc.poll() is not None:
            return bool(predicate())
        time.sleep(interval)
    return bool(predicate())


# ---------------------------------------------------------------------------------------
# A small, fast stand-in scene for the node's plumbing tests: a textured poster (an
# astronaut photograph that ships with scikit-image) 0.6 m in front of the camera, on a
# background 1 m away. The model is its SIFT keypoints lifted with the same intrinsics, so
# the real pipeline finds exactly one instance, at the identity rotation, 0.6 m ahead.

D455_K = ((379.05, 0.0, 321.89), (0.0, 378.68, 238.97), (0.0, 0.0, 1.0))
POSTER_Z = 0.6


# Textures of the posters (scikit-image's sample photographs), by model name.
POSTER_TEXTURES = {"poster": ("astronaut", 100, 150), "cat": ("chelsea", 50, 100)}


def poster_texture(name: str = "poster"):
    from skimage import data

    image, top, left = POSTER_TEXTURES[name]
    return getattr(data, image)()[top:top + 200, left:left + 200].copy()


def poster_model(path, name: str = "poster") -> Path:
    """The model of a poster (``name``: one of POSTER_TEXTURES), named ``name``."""
    import numpy as np

    from multi_instance_reg.frontends.sift.features import SiftSettings, extract_sift
    from multi_instance_reg.models.model import ObjectModel, save_model

    K = np.array(D455_K)
    uv, desc = extract_sift(poster_texture(name), SiftSettings())
    # Model frame: the poster's centre, axes along the camera's.
    xyz = np.c_[(uv[:, 0] - 99.5) * POSTER_Z / K[0, 0], (uv[:, 1] - 99.5) * POSTER_Z / K[1, 1], np.zeros(len(uv))]
    extent = np.array([200 * POSTER_Z / K[0, 0], 200 * POSTER_Z / K[1, 1], 0.002])
    model = ObjectModel(xyz.astype(np.float32), desc, xyz.astype(np.float32), extent, np.eye(4), np.eye(4), name)
    return save_model(model, Path(path))


def poster_frame(posters: dict | None = None):
    """(rgb (480, 640, 3) uint8, depth (480, 640) uint16 mm, K (3, 3)). ``posters``: {name:
    horizontal shift of its centre in pixels}; by default the one "poster", its centre on the
    optical axis's pixel (cx, cy) rounded, so its pose is ~ (0, 0, POSTER_Z)."""
    import numpy as np

    rgb = np.full((480, 640, 3), 90, np.uint8)
    depth = np.full((480, 640), 1000, np.uint16)
    for name, shift in (posters or {"poster": 0}).items():
        top, left = 239 - 100, 322 - 100 + shift
        rgb[top:top + 200, left:left + 200] = poster_texture(name)
        depth[top:top + 200, left:left + 200] = int(POSTER_Z * 1000)
    return rgb, depth, np.array(D455_K)


class CameraPublisher:
    """Publishes colour + aligned depth + camera_info like realsense-ros, from a Probe
    (under ``namespace``, e.g. "/left", for a node started with ``-r __ns:=/left``)."""

    def __init__(self, probe: Probe, namespace: str = ""):
        from sensor_msgs.msg import CameraInfo, Image

        self.probe = probe
        prefix = namespace.rstrip("/")
        self.colour = probe.publisher(Image, f"{prefix}/camera/camera/color/image_raw")
        self.depth = probe.publisher(Image, f"{prefix}/camera/camera/aligned_depth_to_color/image_raw")
        self.info = probe.publisher(CameraInfo, f"{prefix}/camera/camera/color/camera_info")

    def wait_for_subscribers(self, timeout: float = 30.0, proc=None) -> bool:
        pubs = (self.colour, self.depth, self.info)
        ok = wait_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), timeout, proc=proc)
        time.sleep(0.3)
        return ok

    @staticmethod
    def image(arr, encoding: str, stamp=None, overrides: dict | None = None):
        from sensor_msgs.msg import Image

        from multi_instance_reg.messages import array_to_image_fields

        fields = array_to_image_fields(arr, encoding)
        fields["data"] = fields["data"].tobytes()
        fields.update(overrides or {})
        msg = Image(**fields)
        if stamp is not None:
            msg.header.stamp = stamp
        msg.header.frame_id = "camera_color_optical_frame"
        return msg

    def send(self, rgb, depth, K, colour_msg=None, depth_msg=None, with_info: bool = True):
        """Publish one frame stamped now; returns its stamp in ns."""
        from builtin_interfaces.msg import Time
        from sensor_msgs.msg import CameraInfo

        ns = time.time_ns()
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if with_info:
            info = CameraInfo(width=rgb.shape[1], height=rgb.shape[0], k=[float(v) for v in K.reshape(-1)],
                              distortion_model="plumb_bob", d=[0.0] * 5)
            info.header.stamp = stamp
            info.header.frame_id = "camera_color_optical_frame"
            self.info.publish(info)
        if colour_msg is None:
            colour_msg = self.image(rgb, "rgb8", stamp)
        if depth_msg is None:
            depth_msg = self.image(depth, "16UC1", stamp)
        colour_msg.header.stamp = stamp
        depth_msg.header.stamp = stamp
        self.colour.publish(colour_msg)
        self.depth.publish(depth_msg)
        return ns


def set_parameters(probe: Probe, values: dict, node: str = "/instance_registration", timeout: float = 10.0):
    """Call the node's SetParameters service (what `ros2 param set` does); returns the results."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    client = probe.node.create_client(SetParameters, f"{node}/set_parameters")
    try:
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"{node}/set_parameters is not available")
        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        future = client.call_async(request)
        if not wait_until(future.done, timeout):
            raise TimeoutError("SetParameters did not answer")
        return future.result().results
    finally:
        probe.node.destroy_client(client)
