"""``mireg bench frames``: accuracy and latency of the per-frame pipeline on scene bags.

    mireg bench frames [BAG ...] [--model MODEL.npz | --capture BAG ...] [--params FILE.yaml]

Without BAGs, a synthetic scene bag is generated first in a temporary directory: ``--scenes``
tabletop scenes with 4 to 12 instances plus distractors at 640x480, ``--frames`` frames each.
Without --model, the model is built from capture bags (default: generated, the object
resting on its bottom, its top and both long sides, so that the model sees every face). Prints MHF1, MHR, MHP, MF, the
median RTE / RRE of the hits, the latency per frame (p50, p95, p99) and each stage's p50 / p95.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from ...errors import InputError
from .scenes import generate_benchmark_bag, generate_capture_bags, model_from_captures

HELP = "per-frame pipeline on scene bags: MHF1/MHR/MHP/MF, RTE/RRE, latency by stage"



def add_arguments(parser) -> None:
    from ...synthetic.sensor import SENSOR_PROFILES
    from ...synthetic.untextured import PRESETS
    UNTEXTURED_CHOICES = tuple(PRESETS) + ("all",)
    parser.add_argument("bags", nargs="*", help="scene bags with ground truth (default: generate --scenes of them)")
    parser.add_argument("--model", default=None, action="append",
                        help="object model (.npz); default: built from --capture. Give it again for several models: "
                             "each alone, then all in one pass, on the same frames (per-object MHF1, confusions, "
                             "latency side by side)")
    parser.add_argument("--capture", nargs="+", default=None, help="capture bag(s) to build the model from (default: generate)")
    parser.add_argument("--params", default=None, help="the node's parameter YAML (frontend.* and ecc.* are used)")
    parser.add_argument("--object", default=None, help="object of the generated bags (default: the generator's)")
    parser.add_argument("--objects", default=None, metavar="A,B,...",
                        help="generate mixed scenes of these objects (--instances-each of each, 3 distractors) and a "
                             "model of each from generated captures; then as with several --model")
    parser.add_argument("--instances-each", type=int, default=3,
                        help="with --objects: instances of each object per scene (default 3)")
    parser.add_argument("--scenes", type=int, default=6, help="generated scenes (default 6; instances 4..12)")
    parser.add_argument("--frames", type=int, default=5, help="frames per generated scene (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the generated bags (default 0)")
    parser.add_argument("--max-rre-deg", type=float, default=10.0, help="hit: rotation error below this (default 10 deg)")
    parser.add_argument("--max-rte", type=float, default=0.02, help="hit: translation error below this (default 0.02 m)")
    parser.add_argument("--min-visibility", type=float, default=0.25,
                        help="instances less visible than this are not counted as present (default 0.25)")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    parser.add_argument("--untextured", default=None, choices=UNTEXTURED_CHOICES,
                        help="benchmark the shape front end on untextured generated scenes instead "
                             "(model from the object's mesh; also distractor-only scenes and the model build time; "
                             "all: pallet, cylinders and bracket)")
    parser.add_argument("--sensor", choices=tuple(SENSOR_PROFILES), default="d455",
                        help="--untextured: the generated depth's sensor profile (d455, the default, or realistic: "
                             "as mireg synth's)")
    parser.add_argument("--randomise", action="store_true",
                        help="--untextured: each figure of the sensor profile drawn per scene seed from a range")
    parser.add_argument("--depth-noise-correlation", type=float, default=0.0, metavar="PX",
                        help="generated scene bags: depth noise shared by neighbouring pixels over about PX pixels, "
                             "as a stereo matcher's window makes it (default 0: independent per pixel; the "
                             "captures the model is built from keep the default)")
    parser.add_argument("--correspondences", default=None, choices=("auto", "sift", "shape", "both"),
                        help="override frontend.correspondences (shape/both: the model is built from the object's mesh plus the capture bags)")
    parser.add_argument("--ignore-ground-truth", action="store_true",
                        help="build the model as from a real capture, without the captures' object poses: views "
                             "registered to each other by texture (shape/both: placed on the mesh by shape); the "
                             "first view's ground truth relates the model's frame to the object's for scoring only")
    parser.add_argument("--no-gravity", action="store_true",
                        help="ignore the accelerometer the bags carry (the direction of gravity per frame): as "
                             "before it existed, for A/B; with given BAGs without it, the same anyway")


def model_from_mesh_and_captures(object_name, captures, ignore_ground_truth: bool = False) -> "object":
    """Shape from the generated object's mesh, texture from the capture bags: what
    ``build-model --mesh`` with capture bags makes (placed by their ground truth, which is in
    the mesh frame, or with ``ignore_ground_truth`` by shape)."""
    from ...models.capture_alignment import place_capture_keypoints
    from ...models.mesh_model import add_capture_keypoints, build_model_from_mesh
    from ...models.model import BuildSettings
    from ...synthetic.objects import get_object, object_mesh
    from ...synthetic.scene import DEFAULT_OBJECT
    from ..build_model import views_from_bag

    spec = get_object(object_name or DEFAULT_OBJECT)
    mesh = object_mesh(spec)
    model = build_model_from_mesh(mesh, spec.name)
    views = []
    for bag in captures:
        views += views_from_bag(bag, None, None)[0]
    if not ignore_ground_truth:
        return add_capture_keypoints(model, views, BuildSettings())
    placed = place_capture_keypoints(model, mesh, views, BuildSettings())
    print(f"captures placed by shape: the object found in {placed.found} of {len(views)} views; {placed.placed} "
          f"placed, {placed.by_texture_alone} of them by their texture alone", file=sys.stderr)
    return model


def run_models(args, bags, models, config) -> int:
    """Each model alone, then all of them in one pass, on the same frames: per-object MHF1,
    confusions and latency side by side (issue 11's targets)."""
    from ...rgbd.multi_model import check_model_names
    from ..offline import metrics_dict

    check_model_names(models)
    runs = [[m] for m in models] + [models]
    figures = []
    for run_models_ in runs:
        total = _replay_all(args, bags, run_models_, config)
        figures.append(metrics_dict(total, args.max_rre_deg, args.max_rte, args.min_visibility))
    alone, together = figures[:-1], figures[-1]
    print(f"frames {together['frames']}, models {', '.join(m.name for m in models)}; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'object':<14} {'MHF1 alone':>10} {'MHF1 all':>9} {'present':>8} {'found':>6} {'hits':>5}  "
          f"{'p50 alone':>9}")
    for m, f in zip(models, alone):
        o = together["objects"][m.name]
        print(f"{m.name:<14} {f['MHF1']:>10.3f} {o['MHF1']:>9.3f} {o['gt']:>8} {o['est']:>6} {o['hits']:>5}  "
              f"{f['latency_ms']['total']['p50']:>7.1f} ms")
    p50_all = together["latency_ms"]["total"]["p50"]
    p50_one = [f["latency_ms"]["total"]["p50"] for f in alone]
    print(f"all {len(models)} models in one pass: p50 {p50_all:.1f} ms, p95 {together['latency_ms']['total']['p95']:.1f} ms"
          f" = {p50_all / max(p50_one):.2f} x the slowest single model, {p50_all / min(p50_one):.2f} x the fastest; "
          f"stages p50: " + "  ".join(f"{s} {together['latency_ms'][s]['p50']:.1f}"
                                      for s in ("sift", "matching", "lifting", "ecc", "refinement")))
    print(f"reported as the wrong object: {together['confusions']} (alone: "
          f"{', '.join(str(f['confusions']) for f in alone)})")
    side = side_by_side_latency(bags, models, config)
    print(f"side by side, frame by frame ({side['frames']} frames, each through {models[0].name} alone and all "
          f"{len(models)} in turn, {side['repeats']} times, its median): p50 {side['one_p50']:.1f} -> "
          f"{side['all_p50']:.1f} ms = {side['ratio']:.2f} x; "
          f"load average {os.getloadavg()[0]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"alone": dict(zip((m.name for m in models), alone)),
                                               "together": together, "side_by_side": side}, indent=2))
    return 0


