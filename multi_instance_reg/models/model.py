"""The stored object model ("the scan of the object"): SIFT keypoints lifted to 3D in a model
frame centred on the object, plus a dense cloud for markers.

File format (npz, read with allow_pickle=False):
  schema_version   ()      int      MODEL_SCHEMA_VERSION
  keypoints_xyz    (S, 3)  float32  keypoint positions, model frame, metres
  descriptors      (S, 128) float32 SIFT descriptors (plain, not RootSIFT)
  points_xyz       (P, 3)  float32  dense object cloud, model frame (for markers)
  extent           (3,)    float64  size of the object's box along the model axes
  T_capture_model  (4, 4)  float64  model frame in the optical frame of the first capture frame
                                    (of the first one placed, when views registered by texture leave it out)
  T_object_model   (4, 4)  float64  optional: model frame in the object's ground-truth frame
  name             ()      str      optional: the object's name (`mireg build-model --name`); a file
                                    without one, or with an empty one, is named after its file
                                    stem when loaded (``model_name``)
Optional, from a mesh (`mireg build-model --mesh`; files without them load as before):
  shape_voxel      ()      float64  metres: the voxel the shape data (and every frame) is sampled at
  shape_points     (Q, 3)  float32  the surface, voxel-downsampled, model frame
  shape_normals    (Q, 3)  float32  outward unit normals there
  shape_descriptors (Q, 33) float32 FPFH descriptors there (frontends/shape/geometry.py)
  shape_variation  (Q,)    float32  surface variation there (flat faces ~0; edges, corners higher)
  shape_grey       (Q,)    uint8    optional: the mesh's grey level there (a mesh with colour)
  box_centre       (3,)    float64  centre of the object's box in the model frame (default 0)
  symmetry_discrete (S, 4, 4) float64  symmetries, identity first (multi_instance_reg/symmetry.py)
  symmetry_axis    (3,)    float64  continuous symmetry about this axis ...
  symmetry_point   (3,)    float64  ... through this point
A model may then have no SIFT keypoints at all (0 rows): it is found by shape alone.

The model frame of a capture: origin at the centre of the object's bounding box; z along the table normal
(up, towards the camera) when a table plane was found, else the capture camera's axes. Of a
mesh: the mesh's own frame (poses come out in the CAD coordinates).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..files import require_npz_archive
from ..messages import CameraIntrinsics
from ..transforms import apply_transform, invert_transform, make_transform
from ..frontends.sift.features import SiftSettings, extract_sift
from ..rgbd.lifting import backproject, depth_to_cloud, fit_dominant_plane, lookup_depth, undistort_pixels

MODEL_SCHEMA_VERSION = 1
_REQUIRED = ("schema_version", "keypoints_xyz", "descriptors", "points_xyz", "extent", "T_capture_model")


@dataclass
class ObjectModel:
    keypoints_xyz: np.ndarray            # (S, 3) float32, model frame
    descriptors: np.ndarray              # (S, 128) float32
    points_xyz: np.ndarray               # (P, 3) float32, model frame
    extent: np.ndarray                   # (3,) float64
    T_capture_model: np.ndarray          # (4, 4) float64
    T_object_model: np.ndarray | None = None
    name: str = ""
    # Shape data (from a mesh); None when the model has none.
    shape_points: np.ndarray | None = None       # (Q, 3) float32
    shape_normals: np.ndarray | None = None      # (Q, 3) float32
    shape_descriptors: np.ndarray | None = None  # (Q, 33) float32
    shape_variation: np.ndarray | None = None    # (Q,) float32
    shape_voxel: float = 0.0
    shape_grey: np.ndarray | None = None         # (Q,) uint8, the mesh's colour as grey (None: no colour)
    box_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    symmetries: "Symmetries | None" = None
    # Not stored: how many views a build without ground truth placed (None: all, by their poses),
    # and which view's optical frame is the capture frame (the first placed).
    views_placed: int | None = None
    capture_view: int = 0

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints_xyz)

    @property
    def has_shape(self) -> bool:
        return self.shape_descriptors is not None and len(self.shape_descriptors) >= 3

    def box_corners(self) -> np.ndarray:
        """(8, 3) corners of the object's box in the model frame."""
        h = np.asarray(self.extent, dtype=np.float64) / 2.0
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        return signs * h + np.asarray(self.box_centre, dtype=np.float64)


