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
import threading

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from ...messages import CameraIntrinsics
from ...threads import map_in_chunks
from ...transforms import apply_transform, invert_transform

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


@numba.njit(cache=True, fastmath=True, nogil=True)
def _normals_and_variation(points, nbr_normal, nbr_feature):
    # Rows of the neighbour tables (of all points, or of a part of them).
    n = nbr_normal.shape[0]
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
    return _orient(normals, points, toward, along), variation, nbr_f


# The most a frame cloud's normal may be turned by the depth noise, per axis (degrees):
# ``normal_radius`` widens the neighbourhood until the plane fit's slope error is this.
NORMAL_TILT_DEG = 5.0
# ``surface_normals``' smoothing averages a point's normal with those of the neighbours
# within this angle of it (not across an edge), twice.
SMOOTH_DEG = 40.0
SMOOTH_ROUNDS = 2


def normal_radius(voxel: float, sigma: float) -> float:
    """Metres: the neighbourhood for normals on a cloud of ``voxel`` spacing whose depth noise
    is ``sigma`` (metres, 1 sigma): NORMAL_RADIUS voxels, wider where a plane fitted over
    it would tilt by more than NORMAL_TILT_DEG per axis. Over n points within r, each off by
    sigma (the noise of a real camera is correlated over several pixels: the voxels' means
    keep it), the slope's error is 2 sigma / (r sqrt(n)), n = pi r^2 / voxel^2. At 2.5
    voxels, on the realistic sensor at 1.76 m (sigma 15 mm), carton tops' normals were a
    median 21 deg off (69 % over the 15 deg a face allows)."""
    wide = math.sqrt(2.0 * sigma * voxel / (math.sqrt(math.pi) * math.tan(math.radians(NORMAL_TILT_DEG))))
    return max(NORMAL_RADIUS * voxel, wide)


@numba.njit(cache=True, fastmath=True, nogil=True)
def _smoothed(normals, nbr, cos_min):
    # Each normal averaged with its neighbours' (sign-aligned) that lie within the angle.
    out = np.empty_like(normals)
    for i in range(normals.shape[0]):
        sx, sy, sz = 0.0, 0.0, 0.0
        for k in range(nbr.shape[1]):
            j = nbr[i, k]
            if j < 0:
                break
            c = normals[i, 0] * normals[j, 0] + normals[i, 1] * normals[j, 1] + normals[i, 2] * normals[j, 2]
            if abs(c) < cos_min:
                continue
            s = 1.0 if c > 0 else -1.0
            sx += s * normals[j, 0]
            sy += s * normals[j, 1]
            sz += s * normals[j, 2]
        norm = math.sqrt(sx * sx + sy * sy + sz * sz)
        if norm > 0:
            out[i, 0], out[i, 1], out[i, 2] = sx / norm, sy / norm, sz / norm
        else:
            out[i, 0], out[i, 1], out[i, 2] = normals[i, 0], normals[i, 1], normals[i, 2]
    return out


def surface_normals(points: np.ndarray, voxel: float, toward, tree=None, radius: float | None = None) -> np.ndarray:
    """The normals of ``normals_and_variation`` alone (facing ``toward``), without the wider
    neighbourhood the variation and FPFH need: point-pair voting uses only the normals, and
    that search was half of the frame cloud's time. ``radius``: metres (``normal_radius``),
    where wider than NORMAL_RADIUS voxels: each normal is then averaged with those of its
    neighbours within it that turn by at most SMOOTH_DEG (SMOOTH_ROUNDS times): the noise
    averages out over a face, not across its edges (a plane fit that wide rounded the
    cartons' edges: a carton on the realistic sensor's pallet lost its face pose)."""
    tree = tree or cKDTree(points)
    nbr_n = neighbours(points, NORMAL_RADIUS * voxel, 16, tree)
    pts = np.ascontiguousarray(points, np.float64)
    # Rows in parts on the shared thread pool (an eigen-decomposition per point; the frame
    # cloud's other core is free once its segments are found).
    parts = map_in_chunks(lambda rows: _normals_and_variation(pts, rows, np.zeros((len(rows), 0), np.int64))[0],
                          nbr_n)
    normals = np.concatenate(parts)
    if radius is not None and radius > NORMAL_RADIUS * voxel * (1 + 1e-9):
        wide = neighbours(points, radius, max(16, int(math.ceil(math.pi * (radius / voxel) ** 2))), tree)
        for _ in range(SMOOTH_ROUNDS):
            normals = _smoothed(normals, wide, math.cos(math.radians(SMOOTH_DEG)))
    return _orient(normals, points, toward, None)


