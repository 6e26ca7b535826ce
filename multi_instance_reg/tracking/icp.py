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
from ..frontends.shape.geometry import apply_twist, normals_and_variation

# The tracker's distances (icp_max_distance, icp_inlier_distance) hold up to this depth and grow
# with its square beyond: the depth noise of a stereo or structured-light camera does (NOTES:
# D455 about 2 % at 4 m), and a fixed 6 mm confirms nothing of an object 2 m away.
NOISE_REF_M = 1.0


@dataclass
class IcpResult:
    T: np.ndarray           # (4, 4) refined model -> camera transform
    fitness: float          # share of the visible model points that the depth confirms (0..1)
    visible: int            # model points that face the camera, project into the image and have a depth measurement there
    rmse: float             # metres, point-to-plane, over the confirmed points
    in_view: float = 1.0    # share of the model points facing the camera that project into the image
    occluded: int = 0       # visible model points behind the measured surface (something in front of them)
    free: int = 0           # visible model points in front of the measured surface by more than the first pairing
                            # distance: the camera saw through where the model says there is surface

    @property
    def free_share(self) -> float:
        '''Share of the visible model points standing in space the camera saw to be empty:
        evidence against the pose that no occlusion can explain.'''
        return self.free / self.visible if self.visible else 0.0

    @property
    def unoccluded_fitness(self) -> float:
        """Share of the visible model points the depth confirms, those hidden behind something
        else left out: how well the pose fits where the object can be seen at all."""
        seen = self.visible - self.occluded
        return self.fitness * self.visible / seen if seen > 0 else 0.0


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


@numba.njit(cache=True, fastmath=True, nogil=True)
def _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, max_dist, free_dist, noise_ref, centre, A, b):
    """One projective association pass; fills the normal equations A x = b of the twist
    x = (omega, tau), q -> q + omega x (q - centre) + tau (the rotation about the object's
    centre, so that rotation and translation are nearly decoupled), and returns (pairs used,
    visible, squared error). Visible: facing the camera, inside the image and with a depth
    measurement there (a pixel without one, e.g. a side face seen at a grazing angle, is no
    evidence for or against the pose). Free: visible, facing the camera within 60 deg,
    more than ``free_dist`` in front of the measured surface. ``noise_ref`` > 0: the distances
    hold at that depth and grow with its square beyond (a stereo or structured-light camera's
    depth noise grows with the square of the distance), 0: as given everywhere."""
    H, W = depth.shape
    used = 0
    visible = 0
    facing = 0
    inside = 0
    occluded = 0
    free = 0
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
        facing += 1
        u = fx * qx / qz + cx
        v = fy * qy / qz + cy
        iu = int(u + 0.5)
        iv = int(v + 0.5)
        if iu < 0 or iv < 0 or iu >= W or iv >= H:
            continue
        inside += 1
        z = depth[iv, iu]
        if not (z > 0.0):
            continue
        visible += 1
        grow = 1.0
        if noise_ref > 0.0 and qz > noise_ref:
            grow = (qz / noise_ref) * (qz / noise_ref)
        if abs(z - qz) > max_dist * grow:
            if z < qz:
                occluded += 1
            elif z > qz + free_dist * grow and -(nx * qx + ny * qy + nz * qz) > 0.5 * np.sqrt(qx * qx + qy * qy + qz * qz):
                # Only a face the camera looks at (within 60 deg): one seen at a grazing angle
                # lands a pixel beside where it should for the slightest error in the pose.
                free += 1
            continue
        s = z / qz                                   # the depth pixel lifted along q's ray
        r = nx * (qx * s - qx) + ny * (qy * s - qy) + nz * (qz * s - qz)
        # d r / d (omega, tau) for q -> q + omega x (q - centre) + tau: -((q - centre) x n, n);
        # signs folded into b.
        rx, ry, rz = qx - centre[0], qy - centre[1], qz - centre[2]
        j0 = ry * nz - rz * ny
        j1 = rz * nx - rx * nz
        j2 = rx * ny - ry * nx
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
    return used, visible, sq, facing, inside, occluded, free