def save_model(model: ObjectModel, path) -> Path:
    path = Path(path)
    if path.suffix != ".npz":
        raise InputError(f"model file {path} must end in .npz")
    arrays = {
        "schema_version": np.array(MODEL_SCHEMA_VERSION, dtype=np.int64),
        "keypoints_xyz": np.asarray(model.keypoints_xyz, dtype=np.float32),
        "descriptors": np.asarray(model.descriptors, dtype=np.float32),
        "points_xyz": np.asarray(model.points_xyz, dtype=np.float32),
        "extent": np.asarray(model.extent, dtype=np.float64),
        "T_capture_model": np.asarray(model.T_capture_model, dtype=np.float64),
        "name": np.array(str(model.name)),
    }
    if model.T_object_model is not None:
        arrays["T_object_model"] = np.asarray(model.T_object_model, dtype=np.float64)
    if model.has_shape:
        arrays.update(shape_voxel=np.array(float(model.shape_voxel)),
                      shape_points=np.asarray(model.shape_points, np.float32),
                      shape_normals=np.asarray(model.shape_normals, np.float32),
                      shape_descriptors=np.asarray(model.shape_descriptors, np.float32),
                      shape_variation=np.asarray(model.shape_variation, np.float32))
    if model.has_shape and model.shape_grey is not None:
        arrays["shape_grey"] = np.asarray(model.shape_grey, np.uint8)
    if np.any(np.asarray(model.box_centre) != 0):
        arrays["box_centre"] = np.asarray(model.box_centre, np.float64)
    if model.symmetries is not None and not model.symmetries.is_trivial:
        arrays["symmetry_discrete"] = np.asarray(model.symmetries.discrete, np.float64)
        if model.symmetries.axis is not None:
            arrays["symmetry_axis"] = np.asarray(model.symmetries.axis, np.float64)
            arrays["symmetry_point"] = np.asarray(model.symmetries.point, np.float64)
    _check_arrays(arrays, str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


NAME_RULE = "letters, digits and underscores, not starting with a digit"


def is_valid_name(name: str) -> bool:
    """Names become part of topic names (instances/<name>/poses) and marker namespaces, so
    they follow what a ROS name token allows."""
    import re

    return re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)) is not None


def model_name(stored: str, path) -> str:
    """The name a model goes by: the one stored in its file, else its file stem (``a/can.npz``
    -> ``can``; characters a topic name cannot hold become ``_``), so that files written
    before names were used still get a distinct one."""
    import re

    name = str(stored).strip()
    if name:
        return name
    stem = re.sub(r"[^A-Za-z0-9_]", "_", Path(path).stem) or "object"
    return stem if is_valid_name(stem) else "_" + stem


def load_model(path) -> ObjectModel:
    """Read and check a model file; InputError names what is wrong with it. The model's
    ``name`` is the stored one, or the file stem when none is stored (``model_name``)."""
    path = require_npz_archive(path, "model file", "build one with `mireg build-model`")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except ValueError as exc:  # object arrays need pickle, which is never used for models
        raise InputError(f"model file {path} is not a valid model: {str(exc).split('.')[0]}") from None
    except Exception as exc:  # zipfile.BadZipFile, EOFError, OSError: a damaged archive
        raise InputError(f"model file {path} is not a readable .npz ({type(exc).__name__}: {exc}); "
                         f"rebuild it with `mireg build-model`") from None
    _check_arrays(arrays, str(path))
    from ..symmetry import Symmetries

    shape = {}
    if "shape_descriptors" in arrays:
        shape = dict(shape_voxel=float(arrays["shape_voxel"]),
                     **{k: arrays[k].astype(np.float32) for k in
                        ("shape_points", "shape_normals", "shape_descriptors", "shape_variation")})
    if "symmetry_discrete" in arrays:
        shape["symmetries"] = Symmetries(arrays["symmetry_discrete"].astype(np.float64),
                                         arrays.get("symmetry_axis"), arrays.get("symmetry_point"))
    if "shape_grey" in arrays and "shape_descriptors" in arrays:
        shape["shape_grey"] = arrays["shape_grey"].astype(np.uint8)
    if "box_centre" in arrays:
        shape["box_centre"] = arrays["box_centre"].astype(np.float64)
    return ObjectModel(**shape,
        keypoints_xyz=arrays["keypoints_xyz"].astype(np.float32),
        descriptors=arrays["descriptors"].astype(np.float32),
        points_xyz=arrays["points_xyz"].astype(np.float32),
        extent=arrays["extent"].astype(np.float64),
        T_capture_model=arrays["T_capture_model"].astype(np.float64),
        T_object_model=arrays["T_object_model"].astype(np.float64) if "T_object_model" in arrays else None,
        name=model_name(arrays["name"] if "name" in arrays else "", path),
    )


