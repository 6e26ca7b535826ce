"""``mireg offline``: replay a recorded bag through the per-frame pipeline, without ROS.

    mireg offline BAG [BAG2 ... | FOLDER] --model MODEL.npz [--model MODEL2.npz ...] -o OUTDIR [--params FILE.yaml]
                  [--topics COLOUR DEPTH INFO] [--ray | --workers N | --address ADDR]

Several bags (or a folder of bags) write each bag's files into OUTDIR/<bag name>/ and a list
in OUTDIR/summary.json; with Ray each bag is a task on a worker (docs/scale_out.md).

Writes OUTDIR/poses.json (the public contract below). When the bag carries ground truth it
also writes OUTDIR/metrics.json, overlay_*.png (each instance's box with its id) and
found_vs_present.png (instances found against instances present, frame by frame).

poses.json: {"frames": [{"stamp_ns": int, "frame_id": str, "latency_ms": float,
             "instances": [{"id": int, "object": str, "T": [[4 x 4]], "inliers": int, "score": float,
                            "track_id": int, "state": str, "source": str}]}]}
T maps the model frame into the camera optical frame (metres). The tracker runs over the bag
(every frame, in order) unless --no-tracking: then track_id, state and source are absent and
every frame is solved alone. id is the rank of the instance in its frame by inliers (among its
object's instances). object is the name of the model (``mireg build-model --name``); instances
are listed by object, in the order the models were given, then by id.
metrics.json: the figures over all objects at the top level (as with one model), "objects"
with each object's, and "confusions" (instances reported as the wrong object).
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..progress import Progress

HELP = "replay a bag through the pipeline: poses.json, and metrics.json + pictures with ground truth"

STAGE_ORDER = ("sift", "matching", "lifting", "ecc", "refinement", "tracking", "total")


def add_arguments(parser) -> None:
    parser.add_argument("bag", nargs="+",
                        help="rosbag2 directory, .db3 or .mcap; several, or a folder holding bags: each bag's files go "
                             "into OUTDIR/<bag name>/ and OUTDIR/summary.json lists them all")
    parser.add_argument("--model", required=True, action="append",
                        help="object model (.npz) from `mireg build-model`; give it again for each further object "
                             "(one SIFT pass for all; models need different names)")
    parser.add_argument("-o", "--output", required=True, help="output directory")
    parser.add_argument("--params", default=None, help="the node's parameter YAML (frontend.* and ecc.* are used)")
    parser.add_argument("--topics", nargs=3, metavar=("COLOUR", "DEPTH", "INFO"), default=None,
                        help="colour, aligned depth and camera_info topics, raw or compressed (default: realsense-ros names; "
                             "their /compressed and /compressedDepth topics when the raw ones are absent)")
    parser.add_argument("--max-rre-deg", type=float, default=10.0, help="hit: rotation error below this (default 10 deg)")
    parser.add_argument("--max-rte", type=float, default=0.02, help="hit: translation error below this (default 0.02 m)")
    parser.add_argument("--min-visibility", type=float, default=0.25,
                        help="instances with a smaller visible fraction (/ground_truth/visibility) are not counted "
                             "as present (default 0.25)")
    parser.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0 = all)")
    parser.add_argument("--no-tracking", action="store_true",
                        help="every frame alone, as before tracking existed: no track_id/state/source, ids are per-frame ranks")
    parser.add_argument("--detect-every", type=int, default=1, metavar="N",
                        help="run the detector on every N-th frame only and the tracker's depth update on every frame, "
                             "as the live node does when detection is slower than the camera (default 1: every frame)")
    parser.add_argument("--overlays", type=int, default=4, help="overlay pictures to write with ground truth (default 4)")
    parser.add_argument("--no-gravity", action="store_true",
                        help="ignore the camera's accelerometer (/camera/camera/accel/sample or /camera/camera/imu) even "
                             "when the bag has it: every frame without the direction of gravity, as before (A/B)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    from ..distributed.ray_runner import add_ray_arguments

    add_ray_arguments(parser, "bags (one task per bag: a tracked bag stays in order)")


def load_config(params_path):
    """PipelineConfig with the frontend.*, ecc.* and workspace.* entries of a node parameter file
    (or of a dict of dotted names) applied."""
    from ..rgbd.pipeline import PipelineConfig

    return _config_from_params(PipelineConfig(), params_path, ("frontend", "ecc", "workspace"))


def load_tracker_config(params_path):
    """TrackerConfig with the tracking.* entries of a node parameter file applied; None (no
    tracking, as --no-tracking) when the file sets the node's tracking.enabled to false. The
    node's other live-stream settings (tracking.LiveConfig) do not apply offline."""
    from ..tracking import TRACKING_ENABLED, LiveConfig, TrackerConfig

    values = _params(params_path)
    if not TRACKING_ENABLED.check(values.get(TRACKING_ENABLED.name, True)):
        return None
    live = {f"tracking.{name}" for name in LiveConfig.__dataclass_fields__}
    return _config_from_params(TrackerConfig(), {k: v for k, v in values.items() if k not in live},
                               ("tracking",), strip=True)