def side_by_side_latency(bags, models, config, repeats: int = 3) -> dict:
    """p50 latency of the first model alone and of all models: each frame through both in
    turn, ``repeats`` times (which goes first alternating), so that a host whose speed
    drifts slows both alike; per frame the median of its runs, then the median over frames
    (a single run of a frame moved the ratio by up to 0.1 on the shared 2-core host)."""
    import time

    from ...datasets.rgbd_bag import RGBDBag
    from ...rgbd.multi_model import MultiModelRegistration

    one, every = MultiModelRegistration(models[:1], config), MultiModelRegistration(models, config)
    one.warm_up()
    times = {"one": [], "all": []}
    for bag in bags:
        with RGBDBag(bag) as frames:
            for f in frames:
                runs = {"one": [], "all": []}
                for r in range(repeats):
                    pair = (("one", one), ("all", every))
                    for key, reg in (pair if r % 2 == 0 else pair[::-1]):
                        t0 = time.perf_counter()
                        reg.register_frame(f.rgb, f.depth_m, f.intrinsics, f.gravity)
                        runs[key].append((time.perf_counter() - t0) * 1e3)
                for key in times:
                    times[key].append(float(np.median(runs[key])))
    p50 = {k: float(np.median(v)) for k, v in times.items()}
    return {"frames": len(times["one"]), "repeats": repeats, "one_p50": p50["one"], "all_p50": p50["all"],
            "ratio": p50["all"] / p50["one"]}


