"""sensor_msgs Image / CameraInfo <-> numpy: every supported encoding, padding, byte order, errors."""
from types import SimpleNamespace

import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.messages import (array_to_image_fields, camera_info_to_intrinsics, colour_to_rgb,
                                         depth_to_metres, image_to_array)


def image_msg(arr, encoding, pad=0, bigendian=False):
    """A duck-typed Image holding arr, each row padded by ``pad`` bytes."""
    arr = np.ascontiguousarray(arr)
    if bigendian and arr.itemsize > 1:
        arr = arr.astype(arr.dtype.newbyteorder(">"))
    h, w = arr.shape[:2]
    row = arr.reshape(h, -1).view(np.uint8)
    rows = np.concatenate([row, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return SimpleNamespace(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
                           step=row.shape[1] + pad, data=rows.reshape(-1).tobytes())


RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8)


@pytest.mark.parametrize("pad", [0, 3])
@pytest.mark.parametrize("encoding, make", [
    ("rgb8", lambda c: c),
    ("bgr8", lambda c: c[:, :, ::-1]),
    ("rgba8", lambda c: np.concatenate([c, np.full(c.shape[:2] + (1,), 7, np.uint8)], axis=2)),
    ("bgra8", lambda c: np.concatenate([c[:, :, ::-1], np.full(c.shape[:2] + (1,), 7, np.uint8)], axis=2)),
])
def test_colour_encodings_give_rgb(encoding, make, pad):
    out = colour_to_rgb(image_msg(make(RGB), encoding, pad))
    assert out.dtype == np.uint8 and out.shape == (5, 7, 3)
    np.testing.assert_array_equal(out, RGB)


def test_mono8_repeats_into_three_channels():
    grey = RGB[:, :, 0]
    out = colour_to_rgb(image_msg(grey, "mono8", pad=1))
    assert out.shape == (5, 7, 3)
    np.testing.assert_array_equal(out[:, :, 2], grey)


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 2])
def test_depth_16uc1_millimetres(bigendian, pad):
    mm = RNG.integers(0, 5000, (4, 6), dtype=np.uint16)
    mm[0, 0] = 0
    out = depth_to_metres(image_msg(mm, "16UC1", pad, bigendian))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, mm / 1000.0, rtol=1e-6)
    assert out[0, 0] == 0


@pytest.mark.parametrize("bigendian", [False, True])
def test_depth_32fc1_metres_invalid_becomes_zero(bigendian):
    m = RNG.uniform(0.2, 3.0, (4, 6)).astype(np.float32)
    m[1, 1], m[2, 2], m[3, 3] = np.nan, np.inf, -1.0
    out = depth_to_metres(image_msg(m, "32FC1", pad=4, bigendian=bigendian))
    assert out[1, 1] == 0 and out[2, 2] == 0 and out[3, 3] == 0
    ok = np.isfinite(m) & (m > 0)
    np.testing.assert_array_equal(out[ok], m[ok])


def test_unknown_encoding_is_an_input_error():
    msg = image_msg(RGB[:, :, :2].copy(), "yuv422")
    with pytest.raises(InputError, match="unsupported image encoding 'yuv422'"):
        colour_to_rgb(msg)


def test_depth_encoding_as_colour_and_colour_as_depth_are_refused():
    with pytest.raises(InputError, match="colour image has encoding '16UC1'"):
        colour_to_rgb(image_msg(np.zeros((2, 2), np.uint16), "16UC1"))
    with pytest.raises(InputError, match="depth image has encoding 'rgb8'"):
        depth_to_metres(image_msg(RGB, "rgb8"))


def test_short_data_and_small_step_are_refused():
    msg = image_msg(RGB, "rgb8")
    msg.data = msg.data[:-5]
    with pytest.raises(InputError, match="bytes"):
        image_to_array(msg)
    msg = image_msg(RGB, "rgb8")
    msg.step = 7 * 3 - 1
    with pytest.raises(InputError, match="step"):
        image_to_array(msg)


@pytest.mark.parametrize("encoding, arr", [("rgb8", RGB), ("16UC1", np.arange(12, dtype=np.uint16).reshape(3, 4)),
                                           ("32FC1", np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4))])
def test_array_to_image_fields_round_trip(encoding, arr):
    fields = array_to_image_fields(arr, encoding)
    msg = SimpleNamespace(**fields)
    np.testing.assert_array_equal(image_to_array(msg), arr)
    assert fields["step"] == arr.shape[1] * arr.itemsize * (arr.shape[2] if arr.ndim == 3 else 1)