def _params(params_path) -> dict:
    from ..params import read_params_yaml

    if isinstance(params_path, dict):        # entries already read (mireg tune's trials)
        return params_path
    return {} if params_path is None else read_params_yaml(params_path)


def _config_from_params(config, params, groups, strip: bool = False):
    """``params``: a node parameter file's path (None: none) or its entries already read."""
    from ..params import with_overrides

    values = params if isinstance(params, dict) else _params(params)
    ours = {(k.split(".", 1)[1] if strip else k): v for k, v in values.items() if k.split(".", 1)[0] in groups}
    return with_overrides(config, ours)


@dataclass
class ReplayResult:
    frames: list[dict] = field(default_factory=list)          # poses.json entries
    timings: list[dict] = field(default_factory=list)         # per frame, ms by stage
    cpu_ms: list[float] = field(default_factory=list)         # per frame, CPU time of this process (all threads)
    scores: list = field(default_factory=list)                # metrics.SceneScore per frame with ground truth
    detection_scores: list = field(default_factory=list)      # the same for the detector alone (frames it ran on)
    identity: object = None                                   # metrics.IdentityScore when tracking
    present: list[int] = field(default_factory=list)          # per frame: ground-truth instances (-1 without)
    in_view: list[int] = field(default_factory=list)          # per frame: ground-truth instances visible at all (-1 without)
    found: list[int] = field(default_factory=list)
    hits: list[int] = field(default_factory=list)
    object_scores: dict = field(default_factory=dict)         # object name -> its SceneScores, frame by frame
    object_identity: dict | None = None                       # object name -> IdentityScore when tracking
    confusions: int = 0                                       # estimates reported as the wrong object
    skipped: int = 0
    skip_reasons: str = ""
    has_ground_truth: bool = False
    gravity_frames: int = 0                                   # frames given the direction of gravity (IMU)
    deadline_cuts: int = 0                                    # frames whose shape search its deadline cut

    def latency_summary(self) -> dict:
        out = {}
        extra = ("shape",) if self.timings and "shape" in self.timings[0] else ()
        for stage in STAGE_ORDER + extra:
            vals = np.array([t[stage] for t in self.timings]) if self.timings else np.zeros(0)
            out[stage] = {q: float(np.percentile(vals, int(q[1:]))) if len(vals) else None for q in ("p50", "p95", "p99")}
        return out


def estimates_in_object_frame(model, transforms: np.ndarray) -> np.ndarray:
    """Estimated model->camera transforms as object->camera, comparable with ground truth."""
    from ..transforms import invert_transform

    transforms = np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4)
    if model.T_object_model is None:
        return transforms
    return transforms @ invert_transform(model.T_object_model)


def object_frame_symmetries(model):
    """The model's symmetries in the object (ground-truth) frame, or None."""
    if model.symmetries is None or model.symmetries.is_trivial:
        return None
    T_om = np.eye(4) if model.T_object_model is None else model.T_object_model
    return model.symmetries.conjugated(T_om)


def evaluate_frame(T_gt, T_est, visibility=None, min_visibility: float = 0.0, max_rre_deg: float = 10.0,
                   max_rte: float = 0.02, symmetries=None):
    """Score one frame. Instances less visible than ``min_visibility`` are not "present": they
    do not count against recall, and an estimate that hits one is neither credit nor blame."""
    return match_frame(T_gt, T_est, visibility, min_visibility, max_rre_deg, max_rte, symmetries)[0]