def _replay_all(args, bags, models, config):
    from ..offline import ReplayResult, replay

    total = ReplayResult()
    for bag in bags:
        r = replay(bag, models, config, None, args.max_rre_deg, args.max_rte, progress=sys.stderr.isatty(),
                   min_visibility=args.min_visibility, gravity=not args.no_gravity)
        for name in ("frames", "timings", "cpu_ms", "scores", "present", "found", "hits"):
            getattr(total, name).extend(getattr(r, name))
        for name, scores in r.object_scores.items():
            total.object_scores.setdefault(name, []).extend(scores)
        total.skipped += r.skipped
        total.confusions += r.confusions
        total.deadline_cuts += r.deadline_cuts
    return total


def run(args) -> int:
    from ...models.model import load_model
    from ..offline import ReplayResult, format_report, load_config, metrics_dict, replay

    config = load_config(args.params)
    if args.untextured:
        from .untextured import run_untextured

        return run_untextured(args, config)
    if args.correspondences:
        from dataclasses import replace

        config = replace(config, frontend=replace(config.frontend, correspondences=args.correspondences))
    with tempfile.TemporaryDirectory(prefix="mireg_bench_frames_") as tmp:
        tmp = Path(tmp)
        bags = list(args.bags)
        if args.objects:
            objects = [o.strip() for o in args.objects.split(",") if o.strip()]
            if not bags:
                print(f"generating {args.scenes} mixed scenes of {args.frames} frames ...", file=sys.stderr)
                bags = [generate_benchmark_bag(tmp / "scenes", objects, args.scenes, args.frames, args.seed,
                                               instances_each=args.instances_each,
                                               depth_noise_correlation_px=args.depth_noise_correlation)]
            models = []
            for obj in objects:
                print(f"generating capture bags of {obj} and its model ...", file=sys.stderr)
                models.append(model_from_captures(generate_capture_bags(tmp / obj, obj, args.seed), args.ignore_ground_truth))
            return run_models(args, bags, models, config)
        if args.model and len(args.model) > 1:
            if not bags:
                raise InputError("several --model need scene bags (or use --objects to generate mixed scenes)")
            return run_models(args, bags, [load_model(p) for p in args.model], config)
        if not bags:
            print(f"generating {args.scenes} scenes of {args.frames} frames ...", file=sys.stderr)
            bags = [generate_benchmark_bag(tmp / "scenes", args.object, args.scenes, args.frames, args.seed,
                                           depth_noise_correlation_px=args.depth_noise_correlation)]
        if args.model:
            model = load_model(args.model[0])
        else:
            captures = args.capture
            if not captures:
                print("generating capture bags (4 resting poses) ...", file=sys.stderr)
                captures = generate_capture_bags(tmp, args.object, args.seed)
            how = "without their ground truth" if args.ignore_ground_truth else "placed by their ground truth"
            if args.correspondences in ("shape", "both"):
                model = model_from_mesh_and_captures(args.object, captures, args.ignore_ground_truth)
                print(f"model: the object's mesh and {model.num_keypoints} keypoints from {len(captures)} capture "
                      f"bag(s) {how}", file=sys.stderr)
            else:
                model = model_from_captures(captures, args.ignore_ground_truth)
                print(f"model: {model.num_keypoints} keypoints from {len(captures)} capture bag(s) {how}",
                      file=sys.stderr)
        total = ReplayResult()
        load = []
        for bag in bags:
            r = replay(bag, model, config, None, args.max_rre_deg, args.max_rte, progress=sys.stderr.isatty(),
                       min_visibility=args.min_visibility, gravity=not args.no_gravity)
            for name in ("frames", "timings", "cpu_ms", "scores", "present", "found", "hits"):
                getattr(total, name).extend(getattr(r, name))
            total.skipped += r.skipped
            total.deadline_cuts += r.deadline_cuts
            load.append(os.getloadavg()[0])
    if not total.scores:
        raise InputError("the scene bags have no ground truth (/ground_truth/poses); the benchmark needs it")
    metrics = metrics_dict(total, args.max_rre_deg, args.max_rte, args.min_visibility)
    # Other processes on a shared machine slow every stage: say how busy it was.
    metrics["load_average"] = float(np.mean(load)) if load else float("nan")
    print(format_report(metrics))
    if args.json:
        Path(args.json).write_text(json.dumps(metrics, indent=2))
    return 0
