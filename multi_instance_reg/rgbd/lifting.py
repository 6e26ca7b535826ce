"""Keypoints to 3D: robust depth lookup, undistortion, back-projection (camera optical frame)."""
from __future__ import annotations

import cv2
import numba
import numpy as np

from ..messages import CameraIntrinsics


def lookup_depth(depth_m: np.ndarray, uv: np.ndarray, window: int = 5, depth_min: float = 0.1,
                 depth_max: float = 4.0, max_spread: float = 0.0) -> np.ndarray:
    """Depth in metres at each keypoint: the median of the valid pixels in a window x window
    patch around it, so a single missing (0) pixel does not lose the keypoint.

    Valid = finite and within [depth_min, depth_max]. Returns (K,) float32 with 0 where no
    pixel of the window is valid, or (max_spread > 0) where the valid pixels straddle a depth
    edge: some pixel differs from the median by more than max_spread.
    """
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros(0, np.float32)
    return _window_medians(np.ascontiguousarray(depth_m, dtype=np.float32), uv, max(int(window), 1) // 2,
                           np.float32(depth_min), np.float32(depth_max), np.float32(max_spread))


@numba.njit(cache=True)
def _window_medians(depth, uv, r, depth_min, depth_max, max_spread):
    # A compiled loop: numpy's nanmedian over (K, window^2) patches took ~2.5 ms a frame.
    # Windows are clipped to the image like an edge-replicated border.
    h, w = depth.shape
    out = np.zeros(len(uv), np.float32)
    buf = np.empty((2 * r + 1) ** 2, np.float32)
    for k in range(len(uv)):
        col = int(np.rint(uv[k, 0]))
        row = int(np.rint(uv[k, 1]))
        if col < 0 or col >= w or row < 0 or row >= h:
            continue
        n = 0
        for dr in range(-r, r + 1):
            rr = min(max(row + dr, 0), h - 1)
            for dc in range(-r, r + 1):
                v = depth[rr, min(max(col + dc, 0), w - 1)]
                if np.isfinite(v) and v >= depth_min and v <= depth_max:
                    buf[n] = v
                    n += 1
        if n == 0:
            continue
        med = np.median(buf[:n])
        if max_spread > 0:
            for q in range(n):
                if abs(buf[q] - med) > max_spread:
                    med = 0.0
                    break
        out[k] = med
    return out


def undistort_pixels(uv: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Pixel coordinates as a distortion-free pinhole camera with the same K would see them."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0 or not intrinsics.has_distortion:
        return uv
    K = np.asarray(intrinsics.K, dtype=np.float64)
    D = np.asarray(intrinsics.D, dtype=np.float64)
    if intrinsics.distortion_model == "equidistant":
        und = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), K, D[:4], P=K)
    else:
        und = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, D, P=K)
    return und.reshape(-1, 2)


