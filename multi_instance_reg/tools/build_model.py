"""``mireg build-model``: the stored object model from a capture bag, or from PNG files.

    mireg build-model CAPTURE_BAG [MORE_BAGS ...] -o MODEL.npz [--frames 0,10,20 | 0:60:10] [--roi x,y,w,h] [--depth-range 0.2 1.5]
    mireg build-model --rgb colour.png --depth depth.png --intrinsics fx,fy,cx,cy -o MODEL.npz
    mireg build-model --mesh FILE.ply|.stl|.obj [--units m|mm] [--name N] [--symmetry auto|none|z:inf,x:2]
                      [--models-info models_info.json --obj-id N] [CAPTURE_BAG ...] -o MODEL.npz

The object is isolated by the ROI and depth range, the removal of the dominant (table) plane
and the blob nearest the image centre. Several frames are merged with their ground-truth
poses when the bag has them, else by registering each frame to the model built so far.
Several bags of one object (e.g. upright, then upside down, so that the model sees every
face) are merged the same way; the first frame of the first bag defines the capture frame.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..errors import InputError

HELP = "build the stored object model (npz) from a capture bag or colour/depth PNGs"


def add_arguments(parser) -> None:
    parser.add_argument("bag", nargs="*", help="capture bag(s) (rosbag2 directory, .db3 or .mcap)")
    parser.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    parser.add_argument("--frames", default=None,
                        help="frames of the bag to merge: indices '0,10,20' or a range 'start:stop:step' "
                             "(default: up to 12 spread over the bag with ground truth or with --mesh, else the first)")
    parser.add_argument("--roi", default=None, help="x,y,w,h pixel box around the object (default: whole image)")
    parser.add_argument("--depth-range", nargs=2, type=float, metavar=("MIN", "MAX"), default=(0.1, 4.0),
                        help="metres: depth kept for the object (default 0.1 4.0)")
    parser.add_argument("--tilts", default="2",
                        help="simulated view tilts, comma-separated (ASIFT-style: SIFT also on each view warped "
                             "to look more oblique, so that instances seen at grazing angles match); '' = off (default 2)")
    parser.add_argument("--name", default=None,
                        help="object name stored in the model, used in every output (poses.json \"object\", topics, "
                             "markers); two models loaded together need different names (default: the object named "
                             "in the capture bag's /ground_truth/object, else the mesh's file stem, else the output's)")
    parser.add_argument("--ignore-ground-truth", action="store_true",
                        help="do not use the capture bags' ground-truth object poses, as with a real capture: views "
                             "are registered to each other by their texture (and, with --mesh, placed on the mesh by "
                             "shape); by default ground truth is used when every view has it")
    parser.add_argument("--topics", nargs=3, metavar=("COLOUR", "DEPTH", "INFO"), default=None,
                        help="colour, aligned depth and camera_info topics, raw or compressed (default: realsense-ros names; "
                             "their /compressed and /compressedDepth topics when the raw ones are absent)")
    mesh = parser.add_argument_group("from a mesh (shape; texture too from capture bags, or from the mesh's own colours)")
    mesh.add_argument("--mesh", default=None, help="triangle mesh of the object: .ply, .stl or .obj; the model frame is the mesh's")
    mesh.add_argument("--units", choices=("m", "mm"), default="m", help="units of the mesh's coordinates (default m)")
    mesh.add_argument("--symmetry", default="auto",
                      help="the object's symmetries: auto (found from the mesh), none, or items AXIS:N / AXIS:inf about "
                           "the mesh's axes through its box centre, e.g. 'x:2,y:2' (a box), 'z:inf,x:2' (a cylinder); "
                           "auto takes them from a BOP models_info.json instead when there is one (--models-info)")
    mesh.add_argument("--render-views", type=int, default=None,
                      help="a mesh with colour (PLY vertex colours or a texture) and no capture bags gets SIFT keypoints "
                           "from this many renders around it (default 30; 0 = none: the model is found by shape alone)")
    mesh.add_argument("--render-distance", type=float, default=None,
                      help="metres from the object's centre to the rendering camera (default 0.6: the distance the "
                           "object is seen from; a Primesense-like camera, fx 550 px at 640 x 480)")
    mesh.add_argument("--models-info", default=None,
                      help="BOP models_info.json holding the object's symmetries (symmetries_discrete / "
                           "symmetries_continuous); default: models_info.json beside the mesh, if any")
    mesh.add_argument("--obj-id", type=int, default=None,
                      help="the mesh's object id in --models-info (default: from a BOP file name, obj_000002.ply -> 2)")
    png = parser.add_argument_group("from PNG files instead of a bag")
    png.add_argument("--rgb", help="colour PNG (8-bit)")
    png.add_argument("--depth", help="depth PNG (16-bit, millimetres by default)")
    png.add_argument("--depth-scale", type=float, default=0.001, help="metres per depth PNG unit (default 0.001)")
    png.add_argument("--intrinsics", help="fx,fy,cx,cy of the colour image")


def parse_roi(text: str | None):
    if text is None:
        return None
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--roi must be x,y,w,h in whole pixels, got '{text}'") from None
    return x, y, w, h


def parse_frames(text: str | None, n_frames: int, has_gt: bool) -> list[int]:
    if text is None:
        if has_gt and n_frames > 1:
            return sorted(set(np.linspace(0, n_frames - 1, min(12, n_frames)).round().astype(int).tolist()))
        return [0]
    try:
        if ":" in text:
            parts = [int(p) if p else None for p in text.split(":")]
            idx = list(range(n_frames))[slice(*parts)]
        else:
            idx = sorted({int(p) for p in text.split(",") if p.strip()})
    except ValueError:
        raise InputError(f"--frames must be '0,10,20' or 'start:stop:step', got '{text}'") from None
    bad = [i for i in idx if not 0 <= i < n_frames]
    if bad or not idx:
        raise InputError(f"--frames {text} selects {bad or 'no'} frame(s) outside the bag's {n_frames} frames")
    return idx


def views_from_bag(path, frames_text, topics, spread: bool | None = None) -> tuple[list, dict | None]:
    """The bag's capture views: ``frames_text`` (``--frames``), else up to 12 spread over the
    bag where the views are placed independently (``spread``; default: when the bag has ground
    truth), else the first (views registered to each other by texture chain from it)."""
    from ..datasets.rgbd_bag import RGBDBag
    from ..models.model import CaptureView

    kwargs = dict(zip(("colour_topic", "depth_topic", "info_topic"), topics)) if topics else {}
    with RGBDBag(path, **kwargs) as bag:
        want = set(parse_frames(frames_text, bag.num_colour_messages,
                                bag.has_ground_truth if spread is None else spread))
        views = []
        for i, frame in enumerate(bag):
            if i in want:
                T = None
                if frame.gt_poses is not None and len(frame.gt_poses):
                    if len(frame.gt_poses) > 1:
                        raise InputError(f"capture bag {path} shows {len(frame.gt_poses)} instances in frame {i}; "
                                         f"a capture bag must show the object once")
                    T = frame.gt_poses[0]
                views.append(CaptureView(frame.rgb, frame.depth_m, frame.intrinsics, T))
            if i >= max(want):
                break
        description = bag.object_description
    if not views:
        raise InputError(f"bag {path} yielded none of the frames {sorted(want)} (skipped: {bag.skipped.summary() or 'none'})")
    return views, description


def views_from_png(rgb_path, depth_path, intrinsics_text, depth_scale) -> list:
    import cv2

    from ..messages import CameraIntrinsics
    from ..models.model import CaptureView

    if not (rgb_path and depth_path and intrinsics_text):
        raise InputError("building from PNG files needs --rgb, --depth and --intrinsics fx,fy,cx,cy")
    bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"cannot read colour image {rgb_path}")
    depth_raw = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
    if depth_raw is None:
        raise InputError(f"cannot read depth image {depth_path}")
    if depth_raw.ndim != 2 or depth_raw.dtype != np.uint16:
        raise InputError(f"depth image {depth_path} must be a single-channel 16-bit PNG, got "
                         f"{depth_raw.dtype} with shape {depth_raw.shape}")
    if depth_raw.shape != bgr.shape[:2]:
        raise InputError(f"depth image is {depth_raw.shape[1]}x{depth_raw.shape[0]} but colour is "
                         f"{bgr.shape[1]}x{bgr.shape[0]}; the depth must be aligned to colour")
    try:
        fx, fy, cx, cy = (float(v) for v in intrinsics_text.split(","))
    except ValueError:
        raise InputError(f"--intrinsics must be fx,fy,cx,cy, got '{intrinsics_text}'") from None
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    intr = CameraIntrinsics(K=K, width=bgr.shape[1], height=bgr.shape[0])
    return [CaptureView(np.ascontiguousarray(bgr[:, :, ::-1]), depth_raw.astype(np.float32) * depth_scale, intr)]


OVERLAP_DISTANCE_M = 0.004      # a view's object point meets the capture's where one lies this close
OVERLAP_SAMPLE = 3000
_AGAINST: dict = {}     # the placed views of the last call (the very arrays), their matcher and tree


def register_view_with_ecc(xyz, desc, model_xyz, model_desc, cloud=None, model_cloud=None):
    """View -> capture registration of a view without ground truth (``ViewRegistration``, or
    None if ECC finds no instance): match its keypoints to the views registered so far; of
    ECC's instances, the one whose object points (``cloud``) land best on theirs
    (``model_cloud``), ties to the most inliers.
    Why not simply the most inliers: a print repeated on two faces (a wrapper's front and
    back) matches both, and a view turned onto the wrong face by 180 deg puts its keypoints
    2-3 cm from where they are and misleads every view registered after it (synthetic snack
    box, 32 views without ground truth: 8 turned, the model then found 105 of 205 instances
    against 200). The instance's ECC score and inlier count go back with it, so that
    ``register_views`` can place the surest views first."""
    from scipy.spatial import cKDTree

    from ..core import ECC, ECCConfig
    from ..frontends.sift.matching import DescriptorMatcher, prepare_descriptors
    from ..models.model import ViewRegistration
    from ..transforms import apply_transform

    # register_views tries every pending view against the same placed views: the matcher and the
    # tree over them are built once for all of those calls (most of the cost otherwise).
    if not (_AGAINST.get("arrays") is not None and all(a is b for a, b in zip(_AGAINST["arrays"],
                                                                            (model_xyz, model_desc, model_cloud)))):
        _AGAINST.update(arrays=(model_xyz, model_desc, model_cloud),
                        matcher=DescriptorMatcher(prepare_descriptors(model_desc), model_xyz, ratio=0.8, separation=0.01),
                        tree=cKDTree(model_cloud) if model_cloud is not None and len(model_cloud) else None)
    matcher = _AGAINST["matcher"]
    s_idx, m_idx, _ = matcher.match(prepare_descriptors(desc))
    if len(s_idx) < 6:
        return None
    res = ECC(ECCConfig.metric()).register(xyz[s_idx].astype(np.float64), model_xyz[m_idx].astype(np.float64))
    if len(res.transforms) == 0:
        return None

    def chosen(m, overlap=float("nan")):
        return ViewRegistration(np.asarray(res.transforms[m]), int(res.inlier_counts[m]), float(res.scores[m]), overlap)

    if cloud is None or model_cloud is None or len(cloud) == 0 or len(model_cloud) == 0:
        return chosen(0)
    pts = cloud[np.random.default_rng(0).permutation(len(cloud))[:OVERLAP_SAMPLE]]
    tree = _AGAINST["tree"]
    best, best_key = None, None
    for m, T in enumerate(res.transforms):
        d, _ = tree.query(apply_transform(np.asarray(T), pts), k=1, distance_upper_bound=2 * OVERLAP_DISTANCE_M)
        overlap = float(np.mean(d < OVERLAP_DISTANCE_M))
        # Overlap in steps of 5 %: within that, the most inliers (ECC's order) wins.
        key = (round(20 * overlap), -m)
        if best_key is None or key > best_key:
            best, best_key = chosen(m, overlap), key
    return best


def check_name(name: str) -> None:
    from ..models.model import NAME_RULE, is_valid_name

    if not is_valid_name(name):
        raise InputError(f"object name '{name}': use {NAME_RULE} (it becomes part of topic names, "
                         f"e.g. instances/<name>/poses); give one with --name")


def mesh_symmetry(mesh_path, symmetry_text: str, models_info, obj_id) -> tuple:
    """What ``build_model_from_mesh`` is to take as the symmetries (``Symmetries``, text, or
    None: find them from the mesh), and where they come from (said in the build's line):
    --symmetry text; else a BOP models_info.json (given, or beside a mesh named obj_NNNNNN
    and listing it); else the mesh's shape."""
    import re

    from ..datasets.bop import read_models_info
    from ..symmetry import Symmetries

    if models_info and symmetry_text != "auto":
        raise InputError("give the symmetries either as --symmetry or from --models-info, not both")
    if symmetry_text != "auto":
        return symmetry_text, "from --symmetry"
    mesh_path = Path(mesh_path)
    path = Path(models_info) if models_info else mesh_path.parent / "models_info.json"
    if not models_info and not path.is_file():
        if obj_id is not None:
            raise InputError(f"--obj-id {obj_id} names an object of a BOP models_info.json, and there is none beside "
                             f"{mesh_path}; give one with --models-info")
        return None, "found from the mesh"
    if obj_id is None:
        m = re.fullmatch(r"obj_0*(\d+)", mesh_path.stem)
        if m is None:
            if models_info:
                raise InputError(f"which object of {path} is {mesh_path.name}? its name is not BOP's obj_NNNNNN.ply: "
                                 f"give --obj-id")
            return None, "found from the mesh"
        obj_id = int(m.group(1))
    info = read_models_info(path)
    if obj_id not in info:
        if not models_info:
            return None, f"found from the mesh ({path} beside it does not list object {obj_id})"
        raise InputError(f"{path} has no object {obj_id} (it lists {', '.join(map(str, sorted(info))) or 'none'}); "
                         f"give the mesh's id with --obj-id")
    # An entry without symmetries: the object has none (BOP leaves the keys out).
    return info[obj_id].symmetries() or Symmetries(), f"from {path}, object {obj_id}"


def run(args) -> int:
    from ..models.model import BuildSettings, CaptureView, build_model, model_name, save_model

    out = Path(args.output)
    if out.suffix != ".npz":
        raise InputError(f"output {out} must end in .npz")
    if args.mesh:
        return run_mesh(args, out)
    if args.models_info or args.obj_id is not None:
        raise InputError("--models-info and --obj-id give a mesh's symmetries: use them with --mesh")
    lo, hi = args.depth_range
    if not 0 <= lo < hi:
        raise InputError(f"--depth-range {lo} {hi}: need 0 <= MIN < MAX (metres)")
    if args.bag and (args.rgb or args.depth):
        raise InputError("give either a capture bag or --rgb/--depth PNG files, not both")
    description = None
    if args.bag:
        views = []
        for bag in args.bag:
            more, desc = views_from_bag(bag, args.frames, args.topics)
            views += more
            description = description or desc
        if args.ignore_ground_truth:
            views = [CaptureView(v.rgb, v.depth_m, v.intrinsics) for v in views]
    elif args.rgb or args.depth:
        views = views_from_png(args.rgb, args.depth, args.intrinsics, args.depth_scale)
    else:
        raise InputError("give a capture bag, or --rgb, --depth and --intrinsics")
    try:
        tilts = tuple(float(t) for t in args.tilts.split(",") if t.strip())
    except ValueError:
        raise InputError(f"--tilts must be numbers like '2' or '1.5,2', got '{args.tilts}'") from None
    if any(t <= 1.0 for t in tilts):
        raise InputError(f"--tilts must be greater than 1 (1 is the view itself), got '{args.tilts}'")
    settings = BuildSettings(roi=parse_roi(args.roi), depth_range=(lo, hi), tilts=tilts)
    name = args.name or (description or {}).get("name", "") or model_name("", out)
    check_name(name)
    model = build_model(views, settings, name=name, register_view=register_view_with_ecc)
    save_model(model, out)
    placed = (f"{model.views_placed} of {len(views)} view(s) (registered by texture; {len(views) - model.views_placed} "
              f"left out: not registered surely" + (f"; the capture frame is view {model.capture_view}'s, the first placed"
                                                      if model.capture_view else "") + ")"
              if model.views_placed is not None else f"{len(views)} view(s)")
    print(f"model {out} ('{model.name}'): {model.num_keypoints} keypoints from {placed}, {len(model.points_xyz)} cloud points, "
          f"extent {np.round(model.extent, 3).tolist()} m" + (", with T_object_model" if model.T_object_model is not None else ""),
          file=sys.stderr)
    return 0


def run_mesh(args, out: Path) -> int:
    """The model from a mesh, plus SIFT keypoints from capture bags: placed in the mesh frame
    by the views' ground truth (as the synthetic captures have it) or by shape."""
    import time

    from ..meshes import load_mesh
    from ..models.capture_alignment import place_capture_keypoints
    from ..models.mesh_model import (RENDER_DISTANCE_M, RENDER_VIEWS, add_capture_keypoints, add_rendered_keypoints,
                                   build_model_from_mesh)
    from ..models.model import BuildSettings, model_name, save_model

    if args.rgb or args.depth:
        raise InputError("give either --mesh (with capture bags, optionally) or --rgb/--depth PNG files, not both")
    t0 = time.perf_counter()
    mesh = load_mesh(args.mesh, args.units)
    name = args.name or model_name("", args.mesh)
    check_name(name)
    symmetry, symmetry_source = mesh_symmetry(args.mesh, args.symmetry, args.models_info, args.obj_id)
    model = build_model_from_mesh(mesh, name, symmetry)
    views = []
    for bag in args.bag:
        # Placed on the mesh view by view (by ground truth or by shape): spread frames by default.
        more, _ = views_from_bag(bag, args.frames, args.topics, spread=True)
        views += more
    placed, rendered = "", 0
    render_views = RENDER_VIEWS if args.render_views is None else args.render_views
    distance = RENDER_DISTANCE_M if args.render_distance is None else args.render_distance
    if render_views < 0 or not 0.05 <= distance <= 20.0:
        raise InputError(f"--render-views must be 0 or more and --render-distance 0.05-20 m; got {render_views} "
                         f"and {distance}")
    if views and (args.render_views or args.render_distance is not None):
        raise InputError("--render-views and --render-distance give a coloured mesh keypoints when there are no capture "
                         "bags; with capture bags the keypoints come from those")
    if not views and mesh.has_colour and render_views:
        _, per_view = add_rendered_keypoints(model, mesh, BuildSettings(), render_views, distance)
        rendered = len(per_view)
        colour = "its texture" if mesh.texture is not None else "its vertex colours"
        placed = (f" (rendered from {colour} at {distance:g} m: {min(per_view)}-{max(per_view)} a view, "
                  f"median {int(np.median(per_view))})")
    elif not views and (args.render_views or args.render_distance is not None):
        raise InputError(f"--render-views and --render-distance need a mesh with colour; {args.mesh} has neither vertex "
                         f"colours nor a texture")
    if views:
        lo, hi = args.depth_range
        settings = BuildSettings(roi=parse_roi(args.roi), depth_range=(lo, hi))
        if args.ignore_ground_truth or not all(v.T_camera_object is not None for v in views):
            # Each view's pose from the mesh's shape, its symmetric pose from the texture.
            align = place_capture_keypoints(model, mesh, views, settings)
            placed = (f" (placed by shape: the object found in {align.found} of {len(views)} view(s); "
                      f"{align.placed} placed, {align.by_texture_alone} of them by their texture alone)")
            if align.placed < max(2, len(views) // 4):
                print(f"warning: few capture views could be placed on the mesh{placed}; the model has the texture "
                      f"of those only", file=sys.stderr)
        else:
            add_capture_keypoints(model, views, settings)
            placed = " (placed by ground truth)"
    save_model(model, out)
    print(f"model {out} ('{model.name}'): from mesh {args.mesh} ({len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles) in "
          f"{time.perf_counter() - t0:.2f} s: {len(model.shape_points)} shape points at voxel {model.shape_voxel * 1000:.1f} mm, "
          f"{model.num_keypoints} SIFT keypoints from {len(views) or rendered} view(s){placed}, extent {np.round(model.extent, 3).tolist()} m, "
          f"symmetries: {model.symmetries.describe() if model.symmetries is not None else 'none'} ({symmetry_source})", file=sys.stderr)
    return 0
