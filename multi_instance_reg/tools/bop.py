"""``mireg bop``: datasets in the BOP layout (bop.felk.cvut.cz) through the pipeline.

    mireg bop run DATASET -o OUT [--split test] [--model ID=MODEL.npz ...] [--objects 1,2]
                  [--scenes 1,2] [--images 0,5] [--all-images] [--all-objects] [--tracking | --no-tracking]
                  [--params FILE.yaml] [--overlays N] [--method NAME] [--csv FILE]
                  [--ray | --workers N | --address ADDR] [--retries N]
    mireg bop model DATASET --obj ID -o MODEL.npz
    mireg bop to-bag DATASET --scene ID -o BAG [--split test] [--images 0,5] [--rate 30] [--storage sqlite3|mcap]
    mireg bop score RESULTS.csv --dataset DATASET [--split test] [-o SCORES.json]   (tools/bop_score.py)

``run`` writes the BOP results CSV (``OUT/<method>_<dataset>-<split>.csv``: one row per pose,
time = the image's seconds), ``OUT/summary.json`` (per image: poses per object, wall-clock
and CPU seconds, and with ground truth hits at 10 deg / 2 cm over the object's symmetries,
instances under 10 % visible not counted) and overlays ``OUT/overlays/SSSSSS_IIIIII.png``
(models' boxes green, ground truth grey, each pose's model surface points in a colour of its
own). Models: ``--model ID=FILE.npz`` (BOP object id = a model from ``mireg build-model``,
whose object frame must be the BOP mesh's) or, for every object without one, built from the
dataset's ``models/obj_NNNNNN.ply`` (mm) as ``mireg build-model --mesh`` does, with the
symmetries ``models_info.json`` lists (kept in ``OUT/models/``). Which objects: those given,
else the targets' (``test_targets_bop19.json``), else the ground truth's, else all in
``models_info.json``; with a targets file each image is searched only for the objects its
targets name (BOP's localisation task gives them; ``--all-objects``: every object in every
image). Images are solved alone (BOP images are not a video) unless
``--tracking``, which runs each scene's images in id order through the tracker.
``--ray`` / ``--workers`` / ``--address``: the images (scenes with --tracking) as tasks on Ray
workers, each finished one in ``OUT/parts/`` so that a rerun skips it (docs/scale_out.md).

``model`` builds one object's model file from the dataset's mesh (the same code path).
``to-bag`` writes one scene as a realsense-ros rosbag2 (topics as ``datasets/rgbd_bag.py``
reads them, ground truth on /ground_truth/*), to play into the node or read with ``mireg
offline``; image ids become stamps at ``--rate`` Hz.

Sub-commands live in ``SUBCOMMANDS`` (name -> (help, add_arguments, run)): a new one (e.g. a
scorer) adds its entry.
"""
from __future__ import annotations

import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError

HELP = "BOP datasets: run the pipeline (results CSV, overlays), build a model from its mesh, convert a scene to a bag"

HIT_RRE_DEG, HIT_RTE_M = 10.0, 0.02      # the summary's quick hit count (the scoring proper is BOP's)
MIN_VISIB_FRACT = 0.1                    # BOP does not count instances less visible than this


def parse_ids(text: str | None, what: str) -> list[int] | None:
    """'1,2,5' -> [1, 2, 5]; None stays None."""
    if text is None:
        return None
    try:
        ids = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--{what} must be comma-separated integer ids like '1,2,5', got '{text}'") from None
    if not ids or any(i < 0 for i in ids):
        raise InputError(f"--{what} must list ids >= 0, got '{text}'")
    return ids


def parse_model_args(items: list[str] | None) -> dict[int, str]:
    """``--model ID=FILE.npz`` items -> {obj_id: path}."""
    out = {}
    for item in items or []:
        obj, sep, path = item.partition("=")
        if not sep or not path:
            raise InputError(f"--model '{item}' must be ID=MODEL.npz, the BOP object id and its model file, e.g. 2=cup.npz")
        try:
            obj_id = int(obj)
        except ValueError:
            raise InputError(f"--model '{item}': '{obj}' is not an integer BOP object id") from None
        if obj_id in out:
            raise InputError(f"--model gives object {obj_id} twice")
        out[obj_id] = path
    return out


def _open(args):
    from ..datasets.bop import BopDataset

    return BopDataset(args.dataset, args.split)


# --------------------------------------------------------------------------- models