def backproject(uv_undistorted: np.ndarray, depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(K, 3) float32 points in the camera optical frame (z forward) from undistorted pixels and z depth."""
    K = intrinsics.K
    uv = np.asarray(uv_undistorted, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(depth, dtype=np.float64).reshape(-1)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1).astype(np.float32)


def depth_to_cloud(depth_m: np.ndarray, intrinsics: CameraIntrinsics, mask: np.ndarray | None = None,
                   stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every valid (and masked) depth pixel: (points (P, 3) float32, pixel indices (P, 2) rows, cols)."""
    if intrinsics.has_distortion:
        return _depth_to_cloud_numpy(depth_m, intrinsics, mask, stride)
    K = np.asarray(intrinsics.K, dtype=np.float64)
    has_mask = mask is not None
    return _lift_grid(np.asarray(depth_m), np.asarray(mask) if has_mask else np.zeros((1, 1), np.bool_), has_mask,
                      int(stride), K[0, 2], K[1, 2], K[0, 0], K[1, 1])


def _depth_to_cloud_numpy(depth_m, intrinsics, mask=None, stride=1):
    # With distortion (OpenCV undistorts), and the reference the compiled path is tested against.
    d = depth_m[::stride, ::stride]
    valid = np.isfinite(d) & (d > 0)
    if mask is not None:
        valid &= mask[::stride, ::stride].astype(bool)
    rows, cols = np.nonzero(valid)
    rows_full, cols_full = rows * stride, cols * stride
    uv = np.stack([cols_full, rows_full], axis=1).astype(np.float64)
    pts = backproject(undistort_pixels(uv, intrinsics), d[rows, cols], intrinsics)
    return pts, np.stack([rows_full, cols_full], axis=1)


@numba.njit(cache=True, nogil=True)
def _lift_grid(depth, mask, has_mask, stride, cx, cy, fx, fy):
    # depth_to_cloud without distortion in two passes over the sampled pixels (count, fill),
    # the same float64 arithmetic as ``backproject``: the numpy steps (masks, nonzero,
    # gathers, stacks) took ~4 ms of a frame's first, single-threaded, milliseconds.
    h, w = depth.shape
    n = 0
    for r in range(0, h, stride):
        for c in range(0, w, stride):
            v = depth[r, c]
            if np.isfinite(v) and v > 0 and (not has_mask or mask[r, c] != 0):
                n += 1
    pts = np.empty((n, 3), np.float32)
    pix = np.empty((n, 2), np.int64)
    k = 0
    for r in range(0, h, stride):
        for c in range(0, w, stride):
            v = depth[r, c]
            if np.isfinite(v) and v > 0 and (not has_mask or mask[r, c] != 0):
                z = np.float64(v)
                pts[k, 0] = np.float32((np.float64(c) - cx) / fx * z)
                pts[k, 1] = np.float32((np.float64(r) - cy) / fy * z)
                pts[k, 2] = np.float32(z)
                pix[k, 0] = r
                pix[k, 1] = c
                k += 1
    return pts, pix


def fit_dominant_plane(points: np.ndarray, thresh: float, iterations: int = 200, seed: int = 0,
                       max_sample: int = 5000) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC plane n.x + d = 0 (|n| = 1, oriented towards the camera: d > 0) with the most
    points within ``thresh``, refined by least squares on its inliers.

    Returns (n, d, inlier mask over ``points``) or None for fewer than 50 points.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 50:
        return None
    rng = np.random.default_rng(seed)
    sample = points if len(points) <= max_sample else points[rng.choice(len(points), max_sample, replace=False)]
    # All hypotheses at once: (I, 3) normals from random triples.
    tri = sample[rng.integers(0, len(sample), size=(iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    if not ok.any():
        return None
    normals = normals[ok] / norms[ok, None]
    offsets = -np.einsum("ij,ij->i", normals, tri[ok, 0])
    counts = _plane_counts(np.ascontiguousarray(sample.T), np.ascontiguousarray(normals), offsets, float(thresh))
    best = int(np.argmax(counts))
    n, d = normals[best], offsets[best]
    inl = np.abs(points @ n + d) < thresh
    if inl.sum() >= 3:  # least-squares refit on the inliers
        c = points[inl].mean(axis=0)
        _, _, vt = np.linalg.svd(points[inl] - c, full_matrices=False)
        n = vt[2]
        d = -n @ c
        inl = np.abs(points @ n + d) < thresh
    if d < 0:  # orient the normal towards the camera (the origin is on the positive side)
        n, d = -n, -d
    return n, float(d), inl


@numba.njit(cache=True, nogil=True)
def _plane_counts(xyz, normals, offsets, thresh):
    # Each hypothesis's points (xyz: (3, N)) within thresh, in one pass: the (points x
    # hypotheses) arrays of distances and flags cost 1-3 ms a call (support_mask calls this
    # 4 times a frame).
    counts = np.zeros(normals.shape[0], np.int64)
    x, y, z = xyz[0], xyz[1], xyz[2]
    for h in range(normals.shape[0]):
        n0, n1, n2, d = normals[h, 0], normals[h, 1], normals[h, 2], offsets[h]
        c = 0
        for i in range(x.shape[0]):
            c += abs(x[i] * n0 + y[i] * n1 + z[i] * n2 + d) < thresh
        counts[h] = c
    return counts


def support_planes(depth_m: np.ndarray, intrinsics: CameraIntrinsics, count: int = 1, thresh: float = 0.01,
                   min_share: float = 0.2, stride: int = 8, seed: int = 0,
                   object_reach: float = 0.0) -> list[tuple[np.ndarray, float]]:
    """Up to ``count`` dominant planes of a depth image (the table, then e.g. a wall), each
    holding at least ``min_share`` of the valid pixels; found on a sparse pixel grid.

    The tops of many like objects resting on a table (ten snack bars lying flat) form a
    plane of their own, parallel to the table and nearer than ``object_reach`` (the object's
    size) to it: of two such planes only the farther, the support, is returned, so that the
    objects are not removed with the "plane" of their tops."""
    pts, _ = depth_to_cloud(depth_m, intrinsics, stride=stride)
    pts = pts.astype(np.float64)
    total = len(pts)
    planes: list[tuple[np.ndarray, float]] = []
    for k in range(count + 2):      # a plane of object tops costs a try
        if len(planes) == count:
            break
        # Hypotheses scored on 2,000 of the ~4,800 grid points: the same planes on the
        # synthetic scenes (the refit uses all of them), in two thirds of the time.
        plane = fit_dominant_plane(pts, thresh, iterations=100, seed=seed + k, max_sample=2000)
        if plane is None or plane[2].sum() < min_share * total:
            break
        n, d, inliers = plane
        pts = pts[~inliers]
        twin = next((i for i, (n0, d0) in enumerate(planes)
                     if n0 @ n > _PARALLEL_COS and abs(d0 - d) < object_reach), None)
        if twin is None:
            planes.append((n, d))
        elif d > planes[twin][1]:   # d: the plane's distance from the camera
            planes[twin] = (n, d)
    return planes


_PARALLEL_COS = float(np.cos(np.radians(10.0)))


def off_planes(points: np.ndarray, planes, thresh: float) -> np.ndarray:
    """(N,) bool: points more than ``thresh`` in front of every plane (on the camera's side)."""
    keep = np.ones(len(points), bool)
    for n, d in planes:
        keep &= points @ n + d > thresh
    return keep