def _orient(normals: np.ndarray, points: np.ndarray, toward, along) -> np.ndarray:
    """Normals flipped to face ``toward`` (a viewpoint) or to agree with ``along`` (N, 3)."""
    if toward is not None:
        flip = np.einsum("ij,ij->i", normals, np.asarray(toward, np.float64) - points) < 0
    else:
        flip = np.einsum("ij,ij->i", normals, along) < 0
    normals[flip] *= -1.0
    return normals


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

class PointGrid:
    """Points sorted into cubic cells of side ``cell`` (a dense table of where each cell's
    points start), for the nearest point within ``cell`` of a query in compiled code (27
    cells visited; ICP reads them from each cell's list of candidates, ``neighbour_lists``).
    Built once per frame; ICP asks it a few hundred queries per round, for which a k-d
    tree's per-call overhead dominated."""

    MAX_CELLS = 1 << 22     # cells are widened beyond this (a wide, deep scene; 32 MB table)

    def __init__(self, points: np.ndarray, normals: np.ndarray, cell: float):
        pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        self.lo = pts.min(axis=0) if len(pts) else np.zeros(3)
        span = (pts.max(axis=0) - self.lo) if len(pts) else np.zeros(3)
        cell = float(cell)
        if np.prod(np.floor(span / cell) + 1) > self.MAX_CELLS:
            cell *= (np.prod(span / cell + 1) / self.MAX_CELLS) ** (1 / 3) * 1.01
        self.cell = cell
        self.dims = (np.floor(span / cell) + 1).astype(np.int64)
        idx = np.minimum(np.floor((pts - self.lo) / cell).astype(np.int64), self.dims - 1)
        keys = (idx[:, 0] * self.dims[1] + idx[:, 1]) * self.dims[2] + idx[:, 2]
        order = np.argsort(keys, kind="stable")
        self.start = np.searchsorted(keys[order], np.arange(int(np.prod(self.dims)) + 1))
        self.points = np.ascontiguousarray(pts[order])
        self.normals = np.ascontiguousarray(np.asarray(normals, np.float64).reshape(-1, 3)[order])
        self._lists = None
        self._lists_lock = threading.Lock()

    def neighbour_lists(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each cell's candidates (``_neighbour_lists``), built on first use (0.3-2 ms): a frame
        whose hypotheses are all dropped before ICP does not pay for them. Thread-safe."""
        with self._lists_lock:
            if self._lists is None:
                self._lists = _neighbour_lists(self.points, self.start, self.dims)
            return self._lists


@numba.njit(cache=True, nogil=True)
def _grid_nearest(x, y, z, pts, start, lo, dims, cell, max_dist):
    """Index (into the grid's points) of the nearest point closer than ``max_dist`` (<=
    cell), -1 if none. The query's own column of cells first; a neighbouring cell is
    skipped when its box is no nearer than the best point so far (the answer is the same)."""
    fx, fy, fz = (x - lo[0]) / cell, (y - lo[1]) / cell, (z - lo[2]) / cell
    bx, by, bz = int(math.floor(fx)), int(math.floor(fy)), int(math.floor(fz))
    best, best_d2 = -1, max_dist * max_dist
    # Distance from the query to the lower / upper neighbour cell along each axis.
    gx = ((fx - bx) * cell, (bx + 1 - fx) * cell)
    gy = ((fy - by) * cell, (by + 1 - fy) * cell)
    gz = ((fz - bz) * cell, (bz + 1 - fz) * cell)
    for c in range(9):
        # Columns in the order (0, 0), then the other eight.
        dx = (0, -1, 1, 0, 0, -1, -1, 1, 1)[c]
        dy = (0, 0, 0, -1, 1, -1, 1, -1, 1)[c]
        kx, ky = bx + dx, by + dy
        if kx < 0 or ky < 0 or kx >= dims[0] or ky >= dims[1]:
            continue
        ex = 0.0 if dx == 0 else (gx[0] if dx < 0 else gx[1])
        ey = 0.0 if dy == 0 else (gy[0] if dy < 0 else gy[1])
        col2 = ex * ex + ey * ey
        if col2 >= best_d2:
            continue
        z0 = bz - 1 if col2 + gz[0] * gz[0] < best_d2 else bz
        z1 = bz + 1 if col2 + gz[1] * gz[1] < best_d2 else bz
        z0, z1 = max(z0, 0), min(z1, dims[2] - 1)
        if z0 > z1:
            continue
        # The cells along z of one (x, y) hold consecutive points.
        base = (kx * dims[1] + ky) * dims[2]
        for j in range(start[base + z0], start[base + z1 + 1]):
            ex2, ey2, ez2 = pts[j, 0] - x, pts[j, 1] - y, pts[j, 2] - z
            d2 = ex2 * ex2 + ey2 * ey2 + ez2 * ez2
            if d2 < best_d2:
                best, best_d2 = j, d2
    return best


@numba.njit(cache=True, nogil=True)
def _neighbour_lists(pts, start, dims):
    """For every cell, the points of its 3 x 3 x 3 cells in the order ``_grid_nearest`` visits
    them (its columns in that order, each from low z up, a cell's points as stored): (first
    (cells + 1,), point index and its coordinates, one row per entry). A query then scans one
    contiguous run instead of up to nine columns (ICP, 40 % less time a query), and keeps the
    same nearest point: the cells ``_grid_nearest`` skips hold none nearer than its best."""
    D0, D1, D2 = dims[0], dims[1], dims[2]
    ncell = D0 * D1 * D2
    occupied = np.empty(min(ncell, pts.shape[0]), np.int64)     # no more cells hold points than there are points
    no = 0
    for c in range(ncell):
        if start[c + 1] > start[c]:
            occupied[no] = c
            no += 1
    first = np.zeros(ncell + 1, np.int64)
    for k in range(no):
        c = occupied[k]
        cx, cy, cz = c // (D1 * D2), (c // D2) % D1, c % D2
        for tx in range(max(cx - 1, 0), min(cx + 1, D0 - 1) + 1):
            for ty in range(max(cy - 1, 0), min(cy + 1, D1 - 1) + 1):
                for tz in range(max(cz - 1, 0), min(cz + 1, D2 - 1) + 1):
                    first[(tx * D1 + ty) * D2 + tz + 1] += start[c + 1] - start[c]
    for c in range(ncell):
        first[c + 1] += first[c]
    index = np.empty(first[ncell], np.int64)
    xyz = np.empty((first[ncell], 3))
    fill = first[:ncell].copy()
    # Appended offset by offset in the visiting order: cell t gets the points of t + offset.
    for o in range(9):
        dx = (0, -1, 1, 0, 0, -1, -1, 1, 1)[o]
        dy = (0, 0, 0, -1, 1, -1, 1, -1, 1)[o]
        for dz in range(-1, 2):
            for k in range(no):
                c = occupied[k]
                tx, ty, tz = c // (D1 * D2) - dx, (c // D2) % D1 - dy, c % D2 - dz
                if tx < 0 or ty < 0 or tz < 0 or tx >= D0 or ty >= D1 or tz >= D2:
                    continue
                t = (tx * D1 + ty) * D2 + tz
                f = fill[t]
                for j in range(start[c], start[c + 1]):
                    index[f] = j
                    xyz[f, 0], xyz[f, 1], xyz[f, 2] = pts[j, 0], pts[j, 1], pts[j, 2]
                    f += 1
                fill[t] = f
    return first, index, xyz


@numba.njit(cache=True, nogil=True)
def _listed_nearest(x, y, z, first, index, xyz, pts, start, lo, dims, cell, max_dist):
    """``_grid_nearest`` by the cell's list of candidates (``_neighbour_lists``); the same
    answer (distances computed alike, candidates in the same order). A query outside the
    grid's box has no list: searched as before."""
    bx = int(math.floor((x - lo[0]) / cell))
    by = int(math.floor((y - lo[1]) / cell))
    bz = int(math.floor((z - lo[2]) / cell))
    if bx < 0 or by < 0 or bz < 0 or bx >= dims[0] or by >= dims[1] or bz >= dims[2]:
        return _grid_nearest(x, y, z, pts, start, lo, dims, cell, max_dist)
    c = (bx * dims[1] + by) * dims[2] + bz
    best, best_d2 = -1, max_dist * max_dist
    for k in range(first[c], first[c + 1]):
        ex, ey, ez = xyz[k, 0] - x, xyz[k, 1] - y, xyz[k, 2] - z
        d2 = ex * ex + ey * ey + ez * ez
        if d2 < best_d2:
            best, best_d2 = k, d2
    return index[best] if best >= 0 else -1


@numba.njit(cache=True, nogil=True)
def apply_twist(T, x, centre):
    """exp of the twist x = (omega, tau) about ``centre``, applied on the left of T (Rodrigues);
    the ICP step here and the tracker's (``tracking/icp.py``)."""
    w0, w1, w2 = x[0], x[1], x[2]
    theta = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    if theta < 1e-12:
        R = np.eye(3) + K
    else:
        R = np.eye(3) + np.sin(theta) / theta * K + (1.0 - np.cos(theta)) / (theta * theta) * (K @ K)
    out = np.eye(4)
    out[:3, :3] = R @ np.ascontiguousarray(T[:3, :3])   # contiguous: numba warns on the slice
    out[:3, 3] = R @ (T[:3, 3] - centre) + centre + x[3:]
    return out


@numba.njit(cache=True, nogil=True)
def _icp_grid(T0, mp, mn, use_normals, sp, sn, start, lo, dims, cell, first, index, xyz, max_dist, iterations):
    T = T0.copy()
    share = 0.0
    floor = 0.5 * max_dist
    P = mp.shape[0]
    src = np.empty((P, 3))
    dst = np.empty((P, 3))
    nrm = np.empty((P, 3))
    H = np.empty((6, 6))
    g = np.empty(6)
    a = np.empty(6)
    pos = np.empty((P, 3))
    facing = np.ones(P, np.bool_)
    for it in range(iterations):
        m = 0
        seen = 0
        # Every point posed and judged first, without branches (the compiler vectorises this
        # loop; the pose's entries as scalars, which the stores cannot alias).
        t00, t01, t02, t03 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
        t10, t11, t12, t13 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
        t20, t21, t22, t23 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
        for i in range(P):
            px = t00 * mp[i, 0] + t01 * mp[i, 1] + t02 * mp[i, 2] + t03
            py = t10 * mp[i, 0] + t11 * mp[i, 1] + t12 * mp[i, 2] + t13
            pz = t20 * mp[i, 0] + t21 * mp[i, 1] + t22 * mp[i, 2] + t23
            pos[i, 0], pos[i, 1], pos[i, 2] = px, py, pz
            if use_normals:
                # Facing the camera by more than grazing (as in ``depth_support``).
                nx = t00 * mn[i, 0] + t01 * mn[i, 1] + t02 * mn[i, 2]
                ny = t10 * mn[i, 0] + t11 * mn[i, 1] + t12 * mn[i, 2]
                nz = t20 * mn[i, 0] + t21 * mn[i, 1] + t22 * mn[i, 2]
                facing[i] = nx * px + ny * py + nz * pz < -0.2 * math.sqrt(px * px + py * py + pz * pz)
        for i in range(P):
            if not facing[i]:
                continue
            px, py, pz = pos[i, 0], pos[i, 1], pos[i, 2]
            seen += 1
            # The nearest scene point within max_dist (``_listed_nearest``, written out here:
            # as a call it cost the kernel the time the lists save).
            bx = int(math.floor((px - lo[0]) / cell))
            by = int(math.floor((py - lo[1]) / cell))
            bz = int(math.floor((pz - lo[2]) / cell))
            if bx < 0 or by < 0 or bz < 0 or bx >= dims[0] or by >= dims[1] or bz >= dims[2]:
                j = _grid_nearest(px, py, pz, sp, start, lo, dims, cell, max_dist)
            else:
                c = (bx * dims[1] + by) * dims[2] + bz
                best, best_d2 = -1, max_dist * max_dist
                for k in range(first[c], first[c + 1]):
                    ex, ey, ez = xyz[k, 0] - px, xyz[k, 1] - py, xyz[k, 2] - pz
                    d2 = ex * ex + ey * ey + ez * ez
                    if d2 < best_d2:
                        best, best_d2 = k, d2
                j = index[best] if best >= 0 else -1
            if j < 0:
                continue
            src[m, 0], src[m, 1], src[m, 2] = px, py, pz
            for k in range(3):
                dst[m, k] = sp[j, k]
                nrm[m, k] = sn[j, k]
            m += 1
        share = m / seen if seen > 0 else 0.0
        if m < 6:
            break
        # Linearised about the points' centroid c: minimise sum ((R_d (src - c) + c + t_d -
        # dst) . n)^2 over a small rotation (w) and t_d. Damped: directions the surface does
        # not constrain (sliding along a face seen alone) stay put instead of drifting.
        c0, c1, c2 = 0.0, 0.0, 0.0
        for i in range(m):
            c0 += src[i, 0]
            c1 += src[i, 1]
            c2 += src[i, 2]
        c0, c1, c2 = c0 / m, c1 / m, c2 / m
        H[:] = 0.0
        g[:] = 0.0
        for i in range(m):
            sx, sy, sz = src[i, 0] - c0, src[i, 1] - c1, src[i, 2] - c2
            nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
            a[0], a[1], a[2] = sy * nz - sz * ny, sz * nx - sx * nz, sx * ny - sy * nx
            a[3], a[4], a[5] = nx, ny, nz
            b = (dst[i, 0] - src[i, 0]) * nx + (dst[i, 1] - src[i, 1]) * ny + (dst[i, 2] - src[i, 2]) * nz
            for r in range(6):
                g[r] += a[r] * b
                for s in range(r, 6):
                    H[r, s] += a[r] * a[s]
        for r in range(6):
            for s in range(r):
                H[r, s] = H[s, r]
        damp = 1e-3 * (H[0, 0] + H[1, 1] + H[2, 2] + H[3, 3] + H[4, 4] + H[5, 5]) / 6.0 + 1e-12
        for r in range(6):
            H[r, r] += damp
        x = np.linalg.solve(H, g)
        angle = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
        # T <- T_d T with T_d = (R_d, c - R_d c + t_d): about c, then shifted.
        T = apply_twist(T, x, np.array((c0, c1, c2)))
        if angle < 1e-4 and math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5]) < 1e-5:
            break
        # Tighter, but not below half the start: the depth noise (several mm at 2 m) must
        # not leave only a few random pairs, which let the model slide along a face.
        if it >= 2:
            max_dist = max(0.6 * max_dist, floor)
    return T, share


