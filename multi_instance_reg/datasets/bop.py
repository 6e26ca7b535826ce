"""Datasets in the BOP layout (bop.felk.cvut.cz; NOTES.md section 14): reading, writing, and
the results CSV.

Reading::

    ds = BopDataset("/data/icbin", split="test")
    for frame in ds.frames(skipped=counter):       # BopFrame: an RGBDFrame plus where it came from
        frame.rgb, frame.depth_m, frame.intrinsics, frame.gt_poses, frame.gt_visibility
        frame.scene_id, frame.im_id, frame.gt_obj_ids
    ds.models_info[2].diameter_mm, ds.models_info[2].symmetries()     # models/models_info.json
    ds.targets                                                        # test_targets_bop19.json (or None)

A ``BopFrame`` is the bag reader's ``RGBDFrame`` (rgb uint8, depth float32 metres, intrinsics,
ground truth (K, 4, 4) model -> camera in metres, visible fractions), so the pipeline, the
benchmarks and the scoring take frames from either without asking where they came from. Its
``stamp_ns`` is made from the image id at 30 Hz (``bop_stamp_ns``), as a synthetic scene's bag
stamps its frames, so that a synthetic scene exported in both forms reads back alike.

Errors: a scene without ``scene_camera.json``, a JSON file that cannot be parsed or lacks a
field, a ground-truth object id that ``models_info.json`` does not list: InputError naming the
file (these stop a run). A bad image (missing, unreadable, of the wrong size) makes
``read_frame`` raise InputError naming the file; ``frames`` skips that image and counts it in
its ``SkipCounter``.

Results (what BOP's evaluation reads): ``write_results_csv`` / ``read_results_csv`` with
``BopEstimate`` rows ``scene_id,im_id,obj_id,score,R,t,time`` (R: 9 numbers row-major separated
by spaces; t: 3 numbers in mm; time: seconds for the whole image, the same on every row of an
image, -1 if unknown).

Writing (``BopWriter``): camera.json, per scene scene_camera.json, scene_gt.json,
scene_gt_info.json and rgb/ + depth/ PNGs, models/obj_NNNNNN.ply (mm) + models_info.json
from meshes (with symmetries). Used by ``mireg synth ... --bop``.
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics
from .rgbd_bag import RGBDFrame, SkipCounter

# A BOP image id as a stamp: 30 Hz from the synthetic scenes' start (synthetic/scene.py
# START_STAMP_NS, FRAME_RATE_HZ), so that an exported synthetic scene reads back with its
# bag's stamps and a converted BOP scene plays as a 30 Hz recording.
BOP_START_STAMP_NS = 1_700_000_000 * 1_000_000_000
BOP_RATE_HZ = 30.0
BOP_FRAME_ID = "camera_color_optical_frame"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
TARGET_FILES = ("test_targets_bop19.json", "test_targets_bop24.json")
RESULTS_HEADER = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")


def bop_stamp_ns(im_id: int, rate_hz: float = BOP_RATE_HZ) -> int:
    """The stamp given to image ``im_id`` (see the module's docstring)."""
    return BOP_START_STAMP_NS + int(round(int(im_id) * 1e9 / rate_hz))


def model_file_name(obj_id: int) -> str:
    return f"obj_{int(obj_id):06d}.ply"


def object_name(obj_id: int) -> str:
    """The object name a model built from a BOP mesh goes by (a valid model/topic name)."""
    return f"obj_{int(obj_id):06d}"


@dataclass
class BopFrame(RGBDFrame):
    """An ``RGBDFrame`` read from a BOP dataset, with where it came from."""
    scene_id: int = -1
    im_id: int = -1
    gt_obj_ids: np.ndarray | None = None     # (K,) BOP object id of each ground-truth pose


# --------------------------------------------------------------------------- JSON helpers

def _load_json(path: Path, what: str):
    if not path.is_file():
        raise InputError(f"{path} does not exist ({what})")
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path} is not valid JSON ({exc}); {what}") from None


