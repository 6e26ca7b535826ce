"""Starting and stopping the node as a person does, from the outside: Ctrl-C in a terminal (SIGINT to
the whole process group, the detector process included), a signal while the node is still
starting, SIGKILL of the node (its detector left behind), and what the node says about input
that cannot work (an unknown parameter, colour and depth that never pair, a camera_info
OpenCV cannot use). Real processes, one ROS_DOMAIN_ID per test.
"""
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from ros_testing import (CameraPublisher, Probe, output, poster_frame, poster_model, start, start_logged, stop,
                         wait_until)
from test_ros_node import UNTRACKED

# What a clean stop never prints (the detector's KeyboardInterrupt, rcl's error for a publisher
# made on a context already shut down, the orphan's ConnectionResetError, a detector restart).
NOISE = ("Traceback", "KeyboardInterrupt", "RCLError", "ConnectionResetError", "BrokenPipeError", "restarted it",
         "the pipeline failed")


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return poster_model(tmp_path_factory.mktemp("model") / "poster.npz")


def start_in_group(domain_id, model, *params):
    """The node as the leader of a process group of its own, as a shell starts a command (its
    detector process joins the group)."""
    args = ["multi_instance_reg.ros.node", "--ros-args", "-p", f"model_path:={model}"]
    for p in params:
        args += ["-p", p]
    return start(args, domain_id, start_new_session=True)


def group_members(pgid: int) -> list[str]:
    """The command lines of the group's processes still running (zombies, which no init may
    reap here, aside)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) == pgid and fields[0] != "Z":   # state, ppid, pgrp
                members.append((stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()[:200])
        except OSError:
            continue
    return members


def group_alive(pgid: int) -> bool:
    """Whether a process of the group runs on after a moment (one closing its output is
    still exiting)."""
    return not wait_until(lambda: not group_members(pgid), 3.0)


def read_to_end(proc, timeout: float) -> str:
    """Everything the node and any process that inherited its output printed, once all of them
    closed it (so a detector left running past ``timeout`` fails the test)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        raise AssertionError(f"a process of the node's group was still running {timeout:g} s after the signal:\n{out}")
    return out


def kill_group(proc) -> None:
    """Whatever of the node's group a failed test left running."""
    if group_alive(proc.pid):
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def assert_quiet(out: str) -> None:
    noisy = [word for word in NOISE if word in out]
    assert not noisy, f"{noisy} in:\n{out}"


def stream_until_detected(probe, proc, count: int = 3) -> None:
    """Frames at ~10 Hz until the detector has published ``count`` times (it is busy then)."""
    from geometry_msgs.msg import PoseArray

    poses = probe.subscribe(PoseArray, "/instances/poses")
    camera = CameraPublisher(probe)
    assert camera.wait_for_subscribers(60, proc=proc), stop(proc)
    rgb, depth, K = poster_frame()
    deadline = time.monotonic() + 60
    while len(poses) < count and time.monotonic() < deadline and proc.poll() is None:
        camera.send(rgb, depth, K)
        time.sleep(0.1)
    assert len(poses) >= count, stop(proc)
    for _ in range(3):   # frames in flight when the signal comes
        camera.send(rgb, depth, K)
        time.sleep(0.03)


def test_ctrl_c_while_detecting_ends_quietly_without_restarting_the_detector(model):
    proc = start_in_group(101, model, UNTRACKED)
    probe = Probe(101)
    try:
        stream_until_detected(probe, proc)
        os.killpg(proc.pid, signal.SIGINT)   # what Ctrl-C in the terminal does
        out = read_to_end(proc, 30)
    finally:
        probe.close()
        kill_group(proc)
    assert proc.returncode in (0, 130), out
    assert_quiet(out)
    assert out.count("interrupted") == 1, out
    assert not group_alive(proc.pid), group_members(proc.pid)


@pytest.mark.parametrize("domain,sig,after_s", [(102, signal.SIGINT, 0.5), (106, signal.SIGINT, 2.0),
                                                (107, signal.SIGINT, 3.5), (108, signal.SIGTERM, 2.5),
                                                (109, signal.SIGTERM, 4.0)])