def _check_arrays(a: dict, where: str) -> None:
    missing = [k for k in _REQUIRED if k not in a]
    if missing:
        raise InputError(f"model file {where} lacks {', '.join(missing)}; rebuild it with `mireg build-model`")
    version = a["schema_version"]
    if version.shape != () or not np.issubdtype(version.dtype, np.integer) or int(version) != MODEL_SCHEMA_VERSION:
        raise InputError(f"model file {where} has schema_version {version!r}; this version reads "
                         f"{MODEL_SCHEMA_VERSION}: rebuild it with `mireg build-model`")

    def shape_ok(key, shape):
        arr = a[key]
        if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
            raise InputError(f"model file {where}: {key} has shape {arr.shape}, expected "
                             f"({', '.join('N' if s is None else str(s) for s in shape)})")
        if not np.issubdtype(arr.dtype, np.number) or not np.all(np.isfinite(arr)):
            raise InputError(f"model file {where}: {key} must hold finite numbers")

    shape_ok("keypoints_xyz", (None, 3))
    shape_ok("descriptors", (None, 128))
    shape_ok("points_xyz", (None, 3))
    shape_ok("extent", (3,))
    shape_ok("T_capture_model", (4, 4))
    if "T_object_model" in a:
        shape_ok("T_object_model", (4, 4))
    s = len(a["keypoints_xyz"])
    if len(a["descriptors"]) != s:
        raise InputError(f"model file {where}: {s} keypoints but {len(a['descriptors'])} descriptors")
    shape_keys = ("shape_voxel", "shape_points", "shape_normals", "shape_descriptors", "shape_variation")
    if any(k in a for k in shape_keys):
        if not all(k in a for k in shape_keys):
            raise InputError(f"model file {where} has only some of {', '.join(shape_keys)}; "
                             f"rebuild it with `mireg build-model --mesh`")
        shape_ok("shape_points", (None, 3))
        q = len(a["shape_points"])
        shape_ok("shape_normals", (q, 3))
        shape_ok("shape_descriptors", (q, 33))
        shape_ok("shape_variation", (q,))
        shape_ok("shape_voxel", ())
        if q < 3 or not float(a["shape_voxel"]) > 0:
            raise InputError(f"model file {where}: shape data with {q} points and voxel {float(a['shape_voxel'])}; "
                             f"rebuild it with `mireg build-model --mesh`")
    if "shape_grey" in a and "shape_points" in a:
        shape_ok("shape_grey", (len(a["shape_points"]),))
    if "box_centre" in a:
        shape_ok("box_centre", (3,))
    if "symmetry_discrete" in a:
        shape_ok("symmetry_discrete", (None, 4, 4))
        if ("symmetry_axis" in a) != ("symmetry_point" in a):
            raise InputError(f"model file {where}: symmetry_axis and symmetry_point go together")
        if "symmetry_axis" in a:
            shape_ok("symmetry_axis", (3,))
            shape_ok("symmetry_point", (3,))
    if s < 3 and "shape_descriptors" in a:
        return
    if s < 3:
        raise InputError(f"model file {where} has {s} keypoints (at least 3 needed); rebuild it from views "
                         f"where the object is textured and has valid depth")