def _numbers(value, count: int, path: Path, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.size != count or not np.all(np.isfinite(arr)):
        raise InputError(f"{path}: {where} must be {count} finite numbers, got {value!r}")
    return arr


def _by_id(path: Path, what: str) -> list[tuple[int, object]]:
    """A BOP JSON file keyed by object or image id ("2": ...) as (id, entry) pairs."""
    raw = _load_json(path, what)
    if not isinstance(raw, dict):
        raise InputError(f"{path} must map ids to entries ({what}), got a {type(raw).__name__}")
    out = []
    for key, entry in raw.items():
        try:
            out.append((int(key), entry))
        except (TypeError, ValueError):
            raise InputError(f"{path}: key '{key}' is not an integer id") from None
    return out


# --------------------------------------------------------------------------- models_info

@dataclass
class BopModelInfo:
    """One entry of models_info.json (lengths in mm, as the file has them)."""
    obj_id: int
    diameter_mm: float
    min_mm: np.ndarray                      # (3,) min_x, min_y, min_z
    size_mm: np.ndarray                     # (3,) size_x, size_y, size_z
    symmetries_discrete: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))   # (S, 4, 4), t in mm
    symmetries_continuous: list = field(default_factory=list)   # [(axis (3,), offset (3,) mm)]

    def symmetries(self):
        """The object's symmetries as ``symmetry.Symmetries`` in metres (model frame), None
        when it has none. One continuous axis is what ``Symmetries`` holds: with several
        (a sphere) the first is kept, with the discrete ones."""
        from ..symmetry import Symmetries

        if not len(self.symmetries_discrete) and not self.symmetries_continuous:
            return None
        disc = [np.eye(4)]
        for S in self.symmetries_discrete:
            S = np.array(S, np.float64)
            S[:3, 3] /= 1000.0
            if np.linalg.norm(S - np.eye(4)) > 1e-9:
                disc.append(S)
        axis = point = None
        if self.symmetries_continuous:
            a, offset = self.symmetries_continuous[0]
            axis = np.asarray(a, np.float64) / np.linalg.norm(a)
            point = np.asarray(offset, np.float64) / 1000.0
        return Symmetries(np.stack(disc), axis, point)


