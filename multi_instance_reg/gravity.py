"""The direction of gravity from the camera's accelerometer, per frame. No ROS.

realsense-ros (4.x) publishes a D455's accelerometer as sensor_msgs/Imu on
``/camera/camera/accel/sample`` (``enable_accel:=true``; frame ``camera_accel_optical_frame``,
best-effort "SENSOR_DATA" QoS), or together with the gyro on ``/camera/camera/imu``
(``unite_imu_method:=1|2``; frame ``camera_imu_optical_frame``). librealsense rotates the IMU's
samples into the depth sensor's axes (x right, y down, z forward, as every optical frame), and
the D455's depth-to-colour rotation is a fraction of a degree, so the reading is taken as
given in the colour optical frame. At rest an accelerometer reads the reaction to gravity:
about 9.81 m/s^2 pointing *up* (a level camera: y = -9.8). Its mean over a short window before
a frame's stamp is that frame's "up"; a robot may give the same from TF instead (the camera's
optical frame against a gravity-aligned base frame).
"""
from __future__ import annotations

from collections import deque

import numpy as np

ACCEL_TOPIC = "/camera/camera/accel/sample"
IMU_TOPIC = "/camera/camera/imu"
ACCEL_FRAME_ID = "camera_accel_optical_frame"
IMU_TYPE = "sensor_msgs/msg/Imu"
STANDARD_GRAVITY = 9.80665
# Samples averaged before each frame: 0.1 s (10-20 samples at the D455's 100-200 Hz) keeps the
# white noise to a few hundredths of a degree, and lags a hand-held camera's tilt (~10 deg/s)
# by half a degree; what the hand's motion adds (0.5-2 m/s^2: 3-12 deg) stays, inside the 20
# deg the front end allows (``shape_gravity_tolerance_deg``), which takes a plane's own normal.
WINDOW_NS = 100_000_000
# A mean further than this from 1 g is no gravity reading (the camera swung or knocked).
MAX_MAGNITUDE_ERROR = 0.25


class AccelWindow:
    """Accelerometer samples as they come (any order); ``up_at(stamp)`` the frame's "up"."""

    def __init__(self, window_ns: int = WINDOW_NS, keep_ns: int = 2_000_000_000):
        self.window_ns, self.keep_ns = int(window_ns), int(keep_ns)
        self._samples: deque = deque()      # (stamp_ns, (3,) m/s^2), in arrival order
        self._newest = None
        self.received = 0

    def add(self, stamp_ns: int, accel) -> None:
        a = np.asarray(accel, np.float64).reshape(3)
        if not np.all(np.isfinite(a)):
            return
        self.received += 1
        self._samples.append((int(stamp_ns), a))
        self._newest = int(stamp_ns) if self._newest is None else max(self._newest, int(stamp_ns))
        while self._samples[0][0] < self._newest - self.keep_ns:
            self._samples.popleft()

    def up_at(self, stamp_ns: int) -> np.ndarray | None:
        """Unit "up" (the samples' direction) from the samples within ``window_ns`` up to
        ``stamp_ns``, or None: none there (no IMU, or it stopped), or their mean is not about
        1 g."""
        lo, hi = int(stamp_ns) - self.window_ns, int(stamp_ns)
        inside = [a for t, a in self._samples if lo <= t <= hi]
        return up_from_samples(inside)


def up_from_samples(samples) -> np.ndarray | None:
    """Unit "up" from accelerometer samples ((N, 3) m/s^2), or None (none, or not about 1 g)."""
    if len(samples) == 0:
        return None
    mean = np.mean(np.asarray(samples, np.float64).reshape(-1, 3), axis=0)
    norm = float(np.linalg.norm(mean))
    if abs(norm - STANDARD_GRAVITY) > MAX_MAGNITUDE_ERROR * STANDARD_GRAVITY:
        return None
    return mean / norm


def imu_accel(msg) -> np.ndarray:
    """(3,) linear acceleration of a sensor_msgs/Imu (rclpy's or rosbags')."""
    a = msg.linear_acceleration
    return np.array([a.x, a.y, a.z], np.float64)


__all__ = ["ACCEL_TOPIC", "IMU_TOPIC", "ACCEL_FRAME_ID", "AccelWindow", "up_from_samples", "imu_accel",
           "STANDARD_GRAVITY", "WINDOW_NS"]