# --------------------------------------------------------------------------- building

@dataclass
class CaptureView:
    """One RGB-D view of the object for model building."""
    rgb: np.ndarray                      # (H, W, 3) uint8
    depth_m: np.ndarray                  # (H, W) float32 metres, 0 = invalid
    intrinsics: CameraIntrinsics
    T_camera_object: np.ndarray | None = None   # ground truth: object frame in this view's optical frame


@dataclass(frozen=True)
class BuildSettings:
    roi: tuple[int, int, int, int] | None = None       # x, y, w, h in pixels
    depth_range: tuple[float, float] = (0.1, 4.0)      # metres
    plane_thresh: float = 0.01                         # metres: table points within this of the plane are removed
    edge_thresh: float = 0.015                         # metres: depth step between neighbours that separates blobs
    min_blob_pixels: int = 200                         # blobs smaller than this are never the object
    sift: SiftSettings = field(default_factory=lambda: SiftSettings(contrast_threshold=0.02, upsample=1.0))
    depth_window: int = 5
    voxel: float = 0.003                               # metres: dense cloud resolution
    min_keypoints: int = 10
    tilts: tuple[float, ...] = (2.0,)                  # simulated view tilts (ASIFT); () = off
    tilt_directions: int = 2                           # directions per tilt (0 .. 180 deg)
    seed: int = 0


def object_mask(view: CaptureView, settings: BuildSettings) -> tuple[np.ndarray, tuple[np.ndarray, float] | None]:
    """(H, W) bool mask of the object in one view, and the table plane (n, d) if one was removed.

    ROI and depth range first; then the dominant plane (the table) and everything behind it
    go; the largest connected blob left is the object.
    """
    depth = view.depth_m
    h, w = depth.shape
    lo, hi = settings.depth_range
    mask = np.isfinite(depth) & (depth >= lo) & (depth <= hi)
    if settings.roi is not None:
        x, y, rw, rh = settings.roi
        if rw <= 0 or rh <= 0 or x < 0 or y < 0 or x + rw > w or y + rh > h:
            raise InputError(f"ROI {x},{y},{rw},{rh} is not inside the {w}x{h} image (x,y,w,h in pixels)")
        roi = np.zeros_like(mask)
        roi[y:y + rh, x:x + rw] = True
        mask &= roi
    if not mask.any():
        raise InputError(f"no valid depth in the ROI and depth range {lo}-{hi} m; check --roi and --depth-range")
    pts, rc = depth_to_cloud(depth, view.intrinsics, mask)
    plane = fit_dominant_plane(pts.astype(np.float64), settings.plane_thresh, seed=settings.seed)
    if plane is not None:
        n, d, inl = plane
        # A plane is "the table" only if it holds a good share of the points; remove it and all
        # below it (signed distance <= thresh: the camera is on the positive side).
        if inl.mean() > 0.15:
            keep = (pts @ n + d) > settings.plane_thresh
            mask = np.zeros_like(mask)
            mask[rc[keep, 0], rc[keep, 1]] = True
        else:
            plane = None
    # Cut the mask along depth edges, so that an object in front of a wall stays a blob of its own.
    d = np.where(np.isfinite(depth), depth, 0.0)
    edge = np.zeros_like(mask)
    edge[:, :-1] |= np.abs(d[:, 1:] - d[:, :-1]) > settings.edge_thresh
    edge[:-1, :] |= np.abs(d[1:, :] - d[:-1, :]) > settings.edge_thresh
    mask_u8 = cv2.morphologyEx((mask & ~edge).astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n_lab, lab, stats, centroids = cv2.connectedComponentsWithStats(mask_u8, connectivity=4)
    areas = stats[1:, cv2.CC_STAT_AREA]
    big = np.nonzero(areas >= max(settings.min_blob_pixels, 1))[0]
    if n_lab <= 1 or len(big) == 0:
        raise InputError("nothing is left of the object after removing the table plane; "
                         "check --roi and --depth-range")
    # The object is the blob nearest the centre of the ROI (or image): a scan keeps it in view,
    # while walls and table remnants sit towards the edges.
    if settings.roi is not None:
        x, y, rw, rh = settings.roi
        centre = np.array([x + rw / 2.0, y + rh / 2.0])
    else:
        centre = np.array([w / 2.0, h / 2.0])
    dist = np.linalg.norm(centroids[1:][big] - centre, axis=1)
    chosen = 1 + int(big[np.argmin(dist)])
    obj = lab == chosen
    # Give back the edge pixels that border the object and lie at its depth (its silhouette).
    ring = cv2.dilate(obj.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & mask & ~obj
    if ring.any():
        near = np.abs(d[ring] - np.median(d[obj])) < max(settings.edge_thresh, 0.5 * float(np.ptp(d[obj])))
        rr, cc = np.nonzero(ring)
        obj[rr[near], cc[near]] = True
    return obj, (plane[:2] if plane is not None else None)


def _voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    if len(points) == 0 or voxel <= 0:
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return (sums / counts[:, None]).astype(np.float32)


def simulated_tilts(tilts: tuple[float, ...], directions: int) -> list[np.ndarray]:
    """2x3 affine maps that make a view look as if seen more obliquely (ASIFT's view
    simulation): rotate by phi, then compress by 1/t along x. The identity comes first."""
    maps = [np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])]
    for t in tilts:
        for k in range(directions):
            phi = np.pi * k / directions
            c, s_ = np.cos(phi), np.sin(phi)
            maps.append(np.array([[c / t, -s_ / t, 0.0], [s_, c, 0.0]]))
    return maps


