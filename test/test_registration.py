"""Depth registered to colour (rgbd/registration.py) on scenes with a known answer: each
depth image is ray-cast from the depth camera, and the expected one from the colour camera."""
import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.rgbd.registration import extrinsics_matrix, register_depth, register_to_colour

# A D4xx-like pair: depth 640x480 with a longer focal length than colour, 15 mm apart along x.
K_DEPTH = np.array([[390.0, 0, 319.5], [0, 390.0, 239.5], [0, 0, 1]])
K_COLOUR = np.array([[380.0, 0, 322.0], [0, 379.0, 238.0], [0, 0, 1]])
SHAPE = (480, 640)
T_COLOUR_FROM_DEPTH = np.eye(4)
T_COLOUR_FROM_DEPTH[:3, 3] = (0.015, 0.0, 0.0)


def rays(K, shape):
    """Unit-z ray directions through every pixel centre, (H, W, 3)."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    return np.dstack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(shape)])


def seen_by_depth(P, margin=1.0):
    """Which points (H, W, 3) in the depth camera's frame fall inside its image, ``margin`` px in."""
    u = K_DEPTH[0, 0] * P[..., 0] / P[..., 2] + K_DEPTH[0, 2]
    v = K_DEPTH[1, 1] * P[..., 1] / P[..., 2] + K_DEPTH[1, 2]
    return (u >= -0.5 + margin) & (u <= SHAPE[1] - 0.5 - margin) & (v >= -0.5 + margin) & (v <= SHAPE[0] - 0.5 - margin)


def grown(mask):
    """``mask`` and every pixel next to it."""
    out = mask.copy()
    for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        out |= np.roll(mask, (a, b), (0, 1))
    return out


def cast_plane(K, shape, origin, normal, offset):
    """Depth (z along each ray) where rays from ``origin`` meet the plane n . P = offset."""
    d = rays(K, shape)
    s = (offset - normal @ origin) / (d @ normal)
    return np.where(s > 0, s, 0.0)


def cast_step(K, shape, origin):
    """Background plane z = 1 m (in the depth camera's frame) and a 10 cm square at z = 0.5 m
    in front of it; ``origin``: the camera's centre in that frame (cameras not turned).
    Returns depth and a mask of rays hitting the square."""
    d = rays(K, shape)
    s_near = (0.5 - origin[2]) / d[..., 2]
    hit = s_near[..., None] * d + origin
    on_square = (np.abs(hit[..., 0]) <= 0.05) & (np.abs(hit[..., 1]) <= 0.05)
    s_far = (1.0 - origin[2]) / d[..., 2]
    return np.where(on_square, s_near, s_far), on_square


def test_identity_gives_the_same_image():
    depth = np.random.default_rng(0).uniform(0.3, 3.0, SHAPE).astype(np.float32)
    depth[100:110, 200:230] = 0
    out = register_depth(depth, K_DEPTH, K_DEPTH, np.eye(4), SHAPE)
    assert np.array_equal(out, depth)


def test_a_plane_facing_the_cameras_is_at_its_depth_everywhere_both_see_it():
    depth = cast_plane(K_DEPTH, SHAPE, np.zeros(3), np.array([0.0, 0, 1]), 1.0).astype(np.float32)
    out = register_depth(depth, K_DEPTH, K_COLOUR, T_COLOUR_FROM_DEPTH, SHAPE)
    P = np.dstack([rays(K_COLOUR, SHAPE)[..., :2], np.ones(SHAPE)]) - T_COLOUR_FROM_DEPTH[:3, 3]
    seen = seen_by_depth(P)
    assert 0.9 < seen.mean() < 0.97          # the colour camera sees wider, and 15 mm to the side
    assert np.all(out[seen] == np.float32(1.0))
    assert np.all(out[~seen_by_depth(P, margin=-1.0)] == 0)     # nothing beyond what the depth camera saw