def match_frame(T_gt, T_est, visibility=None, min_visibility: float = 0.0, max_rre_deg: float = 10.0,
                max_rte: float = 0.02, symmetries=None):
    """``evaluate_frame``'s score, and its hits as (ground-truth index, estimate index) pairs
    into the arrays given (the identities the tracking metrics need)."""
    from ..metrics import evaluate_scene

    T_gt = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    gt_index, est_index = np.arange(len(T_gt)), np.arange(len(T_est))
    if visibility is not None and min_visibility > 0:
        seen = np.asarray(visibility) >= min_visibility
        full = evaluate_scene(T_gt, T_est, max_rre_deg, max_rte, symmetries)
        drop = {e for (g, e), hit in zip(full.pairs, full.hit) if hit and not seen[g]}
        gt_index, est_index = np.flatnonzero(seen), np.array([e for e in est_index if e not in drop], dtype=np.int64)
    score = evaluate_scene(T_gt[gt_index], T_est[est_index], max_rre_deg, max_rte, symmetries)
    hits = [(int(gt_index[g]), int(est_index[e])) for (g, e), hit in zip(score.pairs, score.hit) if hit]
    return score, hits


def ground_truth_owners(models, instance_objects: list[str]) -> np.ndarray:
    """(K,) index of the model each ground-truth instance is an instance of, -1 for objects no
    model was given for. With one model and a bag that does not name its objects (or names
    none of them as the model), every instance is the model's: single-object bags score as
    they always did."""
    names = [m.name for m in models]
    if len(models) == 1 and names[0] not in instance_objects:
        return np.zeros(len(instance_objects), np.int64)
    return np.array([names.index(n) if n in names else -1 for n in instance_objects], np.int64)


def count_confusions(models, gt_poses, owners, visibility, min_visibility, published, hit_estimates,
                     margin: float) -> int:
    """Estimates reported as the wrong object: not a hit on their own object, with their box
    centre inside (within ``margin``) the box of a present ground-truth instance of another
    object whose model is loaded."""
    from ..transforms import invert_transform

    index = {m.name: k for k, m in enumerate(models)}
    n = 0
    for e, inst in enumerate(published):
        if e in hit_estimates:
            continue
        k = index[inst.object]
        centre = inst.T[:3, :3] @ np.asarray(models[k].box_centre, np.float64) + inst.T[:3, 3]
        for g, owner in enumerate(owners):
            if owner < 0 or owner == k or (visibility is not None and visibility[g] < min_visibility):
                continue
            other = models[owner]
            T_model = gt_poses[g] @ (np.eye(4) if other.T_object_model is None else other.T_object_model)
            local = invert_transform(T_model) @ np.append(centre, 1.0)
            if np.all(np.abs(local[:3] - other.box_centre) <= np.asarray(other.extent) / 2 + margin):
                n += 1
                break
    return n


