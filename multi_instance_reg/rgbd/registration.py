"""Depth registered to colour: a depth image from the depth camera redrawn as the colour
camera sees it. No ROS.

A camera that records depth unaligned (realsense-ros without ``align_depth.enable``, the
RealSense Viewer) gives depth in the depth imager's own pixels, with its own intrinsics, a
few centimetres beside the colour camera. Every depth pixel is lifted to 3-D with the depth
intrinsics, moved into the colour camera's frame by the extrinsics and drawn into the colour
image:

- **Footprint, not point.** Each depth pixel covers the colour pixels whose centres fall inside
  its own square (its corners at the pixel's depth, projected), so a surface seen at a
  different scale or from the side leaves no pinholes and covers no more than it should.
  The square is widened by ``FOOTPRINT_MARGIN_PX`` on each side: neighbouring pixels of a
  slanted surface are lifted at slightly different depths, so their squares leave slivers
  between them a colour pixel centre can fall into.
- **Nearest surface wins.** Where several depth pixels land on one colour pixel (a background
  the depth camera sees beside an object, that the colour camera sees behind it), the
  smallest depth is kept: a z-buffer.
- **Holes stay holes.** A colour pixel no depth pixel covers (the depth had no measurement
  there, or the colour camera sees behind an edge that the depth camera did not) has depth 0;
  nothing is interpolated across it.

The colour camera's plumb_bob distortion is applied when projecting (realsense-ros' aligned
depth is in the colour image's own, distorted pixels; the pipeline undistorts where it needs
to); the depth stream is taken as rectified (realsense-ros and the Viewer give it so, D = 0).

    depth_c = register_depth(depth_m, K_depth, K_colour, T_colour_from_depth, (h, w), D_colour)
"""
from __future__ import annotations

import math

import numba
import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics

# How far each depth pixel's square reaches past its own edges, in colour pixels (see above).
# Small enough that a one-pixel hole in the depth stays a hole.
FOOTPRINT_MARGIN_PX = 0.2


def extrinsics_matrix(rotation, translation, column_major: bool = True) -> np.ndarray:
    """(4, 4) transform from a rotation of 9 numbers and a translation of 3 (metres).
    realsense2_camera_msgs/Extrinsics and librealsense's rs2_extrinsics store the rotation
    column-major (``column_major``); InputError when the numbers are not a rotation."""
    R = np.asarray(rotation, dtype=np.float64).reshape(-1)
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if R.size != 9 or t.size != 3 or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InputError(f"extrinsics need 9 finite rotation and 3 finite translation values, got "
                         f"{R.size} and {t.size}")
    R = R.reshape(3, 3)
    if column_major:
        R = R.T
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InputError(f"extrinsics rotation is not a rotation matrix ({np.round(R, 4).tolist()}); "
                         "record the camera's own extrinsics topic")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _plumb_bob(D: np.ndarray | None) -> np.ndarray:
    """k1, k2, p1, p2, k3 (zeros where not given)."""
    out = np.zeros(5)
    if D is not None:
        d = np.asarray(D, dtype=np.float64).reshape(-1)[:5]
        out[:len(d)] = d
    return out


def register_depth(depth_m: np.ndarray, K_depth: np.ndarray, K_colour: np.ndarray,
                   T_colour_from_depth: np.ndarray, colour_shape: tuple[int, int],
                   D_colour: np.ndarray | None = None) -> np.ndarray:
    """Depth in metres (H_d, W_d, 0 = none) from the depth camera -> (H_c, W_c) float32 metres
    in the colour camera's pixels, 0 where no depth pixel lands (see the module docstring).
    ``T_colour_from_depth`` maps a point in the depth camera's optical frame into the colour
    camera's. ``D_colour``: the colour camera's plumb_bob coefficients (None: none)."""
    depth = np.asarray(depth_m)
    if depth.ndim != 2:
        raise InputError(f"depth must be one channel (H, W), got shape {depth.shape}")
    h, w = (int(colour_shape[0]), int(colour_shape[1]))
    out = np.full((h, w), np.inf, np.float32)
    Kd = np.asarray(K_depth, dtype=np.float64)
    Kc = np.asarray(K_colour, dtype=np.float64)
    T = np.asarray(T_colour_from_depth, dtype=np.float64)
    _splat(np.ascontiguousarray(depth, dtype=np.float32), Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2],
           Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2], _plumb_bob(D_colour), np.ascontiguousarray(T[:3, :3]),
           np.ascontiguousarray(T[:3, 3]), FOOTPRINT_MARGIN_PX, out)
    out[~np.isfinite(out)] = 0.0
    return out