def _warp(image: np.ndarray, A: np.ndarray, interpolation) -> tuple[np.ndarray, np.ndarray]:
    """Warp with the linear part of A, shifted so that the whole image stays in view."""
    h, w = image.shape[:2]
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], dtype=np.float64) @ A[:, :2].T
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    A = A.copy()
    A[:, 2] = -lo
    size = (int(np.ceil(hi[0] - lo[0])), int(np.ceil(hi[1] - lo[1])))
    return cv2.warpAffine(image, A, size, flags=interpolation, borderMode=cv2.BORDER_CONSTANT), A


def view_keypoints(view: CaptureView, mask: np.ndarray, settings: BuildSettings
                   ) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints on the object in one view, lifted with the object's own depth only:
    (xyz (K, 3) float32 in the view's optical frame, descriptors (K, 128) float32).

    With ``settings.tilts``, SIFT also runs on the view warped to look more oblique, and the
    keypoints found there are mapped back to the view's pixels before lifting: the model
    then also holds the descriptors an instance seen at a grazing angle produces."""
    detect_mask = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8))
    # Depth outside the object is blanked, so the window median never mixes in the table.
    obj_depth = np.where(mask, view.depth_m, 0.0).astype(np.float32)
    all_uv, all_desc = [], []
    for A in simulated_tilts(settings.tilts, settings.tilt_directions):
        if np.allclose(A[:, :2], np.eye(2)):
            uv, desc = extract_sift(view.rgb, settings.sift, detect_mask)
        else:
            # Anti-alias along the compressed direction before warping (ASIFT uses 0.8 sqrt(t^2 - 1)).
            t = 1.0 / np.linalg.det(A[:, :2])
            img, A_full = _warp(view.rgb, A, cv2.INTER_LINEAR)
            blur_sigma = 0.8 * np.sqrt(max(t * t - 1.0, 0.0))
            img = cv2.GaussianBlur(img, (0, 0), sigmaX=blur_sigma, sigmaY=0.01) if blur_sigma > 0 else img
            m, _ = _warp(detect_mask, A, cv2.INTER_NEAREST)
            uv_w, desc = extract_sift(img, settings.sift, m)
            if len(uv_w) == 0:
                continue
            inv = cv2.invertAffineTransform(A_full)
            uv = (uv_w.astype(np.float64) @ inv[:, :2].T + inv[:, 2]).astype(np.float32)
        all_uv.append(uv)
        all_desc.append(desc)
    uv = np.concatenate(all_uv) if all_uv else np.zeros((0, 2), np.float32)
    desc = np.concatenate(all_desc) if all_desc else np.zeros((0, 128), np.float32)
    z = lookup_depth(obj_depth, uv, settings.depth_window, *settings.depth_range)
    ok = z > 0
    xyz = backproject(undistort_pixels(uv[ok], view.intrinsics), z[ok], view.intrinsics)
    return xyz, desc[ok]


@dataclass
class RegisteredView:
    """One capture view's object, brought into the capture frame (the first view's optical
    frame); ``T_capture_view`` is None where the view could not be registered."""
    mask: np.ndarray                     # (H, W) bool: the object's pixels
    plane: tuple[np.ndarray, float] | None   # the table (n, d) removed, in the view's frame
    keypoints_xyz: np.ndarray            # (K, 3) float64, capture frame
    descriptors: np.ndarray              # (K, 128) float32
    cloud: np.ndarray                    # (M, 3) float64 object points, capture frame
    T_capture_view: np.ndarray | None


def view_objects(views: list[CaptureView], settings: BuildSettings = BuildSettings()):
    """Each view's object in its own optical frame (``RegisteredView`` with
    ``T_capture_view`` None): its mask, the table removed, SIFT keypoints and depth points."""
    for view in views:
        mask, plane = object_mask(view, settings)
        xyz, desc = view_keypoints(view, mask, settings)
        cloud, _ = depth_to_cloud(view.depth_m, view.intrinsics, mask, stride=2)
        yield RegisteredView(mask, plane, xyz.astype(np.float64), desc, cloud.astype(np.float64), None)


@dataclass
class ViewRegistration:
    """A view's registration to the views placed before it, with the evidence for it."""
    T: np.ndarray          # (4, 4) view -> placed views' frame
    inliers: int           # ECC's inliers of the chosen instance
    score: float           # ECC's score of it: mean of 1 - residual / inlier_thresh over its inliers
    overlap: float = float("nan")   # share of the view's object points landing on the placed views'