def replay(bag_path, model, config, topics=None, max_rre_deg: float = 10.0, max_rte: float = 0.02,
           max_frames: int = 0, on_frame=None, progress: bool = True, min_visibility: float = 0.0,
           tracker_config=None, detect_every: int = 1, gravity: bool = True) -> ReplayResult:
    """Run every frame of a bag through MultiModelRegistration (``model``: one ObjectModel or
    a list of them) and, with a ``tracker_config``, through one InstanceTracker per object
    (detector on every ``detect_every``-th frame, the trackers' depth update on every frame).
    ``on_frame(index, frame, instances)`` is called with what is published for each
    processed frame (pictures are drawn there). Ground truth is scored per object (an
    instance's object from the bag's /ground_truth/object) and over all objects. ``gravity``:
    give each frame the direction of gravity from the bag's accelerometer, when it has one."""
    from ..datasets.rgbd_bag import RGBDBag
    from ..gravity import ACCEL_TOPIC
    from ..metrics import IdentityScore, combine_scores
    from ..models.model import ObjectModel
    from ..rgbd.multi_model import MultiModelRegistration
    from ..rgbd.pipeline import check_frame

    if detect_every < 1:
        raise InputError(f"--detect-every must be at least 1, got {detect_every}")
    models = [model] if isinstance(model, ObjectModel) else list(model)
    reg = MultiModelRegistration(models, config)
    symmetries = [object_frame_symmetries(m) for m in models]   # hits over the symmetries (BOP); None: plain
    reg.warm_up()   # compile the ECC core's kernels now, not inside the first frame's latency
    trackers = None
    if tracker_config is not None:
        from ..tracking import ObjectTrackers

        trackers = ObjectTrackers(models, tracker_config)
    kwargs = dict(zip(("colour_topic", "depth_topic", "info_topic"), topics)) if topics else {}
    out = ReplayResult(identity=IdentityScore() if trackers is not None else None)
    out.object_scores = {m.name: [] for m in models}
    out.object_identity = {m.name: IdentityScore() for m in models} if trackers is not None else None
    skip_reasons: dict[str, int] = {}
    with RGBDBag(bag_path, accel_topic=ACCEL_TOPIC if gravity else None, **kwargs) as bag:
        out.has_ground_truth = bag.has_ground_truth
        total = bag.num_colour_messages if not max_frames else min(max_frames, bag.num_colour_messages)
        bar = Progress(total, progress)
        try:
            stream, last_stamp = 0, None          # streams: runs of frames whose stamps do not go back
            for index, frame in enumerate(bag):
                if max_frames and index >= max_frames:
                    break
                if last_stamp is not None and frame.stamp_ns < last_stamp:
                    stream += 1
                last_stamp = frame.stamp_ns
                cpu0 = time.process_time()
                detect = trackers is None or index % detect_every == 0
                try:
                    check_frame(frame.rgb, frame.depth_m, frame.intrinsics)
                    result = reg.register_frame(frame.rgb, frame.depth_m, frame.intrinsics,
                                                frame.gravity) if detect else None
                except InputError as exc:
                    skip_reasons[str(exc)] = skip_reasons.get(str(exc), 0) + 1
                    out.skipped += 1
                    bar.update(index + 1, f"(skipped {out.skipped})")
                    continue
                timings = dict(result.timings_ms) if result is not None else {s: 0.0 for s in STAGE_ORDER}
                timings["tracking"] = 0.0
                if trackers is not None:
                    t0 = time.perf_counter()
                    published = trackers.step(frame.stamp_ns, frame.depth_m, frame.intrinsics,
                                              result.instances if result is not None else None, frame.rgb)
                    timings["tracking"] = (time.perf_counter() - t0) * 1e3
                    timings["total"] += timings["tracking"]
                else:
                    published = result.instances
                order = {m.name: k for k, m in enumerate(models)}
                out.frames.append({
                    "stamp_ns": int(frame.stamp_ns), "frame_id": frame.frame_id,
                    "latency_ms": round(float(timings["total"]), 3),
                    "instances": [instance_json(i) for i in sorted(published, key=lambda i: (order[i.object], i.id))]})
                out.timings.append(timings)
                out.cpu_ms.append((time.process_time() - cpu0) * 1e3)
                out.found.append(len(published))
                out.gravity_frames += frame.gravity is not None
                out.deadline_cuts += bool(result is not None and result.deadline_cut)
                if frame.gt_poses is not None:
                    owners = ground_truth_owners(models, bag.instance_objects(len(frame.gt_poses)))
                    scores, detection_scores, hit_estimates = [], [], set()
                    for k, m in enumerate(models):
                        gt = np.flatnonzero(owners == k)
                        est = [e for e, i in enumerate(published) if i.object == m.name]
                        vis = None if frame.gt_visibility is None else frame.gt_visibility[gt]
                        score, hits = match_frame(frame.gt_poses[gt], estimates_in_object_frame(m, [published[e].T for e in est]),
                                                  vis, min_visibility, max_rre_deg, max_rte, symmetries[k])
                        scores.append(score)
                        out.object_scores[m.name].append(score)
                        hit_estimates |= {est[e] for _, e in hits}
                        if trackers is not None:
                            # Identity is kept within a stream: where the stamps went back (a
                            # loop) the tracker starts again, and so does the identity count.
                            matches = [((m.name, stream, int(gt[g])), (m.name, published[est[e]].track_id))
                                       for g, e in hits]
                            out.identity.add_frame(matches, score.n_gt, score.n_est)
                            out.object_identity[m.name].add_frame(matches, score.n_gt, score.n_est)
                            if result is not None:
                                found = [i.T for i in result.instances if i.object == m.name]
                                detection_scores.append(evaluate_frame(
                                    frame.gt_poses[gt], estimates_in_object_frame(m, found), vis, min_visibility,
                                    max_rre_deg, max_rte, symmetries[k]))
                    score = combine_scores(scores)
                    out.scores.append(score)
                    if detection_scores:
                        out.detection_scores.append(combine_scores(detection_scores))
                    out.confusions += count_confusions(models, frame.gt_poses, owners, frame.gt_visibility,
                                                       min_visibility, published, hit_estimates, max_rte)
                    out.present.append(score.n_gt)
                    out.in_view.append(len(frame.gt_poses) if frame.gt_visibility is None
                                       else int(np.count_nonzero(frame.gt_visibility > 0)))
                    out.hits.append(score.hits)
                else:
                    out.present.append(-1)
                    out.in_view.append(-1)
                    out.hits.append(-1)
                if on_frame is not None:
                    on_frame(index, frame, published)
                bar.update(index + 1)
        finally:
            bar.close()
        for reason, n in bag.skipped.reasons.items():
            skip_reasons[reason] = skip_reasons.get(reason, 0) + n
        out.skipped += bag.skipped.count
    out.skip_reasons = "; ".join(f"{n} x {r}" for r, n in sorted(skip_reasons.items(), key=lambda kv: -kv[1]))
    if not out.frames:
        raise InputError(f"no frame of {bag_path} could be processed ({out.skipped} skipped: "
                         f"{out.skip_reasons or 'the bag has no complete colour + depth + camera_info frame'})")
    return out


