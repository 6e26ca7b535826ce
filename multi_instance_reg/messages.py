"""sensor_msgs Image / CameraInfo <-> numpy, for rclpy and rosbags messages alike.

Only attribute access is used (duck typing), so nothing here imports ROS. Colour comes out
as (H, W, 3) uint8 RGB; depth as (H, W) float32 metres with 0 for "no measurement".
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

# encoding -> (numpy dtype, channels)
_ENCODINGS = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "8UC3": (np.uint8, 3),
    "16UC1": (np.uint16, 1), "mono16": (np.uint16, 1), "32FC1": (np.float32, 1),
}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC3", "8UC1")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


def image_to_array(msg) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as an (H, W) or (H, W, C) array in the message's own
    encoding, honouring ``step`` (row padding) and ``is_bigendian``."""
    encoding = msg.encoding
    if encoding not in _ENCODINGS:
        raise InputError(f"unsupported image encoding '{encoding}'; supported: {', '.join(_ENCODINGS)}")
    dtype, channels = _ENCODINGS[encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row_bytes = w * channels * itemsize
    if h <= 0 or w <= 0:
        raise InputError(f"image has no pixels ({w}x{h})")
    if step < row_bytes:
        raise InputError(f"image step {step} is smaller than width*channels*bytes = {row_bytes} ({encoding}, width {w})")
    data = msg.data
    buf = data if isinstance(data, (bytes, bytearray, memoryview)) else np.asarray(data, dtype=np.uint8)
    buf = np.frombuffer(buf, dtype=np.uint8)
    if buf.size < step * (h - 1) + row_bytes:
        raise InputError(f"image data has {buf.size} bytes, {step * h} expected for {h} rows of step {step}")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(h, row_bytes), strides=(step, 1))
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<") if itemsize > 1 else np.dtype(dtype)
    arr = np.ascontiguousarray(rows).view(dt).reshape(h, w, channels) if channels > 1 else \
        np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return arr.astype(dtype, copy=False) if itemsize > 1 else arr


def colour_to_rgb(msg) -> np.ndarray:
    """(H, W, 3) uint8 RGB from any supported colour encoding."""
    arr = image_to_array(msg)
    enc = msg.encoding
    if enc not in COLOUR_ENCODINGS:
        raise InputError(f"colour image has encoding '{enc}'; expected one of {', '.join(COLOUR_ENCODINGS)}")
    if enc in ("mono8", "8UC1"):
        return np.repeat(arr[:, :, None], 3, axis=2)
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(arr[:, :, 2::-1])
    return np.ascontiguousarray(arr[:, :, :3])


def depth_to_metres(msg, depth_scale: float = 0.001) -> np.ndarray:
    """(H, W) float32 metres; 0 where there is no measurement (0, NaN or inf)."""
    arr = image_to_array(msg)
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise InputError(f"depth image has encoding '{enc}'; expected 16UC1 (mm) or 32FC1 (m)")
    if enc == "32FC1":
        depth = arr.astype(np.float32, copy=True)
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        return depth
    return arr.astype(np.float32) * np.float32(depth_scale)


def array_to_image_fields(arr: np.ndarray, encoding: str) -> dict:
    """The fields of a sensor_msgs/Image (without header) holding ``arr`` in ``encoding``.

    Pass them to the message class of your choice: rclpy's ``Image(**fields)`` (give
    ``data`` as bytes) or rosbags' dataclass.
    """
    if encoding not in _ENCODINGS:
        raise InputError(f"unsupported image encoding '{encoding}'")
    dtype, channels = _ENCODINGS[encoding]
    arr = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<"))
    h, w = arr.shape[:2]
    if (arr.shape[2] if arr.ndim == 3 else 1) != channels:
        raise InputError(f"array of shape {arr.shape} does not fit encoding {encoding}")
    return {"height": h, "width": w, "encoding": encoding, "is_bigendian": 0,
            "step": w * channels * arr.itemsize, "data": arr.reshape(-1).view(np.uint8)}


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics and distortion of one camera stream."""
    K: np.ndarray                 # (3, 3)
    width: int
    height: int
    D: np.ndarray = field(default_factory=lambda: np.zeros(0))  # distortion coefficients, OpenCV order for plumb_bob
    distortion_model: str = "plumb_bob"

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.abs(self.D) > 0))


def camera_info_to_intrinsics(msg) -> CameraIntrinsics:
    """CameraIntrinsics from a sensor_msgs/CameraInfo (fields ``k``/``d`` or ROS 1 ``K``/``D``)."""
    k = getattr(msg, "k", None)
    if k is None:
        k = getattr(msg, "K")
    d = getattr(msg, "d", None)
    if d is None:
        d = getattr(msg, "D", ())
    K = np.asarray(k, dtype=np.float64).reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.all(np.isfinite(K))):
        raise InputError(f"camera_info has an invalid K (fx={K[0, 0]}, fy={K[1, 1]}); is the camera calibrated?")
    model = getattr(msg, "distortion_model", "") or "plumb_bob"
    return CameraIntrinsics(K=K, width=int(msg.width), height=int(msg.height),
                            D=np.asarray(d, dtype=np.float64), distortion_model=model)