# A registration is sure when its inliers fit within about a quarter of ECC's inlier threshold on
# average (score >= 0.75, i.e. 3.75 mm at 15 mm): measured on the synthetic snack box, the right
# pose of a view against others scored 0.81-0.93, a view turned onto the face with the repeated
# print 0.50-0.78 (the crops are alike, not the same points), and such a turn, once placed, drew
# the views after it onto it too.
SURE_SCORE = 0.75
# A pending view's registration is recomputed when the view just placed shares this many
# ratio-test matches with it; with fewer it would change little (the cost stays ~n^2/4, not n^2).
STALE_MATCHES = 20


def _pair_matches(descriptors: list) -> np.ndarray:
    """(n, n): ratio-test matches (0.8, RootSIFT) of view i's keypoints among view j's."""
    from ..frontends.sift.matching import prepare_descriptors

    d = [prepare_descriptors(x) for x in descriptors]
    n = len(d)
    counts = np.zeros((n, n), np.int64)
    every = np.concatenate(d)
    start = np.concatenate([[0], np.cumsum([len(x) for x in d])])
    sq = np.einsum("ij,ij->i", every, every)
    for i in range(n):
        if len(d[i]) == 0:
            continue
        d2 = sq[None, :] - 2.0 * (d[i] @ every.T)     # |q|^2 left out: it does not change the order
        q = np.einsum("ij,ij->i", d[i], d[i])[:, None]
        for j in range(n):
            if i == j or start[j + 1] - start[j] < 2:
                continue
            two = np.sqrt(np.maximum(np.partition(d2[:, start[j]:start[j + 1]], 1, axis=1)[:, :2] + q, 0.0))
            counts[i, j] = int(np.sum(two[:, 0] < 0.8 * two[:, 1]))
    return counts