def model_from_bop_mesh(dataset, obj_id: int):
    """The object's model from the dataset's mesh (mm), as ``mireg build-model --mesh``
    builds it, named ``obj_NNNNNN``; symmetries from models_info.json (none when its entry
    lists none; found from the mesh when the dataset has no entry); SIFT keypoints from
    renders of the mesh when it has colour (vertex colours or a texture)."""
    from ..datasets.bop import object_name
    from ..meshes import load_mesh
    from ..models.mesh_model import add_rendered_keypoints, build_model_from_mesh
    from ..models.model import BuildSettings
    from ..symmetry import Symmetries

    mesh = load_mesh(dataset.model_path(obj_id), "mm")
    info = dataset.models_info.get(int(obj_id))
    symmetries = None if info is None else (info.symmetries() or Symmetries())
    model = build_model_from_mesh(mesh, object_name(obj_id), symmetries)
    if mesh.has_colour:
        add_rendered_keypoints(model, mesh, BuildSettings())
    return model


def chosen_objects(dataset, pairs, objects: list[int] | None, given: dict[int, str]) -> list[int]:
    """The objects to look for (see the module's docstring)."""
    if objects is not None:
        return sorted(set(objects) | set(given))
    if given:
        return sorted(given)
    chosen = set(pairs)
    if dataset.targets is not None:
        found = {t.obj_id for t in dataset.targets if (t.scene_id, t.im_id) in chosen}
    else:
        found = set()
        for s in sorted({s for s, _ in pairs}):
            gt = dataset.scene(s).gt
            if gt is not None:
                found |= {o for im, entries in gt.items() if (s, im) in chosen for o, _ in entries}
    return sorted(found or dataset.models_info)


def load_bop_models(dataset, obj_ids: list[int], given: dict[int, str], save_dir: Path | None = None):
    """The models of ``obj_ids``, in order: the given model files, the rest built from the
    dataset's meshes (and saved in ``save_dir`` for reuse with --model)."""
    from ..datasets.bop import object_name
    from ..models.model import load_model, save_model
    from ..rgbd.multi_model import check_model_names

    if not obj_ids:
        raise InputError(f"no object to look for: {dataset.root} lists no object in models/models_info.json; "
                         f"give --model ID=MODEL.npz")
    info_path = dataset.root / "models" / "models_info.json"
    models = []
    for obj in obj_ids:
        if dataset.models_info and obj not in dataset.models_info:
            raise InputError(f"object id {obj} is not in {info_path} (it lists "
                             f"{', '.join(str(i) for i in sorted(dataset.models_info))})")
        if obj in given:
            models.append(load_model(given[obj]))
            continue
        t0 = time.perf_counter()
        model = model_from_bop_mesh(dataset, obj)
        if save_dir is not None:
            # Run with the model as saved (float32 arrays), so that giving the file back with
            # --model, or to mireg offline, gives the same poses.
            model = load_model(save_model(model, save_dir / f"{object_name(obj)}.npz"))
        print(f"mireg bop: built the model of object {obj} from {dataset.model_path(obj)} in "
              f"{time.perf_counter() - t0:.1f} s (symmetries: "
              f"{model.symmetries.describe() if model.symmetries is not None else 'none'})", file=sys.stderr)
        models.append(model)
    check_model_names(models, [given.get(o, f"object {o}'s mesh") for o in obj_ids])
    return models


# --------------------------------------------------------------------------- run