def read_models_info(path) -> dict[int, BopModelInfo]:
    """models_info.json: {obj_id: BopModelInfo}; InputError naming the file if it is bad."""
    path = Path(path)
    out = {}
    for obj_id, entry in _by_id(path, "a BOP dataset's models/models_info.json, keyed by object id"):
        if not isinstance(entry, dict) or "diameter" not in entry:
            raise InputError(f"{path}: object {obj_id} has no 'diameter'")
        try:
            mins = np.array([float(entry[f"min_{a}"]) for a in "xyz"])
            sizes = np.array([float(entry[f"size_{a}"]) for a in "xyz"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: object {obj_id} needs min_x/y/z and size_x/y/z numbers") from None
        disc = np.array([_numbers(s, 16, path, f"object {obj_id} symmetries_discrete entry").reshape(4, 4)
                         for s in entry.get("symmetries_discrete", [])]).reshape(-1, 4, 4)
        for k, S in enumerate(disc):
            # BOP's files round to a few decimals: a loose test still tells a rotation from a typo.
            R = S[:3, :3]
            if not (np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0
                    and np.allclose(S[3], [0, 0, 0, 1], atol=1e-9)):
                raise InputError(f"{path}: object {obj_id} symmetries_discrete entry {k} is not a rigid transform "
                                 f"(a rotation, a translation in mm, last row 0 0 0 1)")
        cont = []
        for s in entry.get("symmetries_continuous", []):
            if not isinstance(s, dict):
                raise InputError(f"{path}: object {obj_id} symmetries_continuous entries must be {{axis, offset}}")
            axis = _numbers(s.get("axis"), 3, path, f"object {obj_id} symmetries_continuous axis")
            if np.linalg.norm(axis) == 0:
                raise InputError(f"{path}: object {obj_id} has a continuous symmetry about a zero axis")
            cont.append((axis, _numbers(s.get("offset", [0, 0, 0]), 3, path,
                                        f"object {obj_id} symmetries_continuous offset")))
        out[obj_id] = BopModelInfo(obj_id, float(entry["diameter"]), mins, sizes, disc, cont)
    return out


def models_info_entry(mesh, symmetries=None) -> dict:
    """models_info.json entry of a mesh (``meshes.TriangleMesh``, metres) in mm, with its
    symmetries (``symmetry.Symmetries`` in metres, or None) in BOP's form: the discrete ones
    without the identity, translations in mm; a continuous axis with a point on it (mm)."""
    from scipy.spatial.distance import pdist

    lo, hi = mesh.bounds
    used = mesh.vertices[np.unique(mesh.triangles)]
    # The diameter is the largest vertex distance; on the hull's candidates, the farthest
    # points from the centre, so that large meshes stay cheap.
    far = used[np.argsort(-np.linalg.norm(used - (lo + hi) / 2, axis=1))[:2000]]
    diameter = float(pdist(far).max()) if len(far) > 1 else 0.0
    entry = {"diameter": round(diameter * 1000.0, 6)}
    for k, a in enumerate("xyz"):
        entry[f"min_{a}"] = round(float(lo[k]) * 1000.0, 6)
    for k, a in enumerate("xyz"):
        entry[f"size_{a}"] = round(float(hi[k] - lo[k]) * 1000.0, 6)
    if symmetries is not None and not symmetries.is_trivial:
        disc = []
        for S in symmetries.discrete:
            if np.linalg.norm(S - np.eye(4)) < 1e-9:
                continue
            S = np.array(S, np.float64)
            S[:3, 3] *= 1000.0
            disc.append([round(float(v), 9) for v in S.reshape(-1)])
        if disc:
            entry["symmetries_discrete"] = disc
        if symmetries.axis is not None:
            entry["symmetries_continuous"] = [{"axis": [round(float(v), 9) for v in symmetries.axis],
                                               "offset": [round(float(v) * 1000.0, 6) for v in symmetries.point]}]
    return entry


# --------------------------------------------------------------------------- targets

@dataclass(frozen=True)
class BopTarget:
    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def read_targets(path) -> list[BopTarget]:
    """test_targets_bop19.json: a list of {scene_id, im_id, obj_id, inst_count}."""
    path = Path(path)
    raw = _load_json(path, "a list of {scene_id, im_id, obj_id, inst_count}")
    if not isinstance(raw, list):
        raise InputError(f"{path} must be a list of {{scene_id, im_id, obj_id, inst_count}}")
    try:
        return [BopTarget(int(t["scene_id"]), int(t["im_id"]), int(t["obj_id"]), int(t["inst_count"])) for t in raw]
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path}: every target needs integer scene_id, im_id, obj_id and inst_count") from None


# --------------------------------------------------------------------------- one scene

@dataclass
class BopScene:
    """One scene folder's JSON files, read and checked (images are read per frame)."""
    directory: Path
    scene_id: int
    cam_K: dict[int, np.ndarray]                       # im_id -> (3, 3)
    depth_scale: dict[int, float]                      # im_id -> mm per depth PNG unit
    gt: dict[int, list[tuple[int, np.ndarray]]] | None = None       # im_id -> [(obj_id, (4, 4) metres)]
    visib_fract: dict[int, np.ndarray] | None = None   # im_id -> (K,)

    @property
    def image_ids(self) -> list[int]:
        return sorted(self.cam_K)


def read_scene(directory, scene_id: int | None = None, models_info: dict | None = None,
               default_depth_scale: float | None = None) -> BopScene:
    """Read a scene folder's scene_camera.json (required), scene_gt.json and
    scene_gt_info.json (when present). ``models_info``: object ids the ground truth may name
    (None: any)."""
    d = Path(directory)
    scene_id = int(d.name) if scene_id is None else int(scene_id)
    cam_path = d / "scene_camera.json"
    if not cam_path.is_file():
        raise InputError(f"{cam_path} does not exist: every BOP scene folder needs its scene_camera.json "
                         f"(cam_K and depth_scale per image id)")
    entries = _by_id(cam_path, "per image id {cam_K, depth_scale}")
    if not entries:
        raise InputError(f"{cam_path} lists no image; it must map image ids to {{cam_K, depth_scale}}")
    cam_K, scales = {}, {}
    for im, entry in entries:
        if not isinstance(entry, dict):
            raise InputError(f"{cam_path}: image {im} must be {{cam_K, depth_scale}}")
        K = _numbers(entry.get("cam_K"), 9, cam_path, f"image {im} cam_K").reshape(3, 3)
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(f"{cam_path}: image {im} cam_K has fx={K[0, 0]}, fy={K[1, 1]}; both must be positive")
        scale = entry.get("depth_scale", default_depth_scale)
        if scale is None or not float(scale) > 0:
            raise InputError(f"{cam_path}: image {im} has no positive depth_scale (and camera.json gives none)")
        cam_K[im], scales[im] = K, float(scale)
    scene = BopScene(d, scene_id, cam_K, scales)
    gt_path = d / "scene_gt.json"
    if gt_path.is_file():
        scene.gt = _read_scene_gt(gt_path, models_info)
        info_path = d / "scene_gt_info.json"
        if info_path.is_file():
            scene.visib_fract = _read_visib_fract(info_path, scene.gt)
    return scene


def _read_scene_gt(path: Path, models_info: dict | None) -> dict:
    out = {}
    for im, entries in _by_id(path, "per image id a list of {obj_id, cam_R_m2c, cam_t_m2c}"):
        poses = []
        for k, e in enumerate(entries if isinstance(entries, list) else [None]):
            if not isinstance(e, dict) or "obj_id" not in e:
                raise InputError(f"{path}: image {im} instance {k} must be {{obj_id, cam_R_m2c, cam_t_m2c}}")
            obj = int(e["obj_id"])
            if models_info and obj not in models_info:
                raise InputError(f"{path}: image {im} names object id {obj}, which models/models_info.json does not "
                                 f"list (it has {', '.join(str(i) for i in sorted(models_info))})")
            T = np.eye(4)
            T[:3, :3] = _numbers(e.get("cam_R_m2c"), 9, path, f"image {im} instance {k} cam_R_m2c").reshape(3, 3)
            T[:3, 3] = _numbers(e.get("cam_t_m2c"), 3, path, f"image {im} instance {k} cam_t_m2c") / 1000.0
            poses.append((obj, T))
        out[im] = poses
    return out


def _read_visib_fract(path: Path, gt: dict) -> dict:
    out = {}
    for im, entries in _by_id(path, "per image id a list of {visib_fract, ...}, one per scene_gt.json instance"):
        if not isinstance(entries, list) or len(entries) != len(gt.get(im, [])):
            raise InputError(f"{path}: image {im} has {len(entries) if isinstance(entries, list) else 'no list of'} "
                             f"instance infos but scene_gt.json has {len(gt.get(im, []))} instances")
        try:
            out[im] = np.array([float(e["visib_fract"]) for e in entries], np.float32)
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: image {im}: every instance needs a visib_fract number") from None
    return out


# --------------------------------------------------------------------------- images

def find_image(folder: Path, im_id: int, kinds: tuple[str, ...]) -> Path | None:
    """``folder/<kind>/NNNNNN.<png|jpg|tif>`` for the first kind that has it."""
    for kind in kinds:
        for suffix in IMAGE_SUFFIXES:
            p = folder / kind / f"{int(im_id):06d}{suffix}"
            if p.is_file():
                return p
    return None


def read_colour(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB from a colour or grey image (grey repeated; 16-bit scaled to 8)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot read image {path} (not a PNG/JPEG/TIFF OpenCV can decode)")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise InputError(f"image {path} is {img.dtype}; colour must be 8- or 16-bit")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return np.ascontiguousarray(img[:, :, 2::-1])
    raise InputError(f"image {path} has shape {img.shape}; expected grey, BGR or BGRA")


def read_depth_m(path: Path, depth_scale: float, size: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 metres from a uint16 depth image (value x ``depth_scale`` = mm), computed
    as the bag reader does (``messages.depth_to_metres``: one float32 product), so that the
    same PNG gives the same metres either way; ``size`` = (width, height) it must have."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"cannot read depth image {path}")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise InputError(f"depth image {path} must be single-channel 16-bit, got {raw.dtype} with shape {raw.shape}")
    if (raw.shape[1], raw.shape[0]) != tuple(size):
        raise InputError(f"depth image {path} is {raw.shape[1]}x{raw.shape[0]} but the colour image is "
                         f"{size[0]}x{size[1]}; BOP depth must be registered to colour at the same size")
    return raw.astype(np.float32) * np.float32(depth_scale / 1000.0)


# --------------------------------------------------------------------------- the dataset

class BopDataset:
    """A BOP dataset's root and one split (see the module's docstring)."""

    def __init__(self, root, split: str = "test"):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(f"BOP dataset {self.root} does not exist (give the folder holding camera.json, "
                             f"models/ and the splits)")
        self.split = split
        self.split_dir = self.root / split
        if not self.split_dir.is_dir():
            present = sorted(p.name for p in self.root.iterdir() if p.is_dir() and p.name != "models")
            raise InputError(f"BOP dataset {self.root} has no split '{split}' (present: {', '.join(present) or 'none'}); "
                             f"choose one with --split")
        self.camera = self._read_camera()
        info = self.root / "models" / "models_info.json"
        self.models_info: dict[int, BopModelInfo] = read_models_info(info) if info.is_file() else {}
        self.targets: list[BopTarget] | None = None
        for name in TARGET_FILES:
            if (self.root / name).is_file():
                self.targets = read_targets(self.root / name)
                break
        self._scenes: dict[int, BopScene] = {}

    @property
    def name(self) -> str:
        return self.root.resolve().name

    def _read_camera(self) -> dict | None:
        path = self.root / "camera.json"
        if not path.is_file():
            return None
        cam = _load_json(path, "{cx, cy, fx, fy, width, height, depth_scale}")
        if not isinstance(cam, dict):
            raise InputError(f"{path} must be {{cx, cy, fx, fy, width, height, depth_scale}}")
        for key in ("width", "height"):
            if key in cam and not (isinstance(cam[key], (int, float)) and cam[key] > 0):
                raise InputError(f"{path}: {key} must be a positive number, got {cam[key]!r}")
        return cam

    @property
    def scene_ids(self) -> list[int]:
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())

    def scene(self, scene_id: int) -> BopScene:
        scene_id = int(scene_id)
        if scene_id not in self._scenes:
            d = self.split_dir / f"{scene_id:06d}"
            if not d.is_dir():
                raise InputError(f"{self.split_dir} has no scene {scene_id} (folder {d.name}); scenes: "
                                 f"{', '.join(str(s) for s in self.scene_ids) or 'none'}")
            default_scale = None if self.camera is None else self.camera.get("depth_scale")
            self._scenes[scene_id] = read_scene(d, scene_id, self.models_info, default_scale)
        return self._scenes[scene_id]

    def model_path(self, obj_id: int) -> Path:
        """models/obj_NNNNNN.ply (mm); InputError when the dataset lacks it."""
        path = self.root / "models" / model_file_name(obj_id)
        if self.models_info and int(obj_id) not in self.models_info:
            raise InputError(f"object id {obj_id} is not in {self.root / 'models' / 'models_info.json'} "
                             f"(it lists {', '.join(str(i) for i in sorted(self.models_info))})")
        if not path.is_file():
            raise InputError(f"{path} does not exist: the dataset has no mesh for object {obj_id}")
        return path

    def images(self, scenes: Iterable[int] | None = None, images: Iterable[int] | None = None,
               targets_only: bool = False) -> list[tuple[int, int]]:
        """(scene_id, im_id) pairs to run, in order: ``scenes`` / ``images`` filter (None: all);
        ``targets_only``: only the images the targets file names (when it exists)."""
        wanted_scenes = self.scene_ids if scenes is None else [int(s) for s in scenes]
        wanted_images = None if images is None else {int(i) for i in images}
        target_pairs = None
        if targets_only and self.targets is not None:
            target_pairs = {(t.scene_id, t.im_id) for t in self.targets}
        out = []
        for s in wanted_scenes:
            for im in self.scene(s).image_ids:
                if wanted_images is not None and im not in wanted_images:
                    continue
                if target_pairs is not None and (s, im) not in target_pairs:
                    continue
                out.append((s, im))
        return out

    def read_frame(self, scene_id: int, im_id: int) -> BopFrame:
        """One image as a BopFrame; InputError naming the file for a missing or bad image."""
        scene = self.scene(scene_id)
        im_id = int(im_id)
        if im_id not in scene.cam_K:
            raise InputError(f"{scene.directory / 'scene_camera.json'} has no image {im_id}")
        colour_path = find_image(scene.directory, im_id, ("rgb", "gray"))
        if colour_path is None:
            raise InputError(f"{scene.directory} has no rgb/ or gray/ image {im_id:06d}.png|jpg|tif")
        depth_path = find_image(scene.directory, im_id, ("depth",))
        if depth_path is None:
            raise InputError(f"{scene.directory / 'depth'} has no image {im_id:06d}.png|tif (the pipeline needs depth)")
        rgb = read_colour(colour_path)
        size = (rgb.shape[1], rgb.shape[0])
        if self.camera is not None and "width" in self.camera and "height" in self.camera \
                and (int(self.camera["width"]), int(self.camera["height"])) != size:
            raise InputError(f"image {colour_path} is {size[0]}x{size[1]} but {self.root / 'camera.json'} says "
                             f"{self.camera['width']}x{self.camera['height']}")
        depth_m = read_depth_m(depth_path, scene.depth_scale[im_id], size)
        intr = CameraIntrinsics(K=scene.cam_K[im_id].copy(), width=size[0], height=size[1])
        gt_poses = vis = obj_ids = None
        if scene.gt is not None:
            entries = scene.gt.get(im_id, [])
            gt_poses = np.array([T for _, T in entries]).reshape(-1, 4, 4)
            obj_ids = np.array([o for o, _ in entries], np.int64)
            if scene.visib_fract is not None and im_id in scene.visib_fract:
                vis = scene.visib_fract[im_id]
        return BopFrame(bop_stamp_ns(im_id), BOP_FRAME_ID, rgb, depth_m, intr, gt_poses, vis, None,
                        scene_id=scene.scene_id, im_id=im_id, gt_obj_ids=obj_ids)

    def frames(self, scenes: Iterable[int] | None = None, images: Iterable[int] | None = None,
               targets_only: bool = False, skipped: SkipCounter | None = None) -> Iterator[BopFrame]:
        """The selected images (``images``' arguments) as BopFrames (``read_frames``). The
        selection is made (and the scenes' JSON read) at once, not lazily."""
        return self.read_frames(self.images(scenes, images, targets_only), skipped)

    def read_frames(self, pairs: Iterable[tuple[int, int]], skipped: SkipCounter | None = None) -> Iterator[BopFrame]:
        """BopFrames of (scene_id, im_id) ``pairs``, in order. A bad image is skipped and
        counted in ``skipped`` (its reason names the file); a bad scene stops (InputError)."""
        for s, im in pairs:
            try:
                frame = self.read_frame(s, im)
            except InputError as exc:
                if skipped is not None:
                    skipped.add(str(exc))
                continue
            yield frame


# --------------------------------------------------------------------------- results CSV

@dataclass
class BopEstimate:
    """One row of a BOP results CSV: an estimated pose of object ``obj_id`` in an image."""
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray           # (3, 3) model -> camera
    t_mm: np.ndarray        # (3,) millimetres
    time_s: float = -1.0    # seconds for the whole image (the same on each of its rows); -1 unknown

    @classmethod
    def from_pose(cls, scene_id: int, im_id: int, obj_id: int, score: float, T_m: np.ndarray,
                  time_s: float = -1.0) -> "BopEstimate":
        """From a (4, 4) model -> camera transform in metres (the pipeline's ``Instance.T``)."""
        T = np.asarray(T_m, np.float64)
        return cls(int(scene_id), int(im_id), int(obj_id), float(score), T[:3, :3].copy(), T[:3, 3] * 1000.0,
                   float(time_s))

    @property
    def T_m(self) -> np.ndarray:
        """(4, 4) model -> camera in metres."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = np.asarray(self.t_mm, np.float64) / 1000.0
        return T


def _check_image_times(rows: list[BopEstimate], where: str) -> None:
    times: dict[tuple[int, int], float] = {}
    for r in rows:
        key = (r.scene_id, r.im_id)
        if key in times and abs(times[key] - r.time_s) > 1e-6:
            raise InputError(f"{where}: scene {key[0]} image {key[1]} has rows with times {times[key]:g} and "
                             f"{r.time_s:g} s; time is for the whole image, the same on each of its rows")
        times[key] = r.time_s


def write_results_csv(path, estimates: Iterable[BopEstimate]) -> Path:
    """Write the BOP results CSV (header ``scene_id,im_id,obj_id,score,R,t,time``)."""
    path = Path(path)
    rows = list(estimates)
    _check_image_times(rows, str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(RESULTS_HEADER)
        for r in rows:
            w.writerow([int(r.scene_id), int(r.im_id), int(r.obj_id), f"{float(r.score):.6f}",
                        " ".join(f"{v:.9f}" for v in np.asarray(r.R, np.float64).reshape(-1)),
                        " ".join(f"{v:.6f}" for v in np.asarray(r.t_mm, np.float64).reshape(-1)),
                        f"{float(r.time_s):.6f}"])
    return path


def read_results_csv(path) -> list[BopEstimate]:
    """Read a BOP results CSV; InputError naming the file and line of the first bad row."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"results file {path} does not exist")
    out = []
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != RESULTS_HEADER:
            raise InputError(f"{path}: line 1 must be the header {','.join(RESULTS_HEADER)}, got {','.join(header or [])!r}")
        for n, row in enumerate(reader, start=2):
            if not row:
                continue
            try:
                if len(row) != 7:
                    raise ValueError(f"{len(row)} fields, not 7")
                R = np.array([float(v) for v in row[4].split()])
                t = np.array([float(v) for v in row[5].split()])
                if R.size != 9 or t.size != 3:
                    raise ValueError(f"R has {R.size} numbers (9 wanted), t {t.size} (3 wanted)")
                out.append(BopEstimate(int(row[0]), int(row[1]), int(row[2]), float(row[3]), R.reshape(3, 3), t,
                                       float(row[6])))
            except ValueError as exc:
                raise InputError(f"{path} line {n}: {exc} (expected scene_id,im_id,obj_id,score,R,t,time)") from None
    _check_image_times(out, str(path))
    return out


# --------------------------------------------------------------------------- writing a dataset

def write_json(path: Path, data) -> None:
    """BOP's JSON files, keys in id order, compact enough to diff."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")


def gt_info_from_mask(mask: np.ndarray, depth_mm: np.ndarray, visib_fract: float) -> dict:
    """scene_gt_info.json entry of one instance from its visible pixels (``mask``, bool):
    visib_fract (given: it needs the unoccluded silhouette), px_count_visib, px_count_valid
    (visible with depth) and bbox_visib [x, y, w, h] ([-1, -1, -1, -1] when unseen)."""
    ys, xs = np.nonzero(mask)
    bbox = [-1, -1, -1, -1] if len(xs) == 0 else [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1),
                                                  int(ys.max() - ys.min() + 1)]
    return {"bbox_visib": bbox, "px_count_valid": int(np.count_nonzero(mask & (depth_mm > 0))),
            "px_count_visib": int(len(xs)), "visib_fract": round(float(visib_fract), 6)}


class BopSceneWriter:
    """Images and JSON of one scene folder; the JSON files are written on ``close``."""

    def __init__(self, writer: "BopWriter", scene_id: int):
        self.writer = writer
        self.scene_id = int(scene_id)
        self.directory = writer.split_dir / f"{self.scene_id:06d}"
        if self.directory.exists():
            raise InputError(f"BOP scene folder {self.directory} already exists; choose another scene id or output")
        self.camera: dict = {}
        self.gt: dict = {}
        self.gt_info: dict = {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def add_image(self, im_id: int, rgb: np.ndarray, depth_mm: np.ndarray, K: np.ndarray,
                  gt: list[tuple[int, np.ndarray]] | None = None, gt_info: list[dict] | None = None) -> None:
        """rgb/NNNNNN.png, depth/NNNNNN.png (uint16 mm, depth_scale 1) and the image's JSON
        entries; ``gt``: [(obj_id, (4, 4) model -> camera in metres)], ``gt_info`` one dict
        per gt instance (e.g. ``gt_info_from_mask``)."""
        import cv2

        rgb = np.asarray(rgb)
        depth_mm = np.asarray(depth_mm)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"colour must be HxWx3 uint8, got {rgb.shape} {rgb.dtype}")
        if depth_mm.shape != rgb.shape[:2] or depth_mm.dtype != np.uint16:
            raise InputError(f"depth must be HxW uint16 mm matching colour {rgb.shape[:2]}, got {depth_mm.shape} {depth_mm.dtype}")
        im = int(im_id)
        for kind, img in (("rgb", np.ascontiguousarray(rgb[:, :, ::-1])), ("depth", depth_mm)):
            p = self.directory / kind / f"{im:06d}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(p), img):
                raise InputError(f"cannot write {p}")
        self.writer.note_camera(np.asarray(K, np.float64), rgb.shape[1], rgb.shape[0])
        self.camera[str(im)] = {"cam_K": [float(v) for v in np.asarray(K, np.float64).reshape(-1)], "depth_scale": 1.0}
        if gt is not None:
            self.gt[str(im)] = [{"cam_R_m2c": [float(v) for v in np.asarray(T)[:3, :3].reshape(-1)],
                                 "cam_t_m2c": [float(v) * 1000.0 for v in np.asarray(T)[:3, 3]],
                                 "obj_id": int(obj)} for obj, T in gt]
            if gt_info is not None:
                if len(gt_info) != len(gt):
                    raise InputError(f"image {im}: {len(gt_info)} gt_info entries for {len(gt)} instances")
                self.gt_info[str(im)] = list(gt_info)

    def close(self) -> None:
        if not self.camera:
            return
        write_json(self.directory / "scene_camera.json", self.camera)
        if self.gt:
            write_json(self.directory / "scene_gt.json", self.gt)
        if self.gt_info:
            write_json(self.directory / "scene_gt_info.json", self.gt_info)


class BopWriter:
    """A BOP dataset folder being written: ``scene(scene_id)`` for images, ``add_model`` for
    meshes. camera.json is written from the first image's intrinsics (depth_scale 1: the
    PNGs hold millimetres). Scenes and models can be added to a folder written before."""

    def __init__(self, root, split: str = "test"):
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise InputError(f"BOP output {self.root} exists and is not a folder")
        self.split_dir = self.root / split
        self.split_dir.mkdir(parents=True, exist_ok=True)

    def scene(self, scene_id: int) -> BopSceneWriter:
        return BopSceneWriter(self, scene_id)

    def note_camera(self, K: np.ndarray, width: int, height: int) -> None:
        path = self.root / "camera.json"
        if not path.is_file():
            write_json(path, {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                              "depth_scale": 1.0, "width": int(width), "height": int(height)})

    def add_model(self, obj_id: int, mesh, symmetries=None) -> Path:
        """models/obj_NNNNNN.ply in mm and its models_info.json entry (``models_info_entry``)."""
        from ..meshes import save_mesh

        path = save_mesh(mesh, self.root / "models" / model_file_name(obj_id), "mm")
        info_path = self.root / "models" / "models_info.json"
        info = json.loads(info_path.read_text()) if info_path.is_file() else {}
        info[str(int(obj_id))] = models_info_entry(mesh, symmetries)
        write_json(info_path, {k: info[k] for k in sorted(info, key=int)})
        return path


__all__ = ["BopDataset", "BopFrame", "BopScene", "BopModelInfo", "BopTarget", "BopEstimate", "BopWriter",
           "BopSceneWriter", "read_models_info", "read_targets", "read_scene", "read_results_csv",
           "write_results_csv", "models_info_entry", "gt_info_from_mask", "bop_stamp_ns", "object_name",
           "model_file_name"]