def _place_by_texture(objects: list, register_view) -> dict:
    """View index -> view -> frame transform, for the views that could be placed, registered
    to each other by texture without depending on the order they came in (best first):
    start from the view sharing the most matches with the others; then, again and again,
    register every pending view against all views placed so far and place, of those whose
    registration is sure (``SURE_SCORE``), the one with the most inliers weighed by the score,
    so that an ambiguous view waits until more of the object is there to decide it. A view
    never registered surely is left out: placed anyway, a turned one drew other views onto
    its turn (the synthetic snack box from 16 views: 4 ended turned against the other 10).
    Last, every view is registered once against all the others (their poses as they were) and takes that pose where it is sure: what drifted while few views were
    placed is pulled back. The frame is the first placed view's in the given order."""
    from ..transforms import apply_transform, invert_transform

    n = len(objects)
    usable = [i for i in range(n) if len(objects[i].keypoints_xyz) >= 3]
    if not usable:
        return {0: np.eye(4)}
    link = _pair_matches([o.descriptors for o in objects])
    link = link + link.T
    seed = max(usable, key=lambda i: (int(link[i].sum()), -i))
    T = {seed: np.eye(4)}

    def union(idx):
        return (np.concatenate([apply_transform(T[j], objects[j].keypoints_xyz) for j in idx]),
                np.concatenate([objects[j].descriptors for j in idx]),
                np.concatenate([apply_transform(T[j], objects[j].cloud) for j in idx]))

    def rank(r):
        return r.inliers * r.score

    cache = {}
    while True:
        placed = list(T)
        kp, desc, cloud = union(placed)
        best = None
        for i in usable:
            if i in T or link[i, placed].sum() < 3:
                continue
            if i not in cache:
                o = objects[i]
                cache[i] = register_view(o.keypoints_xyz, o.descriptors, kp, desc, o.cloud, cloud)
            r = cache[i]
            if r is not None and r.score >= SURE_SCORE and (best is None or rank(r) > rank(cache[best])):
                best = i
        if best is None:
            break
        T[best] = np.asarray(cache.pop(best).T)
        for i in [i for i in cache if link[i, best] >= STALE_MATCHES]:
            del cache[i]
    if len(T) > 2:
        moved = {}
        for i in T:
            o = objects[i]
            kp, desc, cloud = union([j for j in T if j != i])
            r = register_view(o.keypoints_xyz, o.descriptors, kp, desc, o.cloud, cloud)
            if r is not None and r.score >= SURE_SCORE:
                moved[i] = np.asarray(r.T)
        T.update(moved)
    first = min(T)
    to_first = invert_transform(T[first])
    return {i: to_first @ T[i] for i in sorted(T)}


def register_views(views: list[CaptureView], settings: BuildSettings = BuildSettings(),
                   register_view=None) -> list[RegisteredView]:
    """Each view's object (mask, SIFT keypoints, depth points) in the first view's optical
    frame: with the views' ground-truth object poses when all have one, else with
    ``register_view(xyz, desc, model_xyz, model_desc, cloud, model_cloud) -> ViewRegistration
    | None`` (e.g. matching plus ECC against views already placed, the view's and their
    object points given to judge it by; required for several views without ground truth),
    best first (``_place_by_texture``), so that the result does not depend on the order of
    the views. Views that cannot be placed come back with ``T_capture_view`` None; the frame
    is then the first placed view's."""
    if not views:
        raise InputError("no views to build a model from")
    have_gt = all(v.T_camera_object is not None for v in views)
    objects = list(view_objects(views, settings))
    if have_gt:
        poses = {i: views[0].T_camera_object @ invert_transform(v.T_camera_object) for i, v in enumerate(views)}
        poses[0] = np.eye(4)
    elif len(views) == 1:
        poses = {0: np.eye(4)}
    elif register_view is None:
        raise InputError("several views without ground-truth poses need a view registration")
    else:
        poses = _place_by_texture(objects, register_view)
    out: list[RegisteredView] = []
    for i, own in enumerate(objects):
        T_cap_view = poses.get(i)
        if T_cap_view is None:
            out.append(RegisteredView(own.mask, own.plane, np.zeros((0, 3)), np.zeros((0, 128), np.float32),
                                      np.zeros((0, 3)), None))
            continue
        out.append(RegisteredView(own.mask, own.plane, apply_transform(T_cap_view, own.keypoints_xyz), own.descriptors,
                                  apply_transform(T_cap_view, own.cloud), T_cap_view))
    return out


