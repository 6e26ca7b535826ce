"""Projective point-to-plane ICP of the object model against a depth image. No ROS.

Between two full detections each tracked instance is brought up to date on the new frame by
aligning a few hundred model points to the depth image around its predicted pose. The
association is projective (Blais & Levine; KinectFusion): a model point q = R p + t is paired
with the depth pixel it projects to, lifted along the same ray, so no neighbour search is
needed; the residual is the distance along the model normal (point-to-plane), minimised by
Gauss-Newton on a small twist. Pairs farther apart in depth than ``max_distance`` are
occlusions or background and are left out; back-facing model points are skipped.

What comes back says how much of the instance the depth image confirms (``fitness``): an
occluded or vanished instance gets a low one and the tracker treats it as a miss.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..messages import CameraIntrinsics
from ..rgbd.shape import apply_twist, normals_and_variation


@dataclass
class IcpResult:
    T: np.ndarray           # (4, 4) refined model -> camera transform
    fitness: float          # share of the visible model points that the depth confirms (0..1)
    visible: int            # model points that face the camera and project into the image
    rmse: float             # metres, point-to-plane, over the confirmed points


def model_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals of a dense object cloud (the shape front end's PCA normals, at the cloud's
    own point spacing), turned to point away from the cloud's centre: right for the convex
    objects of a tabletop, and only the sign is at stake (point-to-plane residuals do not
    depend on it, the back-face test does)."""
    pts = np.asarray(points, dtype=np.float64)
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    normals, _, _ = normals_and_variation(pts, spacing, along=pts - pts.mean(axis=0))
    return normals


def sample_model(points: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` model points spread over the surface (a fixed random subset of a dense cloud
    is already even), with their normals."""
    pts = np.asarray(points, dtype=np.float64)
    normals = model_normals(pts)
    if len(pts) > count:
        pick = np.sort(np.random.default_rng(seed).choice(len(pts), count, replace=False))
        pts, normals = pts[pick], normals[pick]
    return np.ascontiguousarray(pts), np.ascontiguousarray(normals)


@numba.njit(cache=True, fastmath=True)
def _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, max_dist, A, b):
    """One projective association pass; fills the normal equations A x = b of the twist
    x = (omega, tau) (left-multiplied) and returns (pairs used, visible, squared error)."""
    H, W = depth.shape
    used = 0
    visible = 0
    sq = 0.0
    for i in range(6):
        b[i] = 0.0
        for j in range(6):
            A[i, j] = 0.0
    for k in range(pts.shape[0]):
        px, py, pz = pts[k, 0], pts[k, 1], pts[k, 2]
        qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        if qz <= 1e-3:
            continue
        nx = T[0, 0] * nrm[k, 0] + T[0, 1] * nrm[k, 1] + T[0, 2] * nrm[k, 2]
        ny = T[1, 0] * nrm[k, 0] + T[1, 1] * nrm[k, 1] + T[1, 2] * nrm[k, 2]
        nz = T[2, 0] * nrm[k, 0] + T[2, 1] * nrm[k, 1] + T[2, 2] * nrm[k, 2]
        if nx * qx + ny * qy + nz * qz >= 0.0:      # facing away from the camera
            continue
        u = fx * qx / qz + cx
        v = fy * qy / qz + cy
        iu = int(u + 0.5)
        iv = int(v + 0.5)
        if iu < 0 or iv < 0 or iu >= W or iv >= H:
            continue
        visible += 1
        z = depth[iv, iu]
        if not (z > 0.0) or abs(z - qz) > max_dist:
            continue
        s = z / qz                                   # the depth pixel lifted along q's ray
        r = nx * (qx * s - qx) + ny * (qy * s - qy) + nz * (qz * s - qz)
        # d r / d (omega, tau) for q -> q + omega x q + tau: -(q x n, n); signs folded into b.
        j0 = qy * nz - qz * ny
        j1 = qz * nx - qx * nz
        j2 = qx * ny - qy * nx
        J = (j0, j1, j2, nx, ny, nz)
        for i in range(6):
            b[i] += J[i] * r
            for j in range(i, 6):
                A[i, j] += J[i] * J[j]
        used += 1
        sq += r * r
    for i in range(6):
        for j in range(i):
            A[i, j] = A[j, i]
    return used, visible, sq


@numba.njit(cache=True)
def _icp(T0, pts, nrm, depth, fx, fy, cx, cy, iterations, max_dist, inlier_dist, damping):
    T = T0.copy()
    A = np.zeros((6, 6))
    b = np.zeros(6)
    # Coarse to fine: the pairing distance shrinks from max_dist to inlier_dist.
    for it in range(iterations):
        frac = it / max(iterations - 1, 1)
        gate = max_dist + (inlier_dist - max_dist) * frac
        used, _, _ = _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, gate, A, b)
        if used < 6:
            break
        # Levenberg damping keeps directions the depth does not constrain (a box seen only
        # from the top slides freely) where the prediction put them.
        scale = (A[0, 0] + A[1, 1] + A[2, 2] + A[3, 3] + A[4, 4] + A[5, 5]) / 6.0
        for i in range(6):
            A[i, i] += damping * scale + 1e-12
        x = np.linalg.solve(A, b)  # noqa: the twist
        T = apply_twist(T, x)
        if np.abs(x[:3]).max() < 1e-6 and np.abs(x[3:]).max() < 1e-6:
            break
    used, visible, sq = _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, inlier_dist, A, b)
    return T, used, visible, sq


def align_projective(T_init: np.ndarray, points: np.ndarray, normals: np.ndarray, depth_m: np.ndarray,
                     intrinsics: CameraIntrinsics, iterations: int, max_distance: float, inlier_distance: float,
                     damping: float = 1e-3) -> IcpResult:
    """Projective point-to-plane ICP of model ``points`` / ``normals`` (model frame) against a
    depth image, from ``T_init``: the tracker's update, and the shape front end's refinement
    (``frontend.shape_icp_association: projective``)."""
    K = intrinsics.K
    depth = np.ascontiguousarray(depth_m, dtype=np.float32)
    T, used, visible, sq = _icp(np.ascontiguousarray(T_init, dtype=np.float64), np.ascontiguousarray(points, np.float64),
                                np.ascontiguousarray(normals, np.float64), depth,
                                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                                int(iterations), float(max_distance), float(inlier_distance), float(damping))
    return IcpResult(T, used / visible if visible else 0.0, int(visible),
                     float(np.sqrt(sq / used)) if used else float("nan"))


class ProjectiveICP:
    """Aligns one object model to depth images: ``align(T_init, depth_m, intrinsics)``."""

    def __init__(self, points_xyz: np.ndarray, num_points: int = 400, iterations: int = 8,
                 max_distance: float = 0.02, inlier_distance: float = 0.006, damping: float = 1e-3):
        self.points, self.normals = sample_model(points_xyz, num_points)
        self.iterations = int(iterations)
        self.max_distance = float(max_distance)
        self.inlier_distance = float(inlier_distance)
        self.damping = float(damping)

    def align(self, T_init: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> IcpResult:
        return align_projective(T_init, self.points, self.normals, depth_m, intrinsics, self.iterations,
                                self.max_distance, self.inlier_distance, self.damping)


__all__ = ["IcpResult", "ProjectiveICP", "align_projective", "model_normals", "sample_model"]
