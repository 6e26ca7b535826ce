"""Object models from CAD meshes: surface samples, normals, FPFH descriptors, box, symmetries.

The model frame is the mesh's own frame, so poses come out in the CAD coordinates. The
shape data is sampled at the voxel the frames will be sampled at (``shape.shape_voxel`` of
the mesh's box), from a surface sampled four times denser, so that model and frame
descriptors describe the same neighbourhoods. A model built this way has no SIFT
keypoints; ``add_capture_keypoints`` adds them from capture views whose object poses are
known in the mesh frame (texture and shape in one model), and ``add_rendered_keypoints``
from renders of the mesh itself when it has colour (vertex colours or a texture).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ..meshes import TriangleMesh, sample_surface
from ..symmetry import Symmetries, detect_symmetries, parse_symmetry_text
from .model import ObjectModel
from ..frontends.shape.geometry import describe, shape_voxel, voxel_downsample

MARKER_SPACING_M = 0.003


def view_directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def view_descriptors(dense: np.ndarray, dense_normals: np.ndarray, voxel: float, centre: np.ndarray, views: int):
    """Descriptors of the surface as a camera sees it from ``views`` directions: a frame
    holds only the side facing the camera, and FPFH of a point near a silhouette differs
    from the same point's FPFH on the whole surface. Per direction: the samples whose normal
    faces it (self-occlusion is ignored), voxel-downsampled and described. Returns points,
    normals, surface variation and FPFH of all views stacked (a physical point appears once
    per view that sees it)."""
    tree = cKDTree(dense)
    out = [[], [], [], []]
    for d in view_directions(views):
        faces = dense_normals @ d > 0.1
        if faces.sum() < 10:
            continue
        pts = voxel_downsample(dense[faces], voxel)
        _, j = tree.query(pts, k=1, workers=-1)
        normals, variation, desc = describe(pts, voxel, along=dense_normals[j])
        for lst, val in zip(out, (pts, normals, variation, desc)):
            lst.append(val)
    return tuple(np.concatenate(v) for v in out)


def surface_grey(mesh: TriangleMesh, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(P,) uint8: the mesh's colour as grey at points on triangles ``faces`` with barycentric
    weights ``bary`` (``sample_surface(..., where=True)``): vertex colours or the texture,
    interpolated."""
    from .mesh_render import sample_texture

    if mesh.vertex_colours is not None:
        rgb = np.einsum("pk,pkc->pc", bary, mesh.vertex_colours[mesh.triangles[faces]].astype(np.float64))
    else:
        uv = np.einsum("pk,pkc->pc", bary, mesh.corner_uv[faces].astype(np.float64))
        rgb = sample_texture(mesh, uv, 0).astype(np.float64)
    return np.clip(np.round(rgb @ np.array([0.299, 0.587, 0.114])), 0, 255).astype(np.uint8)


def mesh_symmetries(mesh: TriangleMesh, seed: int = 1) -> Symmetries:
    """The mesh's symmetries (``symmetry.detect_symmetries``) from its surface sampled every
    1 % of its box diagonal, 1.5 samples' spacing allowed."""
    lo, hi = mesh.bounds
    spacing = float(np.linalg.norm(hi - lo)) / 100.0
    sym_pts, _ = sample_surface(mesh, spacing, seed=seed)
    return detect_symmetries(sym_pts, 1.5 * spacing)


