"""Colour and depth pictures of a coloured triangle mesh (``meshes.TriangleMesh``), on a CPU.

A z-buffer rasteriser: a numba kernel walks each triangle's pixel box once, keeps per pixel
the nearest triangle and its perspective-correct barycentric weights; colour is then made
for the visible pixels alone, interpolated from the vertex colours or from the texture
coordinates (the texture sampled bilinearly, from a level of its pyramid chosen for the
view so that a far, small texture does not alias). No lighting: a scanned mesh's colours
already hold the light they were scanned in, and SIFT, which these pictures are made for,
is indifferent to the overall brightness. ``synthetic/render.py`` renders textured quads
and cylinders for the synthetic scenes; a CAD or scanned mesh has neither.

Pixel centres are at integer coordinates, as for OpenCV and the rest of the project.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics
from ..meshes import TriangleMesh

NEAR_M = 0.01
BACKGROUND_RGB = (128, 128, 128)


@dataclass
class MeshRender:
    rgb: np.ndarray              # (H, W, 3) uint8; BACKGROUND_RGB where no triangle is
    depth_m: np.ndarray          # (H, W) float32 camera z, 0 where no triangle is (as a sensor's missing depth)
    triangle: np.ndarray         # (H, W) int32: the visible triangle, -1 where none
    T_camera_object: np.ndarray  # (4, 4) mesh frame -> camera optical frame
    intrinsics: CameraIntrinsics

    @property
    def mask(self) -> np.ndarray:
        return self.triangle >= 0


# Pixels on a shared edge belong to both triangles (the z-buffer keeps the nearer): a
# slightly negative barycentric still counts, so that no crack opens between triangles.
EDGE_EPS = 1e-7


@numba.njit(cache=True, nogil=True)
def _rasterise(u, v, z, tris, zbuf, tri_id, weights, want_weights):
    """Per pixel the nearest triangle (``tri_id``), its camera z (``zbuf``) and, with
    ``want_weights``, the perspective-correct weights of its three corners (``weights``);
    u, v: projected vertices, z: their camera depth (triangles with a corner nearer than
    NEAR_M are skipped)."""
    height, width = zbuf.shape
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        za, zb, zc = z[a], z[b], z[c]
        if za < NEAR_M or zb < NEAR_M or zc < NEAR_M:
            continue
        ua, va, ub, vb, uc, vc = u[a], v[a], u[b], v[b], u[c], v[c]
        area = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
        if abs(area) < 1e-12:
            continue
        x0 = max(int(np.ceil(min(ua, ub, uc) - 1e-9)), 0)
        x1 = min(int(np.floor(max(ua, ub, uc) + 1e-9)), width - 1)
        y0 = max(int(np.ceil(min(va, vb, vc) - 1e-9)), 0)
        y1 = min(int(np.floor(max(va, vb, vc) + 1e-9)), height - 1)
        inv = 1.0 / area
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                # Screen-space barycentrics (either winding: the z-buffer decides what is seen).
                la = ((ub - x) * (vc - y) - (uc - x) * (vb - y)) * inv
                lb = ((uc - x) * (va - y) - (ua - x) * (vc - y)) * inv
                lc = 1.0 - la - lb
                if la < -EDGE_EPS or lb < -EDGE_EPS or lc < -EDGE_EPS:
                    continue
                # 1/z is linear on the screen; attributes are linear in 3D.
                wa, wb, wc = la / za, lb / zb, lc / zc
                s = wa + wb + wc
                depth = 1.0 / s
                if depth < zbuf[y, x]:
                    zbuf[y, x] = depth
                    tri_id[y, x] = t
                    if want_weights:
                        weights[y, x, 0] = wa / s
                        weights[y, x, 1] = wb / s
                        weights[y, x, 2] = wc / s


def rasterise(vertices: np.ndarray, triangles: np.ndarray, T_camera_object: np.ndarray, K: np.ndarray,
              width: int, height: int, weights: bool = False):
    """The project's one triangle rasteriser (mesh pictures here, BOP's VSD in
    ``evaluation.render``): camera z per pixel (float32, 0 where no triangle is), the visible
    triangle (int32, -1 where none) and, with ``weights``, the (H, W, 3) float32 weights of its
    corners (else None), of ``vertices`` (V, 3) placed by ``T_camera_object`` and seen through
    ``K`` (no distortion)."""
    W, H = int(width), int(height)
    K = np.asarray(K, np.float64)
    T = np.asarray(T_camera_object, np.float64)
    cam = np.asarray(vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
    z = np.ascontiguousarray(cam[:, 2])
    safe = np.where(z > NEAR_M, z, 1.0)
    u = np.ascontiguousarray(K[0, 0] * cam[:, 0] / safe + K[0, 1] * cam[:, 1] / safe + K[0, 2])
    v = np.ascontiguousarray(K[1, 1] * cam[:, 1] / safe + K[1, 2])
    zbuf = np.full((H, W), np.inf)
    tri_id = np.full((H, W), -1, np.int32)
    w = np.zeros((H, W, 3) if weights else (1, 1, 3), np.float32)
    _rasterise(u, v, z, np.ascontiguousarray(triangles, np.int64), zbuf, tri_id, w, weights)
    depth = np.where(tri_id >= 0, zbuf, 0.0).astype(np.float32)
    return depth, tri_id, (w if weights else None)


def render_mesh(mesh: TriangleMesh, T_camera_object: np.ndarray, intrinsics: CameraIntrinsics) -> MeshRender:
    """The mesh seen by a pinhole camera (``intrinsics``; distortion is not applied) at
    ``T_camera_object`` (mesh frame -> optical frame). Needs a mesh with colour."""
    if not mesh.has_colour:
        raise InputError("the mesh has no colour (vertex colours or a texture) to render")
    T = np.asarray(T_camera_object, np.float64)
    depth, tri_id, weights = rasterise(mesh.vertices, mesh.triangles, T, intrinsics.K, intrinsics.width,
                                       intrinsics.height, weights=True)
    H, W = depth.shape
    seen = tri_id >= 0
    tris = np.ascontiguousarray(mesh.triangles, np.int64)
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = BACKGROUND_RGB
    t = tri_id[seen]
    w = weights[seen]
    if mesh.vertex_colours is not None and mesh.texture is None:
        corners = mesh.vertex_colours[tris[t]].astype(np.float32)          # (P, 3 corners, 3)
        rgb[seen] = np.clip(np.einsum("pk,pkc->pc", w, corners) + 0.5, 0, 255).astype(np.uint8)
    else:
        uv = np.einsum("pk,pkc->pc", w, mesh.corner_uv[t])
        rgb[seen] = sample_texture(mesh, uv, _texture_level(mesh, T, intrinsics.K, tris))
    return MeshRender(rgb, depth, tri_id, T, intrinsics)


def _texture_level(mesh: TriangleMesh, T, K, tris) -> int:
    """Pyramid level of the texture for this view: texels per pixel over the triangles in
    front of the camera, as the ratio of their texture area to their picture area."""
    cam = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    z = cam[:, 2]
    safe = np.where(z > NEAR_M, z, 1.0)
    u = K[0, 0] * cam[:, 0] / safe + K[0, 1] * cam[:, 1] / safe + K[0, 2]
    v = K[1, 1] * cam[:, 1] / safe + K[1, 2]
    h, w = mesh.texture.shape[:2]
    front = np.all(z[tris] > NEAR_M, axis=1)
    pu, pv = u[tris[front]], v[tris[front]]
    px = 0.5 * np.abs((pu[:, 1] - pu[:, 0]) * (pv[:, 2] - pv[:, 0]) - (pu[:, 2] - pu[:, 0]) * (pv[:, 1] - pv[:, 0]))
    c = mesh.corner_uv[front].astype(np.float64) * [w, h]
    tx = 0.5 * np.abs((c[:, 1, 0] - c[:, 0, 0]) * (c[:, 2, 1] - c[:, 0, 1]) - (c[:, 2, 0] - c[:, 0, 0]) * (c[:, 1, 1] - c[:, 0, 1]))
    if px.sum() <= 0:
        return 0
    return max(int(np.floor(0.5 * np.log2(max(tx.sum() / px.sum(), 1.0)))), 0)


def sample_texture(mesh: TriangleMesh, uv: np.ndarray, level: int) -> np.ndarray:
    """(P, 3) uint8: the texture at texture coordinates ``uv`` (P, 2) (v up from the
    picture's bottom, as PLY and OBJ writers have it), bilinear, on pyramid level ``level``."""
    img = mesh.texture
    for _ in range(level):
        if min(img.shape[:2]) < 4:
            break
        img = cv2.pyrDown(img)
    h, w = img.shape[:2]
    # One row of coordinates: cv2.remap takes maps of at most SHRT_MAX columns.
    mu = (uv[:, 0] * w - 0.5).astype(np.float32)
    mv = ((1.0 - uv[:, 1]) * h - 0.5).astype(np.float32)
    out = np.empty((len(uv), 3), np.uint8)
    step = 30000
    for s in range(0, len(uv), step):
        out[s:s + step] = cv2.remap(img, mu[None, s:s + step], mv[None, s:s + step], cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_WRAP)[0]
    return out


def look_at(centre: np.ndarray, direction: np.ndarray, distance: float) -> np.ndarray:
    """(4, 4) mesh frame -> optical frame of a camera ``distance`` from ``centre`` along the
    unit ``direction`` (from the object towards the camera), looking at ``centre``."""
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    z_axis = -d
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = np.cross(z_axis, up)           # image y (down) along the mesh's -up: "up" up in the picture
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    R = np.stack([x_axis, y_axis, z_axis])  # rows: camera axes in mesh coordinates
    eye = np.asarray(centre, np.float64) + distance * d
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


__all__ = ["MeshRender", "render_mesh", "rasterise", "look_at", "BACKGROUND_RGB", "sample_texture"]