def test_a_signal_while_starting_ends_quietly(model, domain, sig, after_s):
    # The node's start-up: imports (~1-2 s), the detector process spawned and warmed up, the
    # publishers created; a signal may come in any of them. A domain per case: the cases may
    # run at once (pytest-xdist).
    proc = start_in_group(domain, model)
    time.sleep(after_s)
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
    try:
        out = read_to_end(proc, 30)
    finally:
        kill_group(proc)
    assert_quiet(out)
    assert len([line for line in out.splitlines() if "interrupted" in line or "stopped" in line]) <= 1, out
    assert not group_alive(proc.pid), group_members(proc.pid)


def test_detector_left_behind_by_a_killed_node_exits_quietly_on_its_own(model):
    proc = start_in_group(103, model, UNTRACKED)
    probe = Probe(103)
    try:
        stream_until_detected(probe, proc)
        os.kill(proc.pid, signal.SIGKILL)     # the node only: its detector is orphaned
        out = read_to_end(proc, 30)           # the detector holds the output until it exits
    finally:
        probe.close()
        kill_group(proc)
    assert_quiet(out)
    assert out.count("the node process is gone; exiting") == 1, repr(out)
    assert not group_alive(proc.pid), group_members(proc.pid)


def test_an_unknown_parameter_is_named_once(tmp_path):
    # No model: the node stops at once, after its parameters were read.
    proc = start(["multi_instance_reg.ros.node", "--ros-args", "-p", "ecc.inlier_tresh:=0.01", "-p", "no_such_thing:=3"],
                 105)
    try:
        out = read_to_end(proc, 60)
    finally:
        kill_group(proc)
    assert proc.returncode == 1, out
    for name in ("ecc.inlier_tresh", "no_such_thing"):
        lines = [line for line in out.splitlines() if name in line]
        assert len(lines) == 1 and "unknown parameter" in lines[0] and "ignored" in lines[0], out
    assert "did you mean ecc.inlier_thresh" in out, out


def test_colour_and_depth_that_never_pair_and_an_unusable_camera_info_are_named(model, tmp_path):
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import CameraInfo

    proc = start_logged(["multi_instance_reg.ros.node", "--ros-args", "-p", f"model_path:={model}", "-p", UNTRACKED],
                        104, tmp_path / "node.log")
    probe = Probe(104)
    try:
        camera = CameraPublisher(probe)
        assert camera.wait_for_subscribers(60, proc=proc), stop(proc)
        rgb, depth, K = poster_frame()
        # Depth stamped 2.5 s behind colour (another clock, no hardware sync): never within the slop.
        for _ in range(20):
            ns = time.time_ns()
            colour = camera.image(rgb, "rgb8", Time(sec=ns // 10**9, nanosec=ns % 10**9))
            late = ns - 2_500_000_000
            camera.colour.publish(colour)
            camera.depth.publish(camera.image(depth, "16UC1", Time(sec=late // 10**9, nanosec=late % 10**9)))
            time.sleep(0.05)
        assert wait_until(lambda: "never pair" in output(proc), 10, proc=proc), output(proc)
        # Then paired frames with a camera_info of 3 distortion coefficients (OpenCV takes 4, 5, 8, ...).
        for _ in range(5):
            ns = camera.send(rgb, depth, K, with_info=False)
            info = CameraInfo(width=640, height=480, k=[float(v) for v in K.reshape(-1)], distortion_model="plumb_bob",
                              d=[0.05, -0.01, 0.001])
            info.header.stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            camera.info.publish(info)
            time.sleep(0.2)
        time.sleep(4.0)   # the node waits 3.5 s for a first camera_info before it skips a frame
    finally:
        probe.close()
        out = stop(proc)
    pairing = [line for line in out.splitlines() if "never pair" in line]
    assert len(pairing) == 1, out
    offset_ms = float(re.search(r"depth stamp is ([-+]\d+) ms", pairing[0]).group(1))
    assert -2700 < offset_ms < -2400 and "sync_slop_s (20 ms)" in pairing[0], pairing[0]
    assert "3 distortion coefficients" in out, out
    skipping = [line for line in out.splitlines() if "skipping frames" in line]
    assert skipping and all("no camera_info received" not in line for line in skipping), out
    assert_quiet(out)