def build_model_from_mesh(mesh: TriangleMesh, name: str = "", symmetry: "str | Symmetries | None" = None,
                          voxel: float | None = None, seed: int = 0, views: int = 20) -> ObjectModel:
    """``symmetry``: None = find from the mesh; text for ``parse_symmetry_text``; or the
    ``Symmetries`` themselves (e.g. from a BOP models_info.json)."""
    lo, hi = mesh.bounds
    extent = hi - lo
    centre = (lo + hi) / 2.0
    voxel = float(voxel) if voxel else shape_voxel(extent)
    dense, dense_normals, faces, bary = sample_surface(mesh, voxel / 4.0, seed=seed, where=True)
    pts, normals, variation, desc = view_descriptors(dense, dense_normals, voxel, centre, views)
    grey = None
    if mesh.has_colour:
        # Each shape point takes the colour of the dense sample nearest it: what the
        # verification compares with the image (explain.py, appearance).
        _, j = cKDTree(dense).query(pts, k=1, workers=-1)
        grey = surface_grey(mesh, faces, bary)[j]
    diameter = float(np.linalg.norm(extent))
    if isinstance(symmetry, Symmetries):
        symmetries = symmetry
    elif symmetry is None:
        symmetries = mesh_symmetries(mesh, seed + 1)
    else:
        symmetries = parse_symmetry_text(symmetry, centre)
    markers, _ = sample_surface(mesh, max(MARKER_SPACING_M, diameter / 150.0), seed=seed + 2)
    return ObjectModel(
        keypoints_xyz=np.zeros((0, 3), np.float32),
        descriptors=np.zeros((0, 128), np.float32),
        points_xyz=markers.astype(np.float32),
        extent=extent.astype(np.float64),
        T_capture_model=np.eye(4),
        T_object_model=np.eye(4),
        name=name,
        shape_points=pts.astype(np.float32),
        shape_normals=normals.astype(np.float32),
        shape_descriptors=desc,
        shape_variation=variation.astype(np.float32),
        shape_voxel=voxel,
        shape_grey=grey,
        box_centre=centre.astype(np.float64),
        symmetries=symmetries,
    )


def add_capture_keypoints(model: ObjectModel, views, settings, T_mesh_object: np.ndarray | None = None) -> ObjectModel:
    """SIFT keypoints of capture views brought into the mesh frame. Each view needs its
    object pose (``T_camera_object``, e.g. a synthetic capture's ground truth); the object
    frame of the captures is the mesh frame unless ``T_mesh_object`` says otherwise."""
    from .model import object_mask

    if not all(v.T_camera_object is not None for v in views):
        raise InputError("capture views given with --mesh need their object poses (ground truth) to be placed "
                         "in the mesh frame; these bags have none")
    T_mo = np.eye(4) if T_mesh_object is None else np.asarray(T_mesh_object, np.float64)
    _keypoints_in_mesh_frame(model, views, [object_mask(v, settings)[0] for v in views], settings, T_mo)
    return model


def _keypoints_in_mesh_frame(model: ObjectModel, views, masks, settings, T_mesh_object: np.ndarray) -> list[int]:
    """Gives ``model`` the SIFT keypoints of ``views`` on their object ``masks`` (lifted by
    the views' depth), brought into the mesh frame by the views' object poses; returns how
    many each view gave."""
    from ..transforms import apply_transform, invert_transform
    from .model import view_keypoints

    xyz_all, desc_all = [], []
    for view, mask in zip(views, masks):
        xyz, desc = view_keypoints(view, mask, settings)
        T_mesh_cam = T_mesh_object @ invert_transform(view.T_camera_object)
        xyz_all.append(apply_transform(T_mesh_cam, xyz.astype(np.float64)))
        desc_all.append(desc)
    xyz = np.concatenate(xyz_all) if xyz_all else np.zeros((0, 3))
    model.keypoints_xyz = xyz.astype(np.float32)
    model.descriptors = (np.concatenate(desc_all) if desc_all else np.zeros((0, 128))).astype(np.float32)
    return [len(x) for x in xyz_all]


# Rendered views of a coloured mesh: a Primesense-like camera (IC-BIN's K is fx 550, fy 540 at
# 640 x 480) at the distance objects are seen from in a bin or on a table.
RENDER_FOCAL_PX = 550.0
RENDER_SIZE = (640, 480)
RENDER_DISTANCE_M = 0.6
RENDER_VIEWS = 30
CROP_MARGIN_PX = 32


