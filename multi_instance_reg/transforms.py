"""Rigid transforms: fitting (Kabsch/Umeyama without scale) and pose conversions.

Conventions used everywhere in the package:
- a transform is a 4x4 float64 matrix T mapping points of frame A into frame B, y = R x + t;
- a quaternion is (x, y, z, w), as in geometry_msgs/Quaternion.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rigid_fit(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform T with tgt ~ R src + t, det(R) = +1.

    Degenerate inputs (fewer than 3 points, coincident or collinear points) still give a
    proper rotation: the SVD picks some rotation in the unconstrained directions.
    """
    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    if len(src) == 0:
        return np.eye(4)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    wsum = w.sum()
    if not wsum > 0:
        return np.eye(4)
    mu_s = (w[:, None] * src).sum(0) / wsum
    mu_t = (w[:, None] * tgt).sum(0) / wsum
    H = ((src - mu_s) * w[:, None]).T @ (tgt - mu_t)
    U, _, Vt = np.linalg.svd(H)
    # Reflection guard: flip the axis of the smallest singular value.
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return make_transform(R, mu_t - R @ mu_s)


def refine_transform(T: np.ndarray, src: np.ndarray, tgt: np.ndarray, thresh: float, iterations: int) -> np.ndarray:
    """Least squares on the correspondences within ``thresh`` of T, repeated: a tighter
    re-selection than the clustering's inlier threshold, so depth noise at the edges and
    near-miss matches stop pulling the pose."""
    for _ in range(iterations):
        sel = np.linalg.norm(apply_transform(T, src) - tgt, axis=1) < thresh
        if sel.sum() < 3:
            break
        T_new = rigid_fit(src[sel], tgt[sel])
        converged = np.allclose(T_new, T, atol=1e-7)
        T = T_new
        if converged:
            break
    return T


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def invert_transform(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def matrix_to_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 -> (position (3,), quaternion xyzw (4,))."""
    return np.asarray(T[:3, 3], dtype=np.float64).copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def pose_to_matrix(position, quaternion_xyzw) -> np.ndarray:
    """(position, quaternion xyzw) -> 4x4. The quaternion is normalised first."""
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    return make_transform(Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(), position)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees, robust to round-off just outside [-1, 1]."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
