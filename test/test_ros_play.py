"""`mireg play` as a real process over DDS: every message, unchanged, with the bag's timing."""
import subprocess
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from multi_instance_reg.messages import array_to_image_fields, colour_to_rgb
from ros_testing import Probe, ros_env, start, stop, wait_until

# Its tests share ROS_DOMAIN_ID 41: one pytest-xdist worker runs them one after the other.
pytestmark = pytest.mark.xdist_group("ros_domain_41")

TOPIC_IMAGE = "/camera/camera/color/image_raw"
TOPIC_TEXT = "/ground_truth/object"
PERIOD_NS = 100_000_000  # 10 Hz: timing differences are easy to see


def write_bag(path, frames=8):
    """A small bag: rgb8 images whose pixels encode the frame index, and one String."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    Image, Header, Time = ts.types["sensor_msgs/msg/Image"], ts.types["std_msgs/msg/Header"], \
        ts.types["builtin_interfaces/msg/Time"]
    String = ts.types["std_msgs/msg/String"]
    t0 = 1_700_000_000 * 10**9
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        img_conn = writer.add_connection(TOPIC_IMAGE, "sensor_msgs/msg/Image", typestore=ts)
        txt_conn = writer.add_connection(TOPIC_TEXT, "std_msgs/msg/String", typestore=ts)
        writer.write(txt_conn, t0, ts.serialize_cdr(String(data='{"name": "box"}'), "std_msgs/msg/String"))
        for k in range(frames):
            stamp = t0 + k * PERIOD_NS
            pixels = np.full((24, 32, 3), k, np.uint8)
            msg = Image(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                                      frame_id="camera_color_optical_frame"),
                        **array_to_image_fields(pixels, "rgb8"))
            writer.write(img_conn, stamp, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    return t0


@pytest.fixture()
def probe_41():
    probe = Probe(41)
    yield probe
    probe.close()


@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_play_publishes_every_message_unchanged_with_scaled_timing(tmp_path, probe_41, rate):
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    t0 = write_bag(tmp_path / "bag")
    images = probe_41.subscribe(Image, TOPIC_IMAGE)
    texts = probe_41.subscribe(String, TOPIC_TEXT)
    proc = start(["multi_instance_reg.tools.cli", "play", str(tmp_path / "bag"), "--rate", str(rate),
                  "--wait-for", TOPIC_IMAGE, TOPIC_TEXT], 41)
    try:
        assert proc.wait(30) == 0
        assert wait_until(lambda: len(images) == 8, 5)
    finally:
        out = stop(proc)
    assert "published 9 messages" in out
    assert [m.data for _, m in texts] == ['{"name": "box"}']
    for k, (_, msg) in enumerate(images):
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert stamp == t0 + k * PERIOD_NS  # nothing rewritten
        assert msg.header.frame_id == "camera_color_optical_frame"
        assert (colour_to_rgb(msg) == k).all()
    arrivals = np.array([t for t, _ in images])
    gaps = np.diff(arrivals)
    expected = PERIOD_NS / 1e9 / rate
    assert abs(np.median(gaps) - expected) < 0.3 * expected, gaps


def test_play_topics_filter(tmp_path, probe_41):
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    write_bag(tmp_path / "bag", frames=3)
    images = probe_41.subscribe(Image, TOPIC_IMAGE)
    texts = probe_41.subscribe(String, TOPIC_TEXT)
    proc = start(["multi_instance_reg.tools.cli", "play", str(tmp_path / "bag"), "--rate", "5",
                  "--topics", TOPIC_IMAGE, "--wait-for", TOPIC_IMAGE], 41)
    try:
        assert proc.wait(30) == 0
        assert wait_until(lambda: len(images) == 3, 5)
    finally:
        stop(proc)
    assert texts == []


def test_play_into_a_namespace(tmp_path, probe_41):
    """--namespace left: the bag's /camera/... goes out as /left/camera/... (for a node started
    with -r __ns:=/left), and nothing in the root namespace."""
    from sensor_msgs.msg import Image

    write_bag(tmp_path / "bag", frames=3)
    moved = probe_41.subscribe(Image, "/left" + TOPIC_IMAGE)
    root = probe_41.subscribe(Image, TOPIC_IMAGE)
    proc = start(["multi_instance_reg.tools.cli", "play", str(tmp_path / "bag"), "--rate", "5", "--namespace", "left",
                  "--topics", TOPIC_IMAGE, "--wait-for", TOPIC_IMAGE], 41)
    try:
        assert proc.wait(30) == 0
        assert wait_until(lambda: len(moved) == 3, 5)
    finally:
        stop(proc)
    assert root == []


def test_play_bad_input_is_one_clear_line(tmp_path):
    write_bag(tmp_path / "bag", frames=1)
    cases = [([str(tmp_path / "nope")], "does not exist"),
             ([str(tmp_path / "bag"), "--topics", "/other"], "has no topic /other"),
             ([str(tmp_path / "bag"), "--rate", "0"], "--rate must be positive"),
             ([str(tmp_path / "bag"), "--namespace", "2nd camera"], "not a valid ROS namespace")]
    for args, message in cases:
        done = subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", "play", *args],
                              env=ros_env(42), capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, done
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mireg play: error:") and message in lines[0], done.stderr