def render_views(mesh: TriangleMesh, count: int = RENDER_VIEWS, distance: float = RENDER_DISTANCE_M,
                 focal_px: float = RENDER_FOCAL_PX, size: tuple[int, int] = RENDER_SIZE) -> list:
    """``count`` renders (``mesh_render.MeshRender``) of the coloured mesh from directions
    spread over the sphere, ``distance`` from its box centre, looking at it."""
    from .mesh_render import look_at, render_mesh
    from ..messages import CameraIntrinsics

    w, h = size
    K = np.array([[focal_px, 0.0, (w - 1) / 2.0], [0.0, focal_px, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    intrinsics = CameraIntrinsics(K, w, h)
    lo, hi = mesh.bounds
    return [render_mesh(mesh, look_at((lo + hi) / 2.0, d, distance), intrinsics) for d in view_directions(count)]


def add_rendered_keypoints(model: ObjectModel, mesh: TriangleMesh, settings, count: int = RENDER_VIEWS,
                           distance: float = RENDER_DISTANCE_M) -> tuple[ObjectModel, list[int]]:
    """SIFT keypoints of a coloured mesh (vertex colours or texture) from ``count`` renders
    around it (``render_views``), lifted by the rendered depth into the mesh frame: the model
    then takes the SIFT path with no capture bag. Returns the model and the keypoints per view."""
    from ..messages import CameraIntrinsics
    from .model import CaptureView

    from scipy.ndimage import distance_transform_edt

    renders = render_views(mesh, count, distance)
    views, masks = [], []
    for r in renders:
        # SIFT on the object's box (plus a margin for the descriptors' support) rather than the
        # whole picture: the pyramid of a 640 x 480 picture costs several times the object's.
        ys, xs = np.nonzero(r.mask)
        if len(xs) == 0:
            continue
        h, w = r.mask.shape
        x0, y0 = max(int(xs.min()) - CROP_MARGIN_PX, 0), max(int(ys.min()) - CROP_MARGIN_PX, 0)
        x1, y1 = min(int(xs.max()) + CROP_MARGIN_PX + 1, w), min(int(ys.max()) + CROP_MARGIN_PX + 1, h)
        K = np.array(r.intrinsics.K, np.float64)
        K[0, 2] -= x0
        K[1, 2] -= y0
        crop = (slice(y0, y1), slice(x0, x1))
        mask = r.mask[crop]
        # The outline against the render's background would give keypoints (a plain object
        # hundreds) that describe that background as much as the object, and a real scene
        # has other things around it: the background continues the object's own border
        # colours, so that only the object's print makes keypoints.
        _, (iy, ix) = distance_transform_edt(~mask, return_indices=True)
        views.append(CaptureView(np.ascontiguousarray(r.rgb[crop][iy, ix]), np.ascontiguousarray(r.depth_m[crop]),
                                 CameraIntrinsics(K, x1 - x0, y1 - y0), r.T_camera_object))
        masks.append(mask)
    per_view = _keypoints_in_mesh_frame(model, views, masks, settings, np.eye(4))
    return model, per_view


def add_placed_keypoints(model: ObjectModel, objects, poses) -> ObjectModel:
    """SIFT keypoints of capture views (``model.view_objects``: each in its own optical frame)
    brought into the mesh frame by the views' object poses (mesh frame -> view; None: the
    view is left out), e.g. from ``capture_alignment.place_views``."""
    from ..transforms import apply_transform, invert_transform

    placed = [(o, T) for o, T in zip(objects, poses) if T is not None]
    xyz = [apply_transform(invert_transform(T), o.keypoints_xyz) for o, T in placed]
    model.keypoints_xyz = (np.concatenate(xyz) if xyz else np.zeros((0, 3))).astype(np.float32)
    model.descriptors = (np.concatenate([o.descriptors for o, _ in placed]) if placed
                         else np.zeros((0, 128))).astype(np.float32)
    return model


__all__ = ["build_model_from_mesh", "surface_grey", "mesh_symmetries", "add_capture_keypoints", "add_placed_keypoints",
           "add_rendered_keypoints", "render_views", "Symmetries"]
