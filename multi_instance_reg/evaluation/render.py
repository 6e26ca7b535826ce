"""Depth of a triangle mesh at a pose, seen through a pinhole camera: a z-buffer rasteriser.

What VSD needs (BOP, Hodan et al. ECCV 2018): the depth of the model alone at the
estimated and at the true pose. The project's scene renderer (``synthetic/render.py``)
draws quads, discs and cylinders, not meshes, so this is a small rasteriser of its own, in
numba: each triangle is projected, its pixels found by barycentric coordinates over its
image bounding box, and the depth interpolated perspective-correctly (1/z is affine in the
image for a planar triangle). Pixel (row, col) is sampled at image point (col, row), the
convention of ``rgbd.lifting.backproject``. No lens distortion (BOP images have none).
Triangles with a vertex closer than ``NEAR_PLANE_M`` are left out (an object that close is
not a scene BOP scores).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

NEAR_PLANE_M = 0.01
# Pixels on a shared edge belong to both triangles (the z-buffer keeps the nearer): a
# slightly negative barycentric still counts, so that no crack opens between triangles.
EDGE_EPS = 1e-7


@dataclass
class DepthRender:
    """A mesh's depth image (metres, 0 where the mesh is not) and the image box its pixels
    span: rows ``r0:r1``, cols ``c0:c1`` (empty when r0 >= r1)."""
    depth: np.ndarray
    r0: int
    r1: int
    c0: int
    c1: int

    @property
    def empty(self) -> bool:
        return self.r0 >= self.r1 or self.c0 >= self.c1


def render_depth(vertices: np.ndarray, triangles: np.ndarray, T: np.ndarray, K: np.ndarray,
                 width: int, height: int) -> DepthRender:
    """Depth (float32, metres; 0 = background) of the mesh ``vertices`` (V, 3) metres,
    ``triangles`` (F, 3) placed by ``T`` (4, 4) model -> camera, camera matrix ``K``."""
    T = np.asarray(T, np.float64)
    if not np.all(np.isfinite(T)):
        return DepthRender(np.zeros((int(height), int(width)), np.float32), 0, 0, 0, 0)     # a broken pose draws nothing
    P = np.ascontiguousarray(np.asarray(vertices, np.float64) @ T[:3, :3].T + T[:3, 3])
    K = np.asarray(K, np.float64)
    depth = np.zeros((int(height), int(width)), np.float32)
    box = _rasterise(P, np.ascontiguousarray(triangles, dtype=np.int64), float(K[0, 0]), float(K[1, 1]),
                     float(K[0, 2]), float(K[1, 2]), depth, NEAR_PLANE_M)
    return DepthRender(depth, int(box[0]), int(box[1]), int(box[2]), int(box[3]))


@numba.njit(cache=True, nogil=True)
def _rasterise(P, tris, fx, fy, cx, cy, depth, near):
    H, W = depth.shape
    n = P.shape[0]
    u = np.empty(n)
    v = np.empty(n)
    iz = np.empty(n)
    for i in range(n):
        z = P[i, 2]
        if z > near:
            u[i] = fx * P[i, 0] / z + cx
            v[i] = fy * P[i, 1] / z + cy
            iz[i] = 1.0 / z
        else:
            iz[i] = -1.0
    r0, r1, c0, c1 = H, 0, W, 0
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        if iz[a] < 0.0 or iz[b] < 0.0 or iz[c] < 0.0:
            continue
        xa, ya, xb, yb, xc, yc = u[a], v[a], u[b], v[b], u[c], v[c]
        area = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)
        if abs(area) < 1e-12:
            continue
        xmin = max(0, int(np.ceil(min(xa, min(xb, xc)) - 1e-9)))
        xmax = min(W - 1, int(np.floor(max(xa, max(xb, xc)) + 1e-9)))
        ymin = max(0, int(np.ceil(min(ya, min(yb, yc)) - 1e-9)))
        ymax = min(H - 1, int(np.floor(max(ya, max(yb, yc)) + 1e-9)))
        if xmin > xmax or ymin > ymax:
            continue
        inv = 1.0 / area
        for py in range(ymin, ymax + 1):
            for px in range(xmin, xmax + 1):
                wa = ((xb - px) * (yc - py) - (xc - px) * (yb - py)) * inv
                wb = ((xc - px) * (ya - py) - (xa - px) * (yc - py)) * inv
                wc = 1.0 - wa - wb
                if wa < -EDGE_EPS or wb < -EDGE_EPS or wc < -EDGE_EPS:
                    continue
                d = 1.0 / (wa * iz[a] + wb * iz[b] + wc * iz[c])
                cur = depth[py, px]
                if cur == 0.0 or d < cur:
                    depth[py, px] = d
                    r0 = min(r0, py)
                    r1 = max(r1, py + 1)
                    c0 = min(c0, px)
                    c1 = max(c1, px + 1)
    return np.array([r0, r1, c0, c1])


def render_scene(meshes, poses, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, list]:
    """Several meshes at once: the scene's depth (metres, 0 = nothing), each instance's
    visible fraction (its pixels that are the nearest surface / all its pixels) and its
    visible mask. ``meshes``: ``meshes.TriangleMesh`` per instance; ``poses``: (4, 4) each."""
    renders = [render_depth(m.vertices, m.triangles, T, K, width, height) for m, T in zip(meshes, poses)]
    scene = np.zeros((int(height), int(width)), np.float32)
    for r in renders:
        on = (r.depth > 0) & ((scene == 0) | (r.depth < scene))
        scene[on] = r.depth[on]
    fractions, masks = [], []
    for r in renders:
        own = r.depth > 0
        seen = own & (r.depth <= scene)
        fractions.append(float(seen.sum()) / max(1, int(own.sum())))
        masks.append(seen)
    return scene, np.array(fractions), masks


__all__ = ["DepthRender", "render_depth", "render_scene", "NEAR_PLANE_M"]
