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


def is_compressed(msg) -> bool:
    """A sensor_msgs/CompressedImage (``format`` and ``data``, no ``encoding``)?"""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


# compressed_depth_image_transport's payload starts with this header: the compression format
# (int32 enum: 0 = PNG, or PNG of quantised inverse depth for 32FC1; 1 = RVL) and two float32
# quantisation parameters (used for 32FC1 only).
_COMPRESSED_DEPTH_HEADER = np.dtype([("format", "<i4"), ("quant_a", "<f4"), ("quant_b", "<f4")])


def _byte_array(data) -> np.ndarray:
    """A message's uint8[] field (bytes, array.array, numpy or list) as a flat uint8 array."""
    try:
        return np.frombuffer(data, np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def _imdecode(buf: np.ndarray, what: str) -> np.ndarray:
    """The image encoded in ``buf`` as stored (bit depth and channels kept)."""
    import cv2

    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise InputError(f"{what}: the compressed data ({buf.size} bytes) does not decode as an image")
    return img


def compressed_colour_to_rgb(msg) -> np.ndarray:
    """(H, W, 3) uint8 RGB from a sensor_msgs/CompressedImage of image_transport's
    ``compressed`` plugin (format e.g. "rgb8; jpeg compressed bgr8", or just "jpeg"/"png")."""
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise InputError(f"colour image is compressed depth ('{fmt}'); give the colour topic (…/compressed)")
    img = _imdecode(_byte_array(msg.data), "colour image")
    if img.dtype != np.uint8:
        raise InputError(f"compressed colour image decodes to {img.dtype} ('{fmt}'); expected 8-bit colour")
    # The plugin encodes colour as bgr8 ("... compressed bgr8"), which OpenCV decodes as stored;
    # only "compressed rgb8" keeps red first.
    red_first = fmt.replace(" ", "").lower().endswith("compressedrgb8")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    img = img[:, :, :3]
    return np.ascontiguousarray(img if red_first else img[:, :, ::-1])


def compressed_depth_to_metres(msg, depth_scale: float = 0.001) -> np.ndarray:
    """(H, W) float32 metres from a sensor_msgs/CompressedImage of image_transport's
    ``compressedDepth`` plugin with its PNG codec (format e.g. "16UC1; compressedDepth png")."""
    fmt = str(msg.format)
    kind = fmt.split(";")[0].strip()
    if "compresseddepth" not in fmt.lower():
        raise InputError(f"depth image is compressed as '{fmt}', not compressedDepth; record the depth's "
                         f"raw topic or its …/compressedDepth topic (lossy colour codecs ruin depth)")
    if fmt.lower().rstrip().endswith("rvl"):
        raise InputError(f"depth compressed with RVL ('{fmt}') is not supported; record the raw depth topic or set "
                         f"the publisher's compressedDepth format to png")
    data = _byte_array(msg.data)
    if len(data) <= _COMPRESSED_DEPTH_HEADER.itemsize:
        raise InputError(f"compressed depth image has only {len(data)} bytes ('{fmt}')")
    head = data[:_COMPRESSED_DEPTH_HEADER.itemsize].copy().view(_COMPRESSED_DEPTH_HEADER)[0]
    img = _imdecode(data[_COMPRESSED_DEPTH_HEADER.itemsize:], "compressed depth image")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise InputError(f"compressed depth image decodes to {img.dtype} with shape {img.shape}; expected 16-bit, one channel")
    if kind in ("16UC1", "mono16"):
        return img.astype(np.float32) * np.float32(depth_scale)
    if kind == "32FC1":
        # Stored as quantised inverse depth: q = a / z + b, 0 where there was no measurement.
        a, b = float(head["quant_a"]), float(head["quant_b"])
        q = img.astype(np.float64)
        depth = np.zeros(img.shape, np.float32)
        ok = q > b
        depth[ok] = (a / (q[ok] - b)).astype(np.float32)
        return depth
    raise InputError(f"compressed depth image has encoding '{kind}'; expected 16UC1 (mm) or 32FC1 (m)")


def colour_to_rgb(msg) -> np.ndarray:
    """(H, W, 3) uint8 RGB from any supported colour encoding, raw or compressed."""
    if is_compressed(msg):
        return compressed_colour_to_rgb(msg)
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
    """(H, W) float32 metres; 0 where there is no measurement (0, NaN or inf). Raw images, or
    compressedDepth ones (PNG)."""
    if is_compressed(msg):
        return compressed_depth_to_metres(msg, depth_scale)
    arr = image_to_array(msg)
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise InputError(f"depth image has encoding '{enc}'; expected 16UC1 (mm) or 32FC1 (m)")
    if enc == "32FC1":
        depth = arr.astype(np.float32, copy=True)
        invalid = ~np.isfinite(depth) | (depth < 0)
        if invalid.any() and not np.any(depth[~invalid] > 0):
            # Zeroed below, it would read "all zero" later: say what the camera sent.
            raise InputError(f"depth image has no valid pixel ({no_depth_reason(arr)}); "
                             "is the depth stream running and aligned to colour?")
        depth[invalid] = 0.0
        return depth
    return arr.astype(np.float32) * np.float32(depth_scale)


def no_depth_reason(depth: np.ndarray) -> str:
    """Why a depth image without one pixel above zero has none, in a few words."""
    non_finite = int(np.count_nonzero(~np.isfinite(depth)))
    if non_finite == depth.size:
        return "every pixel NaN or inf"
    if non_finite:
        return f"{non_finite} of {depth.size} pixels NaN or inf, the rest zero or negative"
    return "all zero" if not np.any(depth) else "none above zero"


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


def compressed_colour_fields(rgb: np.ndarray, jpeg_quality: int = 90) -> dict:
    """The fields of a sensor_msgs/CompressedImage (without header) holding (H, W, 3) uint8 RGB
    as image_transport's ``compressed`` plugin publishes it: JPEG of the bgr8 image."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise InputError(f"cannot JPEG-encode a colour image of shape {rgb.shape}")
    return {"format": "rgb8; jpeg compressed bgr8", "data": buf.reshape(-1)}


def compressed_depth_fields(depth_mm: np.ndarray) -> dict:
    """The fields of a sensor_msgs/CompressedImage (without header) holding (H, W) uint16
    millimetres as the ``compressedDepth`` plugin publishes 16UC1 with its PNG codec: its
    12-byte header (format 0, no quantisation), then the PNG (lossless)."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(depth_mm, dtype=np.uint16))
    if not ok:
        raise InputError(f"cannot PNG-encode a depth image of shape {depth_mm.shape}")
    head = np.zeros(1, _COMPRESSED_DEPTH_HEADER).view(np.uint8)
    return {"format": "16UC1; compressedDepth png", "data": np.concatenate([head, buf.reshape(-1)])}


# How many distortion coefficients OpenCV's undistortPoints takes per camera_info model
# (fisheye: exactly 4); any other count fails there on every frame, so it is refused up front.
_DISTORTION_COUNTS = {"plumb_bob": (4, 5, 8, 12, 14), "rational_polynomial": (8, 12, 14), "equidistant": (4,)}


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
    named = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    not_finite = [f"{name}={value}" for name, value in named.items() if not np.isfinite(value)]
    if not_finite or not np.all(np.isfinite(K)):
        raise InputError(f"camera_info has a K that is not finite ({', '.join(not_finite) or f'k={list(K.reshape(-1))}'}); "
                         "publish the camera's calibration")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"camera_info has an invalid K (fx={K[0, 0]}, fy={K[1, 1]}); is the camera calibrated?")
    model = getattr(msg, "distortion_model", "") or "plumb_bob"
    D = np.asarray(d, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(D)):
        raise InputError(f"camera_info has distortion coefficients that are not finite (d={list(D)}); "
                         "publish the camera's calibration")
    if np.any(D != 0) and len(D) not in _DISTORTION_COUNTS.get(model, _DISTORTION_COUNTS["plumb_bob"]):
        counts = _DISTORTION_COUNTS.get(model, _DISTORTION_COUNTS["plumb_bob"])
        raise InputError(f"camera_info has {len(D)} distortion coefficients for the {model} model; OpenCV takes "
                         f"{', '.join(map(str, counts[:-1]))}{' or ' if len(counts) > 1 else ''}{counts[-1]}: "
                         "publish the camera's full calibration (realsense-ros: 5, plumb_bob)")
    return CameraIntrinsics(K=K, width=int(msg.width), height=int(msg.height), D=D, distortion_model=model)
