"""BOP's pose-error functions (Hodan et al., ECCV 2018 and ECCVW 2020; NOTES.md section 14):
VSD, MSSD and MSPD, written from their definitions. Lengths in metres, poses (4, 4) model ->
camera in metres, images in pixels.

- MSSD: the largest distance between a model vertex placed by the estimate and by the truth,
  minimised over the object's symmetries S (the truth placed as T_gt @ S).
- MSPD: the same between the two projections of each vertex, in pixels.
- VSD: the model's depth rendered at both poses, converted to distance from the camera
  centre, compared over the pixels where each is visible in the test depth image (visible:
  rendered there and not more than ``delta`` behind the test surface, or the test image has
  no depth there); the error is the share of the union of the two visible masks where the
  distances differ by ``tau`` or more or only one pose is visible. Symmetries need no
  special care: a symmetric pose renders the same.

Symmetries come from models_info.json: ``symmetries_discrete`` (4x4, translation in mm) and
``symmetries_continuous`` ({axis, offset}), a continuous one cut into steps small enough
that the vertex farthest from the axis (at most half the diameter away) moves at most
``max_step`` (1 %) of the diameter between steps: ceil(pi / max_step) steps, 315 at 1 %.
Each continuous step is combined with each discrete symmetry (the identity included).
"""
from __future__ import annotations

import numba
import numpy as np

from ..symmetry import turn_about

# BOP's discretisation of continuous symmetries: a vertex moves at most 1 % of the diameter.
MAX_SYMMETRY_STEP = 0.01


def symmetry_transforms(info, max_step: float = MAX_SYMMETRY_STEP) -> np.ndarray:
    """(S, 4, 4) model-frame symmetries in metres, the identity first, from a
    ``datasets.bop.BopModelInfo`` (lengths in mm as the file has them)."""
    disc = [np.eye(4)]
    for S in np.asarray(info.symmetries_discrete, np.float64).reshape(-1, 4, 4):
        S = S.copy()
        S[:3, 3] /= 1000.0
        disc.append(S)
    turns = []
    steps = int(np.ceil(np.pi / max_step))
    for axis, offset in info.symmetries_continuous:
        point = np.asarray(offset, np.float64) / 1000.0
        turns += [turn_about(axis, point, 2.0 * np.pi * k / steps) for k in range(steps)]
    if not turns:
        return np.stack(disc)
    return np.einsum("cij,djk->cdik", np.stack(turns), np.stack(disc)).reshape(-1, 4, 4)


def vertex_order(vertices: np.ndarray) -> np.ndarray:
    """Vertices farthest from the centre first: under a rotation they move the most, so a
    symmetry that cannot win is usually rejected after a few of them."""
    V = np.asarray(vertices, np.float64)
    return np.argsort(-np.linalg.norm(V - V.mean(axis=0), axis=1), kind="stable").astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _min_max_distance(V, placed, R, t, order, projected, fx, fy, cx, cy, give_up):
    """min over s of max over vertices i of |f(R[s] V[i] + t[s]) - placed[i]|, f = identity
    or the projection; exact, with early exits: symmetries are tried in the order of their
    first vertex's distance (a lower bound of their maximum), a symmetry is dropped as soon as
    one vertex reaches the best maximum so far, and the loop ends once the next bound does.
    ``give_up``: the answer is only wanted below it (inf returned when it is not)."""
    S = R.shape[0]
    first = order[0]
    bound = np.empty(S)
    for s in range(S):
        bound[s] = _vertex_distance2(V, placed, R, t, s, first, projected, fx, fy, cx, cy)
    best = give_up * give_up
    for s in np.argsort(bound):
        if bound[s] >= best:
            break
        worst = 0.0
        for i in order:
            d2 = _vertex_distance2(V, placed, R, t, s, i, projected, fx, fy, cx, cy)
            if d2 > worst:
                worst = d2
                if worst >= best:
                    break
        if worst < best:
            best = worst
    return np.sqrt(best) if best < give_up * give_up else np.inf


@numba.njit(cache=True, nogil=True, inline="always")
def _vertex_distance2(V, placed, R, t, s, i, projected, fx, fy, cx, cy):
    x = R[s, 0, 0] * V[i, 0] + R[s, 0, 1] * V[i, 1] + R[s, 0, 2] * V[i, 2] + t[s, 0]
    y = R[s, 1, 0] * V[i, 0] + R[s, 1, 1] * V[i, 1] + R[s, 1, 2] * V[i, 2] + t[s, 1]
    z = R[s, 2, 0] * V[i, 0] + R[s, 2, 1] * V[i, 1] + R[s, 2, 2] * V[i, 2] + t[s, 2]
    if projected:
        if z <= 0.0:
            return np.inf
        du = fx * x / z + cx - placed[i, 0]
        dv = fy * y / z + cy - placed[i, 1]
        return du * du + dv * dv
    dx, dy, dz = x - placed[i, 0], y - placed[i, 1], z - placed[i, 2]
    return dx * dx + dy * dy + dz * dz