def instance_json(inst) -> dict:
    """One instance of poses.json; tracked ones add track_id, state and source."""
    d = {"id": int(inst.id), "object": inst.object, "T": np.round(inst.T, 7).tolist(), "inliers": int(inst.inliers),
         "score": round(float(inst.score), 5)}
    if hasattr(inst, "track_id"):
        d.update({"track_id": int(inst.track_id), "state": inst.state, "source": inst.source})
    return d


def metrics_dict(result: ReplayResult, max_rre_deg: float, max_rte: float, min_visibility: float = 0.0) -> dict:
    from ..metrics import summarize

    summary = summarize(result.scores)
    extra = {}
    if result.identity is not None:
        extra["identity"] = result.identity.summary()
        extra["detection_only"] = summarize(result.detection_scores)
    objects = {}
    for name, scores in result.object_scores.items():
        objects[name] = summarize(scores)
        if result.object_identity is not None:
            objects[name]["identity"] = result.object_identity[name].summary()
    extra["objects"] = objects
    extra["confusions"] = result.confusions
    return {**summary, **extra, "max_rre_deg": max_rre_deg, "max_rte": max_rte, "min_visibility": min_visibility,
            "frames": len(result.frames), "frames_with_ground_truth": len(result.scores),
            "skipped_frames": result.skipped, "deadline_cut_frames": result.deadline_cuts,
            "latency_ms": result.latency_summary(),
            "cpu_ms_per_frame": {q: float(np.percentile(result.cpu_ms, int(q[1:]))) if result.cpu_ms else None
                                 for q in ("p50", "p95", "p99")}}


def format_report(metrics: dict) -> str:
    lat = metrics["latency_ms"]
    rte, rre = metrics["median_rte"], metrics["median_rre_deg"]
    lines = [
        f"frames {metrics['frames']} (with ground truth {metrics['frames_with_ground_truth']}, skipped {metrics['skipped_frames']}); "
        f"instances present {metrics['gt']}, found {metrics['est']}, hits {metrics['hits']} "
        f"(hit: RRE < {metrics['max_rre_deg']} deg and RTE < {metrics['max_rte'] * 100:g} cm; "
        f"present: visible fraction >= {metrics['min_visibility']})",
        f"MHF1 {metrics['MHF1']:.3f}  MHR {metrics['MHR']:.3f}  MHP {metrics['MHP']:.3f}  MF {metrics['MF']:.3f}",
        f"median RTE {'-' if rte is None else f'{rte * 1000:.2f} mm'}  median RRE {'-' if rre is None else f'{rre:.2f} deg'}",
        f"latency per frame: p50 {lat['total']['p50']:.1f} ms  p95 {lat['total']['p95']:.1f} ms  "
        f"p99 {lat['total']['p99']:.1f} ms  (CPU time per frame, all threads: p50 "
        f"{metrics['cpu_ms_per_frame']['p50']:.1f} ms, p99 {metrics['cpu_ms_per_frame']['p99']:.1f} ms; "
        f"load average during the run {metrics.get('load_average', float('nan')):.2f} on {os.cpu_count()} cores; "
        f"shape search cut by its deadline on {metrics.get('deadline_cut_frames', 0)} of {metrics['frames']} frames)",
        "stages (p50 / p95 ms): " + "  ".join(f"{s} {lat[s]['p50']:.1f} / {lat[s]['p95']:.1f}"
                                            for s in ("sift", "matching", "lifting", "ecc", "refinement")
                                            + (("shape",) if "shape" in lat else ())),
    ]
    return "\n".join(lines)

