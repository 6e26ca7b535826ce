"""Correspondences from shape: depth points -> normals -> FPFH descriptors -> matches, and the
per-instance refinement (point-to-plane ICP) and depth check that shape matches need.

No ROS, no colour. The steps, for the model (once) and for each frame's search region:

1. voxel-downsample the points (voxel from the object's size: ``shape_voxel``);
2. normals by PCA over the neighbours within ``NORMAL_RADIUS`` voxels (oriented towards the
   camera in a frame, along the mesh's face normals in the model), and the surface
   variation lambda_min / sum(lambda) over ``FEATURE_RADIUS`` voxels;
3. FPFH (Rusu et al. 2009): 3 x 11-bin histograms of the Darboux-frame angles to the
   neighbours within ``FEATURE_RADIUS`` voxels (SPFH), plus the distance-weighted mean of the
   neighbours' SPFH; compiled with numba;
4. only "salient" points (surface variation above a threshold: edges, corners, curved
   surfaces) are matched: a flat face's descriptor is the same everywhere and every match on
   it is an outlier;
5. one-to-many: each salient scene point to its ``k`` nearest model descriptors (FLANN).

ECC clusters the matches (90 % and more outliers are normal here); each transform is then
refined by ICP of the model's surface against the frame's points and kept only if the depth
image agrees with the model's visible surface (``depth_support``).
"""
from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from ..messages import CameraIntrinsics
from ..transforms import apply_transform, invert_transform

FPFH_BINS = 11
FPFH_DIM = 3 * FPFH_BINS
NORMAL_RADIUS = 2.5       # voxels
FEATURE_RADIUS = 5.0      # voxels
MAX_NEIGHBOURS = 40


def shape_voxel(extent, points_per_diameter: float = 25.0, minimum: float = 0.004) -> float:
    """Voxel size (metres) for an object of box ``extent``: about 25 voxels across its
    diagonal, never below 4 mm (the depth noise of a D4xx at 1 m is about 2 mm)."""
    return float(max(np.linalg.norm(np.asarray(extent, np.float64)) / points_per_diameter, minimum))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The mean point of each occupied voxel, (M, 3) float64."""
    if len(points) == 0:
        return np.zeros((0, 3))
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    for k in range(3):
        sums[:, k] = np.bincount(inverse, weights=points[:, k], minlength=len(counts))
    return sums / counts[:, None]


def neighbours(points: np.ndarray, radius: float, k: int = MAX_NEIGHBOURS, tree=None) -> np.ndarray:
    """(N, k) indices of each point's nearest neighbours within ``radius`` (itself included),
    -1 where there are fewer."""
    tree = tree or cKDTree(points)
    dist, idx = tree.query(points, k=min(k, len(points)), distance_upper_bound=radius, workers=-1)
    idx = np.where(np.isfinite(dist), idx, -1).astype(np.int64)
    return idx.reshape(len(points), -1)


@numba.njit(cache=True, fastmath=True)
def _normals_and_variation(points, nbr_normal, nbr_feature):
    n = points.shape[0]
    normals = np.zeros((n, 3))
    variation = np.zeros(n)
    for i in range(n):
        for which in range(2):
            nbr = nbr_normal[i] if which == 0 else nbr_feature[i]
            cnt = 0
            m0 = 0.0
            m1 = 0.0
            m2 = 0.0
            for j in nbr:
                if j < 0:
                    break
                m0 += points[j, 0]
                m1 += points[j, 1]
                m2 += points[j, 2]
                cnt += 1
            if cnt < 3:
                continue
            m0 /= cnt
            m1 /= cnt
            m2 /= cnt
            C = np.zeros((3, 3))
            for j in nbr:
                if j < 0:
                    break
                d0 = points[j, 0] - m0
                d1 = points[j, 1] - m1
                d2 = points[j, 2] - m2
                C[0, 0] += d0 * d0
                C[0, 1] += d0 * d1
                C[0, 2] += d0 * d2
                C[1, 1] += d1 * d1
                C[1, 2] += d1 * d2
                C[2, 2] += d2 * d2
            C[1, 0] = C[0, 1]
            C[2, 0] = C[0, 2]
            C[2, 1] = C[1, 2]
            w, v = np.linalg.eigh(C)
            if which == 0:
                normals[i, 0] = v[0, 0]
                normals[i, 1] = v[1, 0]
                normals[i, 2] = v[2, 0]
            else:
                s = w[0] + w[1] + w[2]
                variation[i] = w[0] / s if s > 0 else 0.0
    return normals, variation


def normals_and_variation(points: np.ndarray, voxel: float, toward=None, along=None, tree=None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (N, 3), surface variation (N,) and the FPFH neighbour table (N, k).
    Normals are flipped to face ``toward`` (a viewpoint) or to agree with ``along`` (N, 3)."""
    tree = tree or cKDTree(points)
    nbr_f = neighbours(points, FEATURE_RADIUS * voxel, MAX_NEIGHBOURS, tree)
    nbr_n = neighbours(points, NORMAL_RADIUS * voxel, 16, tree)
    normals, variation = _normals_and_variation(np.ascontiguousarray(points, np.float64), nbr_n, nbr_f)
    if toward is not None:
        flip = np.einsum("ij,ij->i", normals, np.asarray(toward, np.float64) - points) < 0
    else:
        flip = np.einsum("ij,ij->i", normals, along) < 0
    normals[flip] *= -1.0
    return normals, variation, nbr_f