def symmetric_poses(T_gt: np.ndarray, syms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The true pose under every symmetry, T_gt @ S, as rotations (S, 3, 3) and translations (S, 3)."""
    G = np.matmul(np.asarray(T_gt, np.float64), syms)
    return np.ascontiguousarray(G[:, :3, :3]), np.ascontiguousarray(G[:, :3, 3])


def place(T: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(V, 3) vertices moved by the pose T."""
    T = np.asarray(T, np.float64)
    return np.ascontiguousarray(np.asarray(vertices, np.float64) @ T[:3, :3].T + T[:3, 3])


def mssd(T_est: np.ndarray, T_gt: np.ndarray, vertices: np.ndarray, syms: np.ndarray, order: np.ndarray | None = None,
         give_up: float = np.inf) -> float:
    """Maximum symmetry-aware surface distance (metres); inf when it is not below
    ``give_up``. ``vertices`` may be the convex hull's vertices only: the distance |A v + b|
    is convex in v, so its maximum over the model is reached at a hull vertex. ``order``:
    ``vertex_order(vertices)`` (computed when not given)."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    return mssd_placed(place(T_est, V), symmetric_poses(T_gt, syms), V, order, give_up)


def mssd_placed(placed_est: np.ndarray, true_poses, vertices: np.ndarray, order: np.ndarray | None = None,
                give_up: float = np.inf) -> float:
    """``mssd`` from the estimate's placed vertices (``place``) and ``symmetric_poses``:
    what a scorer computes once per estimate and once per true instance."""
    if not np.all(np.isfinite(placed_est)):
        return np.inf                       # a broken pose (NaN in the results) is no pose
    order = vertex_order(vertices) if order is None else order
    R, t = true_poses
    return float(_min_max_distance(vertices, placed_est, R, t, order, False, 0.0, 0.0, 0.0, 0.0, float(give_up)))


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 2) pixel coordinates of camera-frame points (..., 3)."""
    z = points[..., 2:3]
    return np.concatenate([K[0, 0] * points[..., 0:1] / z + K[0, 2], K[1, 1] * points[..., 1:2] / z + K[1, 2]],
                          axis=-1)


def mspd(T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, vertices: np.ndarray, syms: np.ndarray,
         order: np.ndarray | None = None, give_up: float = np.inf) -> float:
    """Maximum symmetry-aware projection distance (pixels) over all model vertices; inf when
    it is not below ``give_up`` or a vertex lies at or behind the camera."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    return mspd_placed(place(T_est, V), symmetric_poses(T_gt, syms), K, V, order, give_up)


def mspd_placed(placed_est: np.ndarray, true_poses, K: np.ndarray, vertices: np.ndarray,
                order: np.ndarray | None = None, give_up: float = np.inf) -> float:
    """``mspd`` from the estimate's placed vertices and ``symmetric_poses`` (see ``mssd_placed``)."""
    if not np.all(np.isfinite(placed_est)) or np.any(placed_est[:, 2] <= 0):
        return np.inf                       # a broken pose, or a vertex at or behind the camera (no projection)
    K = np.asarray(K, np.float64)
    order = vertex_order(vertices) if order is None else order
    R, t = true_poses
    return float(_min_max_distance(vertices, np.ascontiguousarray(project(placed_est, K)), R, t, order, True,
                                   K[0, 0], K[1, 1], K[0, 2], K[1, 2], float(give_up)))


def distance_factor(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W): distance from the camera centre = depth x this (the pixel's ray length per
    unit depth)."""
    K = np.asarray(K, np.float64)
    x = (np.arange(width) - K[0, 2]) / K[0, 0]
    y = (np.arange(height) - K[1, 2]) / K[1, 1]
    return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2).astype(np.float32)


def vsd(depth_est, depth_gt, dist_test: np.ndarray, factor: np.ndarray, delta: float, taus,
        diameter: float) -> np.ndarray:
    """Visible surface discrepancy for each misalignment tolerance ``taus`` (fractions of the
    ``diameter``): (len(taus),) errors in [0, 1]. ``depth_est`` / ``depth_gt``: the model's
    ``render.DepthRender`` at the two poses; ``dist_test``: the test image's distance image
    (depth x ``factor``, 0 where it has no depth); lengths in metres."""
    taus = np.asarray(taus, np.float64)
    if depth_est.empty or depth_gt.empty or depth_est.r0 >= depth_gt.r1 or depth_gt.r0 >= depth_est.r1 \
            or depth_est.c0 >= depth_gt.c1 or depth_gt.c0 >= depth_est.c1:
        # Apart in the image: no pixel is shared, every visible pixel is a miss (or none is
        # visible): the error is 1 for every tau.
        return np.ones(len(taus))
    boxes = [depth_est, depth_gt]
    r0, r1 = min(b.r0 for b in boxes), max(b.r1 for b in boxes)
    c0, c1 = min(b.c0 for b in boxes), max(b.c1 for b in boxes)
    f = factor[r0:r1, c0:c1]
    test = dist_test[r0:r1, c0:c1]
    est = depth_est.depth[r0:r1, c0:c1] * f
    gt = depth_gt.depth[r0:r1, c0:c1] * f
    no_test = test == 0
    on_gt, on_est = gt > 0, est > 0
    visib_gt = on_gt & ((gt - test <= delta) | no_test)
    # The estimate is also visible wherever the truth is and the estimate is rendered: an
    # estimate in front of the true surface is not hidden by it (Hodan et al. 2016, eq. 14).
    visib_est = on_est & ((est - test <= delta) | no_test | visib_gt)
    inter = visib_gt & visib_est
    union = int(np.count_nonzero(visib_gt | visib_est))
    if union == 0:
        return np.ones(len(taus))
    apart = np.abs(gt[inter] - est[inter]) / diameter
    only_one = union - int(np.count_nonzero(inter))
    return np.array([(np.count_nonzero(apart >= tau) + only_one) / union for tau in taus])


__all__ = ["symmetry_transforms", "mssd", "mspd", "vsd", "distance_factor", "project", "vertex_order", "place", "symmetric_poses", "mssd_placed", "mspd_placed",
           "MAX_SYMMETRY_STEP"]