def test_works_on_rosbags_messages():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Image, Header, Time = ts.types["sensor_msgs/msg/Image"], ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=2), frame_id="f"), **array_to_image_fields(RGB[:, :, ::-1], "bgr8"))
    raw = ts.serialize_cdr(msg, "sensor_msgs/msg/Image")
    back = ts.deserialize_cdr(raw, "sensor_msgs/msg/Image")
    np.testing.assert_array_equal(colour_to_rgb(back), RGB)


def test_camera_info_k_d_and_size():
    info = SimpleNamespace(k=[379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1], d=[0.1, -0.05, 0, 0, 0.01],
                           width=640, height=480, distortion_model="plumb_bob")
    intr = camera_info_to_intrinsics(info)
    assert intr.K[0, 0] == 379.05 and intr.K[1, 2] == 238.97
    assert (intr.width, intr.height) == (640, 480)
    assert intr.has_distortion and intr.D.shape == (5,)
    info.d = [0.0] * 5
    assert not camera_info_to_intrinsics(info).has_distortion


def test_uncalibrated_camera_info_is_refused():
    info = SimpleNamespace(k=[0.0] * 9, d=[], width=640, height=480, distortion_model="")
    with pytest.raises(InputError, match="invalid K"):
        camera_info_to_intrinsics(info)



def test_non_finite_principal_point_is_named_not_called_an_invalid_focal_length():
    info = SimpleNamespace(k=[379.05, 0, float("nan"), 0, 378.68, 238.97, 0, 0, 1], d=[], width=640, height=480,
                           distortion_model="plumb_bob")
    with pytest.raises(InputError) as err:
        camera_info_to_intrinsics(info)
    message = str(err.value)
    assert "cx" in message and "nan" in message and "fx=" not in message, message
    assert len(message.splitlines()) == 1


@pytest.mark.parametrize("model,count", [("plumb_bob", 3), ("rational_polynomial", 6), ("equidistant", 2)])
def test_distortion_coefficients_opencv_cannot_take_are_refused_at_the_message(model, count):
    info = SimpleNamespace(k=[379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1], d=[0.1, 0.01, 0.001, 0.002, 0.003, 0.004][:count],
                           width=640, height=480, distortion_model=model)
    with pytest.raises(InputError, match=f"{count} distortion coefficients") as err:
        camera_info_to_intrinsics(info)
    assert model in str(err.value) and "calibrat" in str(err.value)


@pytest.mark.parametrize("model,count", [("plumb_bob", 5), ("plumb_bob", 4), ("plumb_bob", 8), ("rational_polynomial", 8),
                                         ("equidistant", 4), ("plumb_bob", 0)])
def test_distortion_coefficients_opencv_takes_are_used(model, count):
    from multi_instance_reg.rgbd.lifting import undistort_pixels

    info = SimpleNamespace(k=[379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1], d=[0.01] * count,
                           width=640, height=480, distortion_model=model)
    intr = camera_info_to_intrinsics(info)
    assert undistort_pixels(np.array([[100.0, 50.0]]), intr).shape == (1, 2)


def test_all_zero_distortion_of_any_length_is_no_distortion():
    info = SimpleNamespace(k=[379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1], d=[0.0] * 3,
                           width=640, height=480, distortion_model="plumb_bob")
    assert not camera_info_to_intrinsics(info).has_distortion


def test_all_nan_depth_is_called_what_it_is():
    from multi_instance_reg.rgbd.pipeline import check_frame

    info = SimpleNamespace(k=[379.05, 0, 321.89, 0, 378.68, 238.97, 0, 0, 1], d=[], width=6, height=4,
                           distortion_model="plumb_bob")
    for nan_depth in (np.full((4, 6), np.nan, np.float32), np.where(np.eye(4, 6) > 0, 0, np.nan).astype(np.float32)):
        with pytest.raises(InputError) as err:   # the node converts, then checks the frame
            check_frame(np.zeros((4, 6, 3), np.uint8), depth_to_metres(image_msg(nan_depth, "32FC1")),
                        camera_info_to_intrinsics(info))
        assert "NaN" in str(err.value) and "all zero" not in str(err.value), str(err.value)
        assert "no valid pixel" in str(err.value)
    with pytest.raises(InputError, match="every pixel NaN"):   # the same array given to the pipeline
        check_frame(np.zeros((4, 6, 3), np.uint8), np.full((4, 6), np.nan, np.float32), camera_info_to_intrinsics(info))
    zeros = depth_to_metres(image_msg(np.zeros((4, 6), np.uint16), "16UC1"))
    with pytest.raises(InputError, match="all zero"):
        check_frame(np.zeros((4, 6, 3), np.uint8), zeros, camera_info_to_intrinsics(info))