def add_run_arguments(p) -> None:
    p.add_argument("-o", "--output", required=True, help="output folder (CSV, summary.json, overlays/, models/)")
    p.add_argument("--model", action="append", metavar="ID=MODEL.npz",
                   help="BOP object id and its model file from `mireg build-model` (its object frame the BOP mesh's); "
                        "give it again for more objects (default: built from the dataset's models/obj_NNNNNN.ply)")
    p.add_argument("--objects", default=None, metavar="1,2",
                   help="object ids to look for (default: the targets', else the ground truth's, else all)")
    p.add_argument("--scenes", default=None, metavar="1,2", help="scene ids to run (default all)")
    p.add_argument("--images", default=None, metavar="0,5", help="image ids to run, in every chosen scene (default all)")
    p.add_argument("--all-images", action="store_true",
                   help="run every image, not only those the targets file (test_targets_bop19.json) names")
    p.add_argument("--all-objects", action="store_true",
                   help="look for every chosen object in every image (default with a targets file: in each image only "
                        "the objects its targets name, as BOP's localisation task gives them)")
    tracking = p.add_mutually_exclusive_group()
    tracking.add_argument("--tracking", action="store_true",
                          help="run each scene's images in id order through the tracker (default: every image alone)")
    tracking.add_argument("--no-tracking", action="store_false", dest="tracking",
                          help="every image alone, as mireg offline --no-tracking (the default here: BOP images are "
                               "single images, not a video)")
    p.add_argument("--params", default=None, help="the node's parameter YAML (frontend.*, ecc.*, tracking.* are used)")
    p.add_argument("--overlays", type=int, default=20, metavar="N", help="overlay pictures of the first N images (default 20)")
    p.add_argument("--method", default="mireg", help="method name in the CSV's file name (default mireg)")
    p.add_argument("--csv", default=None, help="results CSV path (default OUT/<method>_<dataset>-<split>.csv)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    from ..distributed.ray_runner import add_ray_arguments

    add_ray_arguments(p, "images (with --tracking: the scenes)")


def results_file_name(method: str, dataset: str, split: str) -> str:
    """BOP's ``METHOD_DATASET-SPLIT.csv``: its evaluation splits the name at '_' and '-', so
    those are left out of the parts."""
    import re

    def clean(s):
        return re.sub(r"[^A-Za-z0-9]", "", s) or "x"
    return f"{clean(method)}_{clean(dataset).lower()}-{clean(split)}.csv"


class BopImageSolver:
    """What one worker of ``bop run`` holds: the dataset, the models and the pipeline (loaded
    once, warmed up). ``run(task)`` solves a task's (scene_id, im_id) images: one image, or
    a scene's images in id order through a fresh tracker. The serial run and every Ray
    worker go through this one class, so both give the same poses."""

    def __init__(self, dataset_root: str, split: str, models, obj_ids: list[int], config, tracker_config,
                 overlay_pairs=(), image_targets: bool = False):
        from ..datasets.bop import BopDataset
        from ..rgbd.multi_model import MultiModelRegistration
        from ..rgbd.workspace import Workspace
        from .offline import object_frame_symmetries

        self.ds = BopDataset(dataset_root, split)
        self.models, self.obj_ids = list(models), list(obj_ids)
        self.obj_of = {m.name: o for m, o in zip(self.models, self.obj_ids)}
        self.index_of = {o: k for k, o in enumerate(self.obj_ids)}
        # Each image's objects (``image_targets``: its targets', of those chosen); an image the
        # targets do not name (``--all-images``) is searched for all.
        self.wanted: dict[tuple[int, int], set[int]] = {}
        if image_targets and self.ds.targets is not None:
            for t in self.ds.targets:
                if t.obj_id in self.index_of:
                    self.wanted.setdefault((t.scene_id, t.im_id), set()).add(self.index_of[t.obj_id])
        self.symmetries = [object_frame_symmetries(m) for m in self.models]
        self.reg = MultiModelRegistration(self.models, config)
        self.reg.warm_up()
        self.workspace = Workspace.from_config(config.workspace)      # drawn in the overlays
        self.tracker_config = tracker_config
        self.overlay_pairs = {tuple(p) for p in overlay_pairs}

    def run(self, task) -> dict:
        """{"images": summary entries, "estimates": CSV rows [scene, im, obj, score, R (9), t_mm (3), seconds],
        "skipped": reasons of the images left out, "overlays": {file name: PNG bytes}}."""
        import cv2

        from ..datasets.bop import BopEstimate
        from ..rgbd.pipeline import check_frame
        from ..tracking import ObjectTrackers
        from .offline import estimates_in_object_frame

        out = {"images": [], "estimates": [], "skipped": [], "overlays": {}}
        trackers = None if self.tracker_config is None else ObjectTrackers(self.models, self.tracker_config)
        for scene_id, im_id in task:
            t0, cpu0 = time.perf_counter(), time.process_time()
            try:
                frame = self.ds.read_frame(scene_id, im_id)
                check_frame(frame.rgb, frame.depth_m, frame.intrinsics)
                result = self.reg.register_frame(frame.rgb, frame.depth_m, frame.intrinsics,
                                                 only=self.wanted.get((scene_id, im_id)))
            except InputError as exc:
                out["skipped"].append(f"scene {scene_id} image {im_id}: {exc}")
                continue
            published = result.instances
            if trackers is not None:
                published = trackers.step(frame.stamp_ns, frame.depth_m, frame.intrinsics, result.instances,
                                          rgb=frame.rgb)      # the colour image: the camera's motion
            seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - cpu0
            by_object: dict[int, int] = {}
            for inst in published:
                obj = self.obj_of[inst.object]
                T = estimates_in_object_frame(self.models[self.index_of[obj]], inst.T)[0]
                e = BopEstimate.from_pose(frame.scene_id, frame.im_id, obj, inst.score, T, seconds)
                out["estimates"].append([e.scene_id, e.im_id, e.obj_id, e.score, e.R.reshape(-1).tolist(),
                                         np.asarray(e.t_mm, np.float64).tolist(), e.time_s])
                by_object[obj] = by_object.get(obj, 0) + 1
            entry = {"scene_id": frame.scene_id, "im_id": frame.im_id, "seconds": round(seconds, 4),
                     "cpu_seconds": round(cpu_seconds, 4),       # this process, all threads: less swayed by a loaded host
                     "poses": len(published), "poses_by_object": {str(o): c for o, c in sorted(by_object.items())},
                     "deadline_cut": bool(result.deadline_cut)}     # frontend.shape_deadline_ms stopped the search
            owners = None
            if frame.gt_poses is not None:
                owners = np.array([self.index_of.get(int(o), -1) for o in frame.gt_obj_ids], np.int64)
                entry.update(_hits(frame, owners, self.models, self.symmetries, published))
            out["images"].append(entry)
            if (frame.scene_id, frame.im_id) in self.overlay_pairs:
                ok, png = cv2.imencode(".png", overlay(frame, self.models, published, owners, self.workspace))
                out["overlays"][f"{frame.scene_id:06d}_{frame.im_id:06d}.png"] = png.tobytes()
        return out


def bop_tasks(pairs, tracking: bool) -> list[list[tuple[int, int]]]:
    """One task per image; with tracking one per scene (its images in order, one tracker)."""
    if not tracking:
        return [[p] for p in pairs]
    return [list(group) for _, group in itertools.groupby(pairs, key=lambda p: p[0])]


def describe_bop_task(task) -> str:
    if len(task) == 1:
        return f"scene {task[0][0]} image {task[0][1]}"
    return f"scene {task[0][0]} images {task[0][1]}-{task[-1][1]} ({len(task)})"


def task_key(task) -> str:
    return f"{task[0][0]:06d}_{task[0][1]:06d}" + (f"-{task[-1][1]:06d}" if len(task) > 1 else "")


def run_run(args) -> int:
    from ..datasets.bop import BopEstimate, write_results_csv
    from ..datasets.rgbd_bag import SkipCounter
    from ..distributed.ray_runner import connect, run_serial, run_tasks, wants_ray
    from ..distributed.resume import PartsFolder, run_fingerprint
    from ..progress import Progress
    from .offline import load_config, load_tracker_config

    use_ray = wants_ray(args)
    ds = _open(args)
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output {out_dir} exists and is not a folder")
    pairs = ds.images(parse_ids(args.scenes, "scenes"), parse_ids(args.images, "images"), not args.all_images)
    if not pairs:
        raise InputError(f"no image of {ds.split_dir} is selected (scenes {ds.scene_ids}; check --scenes/--images"
                         + ("" if args.all_images or ds.targets is None else "; the targets file limits the images, "
                            "--all-images runs every one") + ")")
    given = parse_model_args(args.model)
    obj_ids = chosen_objects(ds, pairs, parse_ids(args.objects, "objects"), given)
    config = load_config(args.params)
    tracker_config = load_tracker_config(args.params) if args.tracking else None
    # The first readable image before the models are built (half a minute for a large mesh):
    # a dataset whose images are all bad fails at once.
    unreadable = SkipCounter()
    if next(ds.read_frames(pairs, unreadable), None) is None:
        raise InputError(f"no image of {ds.split_dir} could be processed ({unreadable.count} skipped: "
                         f"{unreadable.summary()})")
    workers = connect(args.address, args.workers) if use_ray else 0    # a cluster not there: said before the models are built
    out_dir.mkdir(parents=True, exist_ok=True)
    models = load_bop_models(ds, obj_ids, given, out_dir / "models")
    overlay_dir = out_dir / "overlays"
    tasks = bop_tasks(pairs, bool(args.tracking))
    results: dict[str, dict] = {}
    image_targets = ds.targets is not None and not args.all_objects
    parts = PartsFolder(out_dir / "parts", run_fingerprint(models, config, tracker_config, dataset=str(ds.root.resolve()),
                                                           split=ds.split, objects=obj_ids, image_targets=image_targets)
                        ) if use_ray else None

    def on_result(task, result):
        if result["overlays"]:
            overlay_dir.mkdir(parents=True, exist_ok=True)
            for name, png in result["overlays"].items():
                (overlay_dir / name).write_bytes(png)
        if parts is not None:
            parts.save(task_key(task), result)
        results[task_key(task)] = result

    if parts is not None:
        for task in tasks:
            done = parts.load(task_key(task))
            if done is not None:
                results[task_key(task)] = done
    todo = [t for t in tasks if task_key(t) not in results]
    worker_args = (str(ds.root), ds.split, models, obj_ids, config, tracker_config, pairs[:max(args.overlays, 0)],
                   image_targets)
    bar = Progress(len(tasks), not args.quiet, unit="scenes" if args.tracking else "images")
    t_run = time.perf_counter()
    try:
        if use_ray:
            if len(results):
                print(f"mireg bop run: {len(results)} of {len(tasks)} task(s) done before (in {parts.folder}); "
                      f"running the other {len(todo)} on {min(workers, len(todo))} Ray worker(s)", file=sys.stderr)
            failures = run_tasks(BopImageSolver, worker_args, todo, describe_bop_task, on_result, workers, args.retries,
                                 bar, done_before=len(results))
        else:
            failures = run_serial(BopImageSolver, worker_args, todo, describe_bop_task, on_result, bar)
    finally:
        bar.close()
    run_seconds = time.perf_counter() - t_run
    images, estimates, skipped = [], [], SkipCounter()
    for task in tasks:
        result = results.get(task_key(task))
        if result is None:
            continue
        images.extend(result["images"])
        estimates.extend(BopEstimate(s, im, o, score, np.array(R).reshape(3, 3), np.array(t), secs)
                         for s, im, o, score, R, t, secs in result["estimates"])
        for reason in result["skipped"]:
            skipped.add(reason)
    if not images:
        raise InputError(f"no image of {ds.split_dir} could be processed ({skipped.count} skipped: "
                         f"{skipped.summary() or 'none selected'}"
                         + (f"; {len(failures)} task(s) failed: {failures[0].task}: {failures[0].error}" if failures else "")
                         + ")")
    csv_path = Path(args.csv) if args.csv else out_dir / results_file_name(args.method, ds.name, ds.split)
    write_results_csv(csv_path, estimates)
    secs = np.array([e["seconds"] for e in images])
    cpu = np.array([e["cpu_seconds"] for e in images])
    summary = {"dataset": str(ds.root), "split": ds.split, "csv": str(csv_path), "objects": obj_ids,
               "objects_per_image": "targets" if image_targets else "all",
               "models": [m.name for m in models], "tracking": bool(args.tracking), "images": images,
               "skipped": skipped.count, "skip_reasons": skipped.reasons,
               "failed_tasks": [f.as_json() for f in failures],
               # How this run went: Ray workers (0: serial), the tasks it ran and their wall-clock seconds.
               "run": {"workers": workers, "tasks_run": len(todo), "tasks_done_before": len(tasks) - len(todo),
                       "wall_seconds": round(run_seconds, 3)},
               "deadline_cut_images": sum(e["deadline_cut"] for e in images),
               "seconds_per_image": {"mean": float(secs.mean()), "p50": float(np.median(secs)), "max": float(secs.max())},
               "cpu_seconds_per_image": {"mean": float(cpu.mean()), "p50": float(np.median(cpu)), "max": float(cpu.max())}}
    line = (f"{len(images)} image(s), {len(estimates)} pose(s), {secs.mean():.2f} s per image (p50 {np.median(secs):.2f}, "
            f"max {secs.max():.2f}; CPU {cpu.mean():.2f} s per image)")
    with_gt = [e for e in images if "gt_instances" in e]
    if with_gt:
        gt_n = sum(e["gt_instances"] for e in with_gt)
        hits = sum(e["hits"] for e in with_gt)
        summary["hits"] = {"gt_instances": gt_n, "hits": hits, "poses": sum(e["poses"] for e in with_gt),
                           "max_rre_deg": HIT_RRE_DEG, "max_rte_m": HIT_RTE_M, "min_visib_fract": MIN_VISIB_FRACT}
        line += f"; {hits} of {gt_n} ground-truth instances hit ({HIT_RRE_DEG:g} deg / {HIT_RTE_M * 1000:g} mm)"
    if summary["deadline_cut_images"]:
        line += f"; the shape search's deadline cut {summary['deadline_cut_images']} image(s)"
    if skipped.count:
        line += f"; {skipped.count} skipped ({skipped.summary()})"
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"mireg bop run: {line}; wrote {csv_path} and {out_dir / 'summary.json'}", file=sys.stderr)
    if failures:
        print(f"mireg bop run: error: {len(failures)} task(s) failed {args.retries + 1} time(s) and are not in the "
              f"results (first: {failures[0].task}: {failures[0].error}; all in summary.json failed_tasks); "
              f"rerun the same command to try them again", file=sys.stderr)
        return 1
    return 0