def icp_point_to_plane(T: np.ndarray, model_pts: np.ndarray, scene_grid: PointGrid, max_dist: float,
                       iterations: int = 10, model_normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Refine T (model -> camera) by point-to-plane ICP of the model points (with
    ``model_normals``: those facing the camera at the current pose; the far side would pull
    the model onto the visible surface) against the scene points and normals in ``scene_grid``
    (nearest within ``max_dist``, at most the grid's cell); returns (T, share of those model points with a scene point
    within ``max_dist``). Compiled: 30-50 hypotheses a frame of ~15 rounds each cost 250 ms
    as numpy calls around a k-d tree."""
    if max_dist > scene_grid.cell * (1 + 1e-9):
        raise ValueError(f"max_dist {max_dist} exceeds the grid's cell {scene_grid.cell}")
    mp = np.ascontiguousarray(model_pts, np.float64)
    use_normals = model_normals is not None
    mn = np.ascontiguousarray(model_normals if use_normals else model_pts, np.float64)
    first, index, xyz = scene_grid.neighbour_lists()
    T, share = _icp_grid(np.ascontiguousarray(T, np.float64), mp, mn, use_normals, scene_grid.points, scene_grid.normals,
                         scene_grid.start, scene_grid.lo, scene_grid.dims, scene_grid.cell, first, index, xyz,
                         float(max_dist), int(iterations))
    return T, float(share)


def depth_support(T: np.ndarray, model_pts: np.ndarray, model_normals: np.ndarray, depth_m: np.ndarray,
                  intrinsics: CameraIntrinsics, tolerance: float, self_hiding: float = 0.0,
                  occluders: np.ndarray | None = None) -> tuple[float, float, int]:
    """How well the depth image agrees with the model at pose T (model -> camera).

    Of the model's surface points facing the camera and inside the image with valid depth:
    (share within ``tolerance`` of the measured depth, share lying clearly in front of
    the measured surface - there is nothing there - i.e. more than ``tolerance`` nearer the
    camera than the measurement, number of such points). Points behind the measurement
    count against the pose (in the number, neither agreeing nor free).

    ``self_hiding`` (metres; 0 for a convex model): a point more than ``tolerance`` plus this
    behind both the measurement and the model's own nearer surface is not visible at this
    pose and not judged at all. The model's surface is drawn where such points are (only
    when there are any), each sample a disc of this radius in its plane (about the samples'
    spacing; the margin: a disc at a face's edge reaches past the edge).

    ``occluders`` ((H, W) uint8): where the measured surface is known to be something else
    (another instance found in the frame): a point behind the measurement there is hidden
    by it, and not judged either.
    An L bracket seen from behind its upright plate hides a third of its facing surface,
    which had counted against the true pose. Compiled (a projection per point; called 2-4
    times per hypothesis)."""
    K = intrinsics.K
    occ = np.zeros((0, 0), np.uint8) if occluders is None else np.ascontiguousarray(occluders, np.uint8)
    return _depth_support(np.ascontiguousarray(T, np.float64), np.ascontiguousarray(model_pts, np.float64),
                          np.ascontiguousarray(model_normals, np.float64), depth_m,
                          float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(tolerance),
                          float(self_hiding), occ)


def is_convex(points: np.ndarray, normals: np.ndarray, tolerance: float) -> bool:
    """Whether a closed surface (samples with outward normals) is convex: no sample lies more
    than ``tolerance`` in front of another's tangent plane. Then whatever faces the camera is
    in view, and the depth check need not look for the model hiding itself."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    for lo in range(0, len(p), 512):
        rows = slice(lo, lo + 512)
        ahead = n[rows] @ p.T - np.einsum("ik,ik->i", n[rows], p[rows])[:, None]
        if ahead.max(initial=0.0) > tolerance:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def posed(T, mp, mn, i):
    """Model point i and its normal at pose T (camera frame): px, py, pz, nx, ny, nz."""
    return (T[0, 0] * mp[i, 0] + T[0, 1] * mp[i, 1] + T[0, 2] * mp[i, 2] + T[0, 3],
            T[1, 0] * mp[i, 0] + T[1, 1] * mp[i, 1] + T[1, 2] * mp[i, 2] + T[1, 3],
            T[2, 0] * mp[i, 0] + T[2, 1] * mp[i, 1] + T[2, 2] * mp[i, 2] + T[2, 3],
            T[0, 0] * mn[i, 0] + T[0, 1] * mn[i, 1] + T[0, 2] * mn[i, 2],
            T[1, 0] * mn[i, 0] + T[1, 1] * mn[i, 1] + T[1, 2] * mn[i, 2],
            T[2, 0] * mn[i, 0] + T[2, 1] * mn[i, 1] + T[2, 2] * mn[i, 2])


@numba.njit(cache=True, nogil=True)
def measured_at(T, mp, mn, i, depth, fx, fy, cx, cy):
    """Model point i (normal mn[i]) at pose T: its camera-frame point and the depth measured
    at its pixel, or 0 there when it does not face the camera clearly (normal within about
    78 deg of the line of sight), lies behind it, falls outside the image or on no depth.
    The projection the depth checks share (here and ``verify.free_space_share``)."""
    px, py, pz, nx, ny, nz = posed(T, mp, mn, i)
    if not (-(nx * px + ny * py + nz * pz) > 0.2 * math.sqrt(px * px + py * py + pz * pz)) or not pz > 0.05:
        return px, py, pz, 0.0
    h, w = depth.shape
    u = round(fx * px / pz + cx)
    v = round(fy * py / pz + cy)
    if u < 0 or u >= w or v < 0 or v >= h:
        return px, py, pz, 0.0
    return px, py, pz, float(depth[v, u])


@numba.njit(cache=True, nogil=True)
def _hidden_by_self(T, mp, mn, fx, fy, cx, cy, bu, bv, bz, nb, tolerance, radius):
    """How many of the ``nb`` points behind the measurement (pixels bu, bv; depth bz) the
    model's own surface at pose T covers nearer than bz - ``tolerance`` - ``radius``: each
    facing sample a disc of ``radius`` in its tangent plane (its plane's depth along the
    pixel's ray, where that ray meets the disc). Only those pixels are looked at, and only
    the discs that reach them (samples bucketed by pixel): drawing every disc over the
    behind points' box was nine tenths of the depth check of a non-convex model (a U
    channel: 0.36 ms a call)."""
    P = mp.shape[0]
    su = np.empty(P, np.int64)
    sv = np.empty(P, np.int64)
    sr = np.empty(P, np.int64)
    sp = np.empty((P, 7))
    deepest = -np.inf
    for k in range(nb):
        deepest = max(deepest, bz[k] - tolerance - radius)
    r2 = radius * radius
    ns = 0
    rmax = 0
    for i in range(P):
        px, py, pz, nx, ny, nz = posed(T, mp, mn, i)
        nd = nx * px + ny * py + nz * pz
        if not (-nd > 0.2 * math.sqrt(px * px + py * py + pz * pz)) or not pz > radius + 0.05:
            continue
        # A disc's depths lie within its radius of its centre's: one no nearer than every
        # behind point's limit hides none of them.
        if pz - 2.0 * radius >= deepest:
            continue
        r = int(math.ceil(radius * fx / (pz - radius) + 0.5))
        su[ns], sv[ns], sr[ns] = int(round(fx * px / pz + cx)), int(round(fy * py / pz + cy)), r
        sp[ns, 0], sp[ns, 1], sp[ns, 2], sp[ns, 3], sp[ns, 4], sp[ns, 5], sp[ns, 6] = px, py, pz, nx, ny, nz, nd
        rmax = max(rmax, r)
        ns += 1
    if ns == 0:
        return 0
    # The samples bucketed by their pixel in cells of rmax + 1 pixels (a counting sort): a
    # disc that reaches a pixel has its centre in the pixel's cell or one of its eight
    # neighbours.
    c = rmax + 1
    umin, vmin = su[:ns].min(), sv[:ns].min()
    cw, ch = (su[:ns].max() - umin) // c + 1, (sv[:ns].max() - vmin) // c + 1
    first = np.zeros(cw * ch + 1, np.int64)
    for i in range(ns):
        first[((sv[i] - vmin) // c) * cw + (su[i] - umin) // c + 1] += 1
    for b in range(cw * ch):
        first[b + 1] += first[b]
    fill = first[:-1].copy()
    order = np.empty(ns, np.int64)
    for i in range(ns):
        b = ((sv[i] - vmin) // c) * cw + (su[i] - umin) // c
        order[fill[b]] = i
        fill[b] += 1
    hidden = 0
    for k in range(nb):
        u, v = bu[k], bv[k]
        limit = bz[k] - tolerance - radius
        dy = (v - cy) / fy
        dx = (u - cx) / fx
        # The pixel's cell (floor division: the pixel may lie left of or above every centre).
        gu, gv = (u - umin) // c, (v - vmin) // c
        found = False
        for yv in range(max(gv - 1, 0), min(gv + 1, ch - 1) + 1):
            if found:
                break
            for xu in range(max(gu - 1, 0), min(gu + 1, cw - 1) + 1):
                if found:
                    break
                b = yv * cw + xu
                for s in range(first[b], first[b + 1]):
                    i = order[s]
                    r = sr[i]
                    if abs(v - sv[i]) > r or abs(u - su[i]) > r:
                        continue
                    px, py, pz, nx, ny, nz, nd = sp[i, 0], sp[i, 1], sp[i, 2], sp[i, 3], sp[i, 4], sp[i, 5], sp[i, 6]
                    den = nx * dx + ny * dy + nz
                    if abs(den) < 1e-9:
                        continue
                    z = nd / den              # the ray (dx, dy, 1) z meets the sample's plane
                    if not z > 0:
                        continue
                    ex, ey, ez = dx * z - px, dy * z - py, z - pz
                    if ex * ex + ey * ey + ez * ez <= r2 and z < limit:
                        found = True
                        break
        if found:
            hidden += 1
    return hidden


@numba.njit(cache=True, nogil=True)
def _depth_support(T, mp, mn, depth, fx, fy, cx, cy, tolerance, self_hiding, occluders):
    by_others = occluders.shape[0] == depth.shape[0]
    m = 0
    agree = 0
    free = 0
    # Points behind the measurement: against the pose, unless the model hides them itself
    # (looked at only when there are any: a true pose in plain view has none).
    bu = np.empty(mp.shape[0], np.int64)
    bv = np.empty(mp.shape[0], np.int64)
    bz = np.empty(mp.shape[0])
    nb = 0
    for i in range(mp.shape[0]):
        px, py, pz, measured = measured_at(T, mp, mn, i, depth, fx, fy, cx, cy)
        if not measured > 0:
            continue
        diff = measured - pz
        if by_others and diff < -tolerance and occluders[round(fy * py / pz + cy), round(fx * px / pz + cx)]:
            continue                # hidden by another instance
        m += 1
        if abs(diff) < tolerance:
            agree += 1
        if diff > tolerance:        # measured surface further away: the model fills empty space
            free += 1
        if diff < -tolerance - self_hiding and self_hiding > 0:
            bu[nb], bv[nb], bz[nb] = round(fx * px / pz + cx), round(fy * py / pz + cy), pz
            nb += 1
    if nb > 0:
        # Behind the model's own nearer surface: not in view at this pose.
        m -= _hidden_by_self(T, mp, mn, fx, fy, cx, cy, bu, bv, bz, nb, tolerance, self_hiding)
    if m == 0:
        return 0.0, 1.0, 0
    return agree / m, free / m, m


def scene_cloud(depth_m: np.ndarray, intrinsics: CameraIntrinsics, mask: np.ndarray, voxel: float,
                stride: int = 1) -> np.ndarray:
    """Search-region depth points (camera frame), voxel-downsampled, (M, 3) float64."""
    from ...rgbd.lifting import depth_to_cloud

    pts, _ = depth_to_cloud(depth_m, intrinsics, mask.astype(bool), stride=stride)
    return voxel_downsample(np.asarray(pts, np.float64), voxel)


__all__ = ["shape_voxel", "voxel_downsample", "describe", "fpfh", "normals_and_variation", "surface_normals", "ShapeMatcher",
           "icp_point_to_plane", "PointGrid", "apply_twist", "depth_support", "is_convex", "scene_cloud",
           "FPFH_DIM"]
