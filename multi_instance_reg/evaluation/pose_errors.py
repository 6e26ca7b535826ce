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

import numpy as np

from ..symmetry import turn_about

# BOP's discretisation of continuous symmetries: a vertex moves at most 1 % of the diameter.
MAX_SYMMETRY_STEP = 0.01
# MSSD / MSPD over many symmetries: vertices probed first to bound the error from below.
PROBE_SIZES = (16, 256)


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


def _min_over_symmetries(largest, syms: np.ndarray, n_vertices: int, probes=(), give_up: float = np.inf) -> float:
    """min over S of ``largest(S_subset, vertex_index or None)`` -> (S,) maxima over vertices.
    With many symmetries, probes of the vertices (nested, small first) bound each symmetry's
    maximum from below; symmetries are then tried exactly in the order of their bounds and
    the search stops once the bound reaches the best exact maximum: the result is exact.
    When every bound reaches ``give_up`` the smallest bound is returned (the error is at
    least that: enough to know that it passes no threshold)."""
    if not len(probes) or len(syms) * n_vertices <= 200_000:
        return float(largest(syms, None).min())
    keep = np.arange(len(syms))
    for idx in probes:
        bound = largest(syms[keep], idx)
        if bound.min() >= give_up:
            return float(bound.min())
        keep, bound = keep[bound < give_up], bound[bound < give_up]
    best = np.inf
    for k in np.argsort(bound, kind="stable"):
        if bound[k] >= best:
            break
        best = min(best, float(largest(syms[keep[k]:keep[k] + 1], None)[0]))
    return best


def probe_indices(n_vertices: int, sizes=PROBE_SIZES, seed: int = 0) -> list[np.ndarray]:
    """Nested random vertex subsets (small first) that MSSD / MSPD use to bound errors from
    below; none when the model has few vertices."""
    order = np.random.default_rng(seed).permutation(n_vertices)
    return [np.sort(order[:n]) for n in sizes if 2 * n <= n_vertices]


def mssd(T_est: np.ndarray, T_gt: np.ndarray, vertices: np.ndarray, syms: np.ndarray,
         probes=(), give_up: float = np.inf) -> float:
    """Maximum symmetry-aware surface distance (metres). ``vertices`` may be the convex hull's
    vertices only: the distance |A v + b| is convex in v, so its maximum over the model is
    reached at a hull vertex."""
    T_est = np.asarray(T_est, np.float64)
    V = np.asarray(vertices, np.float64)
    p_est = V @ T_est[:3, :3].T + T_est[:3, 3]
    G = np.einsum("ij,sjk->sik", np.asarray(T_gt, np.float64), syms)      # (S, 4, 4) true poses

    def largest(Gs, idx):
        Vs, Ps = (V, p_est) if idx is None else (V[idx], p_est[idx])
        p_gt = np.einsum("sij,vj->svi", Gs[:, :3, :3], Vs) + Gs[:, None, :3, 3]
        return np.sqrt(((p_gt - Ps[None]) ** 2).sum(-1)).max(axis=1)

    return _min_over_symmetries(largest, G, len(V), probes, give_up)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 2) pixel coordinates of camera-frame points (..., 3)."""
    z = points[..., 2:3]
    return np.concatenate([K[0, 0] * points[..., 0:1] / z + K[0, 2], K[1, 1] * points[..., 1:2] / z + K[1, 2]],
                          axis=-1)


def mspd(T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, vertices: np.ndarray, syms: np.ndarray,
         probes=(), give_up: float = np.inf) -> float:
    """Maximum symmetry-aware projection distance (pixels) over all model vertices."""
    T_est = np.asarray(T_est, np.float64)
    K = np.asarray(K, np.float64)
    V = np.asarray(vertices, np.float64)
    p_est = V @ T_est[:3, :3].T + T_est[:3, 3]
    if np.any(p_est[:, 2] <= 0):
        return np.inf                       # a vertex at or behind the camera has no projection
    uv_est = project(p_est, K)
    G = np.einsum("ij,sjk->sik", np.asarray(T_gt, np.float64), syms)

    def largest(Gs, idx):
        Vs, U = (V, uv_est) if idx is None else (V[idx], uv_est[idx])
        p_gt = np.einsum("sij,vj->svi", Gs[:, :3, :3], Vs) + Gs[:, None, :3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.sqrt(((project(p_gt, K) - U[None]) ** 2).sum(-1))
        d[p_gt[..., 2] <= 0] = np.inf
        return d.max(axis=1)

    return _min_over_symmetries(largest, G, len(V), probes, give_up)


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
    if depth_gt.empty and depth_est.empty:
        return np.ones(len(taus))
    boxes = [r for r in (depth_est, depth_gt) if not r.empty]
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


__all__ = ["symmetry_transforms", "mssd", "mspd", "vsd", "distance_factor", "project", "probe_indices",
           "MAX_SYMMETRY_STEP"]