def test_a_slanted_plane_is_within_a_pixel_of_its_depth_with_no_pinholes():
    normal = np.array([0.35, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    depth = cast_plane(K_DEPTH, SHAPE, np.zeros(3), normal, 0.8).astype(np.float32)
    out = register_depth(depth, K_DEPTH, K_COLOUR, T_COLOUR_FROM_DEPTH, SHAPE)
    # The same plane from the colour camera, whose centre is at -t in the depth frame.
    expected = cast_plane(K_COLOUR, SHAPE, -T_COLOUR_FROM_DEPTH[:3, 3], normal, 0.8)
    inside = (slice(20, -20), slice(20, -20))
    assert np.all(out[inside] > 0), "a pinhole in a continuous surface"
    # Each colour pixel takes the depth of a depth pixel within about a pixel of it: the
    # plane's depth changes by at most ~2.5 mm per pixel here.
    err = np.abs(out[inside] - expected[inside])
    assert err.max() < 0.003 and np.median(err) < 0.0015


def test_step_edge_nearest_surface_wins_and_the_unseen_strip_stays_empty():
    origin_colour = -T_COLOUR_FROM_DEPTH[:3, 3]
    depth, _ = cast_step(K_DEPTH, SHAPE, np.zeros(3))
    out = register_depth(depth.astype(np.float32), K_DEPTH, K_COLOUR, T_COLOUR_FROM_DEPTH, SHAPE)
    expected, on_square = cast_step(K_COLOUR, SHAPE, origin_colour)
    # Background seen by the colour camera but hidden from the depth camera by the square.
    P = rays(K_COLOUR, SHAPE) * ((1.0 - origin_colour[2]) / 1.0) + origin_colour   # on z = 1
    s = 0.5 / 1.0                                       # where the depth camera's ray to P crosses z = 0.5
    cross = P * s
    shadow = ~on_square & (np.abs(cross[..., 0]) <= 0.05) & (np.abs(cross[..., 1]) <= 0.05)
    # The shadow is a strip f * b * (1/0.5 - 1/1) ~ 5.7 px wide beside the square.
    assert 300 < shadow.sum() < 700
    grow = np.zeros_like(on_square)          # one pixel round each boundary is either
    for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        grow |= np.roll(on_square, (a, b), (0, 1)) != on_square
        grow |= np.roll(shadow, (a, b), (0, 1)) != shadow
    square, hole = on_square & ~grow, shadow & ~grow
    background = ~on_square & ~shadow & ~grow & seen_by_depth(P)
    assert np.all(out[square] == np.float32(0.5)), "the square's own pixels must keep the nearer surface"
    assert np.all(out[hole] == 0), "the strip the depth camera cannot see must stay a hole"
    assert np.allclose(out[background], expected[background], atol=1e-6)


def test_holes_in_the_depth_stay_holes_of_their_size():
    depth = cast_plane(K_DEPTH, SHAPE, np.zeros(3), np.array([0.0, 0, 1]), 1.0).astype(np.float32)
    depth[200:206, 300:306] = 0                 # a 6 x 6 hole
    depth[100, 100] = 0                         # a single missing pixel
    out = register_depth(depth, K_DEPTH, K_COLOUR, T_COLOUR_FROM_DEPTH, SHAPE)
    P = np.dstack([rays(K_COLOUR, SHAPE)[..., :2], np.ones(SHAPE)]) - T_COLOUR_FROM_DEPTH[:3, 3]
    zeros = (out == 0) & seen_by_depth(P)
    # The colour camera's pixels are 390 / 380 of the depth's: 6 depth pixels span ~5.8, and
    # one missing pixel leaves at most one colour pixel empty.
    assert 25 <= zeros[180:230, 280:330].sum() <= 36
    assert zeros[90:110, 90:110].sum() <= 1
    assert zeros.sum() == zeros[180:230, 280:330].sum() + zeros[90:110, 90:110].sum()


def test_colour_distortion_moves_the_depth_as_the_colour_image_is_distorted():
    import cv2

    depth = np.zeros(SHAPE, np.float32)
    depth[300, 500] = 1.2                       # one point off-centre
    D = np.array([0.1, -0.05, 0.001, -0.002, 0.0])
    out = register_depth(depth, K_DEPTH, K_COLOUR, T_COLOUR_FROM_DEPTH, SHAPE, D)
    P = np.array([(500 - 319.5) / 390 * 1.2, (300 - 239.5) / 390 * 1.2, 1.2]) + T_COLOUR_FROM_DEPTH[:3, 3]
    uv, _ = cv2.projectPoints(P[None], np.zeros(3), np.zeros(3), K_COLOUR, D)
    j, i = np.argwhere(out > 0)[0]
    assert abs(i - uv[0, 0, 0]) <= 0.75 and abs(j - uv[0, 0, 1]) <= 0.75


def test_extrinsics_are_read_column_major():
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])       # 90 deg about z
    T = extrinsics_matrix(Rz.T.reshape(-1), [0.015, 0.001, -0.002])   # column-major = rows of R^T
    assert np.allclose(T[:3, :3], Rz) and np.allclose(T[:3, 3], [0.015, 0.001, -0.002])
    with pytest.raises(InputError, match="not a rotation"):
        extrinsics_matrix(np.arange(9.0), np.zeros(3))
    with pytest.raises(InputError, match="9 finite rotation"):
        extrinsics_matrix(np.eye(3).reshape(-1)[:8], np.zeros(3))


def test_a_depth_image_of_another_size_than_its_camera_info_is_refused():
    intr = CameraIntrinsics(K=K_DEPTH, width=640, height=480)
    with pytest.raises(InputError, match="camera_info says 640x480"):
        register_to_colour(np.ones((240, 320), np.float32), intr, intr, np.eye(4))
