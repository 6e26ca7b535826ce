"""Is a pose hypothesis an object, or a piece of a larger surface? Checks against the depth
image beyond ``shape.depth_support`` (which asks whether the model's visible surface is
there). No ROS, no colour.

A face seen alone is placed by its outline: the object ends where the depth image steps
away (to the support below, or to an occluder in front). A model fitted onto part of a
larger surface (a carton onto the top of a crate, a small cylinder's cap onto a wide one's)
agrees with the depth everywhere it covers, and is told apart only by what lies just outside
its outline: the same surface, continuing.

    share, n = outline_continuation(T, surface, surface_normals, depth_m, intrinsics, voxel, tol)
"""
from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from ..messages import CameraIntrinsics
from ..symmetry import best_symmetry
from ..transforms import apply_transform, invert_transform
from ..frontends.shape.geometry import measured_at



def _points_and_normals(depth: np.ndarray, K: np.ndarray, rows: np.ndarray, cols: np.ndarray, step: int = 2
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points and normals (towards the camera; central differences ``step``
    pixels apart) at the given pixels, and which of them have all four neighbours' depth."""
    ok = np.zeros(len(rows), np.bool_)
    P = np.empty((len(rows), 3))
    n = np.empty((len(rows), 3))
    m = _points_and_normals_kernel(np.asarray(depth), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                                   np.asarray(rows, np.int64), np.asarray(cols, np.int64), int(step), P, n, ok)
    return P[:m], n[:m], ok


@numba.njit(cache=True, nogil=True)
def _points_and_normals_kernel(depth, fx, fy, cx, cy, rows, cols, s, P, N, ok):
    # One pass per pixel instead of five gathers and their temporaries (the outline checks
    # call this on every hypothesis); the same arithmetic as the array form it replaced.
    h, w = depth.shape
    m = 0
    for i in range(rows.shape[0]):
        r, c = rows[i], cols[i]
        if r < s or r >= h - s or c < s or c >= w - s:
            continue
        z0, zr, zl, zd, zu = (float(depth[r, c]), float(depth[r, c + s]), float(depth[r, c - s]),
                              float(depth[r + s, c]), float(depth[r - s, c]))
        if not (z0 > 0 and zr > 0 and zl > 0 and zd > 0 and zu > 0):
            continue
        x0, y0 = z0 * (c - cx) / fx, z0 * (r - cy) / fy
        ax = zr * (c + s - cx) / fx - zl * (c - s - cx) / fx
        ay = zr * (r - cy) / fy - zl * (r - cy) / fy
        az = zr - zl
        bx = zd * (c - cx) / fx - zu * (c - cx) / fx
        by = zd * (r + s - cy) / fy - zu * (r - s - cy) / fy
        bz = zd - zu
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
        nx, ny, nz = nx / norm, ny / norm, nz / norm
        if nx * x0 + ny * y0 + nz * z0 > 0:
            nx, ny, nz = -nx, -ny, -nz
        P[m, 0], P[m, 1], P[m, 2] = x0, y0, z0
        N[m, 0], N[m, 1], N[m, 2] = nx, ny, nz
        ok[i] = True
        m += 1
    return m


def _face_continues(P: np.ndarray, nP: np.ndarray, p: np.ndarray, n: np.ndarray, tolerance: float,
                    max_angle_deg: float, reach: np.ndarray | None = None) -> np.ndarray:
    """Which measured points P (normals nP) continue a visible model face: among the eight
    nearest model points p (normals n), two whose plane passes within ``tolerance`` and
    whose normal is within ``max_angle_deg``. One stray normal (a sample at an edge oriented
    the wrong way) must not stand for the surface beside the object, and at a box's edge the
    nearest points are as often on the side face seen beside the top (a carton fitted
    across a wider carton's top, turned onto its side). ``reach`` (metres, per point): a
    point farther than this from its nearest model point does not continue a face."""
    k = min(8, len(p))
    j, tied = _nearest(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(p, np.float64), k)
    if tied.any():
        # Which of two equally near points is among the k: the k-d tree's choice, as
        # before (the model's surface holds a few coincident samples with different normals).
        j[tied] = cKDTree(p).query(P[tied], k=k)[1].reshape(-1, k)
    votes = _face_votes(P, nP, p, n, j, float(tolerance), math.cos(math.radians(max_angle_deg)), min(2, k))
    if reach is not None and votes.any():
        # The nearest model point is among the k found.
        i = np.flatnonzero(votes)
        far = np.min(np.linalg.norm(p[j[i]] - P[i, None, :], axis=2), axis=1) > reach[i]
        votes[i[far]] = False
    return votes


# Cells of ``_nearest``'s grid along the model's longest side: finer grids visited more
# empty cells than they saved distances (recorded channel calls: 2 / 3 / 4 / 5 / 8 / 12
# per side 0.67 / 0.57 / 0.55 / 0.54 / 0.66 / 0.94 ms a call; the plain scan 0.74).
NEAREST_CELLS = 4


@numba.njit(cache=True, nogil=True)
def _nearest(P, p, k):
    """(N, k) indices of each point P's k nearest points p (in no order), and which of P
    have a (k+1)-th nearest as near as the k-th (a tie: either could be among the k).
    Most measured points lie far from the model (the floor past a carton's edge), where a
    k-d tree visited much of itself anyway. The previous point's k + 1 nearest (in raster
    order, mostly a neighbouring pixel's) bound the distance, and only the cells of a
    coarse grid over p (``NEAREST_CELLS`` along its longest side) that the bound reaches are
    scanned, the points within it sorted in. The k + 1 nearest distances are those of a
    scan of all of p (the cells skipped hold no point within the bound), so the k nearest
    and the ties are too."""
    m = p.shape[0]
    kk = min(k + 1, m)
    out = np.empty((P.shape[0], k), np.int64)
    tied = np.zeros(P.shape[0], np.bool_)
    if m == 0 or P.shape[0] == 0:
        return out, tied
    lo0, lo1, lo2 = p[:, 0].min(), p[:, 1].min(), p[:, 2].min()
    e0, e1, e2 = p[:, 0].max() - lo0, p[:, 1].max() - lo1, p[:, 2].max() - lo2
    h = max(max(e0, e1, e2) / NEAREST_CELLS, 1e-9)
    d0, d1, d2 = int(e0 / h) + 1, int(e1 / h) + 1, int(e2 / h) + 1
    ncell = d0 * d1 * d2
    # The points sorted by cell (a counting sort), their coordinates copied in that order.
    cell_of = np.empty(m, np.int64)
    start = np.zeros(ncell + 1, np.int64)
    for j in range(m):
        a0 = min(int((p[j, 0] - lo0) / h), d0 - 1)
        a1 = min(int((p[j, 1] - lo1) / h), d1 - 1)
        a2 = min(int((p[j, 2] - lo2) / h), d2 - 1)
        cell_of[j] = (a0 * d1 + a1) * d2 + a2
        start[cell_of[j] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:ncell].copy()
    index = np.empty(m, np.int64)
    for j in range(m):
        index[fill[cell_of[j]]] = j
        fill[cell_of[j]] += 1
    px, py, pz = np.empty(m), np.empty(m), np.empty(m)
    for s in range(m):
        px[s], py[s], pz[s] = p[index[s], 0], p[index[s], 1], p[index[s], 2]
    best_d, best_j = np.empty(kk), np.zeros(kk, np.int64)
    for i in range(P.shape[0]):
        qx, qy, qz = P[i, 0], P[i, 1], P[i, 2]
        c0a, c0b, c1a, c1b, c2a, c2b = 0, d0 - 1, 0, d1 - 1, 0, d2 - 1
        bound = np.inf
        if i > 0:
            bound = 0.0
            for a in range(kk):
                s = best_j[a]
                dx, dy, dz = qx - px[s], qy - py[s], qz - pz[s]
                bound = max(bound, dx * dx + dy * dy + dz * dz)
            # The cells the bound's sphere reaches (a hair wider: rounding must not drop one).
            r = math.sqrt(bound) * (1.0 + 1e-9) + 1e-12
            c0a, c0b = max(int(math.floor((qx - r - lo0) / h)), 0), min(int(math.floor((qx + r - lo0) / h)), d0 - 1)
            c1a, c1b = max(int(math.floor((qy - r - lo1) / h)), 0), min(int(math.floor((qy + r - lo1) / h)), d1 - 1)
            c2a, c2b = max(int(math.floor((qz - r - lo2) / h)), 0), min(int(math.floor((qz + r - lo2) / h)), d2 - 1)
        filled = 0
        for a0 in range(c0a, c0b + 1):
            g0 = max(lo0 + a0 * h - qx, qx - (lo0 + (a0 + 1) * h), 0.0)
            for a1 in range(c1a, c1b + 1):
                g1 = max(lo1 + a1 * h - qy, qy - (lo1 + (a1 + 1) * h), 0.0)
                for a2 in range(c2a, c2b + 1):
                    g2 = max(lo2 + a2 * h - qz, qz - (lo2 + (a2 + 1) * h), 0.0)
                    # A cell whose box lies beyond the bound holds no point within it (the
                    # margin again for rounding; a point decides by its own distance).
                    if g0 * g0 + g1 * g1 + g2 * g2 > bound * (1.0 + 1e-9):
                        continue
                    c = (a0 * d1 + a1) * d2 + a2
                    for s in range(start[c], start[c + 1]):
                        dx, dy, dz = qx - px[s], qy - py[s], qz - pz[s]
                        x = dx * dx + dy * dy + dz * dz
                        if x > bound:
                            continue
                        if filled < kk:
                            b = filled
                            filled += 1
                        elif x < best_d[kk - 1]:
                            b = kk - 1
                        else:
                            continue
                        while b > 0 and best_d[b - 1] > x:
                            best_d[b], best_j[b] = best_d[b - 1], best_j[b - 1]
                            b -= 1
                        best_d[b], best_j[b] = x, s
                        if filled == kk:
                            bound = best_d[kk - 1]
        for a in range(k):
            out[i, a] = index[best_j[a]]
        tied[i] = kk > k and best_d[k] <= best_d[k - 1] * (1.0 + 1e-12)
    return out, tied


@numba.njit(cache=True, nogil=True)
def _face_votes(P, nP, p, n, j, tolerance, cos_min, need):
    out = np.zeros(P.shape[0], np.bool_)
    for i in range(P.shape[0]):
        votes = 0
        for a in range(j.shape[1]):
            q = j[i, a]
            off = abs((P[i, 0] - p[q, 0]) * n[q, 0] + (P[i, 1] - p[q, 1]) * n[q, 1] + (P[i, 2] - p[q, 2]) * n[q, 2])
            cos = nP[i, 0] * n[q, 0] + nP[i, 1] * n[q, 1] + nP[i, 2] * n[q, 2]
            if off < tolerance and cos > cos_min:
                votes += 1
        out[i] = votes >= need
    return out


# The cosine of the largest angle between a surface's normal and the line of sight at which it
# is taken as facing the camera (about 78 deg; ``facing_camera``, the outline's reach).
MIN_FACING_COS = 0.2


def facing_camera(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Which surface points (camera frame) face the camera clearly (normal within about 78 deg
    of the line of sight, not grazing) and lie in front of it."""
    return _facing(np.ascontiguousarray(p, np.float64), np.ascontiguousarray(n, np.float64))


@numba.njit(cache=True, nogil=True)
def _facing(p, n):
    # One pass (a few times per hypothesis, ~1,200 model points: as numpy temporaries, 50 us
    # a call).
    out = np.empty(p.shape[0], np.bool_)
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        out[i] = (n[i, 0] * -x + n[i, 1] * -y + n[i, 2] * -z > MIN_FACING_COS * math.sqrt(x * x + y * y + z * z)) and z > 0.05
    return out


def image_pixels(p: np.ndarray, intrinsics: CameraIntrinsics, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, inside): each camera-frame point's nearest pixel (column, row) and whether it
    lies in an image of ``shape`` (rows, columns)."""
    K = intrinsics.K
    u = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    h, w = shape
    return u, v, (u >= 0) & (u < w) & (v >= 0) & (v < h)


def outline_continuation(T: np.ndarray, model_pts: np.ndarray, model_normals: np.ndarray, depth_m: np.ndarray,
                         intrinsics: CameraIntrinsics, voxel: float, tolerance: float,
                         max_angle_deg: float = 30.0, up: np.ndarray | None = None,
                         explained: np.ndarray | None = None, normal_step: int = 2) -> tuple[float, int]:
    """Of the valid depth pixels in a band just outside the model's outline at pose T (from
    half a voxel to a voxel and a half beyond its visible surface): the share where the
    nearest visible model face continues (the measured point within ``tolerance`` of its
    plane, the measured normal within ``max_angle_deg`` of its normal) and that is joined
    to the band's inner edge through such pixels, and how many pixels the band has.
    Returns (share, pixels).

    ``up`` (unit, camera frame; the support plane's normal): band pixels no higher than the
    object's lowest point (within ``tolerance``) do not continue it and leave the share. What an object stands on may
    be flush with it (a carton on a carton of its size, a lying bracket's plate on the
    table): the same surface goes on below it, and that is no sign of a larger object.

    ``explained`` ((H, W) uint8): pixels known to be something else (the instances found in
    the frame): left out of the band. A neighbour flush with the object continues its face
    there, and it is no larger surface.

    ``normal_step``: pixels, the central differences' half width for the measured normals
    (wider on a noisier camera, as the verification's own normals: 2 pixels at 1.5 m with
    k = 0.0048 turned most normals of a plane going on past a carton by more than 30 deg)."""
    R, t = T[:3, :3], T[:3, 3]
    p = model_pts @ R.T + t
    floor = None if up is None else float(np.min(p @ up)) + tolerance
    n = model_normals @ R.T
    facing = facing_camera(p, n)
    p, n = p[facing], n[facing]
    if len(p) < 3:
        return 0.0, 0
    K = intrinsics.K
    h, w = depth_m.shape
    z = p[:, 2]
    u = K[0, 0] * p[:, 0] / z + K[0, 2]
    v = K[1, 1] * p[:, 1] / z + K[1, 2]
    px_per_m = K[0, 0] / float(np.median(z))
    vox_px = voxel * px_per_m
    splat = max(1, int(round(0.75 * vox_px)))
    r_in, r_out = max(1, int(round(0.5 * vox_px))), max(2, int(round(1.5 * vox_px)))
    # The model's silhouette, drawn in a crop of the image around it (points splatted over
    # their voxel's footprint), and the band outside it.
    pad = splat + r_out + 1
    u0, v0 = max(int(np.floor(u.min())) - pad, 0), max(int(np.floor(v.min())) - pad, 0)
    u1, v1 = min(int(np.ceil(u.max())) + pad + 1, w), min(int(np.ceil(v.max())) + pad + 1, h)
    if u1 - u0 < 2 or v1 - v0 < 2:
        return 0.0, 0
    ui, vi = np.round(u).astype(np.int64) - u0, np.round(v).astype(np.int64) - v0
    keep = (ui >= 0) & (ui < u1 - u0) & (vi >= 0) & (vi < v1 - v0)
    disc = lambda r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    ui, vi, p, n = ui[keep], vi[keep], p[keep], n[keep]
    if len(p) < 3:
        return 0.0, 0
    crop = np.zeros((v1 - v0, u1 - u0), np.uint8)
    crop[vi, ui] = 1
    body = cv2.dilate(crop, disc(splat))
    band = (cv2.dilate(body, disc(r_out)) > 0) & (cv2.dilate(body, disc(r_in)) == 0)
    rows, cols = np.nonzero(band)
    rows, cols = rows + v0, cols + u0
    P, nP, ok = _points_and_normals(depth_m, K, rows, cols, normal_step)
    rows, cols = rows[ok], cols[ok]
    # Explained pixels stay in the band, as pixels where the object ends: left out of it, a
    # few pixels of continuation where a seam fades (a carton's corner) made most of what
    # was left.
    mine = np.ones(len(rows), bool) if explained is None else explained[rows, cols] == 0
    if len(rows) == 0:
        return 0.0, 0
    counted = len(P)
    # Only surface next to the object in space, not only in the image: a band pixel lies at
    # most the band's reach (its outer edge plus a sample's splat) from a projected model
    # point, which on a surface facing the camera at angle a is at most that reach / cos a
    # away on it. Farther, the image puts it next to the object across a gap the object or a
    # neighbour hides: a neighbour's top in front, at the same height 4-5 cm beside the
    # channel (channel seed 509 frames 0-1: 41-50 mm from the model where the reach is 29 mm;
    # its outline share 0.09 at the true pose, 0.00 without them).
    facing = np.abs(np.sum(nP * P, axis=1)) / np.linalg.norm(P, axis=1)
    reach = (r_out + splat + 1) * P[:, 2] / K[0, 0] / np.maximum(facing, MIN_FACING_COS)
    if floor is not None:
        # The support, not more of the object's own surface: out of the share, yet at least
        # half the band stays in it (a cylinder standing on the table kept 44 pixels of 258,
        # and 8 of them decided). Only the pixels above it are looked at (the floor past a
        # carton's edge is most of the nearest-point search's work).
        above = P @ up > floor
        look = above & mine
        cont = np.zeros(len(P), np.bool_)
        cont[look] = _face_continues(P[look], nP[look], p, n, tolerance, max_angle_deg, reach[look])
        counted = max(int(above.sum()), len(P) // 2, 1)
    else:
        cont = np.zeros(len(P), np.bool_)
        cont[mine] = _face_continues(P[mine], nP[mine], p, n, tolerance, max_angle_deg, reach[mine])
    # Only surface that goes on from the outline itself counts: reached from the band's
    # inner edge through continuing pixels. A neighbour with its faces in line (cartons
    # on a pallet's grid) lies past a gap, a depth step that breaks the chain.
    grid = np.zeros(band.shape, np.uint8)
    grid[rows[cont] - v0, cols[cont] - u0] = 1
    count, labels = cv2.connectedComponents(grid, connectivity=8)
    inner = (cv2.dilate(body, disc(r_in + 1)) > 0) & (grid > 0)
    touching = np.zeros(count, bool)
    touching[labels[inner]] = True
    touching[0] = False
    linked = touching[labels[rows - v0, cols - u0]] & cont
    return float(linked.sum() / counted), int(len(rows))


def texture_agreement(T: np.ndarray, keypoints: np.ndarray, keypoint_normals: np.ndarray, symmetries,
                      model_xyz: np.ndarray, scene_xyz: np.ndarray, depth_m: np.ndarray,
                      intrinsics: CameraIntrinsics, inlier_thresh: float, tolerance: float
                      ) -> tuple[np.ndarray, int, int]:
    """Does the frame's texture agree with a pose found from shape? For a model with SIFT
    keypoints: (T @ S for the symmetry S that the most matches agree with, how many of the
    frame's matches (model_xyz -> scene_xyz) agree with it within ``inlier_thresh``, how
    many of the model's keypoints it shows: facing the camera, inside the image, not hidden
    (the depth there within ``tolerance``)). A pose on a textured face that no match agrees
    with is on something else; one showing only plain faces has nothing to agree with.
    A continuous symmetry's turn is found too: the shape leaves it open, the print does not
    (IC-BIN's cups: shape poses at the turn ICP left them showed 700-1,500 keypoints and
    met 0-2 of the matches, and the texture turned away cups the shape had right)."""
    T = np.asarray(T, np.float64)
    # S m = T^-1 s for the pose T S: the matches' scene points in the pose's model frame.
    in_model = apply_transform(invert_transform(T), np.asarray(scene_xyz, np.float64))
    S, agree, _ = best_symmetry(model_xyz, in_model, None if symmetries is None or symmetries.is_trivial
                                else symmetries, inlier_thresh)
    best = T @ S if agree > 0 else T
    p = keypoints @ best[:3, :3].T + best[:3, 3]
    nrm = keypoint_normals @ best[:3, :3].T
    facing = facing_camera(p, nrm)
    p = p[facing]
    u, v, inside = image_pixels(p, intrinsics, depth_m.shape)
    shown = np.abs(depth_m[v[inside], u[inside]] - p[inside, 2]) < tolerance
    return best, agree, int(shown.sum())


def surface_samples(points: np.ndarray, extent, max_points: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) points spread over a model's dense cloud (model frame), at most ``max_points``,
    and their outward normals (PCA over the neighbours, turned away from the cloud's centre:
    right for the convex objects of a tabletop; only the back-face test reads the sign)."""
    from ..frontends.shape.geometry import shape_voxel, surface_normals, voxel_downsample

    pts = np.asarray(points, np.float64)
    if len(pts) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3))
    voxel = shape_voxel(extent)
    pts = voxel_downsample(pts, voxel)
    normals = -surface_normals(pts, voxel, toward=pts.mean(axis=0))     # away from the centre
    if len(pts) > max_points:
        pick = np.sort(np.random.default_rng(0).choice(len(pts), max_points, replace=False))
        pts, normals = pts[pick], normals[pick]
    return np.ascontiguousarray(pts), np.ascontiguousarray(normals)


def free_space_share(T: np.ndarray, points: np.ndarray, normals: np.ndarray, depth_m: np.ndarray,
                     intrinsics: CameraIntrinsics, pivot: np.ndarray, tolerance: float, slope: float
                     ) -> tuple[float, int]:
    """Does the model at pose T fill space the depth camera sees to be empty?

    Of the model's surface points (model frame, with outward normals) that face the camera
    and project into the image onto a valid depth pixel: the share lying in front of the
    measured surface by more than ``tolerance + slope x`` their distance from ``pivot``
    (camera frame; the inliers' centre), and how many points were judged. The margin grows
    away from the inliers because a pose fitted to a few close matches is sure there and
    may be tilted elsewhere (slope = tan of the tilt allowed); points behind the measurement
    may be hidden and count as neither. Compiled: a projection per point."""
    K = intrinsics.K
    return _free_space_share(np.ascontiguousarray(T, np.float64), points, normals, depth_m,
                             float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                             np.ascontiguousarray(pivot, np.float64), float(tolerance), float(slope))


@numba.njit(cache=True)
def _free_space_share(T, mp, mn, depth, fx, fy, cx, cy, pivot, tolerance, slope):
    m = 0
    free = 0
    for i in range(mp.shape[0]):
        px, py, pz, measured = measured_at(T, mp, mn, i, depth, fx, fy, cx, cy)
        if not measured > 0:
            continue
        m += 1
        dx, dy, dz = px - pivot[0], py - pivot[1], pz - pivot[2]
        if measured - pz > tolerance + slope * math.sqrt(dx * dx + dy * dy + dz * dz):
            free += 1
    if m == 0:
        return 0.0, 0
    return free / m, m


__all__ = ["outline_continuation", "texture_agreement", "surface_samples", "free_space_share"]