def register_to_colour(depth_m: np.ndarray, depth_intrinsics: CameraIntrinsics,
                       colour_intrinsics: CameraIntrinsics, T_colour_from_depth: np.ndarray) -> np.ndarray:
    """``register_depth`` with the two streams' intrinsics (the colour image's size from its
    camera_info). InputError when the depth image is not the size its camera_info says."""
    if tuple(np.shape(depth_m)) != (depth_intrinsics.height, depth_intrinsics.width):
        raise InputError(f"depth image is {np.shape(depth_m)[1]}x{np.shape(depth_m)[0]} but its camera_info says "
                         f"{depth_intrinsics.width}x{depth_intrinsics.height}")
    D = colour_intrinsics.D if colour_intrinsics.has_distortion else None
    if D is not None and colour_intrinsics.distortion_model not in ("plumb_bob", "rational_polynomial") and \
            np.any(np.asarray(D)[5:] != 0):
        raise InputError(f"colour distortion model {colour_intrinsics.distortion_model} is not supported for "
                         "registering depth; record the aligned depth (align_depth.enable:=true)")
    return register_depth(depth_m, depth_intrinsics.K, colour_intrinsics.K, T_colour_from_depth,
                          (colour_intrinsics.height, colour_intrinsics.width), D)


@numba.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _project(x, y, z, fx, fy, cx, cy, d):
    a, b = x / z, y / z
    if d[0] != 0.0 or d[1] != 0.0 or d[2] != 0.0 or d[3] != 0.0 or d[4] != 0.0:
        r2 = a * a + b * b
        radial = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
        a, b = (a * radial + 2.0 * d[2] * a * b + d[3] * (r2 + 2.0 * a * a),
                b * radial + d[2] * (r2 + 2.0 * b * b) + 2.0 * d[3] * a * b)
    return fx * a + cx, fy * b + cy


@numba.njit(cache=True, nogil=True, fastmath=True)
def _splat(depth, fxd, fyd, cxd, cyd, fxc, fyc, cxc, cyc, dist, R, t, margin, out):
    hd, wd = depth.shape
    hc, wc = out.shape
    # Half a depth pixel's diagonal, per metre of depth, turned into the colour frame: the
    # pixel's corners are its centre's point -/+ z times this.
    ex = 0.5 * (R[0, 0] / fxd + R[0, 1] / fyd)
    ey = 0.5 * (R[1, 0] / fxd + R[1, 1] / fyd)
    ez = 0.5 * (R[2, 0] / fxd + R[2, 1] / fyd)
    for v in range(hd):
        yv = (v - cyd) / fyd
        for u in range(wd):
            z = float(depth[v, u])
            if not (z > 0.0):
                continue
            xu = (u - cxd) / fxd
            X = z * (R[0, 0] * xu + R[0, 1] * yv + R[0, 2]) + t[0]
            Y = z * (R[1, 0] * xu + R[1, 1] * yv + R[1, 2]) + t[1]
            Z = z * (R[2, 0] * xu + R[2, 1] * yv + R[2, 2]) + t[2]
            za, zb = Z - z * ez, Z + z * ez
            if Z <= 0.0 or za <= 0.0 or zb <= 0.0:
                continue
            xa, ya = _project(X - z * ex, Y - z * ey, za, fxc, fyc, cxc, cyc, dist)
            xb, yb = _project(X + z * ex, Y + z * ey, zb, fxc, fyc, cxc, cyc, dist)
            x0, x1 = min(xa, xb) - margin, max(xa, xb) + margin
            y0, y1 = min(ya, yb) - margin, max(ya, yb) + margin
            # Colour pixel centres i with x0 <= i < x1 (half-open squares: neighbours tile).
            i0, i1 = max(int(math.ceil(x0)), 0), min(int(math.ceil(x1)) - 1, wc - 1)
            j0, j1 = max(int(math.ceil(y0)), 0), min(int(math.ceil(y1)) - 1, hc - 1)
            if i1 - i0 > 8 or j1 - j0 > 8:
                continue        # a pixel seen edge-on, stretched across the image: not a surface
            zf = np.float32(Z)
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    if zf < out[j, i]:
                        out[j, i] = zf