# --------------------------------------------------------------------------- pictures

def draw_overlay(rgb: np.ndarray, intrinsics, models, instances, gt_poses=None, gt_owners=None,
                 workspace=None) -> np.ndarray:
    """BGR picture: each instance's model box projected (green) with its id (and its object's
    name when there are several models); ground truth in grey (``gt_owners``: the model index
    of each ground-truth instance, default all the first's); the ``workspace`` (a
    ``rgbd.workspace.Workspace``, or None) in orange."""
    from ..models.model import ObjectModel
    from ..rgbd.overlay import draw_box

    models = [models] if isinstance(models, ObjectModel) else list(models)
    by_name = {m.name: m for m in models}
    img = np.ascontiguousarray(rgb[:, :, ::-1]).copy()
    if workspace is not None:
        workspace.draw(img, intrinsics, (0, 140, 255))
    if gt_poses is not None:
        owners = np.zeros(len(gt_poses), np.int64) if gt_owners is None else gt_owners
        for T, k in zip(gt_poses, owners):
            if k >= 0 and models[k].T_object_model is not None:
                draw_box(img, T @ models[k].T_object_model, models[k].box_corners(), intrinsics, (160, 160, 160),
                         thickness=1)
    for inst in instances:
        label = str(getattr(inst, "track_id", inst.id))
        draw_box(img, inst.T, by_name[inst.object].box_corners(), intrinsics, (0, 220, 0),
                 label=f"{inst.object} {label}" if len(models) > 1 else label)
    return img