@numba.njit(cache=True, nogil=True)
def _constrained_step(A, b, radius, damping, min_information):
    """The twist solving A x = b in the directions the depth constrains, 0 in the others.

    The unknowns are scaled to metres at the object's extent (omega * radius, tau) so that
    rotation and translation compare; directions whose information (eigenvalue of the scaled
    normal equations) is below ``min_information`` times the largest are left out: a box seen
    only from its top constrains its height and tilt, not where it lies in that plane, and
    there the residuals are depth noise times the small tilt of noisy normals, which a plain
    solve turns into millimetres of slide on every frame (Gelfand et al. 2003; Zhang et al.
    2016, degeneracy-aware ICP). Levenberg damping, relative to the mean eigenvalue, on top."""
    S = np.array([1.0 / radius, 1.0 / radius, 1.0 / radius, 1.0, 1.0, 1.0])
    As = np.empty((6, 6))
    bs = np.empty(6)
    for i in range(6):
        bs[i] = S[i] * b[i]
        for j in range(6):
            As[i, j] = S[i] * A[i, j] * S[j]
    w, V = np.linalg.eigh(As)
    top = w[5]
    mean = (w[0] + w[1] + w[2] + w[3] + w[4] + w[5]) / 6.0
    y = np.zeros(6)
    for k in range(6):
        if w[k] > min_information * top and w[k] > 0.0:
            c = 0.0
            for i in range(6):
                c += V[i, k] * bs[i]
            c /= w[k] + damping * mean
            for i in range(6):
                y[i] += c * V[i, k]
    for i in range(6):
        y[i] *= S[i]
    return y


@numba.njit(cache=True, nogil=True)
def _icp(T0, pts, nrm, depth, fx, fy, cx, cy, iterations, max_dist, inlier_dist, damping, min_information,
         centroid, radius, noise_ref):
    T = T0.copy()
    A = np.zeros((6, 6))
    b = np.zeros(6)
    # Coarse to fine: the pairing distance shrinks from max_dist to inlier_dist.
    for it in range(iterations):
        frac = it / max(iterations - 1, 1)
        gate = max_dist + (inlier_dist - max_dist) * frac
        centre = np.ascontiguousarray(T[:3, :3]) @ centroid + T[:3, 3]   # contiguous: numba warns on the slice
        used, _, _, _, _, _, _ = _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, gate, max_dist, noise_ref, centre, A, b)
        if used < 6:
            break
        x = _constrained_step(A, b, radius, damping, min_information)
        T = apply_twist(T, x, centre)
        if np.abs(x[:3]).max() < 1e-6 and np.abs(x[3:]).max() < 1e-6:
            break
    centre = np.ascontiguousarray(T[:3, :3]) @ centroid + T[:3, 3]
    used, visible, sq, facing, inside, occluded, free = _pair_pass(T, pts, nrm, depth, fx, fy, cx, cy, inlier_dist,
                                                                   max_dist, noise_ref, centre, A, b)
    return T, used, visible, sq, facing, inside, occluded, free


def align_projective(T_init: np.ndarray, points: np.ndarray, normals: np.ndarray, depth_m: np.ndarray,
                     intrinsics: CameraIntrinsics, iterations: int, max_distance: float, inlier_distance: float,
                     damping: float = 1e-3, min_information: float = 0.0, centroid=None, radius=None,
                     noise_ref: float = 0.0) -> IcpResult:
    """Projective point-to-plane ICP of model ``points`` / ``normals`` (model frame) against a
    depth image, from ``T_init``: the tracker's update, and the shape front end's refinement
    (``frontend.shape_icp_association: projective``). ``centroid`` / ``radius``: the points'
    own unless given (the tracker keeps them). ``noise_ref`` > 0: the distances hold up to that
    depth (m) and grow with its square beyond, as depth noise does; 0: fixed."""
    points = np.ascontiguousarray(points, np.float64)
    if centroid is None:
        centroid = points.mean(axis=0)
    if radius is None:
        radius = float(np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1)))) or 1.0
    K = intrinsics.K
    depth = np.ascontiguousarray(depth_m, dtype=np.float32)
    T, used, visible, sq, facing, inside, occluded, free = _icp(
        np.ascontiguousarray(T_init, dtype=np.float64), points, np.ascontiguousarray(normals, np.float64), depth,
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(iterations), float(max_distance),
        float(inlier_distance), float(damping), float(min_information), np.ascontiguousarray(centroid, np.float64),
        float(radius), float(noise_ref))
    return IcpResult(T, used / visible if visible else 0.0, int(visible),
                     float(np.sqrt(sq / used)) if used else float("nan"), inside / facing if facing else 0.0,
                     int(occluded), int(free))