# ---- compressed images (image_transport's compressed and compressedDepth) ------------------
SMOOTH = np.dstack([np.tile(np.linspace(20, 230, 64, dtype=np.uint8), (48, 1)),
                    np.tile(np.linspace(200, 40, 48, dtype=np.uint8)[:, None], (1, 64)),
                    np.full((48, 64), 90, np.uint8)])


def compressed_msg(format, data):
    return SimpleNamespace(format=format, data=data)


def test_compressed_colour_jpeg_round_trip_keeps_red_first():
    from multi_instance_reg.messages import compressed_colour_fields

    fields = compressed_colour_fields(SMOOTH)
    assert fields["format"] == "rgb8; jpeg compressed bgr8"
    out = colour_to_rgb(compressed_msg(**fields))
    assert out.shape == SMOOTH.shape and out.dtype == np.uint8
    assert np.abs(out.astype(int) - SMOOTH).max() <= 8     # JPEG is lossy...
    assert np.abs(out[:, :, ::-1].astype(int) - SMOOTH).mean() > 30    # ... and not channel-swapped


@pytest.mark.parametrize("fmt, store, expect", [
    ("bgr8; png compressed bgr8", lambda c: c[:, :, ::-1], lambda c: c),    # what the plugin writes
    ("png", lambda c: c[:, :, ::-1], lambda c: c),                          # older publishers
    ("rgb8; png compressed rgb8", lambda c: c, lambda c: c),                # stored red first
    ("mono8; png compressed mono8", lambda c: c[:, :, 0], lambda c: np.repeat(c[:, :, :1], 3, axis=2)),
])
def test_compressed_colour_png_is_exact(fmt, store, expect):
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(store(SMOOTH)))
    np.testing.assert_array_equal(colour_to_rgb(compressed_msg(fmt, buf.tobytes())), expect(SMOOTH))


def test_compressed_depth_16uc1_png_is_lossless_from_any_byte_container():
    import array

    from multi_instance_reg.messages import compressed_depth_fields

    depth_mm = RNG.integers(0, 9000, (48, 64)).astype(np.uint16)
    fields = compressed_depth_fields(depth_mm)
    assert fields["format"] == "16UC1; compressedDepth png"
    for data in (fields["data"], bytes(fields["data"]), array.array("B", bytes(fields["data"]))):
        np.testing.assert_array_equal(depth_to_metres(compressed_msg(fields["format"], data)),
                                      depth_mm.astype(np.float32) * np.float32(0.001))


def test_compressed_depth_32fc1_is_quantised_inverse_depth():
    import cv2

    a, b = 100.0, 10.0               # q = a / z + b, q = 0 for no measurement
    depth = np.array([[0.5, 1.0, 0.0], [2.0, 4.0, 10.0]])
    q = np.where(depth > 0, np.round(a / np.where(depth > 0, depth, 1) + b), 0).astype(np.uint16)
    header = np.array([(0, a, b)], dtype=[("f", "<i4"), ("a", "<f4"), ("b", "<f4")]).tobytes()
    ok, png = cv2.imencode(".png", q)
    out = depth_to_metres(compressed_msg("32FC1; compressedDepth png", header + png.tobytes()))
    np.testing.assert_allclose(out, depth, rtol=1e-6)
    assert out[0, 2] == 0.0


@pytest.mark.parametrize("fmt, data, words", [
    ("16UC1; compressedDepth rvl", b"\0" * 40, "RVL"),
    ("16UC1; compressedDepth png", b"\0" * 12 + b"not a png", "does not decode"),
    ("16UC1; compressedDepth png", b"\0" * 8, "only 8 bytes"),
    ("rgb8; jpeg compressed bgr8", b"\xff\xd8" + b"\0" * 30, "not compressedDepth"),
])
def test_bad_compressed_depth_is_an_input_error_naming_it(fmt, data, words):
    with pytest.raises(InputError, match=words):
        depth_to_metres(compressed_msg(fmt, data))


def test_bad_compressed_colour_is_an_input_error_naming_it():
    from multi_instance_reg.messages import compressed_depth_fields

    with pytest.raises(InputError, match="does not decode"):
        colour_to_rgb(compressed_msg("jpeg", b"\xff\xd8 truncated"))
    with pytest.raises(InputError, match="compressed depth"):
        colour_to_rgb(compressed_msg(**compressed_depth_fields(np.zeros((4, 4), np.uint16))))