def build_model(views: list[CaptureView], settings: BuildSettings = BuildSettings(), name: str = "",
                register_view=None) -> ObjectModel:
    """Merge one or more views of one capture into a model: the views are brought into the
    first view's optical frame (``register_views``), and the model axes are laid along the
    object's box on the table."""
    every = register_views(views, settings, register_view)
    registered = [r for r in every if r.T_capture_view is not None]
    first = next(i for i, r in enumerate(every) if r.T_capture_view is not None)
    plane0 = registered[0].plane
    kp_xyz = [r.keypoints_xyz for r in registered]
    kp_desc = [r.descriptors for r in registered]
    clouds = [r.cloud for r in registered]
    keypoints = np.concatenate(kp_xyz) if kp_xyz else np.zeros((0, 3))
    descriptors = np.concatenate(kp_desc) if kp_desc else np.zeros((0, 128), np.float32)
    if len(keypoints) < settings.min_keypoints:
        raise InputError(f"only {len(keypoints)} SIFT keypoints with valid depth on the object "
                         f"(at least {settings.min_keypoints} needed); check --roi / --depth-range, "
                         f"or capture a better textured view")
    cloud = _voxel_downsample(np.concatenate(clouds), settings.voxel)

    # Model axes: z up from the table (towards the camera) if a table was found, x and y along
    # the sides of the object's smallest rectangle on the table; else the cloud's principal axes.
    pts = cloud.astype(np.float64)
    if plane0 is not None:
        z_axis = plane0[0]    # oriented towards the camera, i.e. up from the table
        x_axis = np.array([1.0, 0.0, 0.0]) - z_axis * z_axis[0]
        if np.linalg.norm(x_axis) < 1e-6:
            x_axis = np.array([0.0, 1.0, 0.0]) - z_axis * z_axis[1]
        x_axis /= np.linalg.norm(x_axis)
        R = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
        (_, _), (_, _), angle = cv2.minAreaRect((pts @ R[:, :2]).astype(np.float32))
        c, s_ = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        R = R @ np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    else:
        _, _, vt = np.linalg.svd(pts - pts.mean(axis=0), full_matrices=False)
        R = vt.T * np.array([1.0, 1.0, np.linalg.det(vt.T)])   # a proper rotation
    local = pts @ R                                   # capture coords expressed along the model axes
    lo, hi = np.percentile(local, 0.5, axis=0), np.percentile(local, 99.5, axis=0)
    if plane0 is not None and 0 < lo[2] - (-plane0[1]) <= 2 * settings.plane_thresh:
        # The object stands on the table: its box reaches down to the plane (n.p + d = 0,
        # i.e. local z = -d); the slice just above the plane went with the table.
        lo[2] = -plane0[1]
    centre = R @ ((lo + hi) / 2.0)
    T_capture_model = make_transform(R, centre)
    T_model_capture = invert_transform(T_capture_model)
    T_object_model = None
    if views[first].T_camera_object is not None:
        T_object_model = invert_transform(views[first].T_camera_object) @ T_capture_model
    return ObjectModel(
        keypoints_xyz=apply_transform(T_model_capture, keypoints).astype(np.float32),
        descriptors=descriptors.astype(np.float32),
        points_xyz=apply_transform(T_model_capture, cloud.astype(np.float64)).astype(np.float32),
        extent=(hi - lo).astype(np.float64),
        T_capture_model=T_capture_model,
        T_object_model=T_object_model,
        name=name,
        views_placed=None if all(v.T_camera_object is not None for v in views) else len(registered),
        capture_view=first,
    )


__all__ = ["ObjectModel", "save_model", "load_model", "MODEL_SCHEMA_VERSION", "CaptureView", "BuildSettings",
           "build_model", "register_views", "ViewRegistration", "view_objects", "RegisteredView", "object_mask", "view_keypoints", "model_name", "is_valid_name", "NAME_RULE"]
