"""The camera's own motion between two frames, from the static scene. No ROS.

    odometry = CameraOdometry()
    D = odometry.step(rgb, depth_m, intrinsics)   # X_now = D @ X_before (optical frames), or None

Objects rest and the camera moves: a hand-held camera shakes a few millimetres and tenths of a
degree a frame, an arm turns it by several degrees between two frames of a slow recording.
A tracker that predicts poses from a velocity mistakes shaking for motion, and a projective
ICP started from the last pose cannot reach across a jump. The scene shows the motion
directly: ORB features of the colour image, lifted to 3D by the depth, matched to the
previous frame's by descriptor alone (no search window, so a jump of any size in the image is
fine), and one rigid motion fitted to them by RANSAC over three-point samples (what moves
on its own, an arm or a carried box, is left out as outliers), refined on its inliers.
Where the frame has too little texture with depth, or too few matches agree, the answer is
None and the tracker falls back on the depth and the detections.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..messages import CameraIntrinsics
from ..rgbd.lifting import backproject, lookup_depth, undistort_pixels

FEATURES = 500              # ORB keypoints a frame
MIN_INLIERS = 15            # matches that must agree on one motion
MIN_INLIER_SHARE = 0.25     # ... and at least this share of the matches
RANSAC_ROUNDS = 64          # with a third of the matches right, 64 samples all miss once in a million
INLIER_M = 0.01             # m, plus INLIER_REL times the depth (depth noise grows with it)
INLIER_REL = 0.01


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid transform taking points src onto dst in the least-squares sense (Kabsch)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cd - R @ cs
    return T


class CameraOdometry:
    """Frame-to-frame camera motion from ORB features with depth (see the module doc)."""

    def __init__(self, features: int = FEATURES, seed: int = 0):
        self._orb = cv2.ORB_create(nfeatures=int(features))
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self._rng = np.random.default_rng(seed)
        self._before: tuple[np.ndarray, np.ndarray] | None = None   # (xyz, descriptors) of the frame before
        self.inliers = 0             # matches that agreed on the last motion
        self._stamp_ns: int | None = None

    def reset(self) -> None:
        """Forget the frame before (the stream jumped back, or restarted)."""
        self._before = None

    def features(self, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """(xyz (K, 3) optical frame, descriptors (K, 32)) of the frame's ORB features that have
        a depth."""
        grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
        keypoints, descriptors = self._orb.detectAndCompute(grey, None)
        if descriptors is None or not keypoints:
            return np.zeros((0, 3)), np.zeros((0, 32), np.uint8)
        uv = np.array([k.pt for k in keypoints], np.float32)
        # Median of a small window, and none on a depth edge: a feature on an object's outline
        # takes its depth from the object or the background at random.
        z = lookup_depth(depth_m, uv, window=3, max_spread=0.02)
        ok = z > 0
        xyz = backproject(undistort_pixels(uv[ok], intrinsics), z[ok], intrinsics)
        return np.asarray(xyz, np.float64), descriptors[ok]

    def step(self, rgb: np.ndarray | None, depth_m: np.ndarray | None,
             intrinsics: CameraIntrinsics | None, stamp_ns: int | None = None) -> np.ndarray | None:
        """The motion D from the frame before to this one (X_now = D @ X_before), or None where
        it cannot be told (the first frame, no colour, too few agreeing matches, the stamps
        went back)."""
        went_back = stamp_ns is not None and self._stamp_ns is not None and int(stamp_ns) < self._stamp_ns
        self._stamp_ns = None if stamp_ns is None else int(stamp_ns)
        if rgb is None or depth_m is None or intrinsics is None or went_back:
            self._before = None
        if rgb is None or depth_m is None or intrinsics is None:
            return None
        now = self.features(rgb, depth_m, intrinsics)
        before, self._before = self._before, now
        self.inliers = 0
        if before is None or len(before[0]) < MIN_INLIERS or len(now[0]) < MIN_INLIERS:
            return None
        matches = self._matcher.match(before[1], now[1])
        if len(matches) < MIN_INLIERS:
            return None
        src = before[0][[m.queryIdx for m in matches]]
        dst = now[0][[m.trainIdx for m in matches]]
        return self._fit(src, dst)

    def _fit(self, src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
        n = len(src)
        tol = INLIER_M + INLIER_REL * dst[:, 2]
        # All samples at once: a Python loop over them cost more than the features.
        s = self._rng.integers(0, n, (RANSAC_ROUNDS, 3))
        s = s[(s[:, 0] != s[:, 1]) & (s[:, 1] != s[:, 2]) & (s[:, 0] != s[:, 2])]
        a, b = src[s], dst[s]                                       # (R, 3, 3)
        # Only matches that keep their mutual distances can belong to one rigid motion, and
        # three points define one only if they span a triangle.
        keep = (np.abs(np.linalg.norm(a - a[:, [1, 2, 0]], axis=2) - np.linalg.norm(b - b[:, [1, 2, 0]], axis=2)).max(axis=1)
                <= 0.02) & (np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1) >= 1e-4)
        if not keep.any():
            return None
        a, b = a[keep], b[keep]
        ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
        U, _, Vt = np.linalg.svd(np.swapaxes(a - ca, 1, 2) @ (b - cb))
        V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
        flip = np.ones((len(a), 3))
        flip[:, 2] = np.sign(np.linalg.det(V @ Ut))
        R = (V * flip[:, None, :]) @ Ut                              # (R', 3, 3)
        t = cb[:, 0] - np.einsum("rij,rj->ri", R, ca[:, 0])
        moved = src @ np.swapaxes(R, 1, 2) + t[:, None, :]              # (R', N, 3)
        counts = (np.linalg.norm(moved - dst[None], axis=2) < tol[None]).sum(axis=1)
        k = int(counts.argmax())
        best = np.linalg.norm(moved[k] - dst, axis=1) < tol
        if best.sum() < max(MIN_INLIERS, MIN_INLIER_SHARE * n):
            return None
        for _ in range(2):          # refit on the inliers, then once more on the refit's
            T = rigid_fit(src[best], dst[best])
            best = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < tol
            if best.sum() < MIN_INLIERS:
                return None
        self.inliers = int(best.sum())
        return T


__all__ = ["CameraOdometry", "rigid_fit"]
