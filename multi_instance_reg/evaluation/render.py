"""Depth of a triangle mesh at a pose, seen through a pinhole camera, for BOP's VSD.

What VSD needs (BOP, Hodan et al. ECCV 2018): the depth of the model alone at the estimated
and at the true pose, and the image box it spans (the error is computed there only). The
rasteriser is the project's one (``models.mesh_render.rasterise``: z-buffered, depth
interpolated perspective-correctly); pixel (row, col) is sampled at image point (col, row),
the convention of ``rgbd.lifting.backproject``. No lens distortion (BOP images have none).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models.mesh_render import NEAR_M as NEAR_PLANE_M
from ..models.mesh_render import rasterise


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
    depth, _, _ = rasterise(vertices, triangles, T, K, width, height)
    rows, cols = np.flatnonzero(depth.any(axis=1)), np.flatnonzero(depth.any(axis=0))
    if len(rows) == 0:
        return DepthRender(depth, 0, 0, 0, 0)
    return DepthRender(depth, int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)


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