OVERLAY_POINTS = 2000       # model surface points drawn per pose


def overlay(frame, models, published, owners, workspace=None):
    """offline's overlay (boxes, ground truth in grey, the ``workspace`` if any) with each pose's model surface points
    in a colour of its own over it: whether a pose sits on its object (a cup lid on lid) is
    judged from the surface, not from the box."""
    import cv2

    from ..rgbd.overlay import draw_points
    from .offline import draw_overlay

    img = draw_overlay(frame.rgb, frame.intrinsics, models, published, frame.gt_poses, owners, workspace)
    by_name = {m.name: m for m in models}
    for k, inst in enumerate(published):
        pts = by_name[inst.object].points_xyz
        hue = np.uint8([[(k * 47) % 180]])
        colour = cv2.applyColorMap(hue, cv2.COLORMAP_HSV)[0, 0]
        draw_points(img, inst.T, pts[::max(1, len(pts) // OVERLAY_POINTS)], frame.intrinsics, colour)
    return img


def _hits(frame, owners, models, symmetries, published) -> dict:
    """Ground-truth instances (visible >= 10 %) and how many a pose of its object hits."""
    from .offline import estimates_in_object_frame, match_frame

    present = hits = 0
    for k, m in enumerate(models):
        gt = np.flatnonzero(owners == k)
        est = [i.T for i in published if i.object == m.name]
        vis = None if frame.gt_visibility is None else frame.gt_visibility[gt]
        score, _ = match_frame(frame.gt_poses[gt], estimates_in_object_frame(m, est), vis, MIN_VISIB_FRACT,
                               HIT_RRE_DEG, HIT_RTE_M, symmetries[k])
        present += score.n_gt
        hits += score.hits
    return {"gt_instances": int(present), "hits": int(hits)}


# --------------------------------------------------------------------------- model

def add_model_arguments(p) -> None:
    p.add_argument("--obj", type=int, required=True, help="BOP object id (models/obj_NNNNNN.ply)")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")


def run_model(args) -> int:
    from ..models.model import save_model

    out = Path(args.output)
    if out.suffix != ".npz":
        raise InputError(f"output {out} must end in .npz")
    ds = _open(args)
    model = load_bop_models(ds, [args.obj], {})[0]
    save_model(model, out)
    print(f"mireg bop model: wrote {out} ('{model.name}', {len(model.shape_points)} shape points, extent "
          f"{np.round(model.extent, 3).tolist()} m)", file=sys.stderr)
    return 0


# --------------------------------------------------------------------------- to-bag

def add_to_bag_arguments(p) -> None:
    from ..datasets.bag_writer import STORAGES

    p.add_argument("--scene", type=int, required=True, help="scene id to convert")
    p.add_argument("-o", "--output", required=True, help="bag directory to create (must not exist)")
    p.add_argument("--images", default=None, metavar="0,5", help="image ids to convert (default all)")
    p.add_argument("--rate", type=float, default=30.0, help="image id i is stamped at i / RATE s (default 30 Hz)")
    p.add_argument("--storage", choices=STORAGES, default="sqlite3", help="rosbag2 storage (default sqlite3)")


def scene_description(ds, scene_id: int, frames) -> dict:
    """The /ground_truth/object JSON of a converted scene: the objects by name
    (``obj_NNNNNN``, as models built from the dataset's meshes are named), and
    ``instance_objects`` when every image lists the same objects in the same order (the bag
    reader names the instances of every frame from that one list)."""
    from ..datasets.bop import object_name

    lists = {tuple(int(o) for o in f.gt_obj_ids) for f in frames if f.gt_obj_ids is not None}
    ids = sorted({o for lst in lists for o in lst})
    d = {"name": object_name(ids[0]) if len(ids) == 1 else "", "generator": "multi_instance_reg.datasets.bop",
         "objects": [{"name": object_name(o), "bop_obj_id": o,
                      **({"dimensions_m": [float(v) / 1000.0 for v in ds.models_info[o].size_mm]}
                         if o in ds.models_info else {})} for o in ids],
         "bop": {"dataset": str(ds.root), "split": ds.split, "scene_id": int(scene_id),
                 "im_ids": [int(f.im_id) for f in frames]}}
    if len(lists) == 1:
        d["instance_objects"] = [object_name(o) for o in next(iter(lists))]
    return d


def run_to_bag(args) -> int:
    from ..datasets.bag_writer import RealSenseBagWriter
    from ..datasets.bop import bop_stamp_ns
    from ..datasets.rgbd_bag import SkipCounter

    if not args.rate > 0:
        raise InputError(f"--rate must be positive, got {args.rate}")
    if Path(args.output).suffix.lower() in (".bag", ".db3", ".mcap"):
        # rosbags (and so mireg offline) reads a path ending in .bag as a ROS 1 bag file.
        raise InputError(f"output {args.output}: a rosbag2 is a folder; name it without {Path(args.output).suffix} "
                         f"(a name ending in .bag is read as a ROS 1 bag file)")
    ds = _open(args)
    pairs = ds.images([args.scene], parse_ids(args.images, "images"))
    if not pairs:
        raise InputError(f"scene {args.scene} of {ds.split_dir} has none of the images {args.images}")
    skipped = SkipCounter()
    frames = list(ds.read_frames(pairs, skipped))
    if not frames:
        raise InputError(f"no image of scene {args.scene} could be read ({skipped.summary()})")
    t0 = time.perf_counter()
    with RealSenseBagWriter(args.output, storage=args.storage) as bag:
        bag.write_object_description(bop_stamp_ns(frames[0].im_id, args.rate), scene_description(ds, args.scene, frames))
        for f in frames:
            depth_mm = np.clip(np.round(f.depth_m * 1000.0), 0, 65535).astype(np.uint16)
            bag.write_frame(bop_stamp_ns(f.im_id, args.rate), f.rgb, depth_mm, f.intrinsics,
                            poses=f.gt_poses, visibility=f.gt_visibility)
    line = f"wrote {len(frames)} frame(s) of scene {args.scene} to {args.output} in {time.perf_counter() - t0:.1f} s"
    if frames[0].gt_poses is not None:
        line += " with ground truth"
    if skipped.count:
        line += f"; {skipped.count} skipped ({skipped.summary()})"
    print(f"mireg bop to-bag: {line}", file=sys.stderr)
    return 0


# --------------------------------------------------------------------------- the command

SUBCOMMANDS = {
    "run": ("run the pipeline over a split: BOP results CSV, summary.json, overlays", add_run_arguments, run_run),
    "model": ("build an object's model (npz) from the dataset's mesh and models_info symmetries",
              add_model_arguments, run_model),
    "to-bag": ("write a scene as a realsense-ros rosbag2 with ground truth", add_to_bag_arguments, run_to_bag),
    "score": ("score a results CSV: AR over VSD, MSSD, MSPD as the BOP challenge; MHR/MHP/MHF1 at 10 deg / 2 cm",
              lambda p: _score().add_arguments(p), lambda args: _score().run(args)),
}
# Sub-commands whose first argument is another file take the dataset as --dataset.
DATASET_AS_OPTION = {"score"}


def _score():
    from . import bop_score      # the scoring lives in evaluation/; its command line in bop_score.py

    return bop_score


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="bop_command", metavar="{" + ",".join(SUBCOMMANDS) + "}", required=True)
    for name, (help_text, add, _) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name in DATASET_AS_OPTION:
            p.add_argument("--dataset", required=True, help="BOP dataset folder (camera.json, models/, the splits)")
        else:
            p.add_argument("dataset", help="BOP dataset folder (camera.json, models/, the splits)")
        p.add_argument("--split", default="test", help="split folder (default test)")
        add(p)


def run(args) -> int:
    return SUBCOMMANDS[args.bop_command][2](args)