FITNESS_SLACK = 0.02   # the share of confirmed points an alignment may lose to noise


class ProjectiveICP:
    """Aligns one object model to depth images: ``align(T_init, depth_m, intrinsics)``."""

    def __init__(self, points_xyz: np.ndarray, num_points: int = 400, iterations: int = 8,
                 max_distance: float = 0.02, inlier_distance: float = 0.006, damping: float = 1e-3,
                 min_information: float = 0.0, noise_ref: float = NOISE_REF_M):
        self.points, self.normals = sample_model(points_xyz, num_points)
        self.centroid = np.ascontiguousarray(self.points.mean(axis=0))
        self.radius = float(np.sqrt(np.mean(np.sum((self.points - self.centroid) ** 2, axis=1)))) or 1.0
        self.min_information = float(min_information)
        self.iterations = int(iterations)
        self.max_distance = float(max_distance)
        self.inlier_distance = float(inlier_distance)
        self.damping = float(damping)
        self.noise_ref = float(noise_ref)

    def align(self, T_init: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> IcpResult:
        """The aligned pose, or the start where the alignment confirms a smaller share of the
        model than the start did (by more than FITNESS_SLACK): the wide first pairing pulled
        the model onto a neighbouring surface (demo scene: a box's track slid 6-9 mm a frame,
        fitness 0.92 -> 0.66 in three frames, 5 cm off before a detection came)."""
        res = align_projective(T_init, self.points, self.normals, depth_m, intrinsics, self.iterations,
                               self.max_distance, self.inlier_distance, self.damping, self.min_information,
                               self.centroid, self.radius, self.noise_ref)
        start = align_projective(T_init, self.points, self.normals, depth_m, intrinsics, 0, self.max_distance,
                                 self.inlier_distance, self.damping, self.min_information, self.centroid,
                                 self.radius, self.noise_ref)
        return start if res.fitness < start.fitness - FITNESS_SLACK else res

    def align_all(self, poses, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> IcpResult:
        """One rigid motion D (camera frame) that aligns every instance at its pose in
        ``poses`` to the depth image at once: the camera's motion when the objects rest. What
        one instance leaves free (a box seen from its top: where it lies on the table) the
        others' faces may constrain, and thousands of points average the depth noise."""
        pts = np.concatenate([T[:3, :3] @ self.points.T + T[:3, 3:4] for T in poses], axis=1).T
        nrm = np.concatenate([T[:3, :3] @ self.normals.T for T in poses], axis=1).T
        return align_projective(np.eye(4), pts, nrm, depth_m, intrinsics, self.iterations, self.max_distance,
                                self.inlier_distance, self.damping, self.min_information, noise_ref=self.noise_ref)


def warm_up() -> None:
    """Compile the alignment's kernels now (one object's and the joint form), not on the first
    frame a track is aligned on. numba caches them on disk, but a new checkout compiles them:
    6 s in a live node's first carried detection, longer than a short stream lasts."""
    rng = np.random.default_rng(0)
    icp = ProjectiveICP(rng.uniform(-0.03, 0.03, (200, 3)), num_points=50, iterations=2)
    depth = np.full((48, 64), 0.5, np.float32)
    intrinsics = CameraIntrinsics(np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]]), 64, 48)
    T = np.eye(4)
    T[2, 3] = 0.45
    icp.align(T, depth, intrinsics)
    icp.align_all([T], depth, intrinsics)


__all__ = ["IcpResult", "ProjectiveICP", "align_projective", "model_normals", "sample_model", "warm_up"]