@numba.njit(cache=True, fastmath=True)
def _spfh(points, normals, nbr, bins):
    n = points.shape[0]
    hist = np.zeros((n, 3 * bins))
    for i in range(n):
        cnt = 0
        for j in nbr[i]:
            if j < 0:
                break
            if j == i:
                continue
            # Darboux frame at the source; the source is the point whose normal makes the
            # smaller angle with the line joining them (Rusu's convention, order-invariant).
            dx = points[j, 0] - points[i, 0]
            dy = points[j, 1] - points[i, 1]
            dz = points[j, 2] - points[i, 2]
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            if dist < 1e-9:
                continue
            dx /= dist
            dy /= dist
            dz /= dist
            ns0, ns1, ns2 = normals[i, 0], normals[i, 1], normals[i, 2]
            nt0, nt1, nt2 = normals[j, 0], normals[j, 1], normals[j, 2]
            if abs(ns0 * dx + ns1 * dy + ns2 * dz) < abs(nt0 * dx + nt1 * dy + nt2 * dz):
                ns0, ns1, ns2, nt0, nt1, nt2 = nt0, nt1, nt2, ns0, ns1, ns2
                dx, dy, dz = -dx, -dy, -dz
            phi = ns0 * dx + ns1 * dy + ns2 * dz
            v0 = ns1 * dz - ns2 * dy
            v1 = ns2 * dx - ns0 * dz
            v2 = ns0 * dy - ns1 * dx
            vn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if vn < 1e-9:
                continue
            v0 /= vn
            v1 /= vn
            v2 /= vn
            w0 = ns1 * v2 - ns2 * v1
            w1 = ns2 * v0 - ns0 * v2
            w2 = ns0 * v1 - ns1 * v0
            alpha = v0 * nt0 + v1 * nt1 + v2 * nt2
            theta = math.atan2(w0 * nt0 + w1 * nt1 + w2 * nt2, ns0 * nt0 + ns1 * nt1 + ns2 * nt2)
            ba = min(int((alpha + 1.0) * 0.5 * bins), bins - 1)
            bp = min(int((phi + 1.0) * 0.5 * bins), bins - 1)
            bt = min(int((theta + math.pi) / (2.0 * math.pi) * bins), bins - 1)
            hist[i, max(ba, 0)] += 1.0
            hist[i, bins + max(bp, 0)] += 1.0
            hist[i, 2 * bins + max(bt, 0)] += 1.0
            cnt += 1
        if cnt > 0:
            for b in range(3 * bins):
                hist[i, b] *= 100.0 / cnt
    return hist


@numba.njit(cache=True, fastmath=True)
def _fpfh(points, spfh, nbr):
    n, d = spfh.shape
    out = np.zeros((n, d), np.float32)
    for i in range(n):
        acc = np.zeros(d)
        wsum = 0.0
        for j in nbr[i]:
            if j < 0:
                break
            if j == i:
                continue
            dx = points[j, 0] - points[i, 0]
            dy = points[j, 1] - points[i, 1]
            dz = points[j, 2] - points[i, 2]
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            if dist < 1e-9:
                continue
            w = 1.0 / dist
            for b in range(d):
                acc[b] += w * spfh[j, b]
            wsum += w
        for b in range(d):
            out[i, b] = spfh[i, b] + (acc[b] / wsum if wsum > 0 else 0.0)
    return out


