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


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> str:
    """Terminate (SIGTERM, then SIGKILL) and return everything it printed."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.stdout.read() if proc.stdout else ""


class Probe:
    """An rclpy node in this test process, on its own context and domain, spun in a thread."""

    def __init__(self, domain_id: int, name: str = "test_probe"):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received: dict[str, list] = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:
                if not self.context.ok():
                    return
                raise

    def subscribe(self, msg_type, topic: str, depth: int = 50) -> list:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        box = self.received.setdefault(topic, [])

        def keep(msg):
            with self._lock:
                box.append((time.monotonic(), msg))
        self.node.create_subscription(msg_type, topic, keep, qos)
        return box

    def publisher(self, msg_type, topic: str, depth: int = 10):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        return self.node.create_publisher(msg_type, topic, qos)

    def close(self):
        import rclpy

        rclpy.try_shutdown(context=self.context)
        self._thread.join(5)
        self.executor.shutdown()
        self.node.destroy_node()


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
