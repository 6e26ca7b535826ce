"""A z-buffered rasteriser of textured quads, discs and cylinders, in numpy and OpenCV.

No ROS, no GPU. Each primitive is rasterised over its bounding box in the image at once:
planar primitives by the inverse of the homography plane -> image, cylinder sides by a
ray-cylinder intersection. Textures are mip-mapped (chosen per pixel from the texel
footprint) and sampled with ``cv2.remap``. Shading is Lambertian from one directional light
plus ambient. The result is noise-free radiance, metric depth and a label per pixel; the
sensor models in :mod:`.sensor` turn them into what a D455 would send.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

LABEL_NOTHING = -1   # background, table, wall
NEAR_PLANE_M = 0.02

# Light: from above, a little from the front left; ambient keeps shadowed faces readable.
LIGHT_DIR_WORLD = np.array([-0.35, -0.45, 0.82]) / np.linalg.norm([-0.35, -0.45, 0.82])
AMBIENT = 0.42
DIFFUSE = 0.62


class Texture:
    """An RGB uint8 picture and its mip-map pyramid."""

    def __init__(self, image: np.ndarray, wrap: bool = False):
        self.levels = [np.ascontiguousarray(image)]
        while min(self.levels[-1].shape[:2]) > 8 and len(self.levels) < 8:
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        self.border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REPLICATE
        self.height, self.width = image.shape[:2]


@dataclass
class Quad:
    """A planar parallelogram ``origin + s*e1 + t*e2`` (s, t in [0, 1]) in the world frame.
    The texture is mapped with s along its columns and t along its rows, over the texel
    rectangle ``tex_rect`` = (u0, v0, u1, v1) (beyond the picture when it tiles).
    ``disc`` keeps only the inscribed ellipse (cylinder caps)."""
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray          # outward unit normal; the back side is never drawn
    texture: Texture
    tex_rect: tuple[float, float, float, float]
    label: int = LABEL_NOTHING
    disc: bool = False
    # Optional (h, w) float32 brightness over the quad (s along columns, t along rows), e.g.
    # the shadows that objects cast on the table.
    lightmap: np.ndarray | None = None


@dataclass
class CylinderSide:
    """The curved surface of a cylinder; ``pose`` is object -> world (axis = object z)."""
    pose: np.ndarray
    radius: float
    height: float
    texture: Texture
    label: int = LABEL_NOTHING


@dataclass
class RenderOutput:
    radiance: np.ndarray        # (H, W, 3) float32, 0..~1, noise-free
    depth_m: np.ndarray         # (H, W) float32, inf where nothing was hit
    labels: np.ndarray          # (H, W) int16
    # label -> number of pixels it would cover with no occluder (image border included,
    # up to a margin of one image size), for labels >= 0.
    coverage: dict = field(default_factory=dict)


def _remap_rows(texture: Texture, U: np.ndarray, V: np.ndarray, row_level: np.ndarray) -> np.ndarray:
    """Sample ``texture`` at level-0 texel coordinates (U, V) (h, w) float32, using mip level
    ``row_level[i]`` for row i: rows of equal level are remapped together, so the cost is one
    remap of the whole box whatever the number of levels."""
    h, w = U.shape
    out = np.empty((h, w, 3), np.uint8)
    change = np.flatnonzero(np.diff(row_level)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [h]])
    for a, b in zip(starts, ends):
        lev = int(row_level[a])
        scale = np.float32(1.0 / (1 << lev))
        off = np.float32(0.5) * scale - np.float32(0.5)   # texel centres on level lev
        img = texture.levels[lev]
        mu = U[a:b] * scale + off
        mv = V[a:b] * scale + off
        if texture.border == cv2.BORDER_WRAP:
            # Fold into the picture first: remap's border path is slow per pixel.
            mu = np.mod(mu, np.float32(img.shape[1]))
            mv = np.mod(mv, np.float32(img.shape[0]))
        out[a:b] = cv2.remap(img, mu, mv, cv2.INTER_LINEAR, borderMode=texture.border)
    return out


def _level(texture: Texture, footprint) -> np.ndarray:
    """Mip level for a footprint in texels per pixel (a bias of 0.3 keeps it a little sharp)."""
    lev = np.log2(np.maximum(footprint, 1e-6)) + 0.3
    return np.clip(lev, 0, len(texture.levels) - 1).astype(np.int32)


class Renderer:
    """Renders lists of primitives for a pinhole camera ``K`` of size ``width`` x ``height``."""

    def __init__(self, K: np.ndarray, width: int, height: int):
        self.K = np.asarray(K, dtype=np.float64)
        self.width, self.height = int(width), int(height)
        self._Kinv = np.linalg.inv(self.K)

    # -- helpers --------------------------------------------------------------------------
    def _bbox(self, corners_cam: np.ndarray, window) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) covering the projection of the convex hull of
        ``corners_cam``, cut at the near plane, clipped to ``window``."""
        wx0, wy0, wx1, wy1 = window
        z = corners_cam[:, 2]
        front = z >= NEAR_PLANE_M
        if not front.any():
            return None
        pts = corners_cam[front]
        if not front.all():
            # The hull cut by the near plane is the hull of the points in front and of where
            # the segments between front and behind points cross the plane.
            a = corners_cam[front][:, None, :]
            b = corners_cam[~front][None, :, :]
            f = (NEAR_PLANE_M - a[..., 2]) / (b[..., 2] - a[..., 2])
            pts = np.concatenate([pts, (a + f[..., None] * (b - a)).reshape(-1, 3)])
        p = pts @ self.K.T
        x = p[:, 0] / p[:, 2]
        y = p[:, 1] / p[:, 2]
        x0 = max(wx0, int(np.floor(max(x.min(), -1e6))))
        y0 = max(wy0, int(np.floor(max(y.min(), -1e6))))
        x1 = min(wx1, int(np.ceil(min(x.max(), 1e6))) + 1)
        y1 = min(wy1, int(np.ceil(min(y.max(), 1e6))) + 1)
        if x0 >= x1 or y0 >= y1:
            return None
        return x0, y0, x1, y1

    def render(self, primitives, T_cam_world: np.ndarray, count_labels=()) -> RenderOutput:
        """Draw ``primitives`` seen from the camera whose world -> camera transform is
        ``T_cam_world``. For labels in ``count_labels`` also count their unoccluded coverage."""
        W, H = self.width, self.height
        radiance = np.zeros((H, W, 3), np.float32)
        zbuf = np.full((H, W), np.inf, np.float32)
        labels = np.full((H, W), LABEL_NOTHING, np.int16)
        count_labels = set(count_labels)
        coverage = {k: 0 for k in count_labels}
        R = T_cam_world[:3, :3]
        t = T_cam_world[:3, 3]
        light_cam = R @ LIGHT_DIR_WORLD
        labels_touched = False      # until an object is drawn, labels are all LABEL_NOTHING
        image_window = (0, 0, W, H)
        wide_window = (-W, -H, 2 * W, 2 * H)
        for prim in primitives:
            counted = prim.label in count_labels
            window = wide_window if counted else image_window
            if isinstance(prim, Quad):
                res = self._raster_quad(prim, R, t, light_cam, window)
            else:
                res = self._raster_cylinder(prim, R, t, light_cam, window)
            if res is None:
                continue
            (x0, y0, x1, y1), inside, z, colour_fn = res
            if counted:
                coverage[prim.label] += int(np.count_nonzero(inside))
                # Keep only the part inside the image.
                cx0, cy0 = max(x0, 0), max(y0, 0)
                cx1, cy1 = min(x1, W), min(y1, H)
                if cx0 >= cx1 or cy0 >= cy1:
                    continue
                sub = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
                inside, z = inside[sub], z[sub]
                colour_fn = colour_fn(sub)
                x0, y0, x1, y1 = cx0, cy0, cx1, cy1
            else:
                colour_fn = colour_fn(None)
            zr = zbuf[y0:y1, x0:x1]
            draw = inside & (z < zr)
            if not draw.any():
                continue
            # copyto(where=) is faster than boolean indexing on large boxes (no compaction).
            np.copyto(zr, z, where=draw)
            if prim.label != LABEL_NOTHING or labels_touched:
                np.copyto(labels[y0:y1, x0:x1], np.int16(prim.label), where=draw)
                labels_touched = True
            np.copyto(radiance[y0:y1, x0:x1], colour_fn(draw), where=draw[:, :, None])
        return RenderOutput(radiance, zbuf, labels, coverage)

    # -- planar primitives ----------------------------------------------------------------
    def _raster_quad(self, q: Quad, R, t, light_cam, window):
        o = R @ q.origin + t
        e1 = R @ q.e1
        e2 = R @ q.e2
        n = R @ q.normal
        if n @ o >= 0:          # back face
            return None
        corners = np.stack([o, o + e1, o + e1 + e2, o + e2])
        box = self._bbox(corners, window)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        Hm = self.K @ np.column_stack([e1, e2, o])   # (s, t, 1) -> z * (u, v, 1)
        try:
            Hi = np.linalg.inv(Hm)
        except np.linalg.LinAlgError:
            return None                               # seen exactly edge-on
        Hf = Hi.astype(np.float32)
        u = np.arange(x0, x1, dtype=np.float32)[None, :]
        v = np.arange(y0, y1, dtype=np.float32)[:, None]
        c = Hf[2, 0] * u + Hf[2, 1] * v + Hf[2, 2]    # = 1 / z
        valid = c > 1e-6
        cs = np.where(valid, c, np.float32(1.0))
        s = (Hf[0, 0] * u + Hf[0, 1] * v + Hf[0, 2]) / cs
        tt = (Hf[1, 0] * u + Hf[1, 1] * v + Hf[1, 2]) / cs
        if q.disc:
            inside = valid & ((s - 0.5) ** 2 + (tt - 0.5) ** 2 <= 0.25)
        else:
            inside = valid & (s >= 0) & (s <= 1) & (tt >= 0) & (tt <= 1)
        z = 1.0 / cs
        shade = np.float32((AMBIENT + DIFFUSE * max(0.0, float(n @ light_cam))) / 255.0)
        u0, v0, u1, v1 = q.tex_rect
        du, dv = np.float32(u1 - u0), np.float32(v1 - v0)
        tex = q.texture

        def make_colour(sub):
            ss, ts = (s, tt) if sub is None else (s[sub], tt[sub])
            rows0 = y0 + (0 if sub is None else sub[0].start)
            cols0 = x0 + (0 if sub is None else sub[1].start)

            def colour(mask):
                levels = self._row_levels(Hi, du, dv, tex, rows0, cols0, mask.shape)
                img = _remap_rows(tex, u0 + ss * du, v0 + ts * dv, levels)
                out = img.astype(np.float32) * shade
                if q.lightmap is not None:
                    lh, lw = q.lightmap.shape
                    light = cv2.remap(q.lightmap, ss * np.float32(lw) - np.float32(0.5),
                                      ts * np.float32(lh) - np.float32(0.5), cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REPLICATE)
                    out *= light[:, :, None]
                return out
            return colour
        return box, inside, z, make_colour

    def _row_levels(self, Hi, du, dv, tex, row0, col0, shape) -> np.ndarray:
        """Mip level per image row: the texel footprint (the larger of the two pixel axes) at
        three columns of the row, the smallest where the plane is in front."""
        h, w = shape
        v = np.arange(row0, row0 + h, dtype=np.float64)[:, None]
        u = np.array([col0, col0 + (w - 1) / 2, col0 + w - 1], dtype=np.float64)[None, :]
        c = Hi[2, 0] * u + Hi[2, 1] * v + Hi[2, 2]
        ok = c > 1e-9
        c = np.where(ok, c, 1.0)
        s = (Hi[0, 0] * u + Hi[0, 1] * v + Hi[0, 2]) / c
        t = (Hi[1, 0] * u + Hi[1, 1] * v + Hi[1, 2]) / c
        su, sv = (Hi[0, 0] - s * Hi[2, 0]) / c, (Hi[0, 1] - s * Hi[2, 1]) / c
        tu, tv = (Hi[1, 0] - t * Hi[2, 0]) / c, (Hi[1, 1] - t * Hi[2, 1]) / c
        fp = np.maximum(np.hypot(su * du, tu * dv), np.hypot(sv * du, tv * dv))
        fp = np.where(ok, fp, np.inf).min(axis=1)
        fp = np.where(np.isfinite(fp), fp, 1e6)
        return _level(tex, fp)

    # -- cylinder sides -------------------------------------------------------------------
    def _raster_cylinder(self, cyl: CylinderSide, R, t, light_cam, window):
        R_co = R @ cyl.pose[:3, :3]
        t_co = R @ cyl.pose[:3, 3] + t
        r, hh = cyl.radius, 0.5 * cyl.height
        corners_obj = np.array([[sx * r, sy * r, sz * hh] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        box = self._bbox(corners_obj @ R_co.T + t_co, window)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        # Rays in the object frame: p0 + lam * d with d = R_oc K^-1 (u, v, 1), so lam = z_cam.
        R_oc = R_co.T
        p0 = (-R_oc @ t_co).astype(np.float32)
        M = (R_oc @ self._Kinv).astype(np.float32)
        u = np.arange(x0, x1, dtype=np.float32)[None, :]
        v = np.arange(y0, y1, dtype=np.float32)[:, None]
        dx = M[0, 0] * u + M[0, 1] * v + M[0, 2]
        dy = M[1, 0] * u + M[1, 1] * v + M[1, 2]
        dz = M[2, 0] * u + M[2, 1] * v + M[2, 2]
        A = dx * dx + dy * dy
        B = p0[0] * dx + p0[1] * dy
        C = np.float32(p0[0] ** 2 + p0[1] ** 2 - r * r)
        disc = B * B - A * C
        ok = (disc > 0) & (A > 1e-12)
        lam = (-B - np.sqrt(np.maximum(disc, 0))) / np.where(ok, A, np.float32(1))
        pz = p0[2] + lam * dz
        inside = ok & (lam > NEAR_PLANE_M) & (np.abs(pz) <= hh)
        z = np.where(inside, lam, np.float32(np.inf))
        tex = cyl.texture
        # One mip level for the whole (small) cylinder, from its distance.
        texels_per_m = tex.width / (2 * np.pi * r)
        level = int(_level(tex, texels_per_m * max(float(np.linalg.norm(t_co)), 0.05) / self.K[0, 0]))
        light_obj = (R_oc @ light_cam).astype(np.float32)

        def make_colour(sub):
            pick = (lambda a: a) if sub is None else (lambda a: a[sub])

            def colour(mask):
                lm = pick(lam)
                px = p0[0] + lm * pick(dx)
                py = p0[1] + lm * pick(dy)
                U = (np.arctan2(py, px) * np.float32(1.0 / (2 * np.pi)) % np.float32(1.0)) * np.float32(tex.width)
                V = (np.float32(hh) - pick(pz)) * np.float32(tex.height / cyl.height)
                img = _remap_rows(tex, U, V, np.full(U.shape[0], level, np.int32))
                lambert = np.maximum((px * light_obj[0] + py * light_obj[1]) / np.float32(r), 0)
                shade = (np.float32(AMBIENT) + np.float32(DIFFUSE) * lambert) / np.float32(255.0)
                return img.astype(np.float32) * shade[:, :, None]
            return colour
        return box, inside, z, make_colour