def fpfh(points: np.ndarray, normals: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """(N, 33) float32 FPFH descriptors from points, normals and the neighbour table."""
    pts = np.ascontiguousarray(points, np.float64)
    spfh = _spfh(pts, np.ascontiguousarray(normals, np.float64), nbr, FPFH_BINS)
    return _fpfh(pts, spfh, nbr)


def describe(points: np.ndarray, voxel: float, toward=None, along=None):
    """(normals (N, 3), surface variation (N,), FPFH (N, 33)) of already downsampled points."""
    tree = cKDTree(points)
    normals, variation, nbr = normals_and_variation(points, voxel, toward, along, tree)
    return normals, variation, fpfh(points, normals, nbr)


class ShapeMatcher:
    """One-to-many nearest descriptors: each query to its ``k`` nearest model descriptors."""

    def __init__(self, model_desc: np.ndarray, k: int = 3, checks: int = 32):
        self.k = int(k)
        self.n_model = len(model_desc)
        self._index = cv2.flann_Index(np.ascontiguousarray(model_desc, np.float32),
                                      {"algorithm": 1, "trees": 4})    # FLANN_INDEX_KDTREE
        self._checks = int(checks)

    def match(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(desc) == 0 or self.n_model == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = min(self.k, self.n_model)
        idx, _ = self._index.knnSearch(np.ascontiguousarray(desc, np.float32), k, params={"checks": self._checks})
        idx = np.asarray(idx, np.int64).reshape(len(desc), k)
        return np.repeat(np.arange(len(desc)), k), idx.ravel()


# --------------------------------------------------------------------------- per instance

def icp_point_to_plane(T: np.ndarray, model_pts: np.ndarray, scene_pts: np.ndarray, scene_normals: np.ndarray,
                       scene_tree: cKDTree, max_dist: float, iterations: int = 10,
                       model_normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Refine T (model -> camera) by point-to-plane ICP of the model points (with
    ``model_normals``: those facing the camera at the current pose; the far side would pull
    the model onto the visible surface) against the scene points; returns (T, share of
    those model points with a scene point within ``max_dist``)."""
    T = np.asarray(T, np.float64).copy()
    share = 0.0
    floor = 0.5 * max_dist
    for it in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        p = model_pts @ R.T + t
        if model_normals is not None:
            # Facing the camera by more than grazing (as in ``depth_support``).
            p = p[np.einsum("ij,ij->i", model_normals @ R.T, p) < -0.2 * np.linalg.norm(p, axis=1)]
        d, j = scene_tree.query(p, k=1, distance_upper_bound=max_dist)   # one thread: small queries
        ok = np.isfinite(d)
        share = float(ok.mean()) if len(ok) else 0.0
        if ok.sum() < 6:
            break
        src, dst, n = p[ok], scene_pts[j[ok]], scene_normals[j[ok]]
        # Linearised about the points' centroid c: minimise sum ((R_d (src - c) + c + t_d -
        # dst) . n)^2 over a small rotation (w) and t_d. Damped: directions the surface does
        # not constrain (sliding along a face seen alone) stay put instead of drifting.
        c = src.mean(axis=0)
        A = np.hstack([np.cross(src - c, n), n])
        b = np.einsum("ij,ij->i", dst - src, n)
        H = A.T @ A
        H[np.diag_indices(6)] += 1e-3 * np.trace(H) / 6.0 + 1e-12
        try:
            x = np.linalg.solve(H, A.T @ b)
        except np.linalg.LinAlgError:
            break
        w, dt = x[:3], x[3:]
        angle = np.linalg.norm(w)
        Rd = cv2.Rodrigues(w.reshape(3, 1))[0] if angle > 0 else np.eye(3)
        T_d = np.eye(4)
        T_d[:3, :3], T_d[:3, 3] = Rd, c - Rd @ c + dt
        T = T_d @ T
        if angle < 1e-4 and np.linalg.norm(dt) < 1e-5:
            break
        # Tighter, but not below half the start: the depth noise (several mm at 2 m) must
        # not leave only a few random pairs, which let the model slide along a face.
        max_dist = max(0.6 * max_dist, floor) if it >= 2 else max_dist
    return T, share


def depth_support(T: np.ndarray, model_pts: np.ndarray, model_normals: np.ndarray, depth_m: np.ndarray,
                  intrinsics: CameraIntrinsics, tolerance: float) -> tuple[float, float, int]:
    """How well the depth image agrees with the model at pose T (model -> camera).

    Of the model's surface points facing the camera and inside the image with valid depth:
    (share within ``tolerance`` of the measured depth, share lying clearly in front of
    the measured surface - there is nothing there - i.e. more than ``tolerance`` nearer the
    camera than the measurement, number of such points). Points behind the measurement may
    be occluded and count as neither."""
    R, t = T[:3, :3], T[:3, 3]
    p = model_pts @ R.T + t
    n = model_normals @ R.T
    facing = np.einsum("ij,ij->i", n, -p) > 0.2 * np.linalg.norm(p, axis=1)
    p = p[facing]
    if len(p) == 0:
        return 0.0, 1.0, 0
    K = intrinsics.K
    z = p[:, 2]
    front = z > 0.05
    p, z = p[front], z[front]
    u = np.round(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(np.int64)
    h, w = depth_m.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], z[inside]
    measured = depth_m[v, u]
    valid = measured > 0
    z, measured = z[valid], measured[valid]
    m = len(z)
    if m == 0:
        return 0.0, 1.0, 0
    diff = measured - z
    agree = np.abs(diff) < tolerance
    free = diff > tolerance          # measured surface further away: the model fills empty space
    return float(agree.mean()), float(free.mean()), m


def scene_cloud(depth_m: np.ndarray, intrinsics: CameraIntrinsics, mask: np.ndarray, voxel: float,
                stride: int = 1) -> np.ndarray:
    """Search-region depth points (camera frame), voxel-downsampled, (M, 3) float64."""
    from .lifting import depth_to_cloud

    pts, _ = depth_to_cloud(depth_m, intrinsics, mask.astype(bool), stride=stride)
    return voxel_downsample(np.asarray(pts, np.float64), voxel)


__all__ = ["shape_voxel", "voxel_downsample", "describe", "fpfh", "normals_and_variation", "ShapeMatcher",
           "icp_point_to_plane", "depth_support", "scene_cloud", "FPFH_DIM"]