def draw_found_vs_present(present, found, hits, width: int = 900, height: int = 360) -> np.ndarray:
    """BGR line plot per frame: instances present (ground truth), found, and hits."""
    import cv2

    img = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 50, 20, 40, 40
    n = len(found)
    ymax = max([1] + list(present) + list(found))
    def xy(i, v):
        x = left + (i / max(n - 1, 1)) * (width - left - right)
        y = height - bottom - v / ymax * (height - top - bottom)
        return int(round(x)), int(round(y))
    cv2.line(img, (left, height - bottom), (width - right, height - bottom), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, height - bottom), (0, 0, 0), 1)
    for v in range(0, ymax + 1, max(1, ymax // 6)):
        _, y = xy(0, v)
        cv2.line(img, (left - 4, y), (width - right, y), (225, 225, 225), 1)
        cv2.putText(img, str(v), (10, y + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"frame (0..{n - 1})", (width // 2 - 50, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (0, 0, 0), 1, cv2.LINE_AA)
    # Wide lines under narrow ones, so equal series stay visible.
    series = [("present", present, (190, 190, 190), 9), ("found", found, (230, 140, 40), 5), ("hits", hits, (0, 150, 0), 2)]
    for k, (label, vals, colour, thick) in enumerate(series):
        pts = [xy(i, v) for i, v in enumerate(vals) if v >= 0]
        if len(pts) == 1:
            cv2.circle(img, pts[0], thick, colour, -1)
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, colour, thick, cv2.LINE_AA)
        cv2.line(img, (left + 10 + 130 * k, 20), (left + 40 + 130 * k, 20), colour, thick)
        cv2.putText(img, label, (left + 46 + 130 * k, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img


BAG_SUFFIXES = (".db3", ".mcap", ".bag")


def is_bag(path: Path) -> bool:
    """A rosbag2 folder (metadata.yaml or a .db3 / .mcap inside) or a bag file."""
    if path.is_file():
        return path.suffix.lower() in BAG_SUFFIXES
    return path.is_dir() and ((path / "metadata.yaml").is_file()
                              or any(p.suffix.lower() in (".db3", ".mcap") for p in path.iterdir()))


def find_bags(paths) -> list[Path]:
    """The bags named, a folder that is no bag standing for the bags in it (sorted by name)."""
    bags = []
    for text in paths:
        path = Path(text)
        if not path.exists():
            raise InputError(f"bag {path} does not exist")
        if is_bag(path) or not path.is_dir():
            bags.append(path)
            continue
        inside = sorted(p for p in path.iterdir() if is_bag(p))
        if not inside:
            raise InputError(f"{path} is neither a bag nor a folder holding bags (rosbag2 folders, .db3, .mcap or .bag files)")
        bags.extend(inside)
    names = {}
    for bag in bags:
        name = bag.stem if bag.is_file() else bag.name
        if name in names:
            raise InputError(f"bags {names[name]} and {bag} have the same name '{name}' (their output folder); "
                             f"rename one or run them separately")
        names[name] = bag
    return bags


def bag_name(bag: Path) -> str:
    return bag.stem if bag.is_file() else bag.name


class BagReplayer:
    """What one worker of ``mireg offline`` holds: the models (loaded once) and the settings.
    ``run(bag)`` replays one bag and returns its output files as bytes, so that the serial
    run and every Ray worker write the same files (the caller writes them)."""

    def __init__(self, models, config, tracker_config, options: dict):
        self.models, self.config, self.tracker_config, self.options = list(models), config, tracker_config, options

    def run(self, bag) -> dict:
        """{"files": {name: bytes}, "line": the one-line report, "frames": n, "metrics": dict or None}."""
        import cv2

        from ..datasets.rgbd_bag import RGBDBag
        from ..rgbd.workspace import Workspace

        o, models = self.options, self.models
        workspace = Workspace.from_config(self.config.workspace)
        # Pictures are drawn for a few frames spread over the bag; the frame count is known only
        # roughly (colour messages), which is good enough for spreading.
        kwargs = dict(zip(("colour_topic", "depth_topic", "info_topic"), o["topics"])) if o["topics"] else {}
        with RGBDBag(bag, **kwargs) as b:
            n_est = b.num_colour_messages if not o["max_frames"] else min(o["max_frames"], b.num_colour_messages)
            has_gt = b.has_ground_truth
            gt_names = b.instance_objects     # reads the description only: usable after the bag is closed
        picks = set(np.linspace(0, max(n_est - 1, 0), min(o["overlays"], n_est)).round().astype(int).tolist()) \
            if has_gt and o["overlays"] > 0 else set()
        files: dict[str, bytes] = {}

        def on_frame(index, frame, instances):
            if index in picks:
                owners = None if frame.gt_poses is None else ground_truth_owners(models, gt_names(len(frame.gt_poses)))
                img = draw_overlay(frame.rgb, frame.intrinsics, models, instances, frame.gt_poses, owners, workspace)
                files[f"overlay_{index:05d}.png"] = cv2.imencode(".png", img)[1].tobytes()

        result = replay(bag, models, self.config, o["topics"], o["max_rre_deg"], o["max_rte"], o["max_frames"],
                        on_frame=on_frame, progress=o["progress"], min_visibility=o["min_visibility"],
                        tracker_config=self.tracker_config, detect_every=o["detect_every"], gravity=o["gravity"])
        files["poses.json"] = json.dumps({"frames": result.frames}).encode()
        lat = result.latency_summary()["total"]
        line = f"{len(result.frames)} frames, latency p50 {lat['p50']:.1f} ms p95 {lat['p95']:.1f} ms"
        if result.skipped:
            line += f", {result.skipped} skipped ({result.skip_reasons})"
        if result.gravity_frames:
            line += f", {result.gravity_frames} of them with gravity from the IMU"
        if result.deadline_cuts:
            line += f", the shape search's deadline (frontend.shape_deadline_ms) cut {result.deadline_cuts} of them"
        metrics = None
        if result.scores:
            metrics = metrics_dict(result, o["max_rre_deg"], o["max_rte"], o["min_visibility"])
            files["metrics.json"] = json.dumps(metrics, indent=2).encode()
            files["found_vs_present.png"] = cv2.imencode(
                ".png", draw_found_vs_present(result.present, result.found, result.hits))[1].tobytes()
            rte = metrics["median_rte"]
            rre = metrics["median_rre_deg"]
            line += (f"; MHF1 {metrics['MHF1']:.3f} MHR {metrics['MHR']:.3f} MHP {metrics['MHP']:.3f} MF {metrics['MF']:.3f}"
                     f", median RTE {'-' if rte is None else f'{rte * 1000:.1f} mm'}"
                     f" RRE {'-' if rre is None else f'{rre:.2f} deg'}")
            if len(models) > 1:
                line += "; " + ", ".join(f"{name} MHF1 {m['MHF1']:.3f}" for name, m in metrics["objects"].items())
                line += f"; {metrics['confusions']} reported as the wrong object"
            if "identity" in metrics:
                ident = metrics["identity"]
                line += (f"; IDF1 {ident['IDF1']:.3f} ID switches {ident['id_switches']} MOTA {ident['MOTA']:.3f}"
                         f" (detector alone: MHF1 {metrics['detection_only']['MHF1']:.3f})")
        return {"files": files, "line": line, "frames": len(result.frames), "metrics": metrics}


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        (folder / name).write_bytes(data)


def run(args) -> int:
    from ..distributed.ray_runner import connect, run_serial, run_tasks, wants_ray
    from ..distributed.resume import PartsFolder, run_fingerprint
    from ..rgbd.multi_model import load_models

    use_ray = wants_ray(args)
    bags = find_bags(args.bag)
    models = load_models(args.model)
    config = load_config(args.params)
    tracker_config = None if args.no_tracking else load_tracker_config(args.params)
    if args.detect_every < 1:
        raise InputError(f"--detect-every must be at least 1, got {args.detect_every}")
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output {out_dir} exists and is not a directory")
    several = len(bags) > 1
    options = {"topics": args.topics, "max_rre_deg": args.max_rre_deg, "max_rte": args.max_rte,
               "max_frames": args.max_frames, "min_visibility": args.min_visibility, "overlays": args.overlays,
               "detect_every": args.detect_every, "gravity": not args.no_gravity,
               "progress": not args.quiet and not several and not use_ray}     # a bar per bag only for one bag here
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict] = {}
    parts = PartsFolder(out_dir / "parts", run_fingerprint(models, config, tracker_config, **{
        k: v for k, v in options.items() if k != "progress"})) if use_ray else None

    def folder(bag):
        return out_dir / bag_name(bag) if several else out_dir

    def on_result(bag, result):
        write_files(folder(bag), result["files"])
        if parts is not None:
            parts.save(bag_name(bag), result)      # written last: the bag is done
        results[bag_name(bag)] = result
        if several:
            print(f"mireg offline: {bag}: {result['line']}; wrote {folder(bag)}", file=sys.stderr)

    if parts is not None:
        for bag in bags:
            done = parts.load(bag_name(bag))
            if done is not None:
                results[bag_name(bag)] = done
    todo = [str(b) for b in bags if bag_name(b) not in results]
    worker_args = (models, config, tracker_config, options)
    bar = Progress(len(bags), several and not args.quiet, unit="bags")
    try:
        if use_ray:
            workers = connect(args.address, args.workers)
            if results:
                print(f"mireg offline: {len(results)} of {len(bags)} bag(s) done before (in {parts.folder}); "
                      f"running the other {len(todo)} on {min(workers, len(todo))} Ray worker(s)", file=sys.stderr)
            failures = run_tasks(BagReplayer, worker_args, todo, str, lambda b, r: on_result(Path(b), r), workers,
                                 args.retries, bar, done_before=len(results))
        else:
            failures = run_serial(BagReplayer, worker_args, todo, str, lambda b, r: on_result(Path(b), r), bar)
    finally:
        bar.close()
    if not several and not failures:
        print(f"mireg offline: {results[bag_name(bags[0])]['line']}; wrote {out_dir}", file=sys.stderr)
    if several:
        done = [b for b in bags if bag_name(b) in results]
        summary = {"bags": [{"bag": str(b), "output": str(folder(b)), "frames": results[bag_name(b)]["frames"],
                             "line": results[bag_name(b)]["line"], "metrics": results[bag_name(b)]["metrics"]}
                            for b in done],
                   "failed_tasks": [f.as_json() for f in failures]}
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        print(f"mireg offline: {len(done)} of {len(bags)} bag(s), {sum(e['frames'] for e in summary['bags'])} frames; "
              f"wrote {out_dir / 'summary.json'}", file=sys.stderr)
    if failures:
        print(f"mireg offline: error: {len(failures)} bag(s) failed {args.retries + 1} time(s) (first: {failures[0].task}: "
              f"{failures[0].error}" + ("; all in summary.json failed_tasks" if several else "")
              + "); rerun the same command to try them again", file=sys.stderr)
        return 1
    return 0
