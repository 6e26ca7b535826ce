"""``mireg bench frames``: accuracy and latency of the per-frame pipeline on a scene bag.

    mireg bench frames [BAG] [--model MODEL.npz | --capture CAPTURE_BAG] [--params FILE.yaml]

Without BAG, a synthetic scene bag (4-12 instances plus distractors, 640x480) and a capture
bag are generated first in a temporary directory; without --model, the model is built from
the capture bag. Prints MHF1, MHR, MHP, MF, median RTE / RRE of the hits, the latency per
frame (p50, p95) and the median of each stage.
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from ..errors import InputError

HELP = "per-frame pipeline on a scene bag: MHF1/MHR/MHP/MF, RTE/RRE, latency by stage"


def add_arguments(parser) -> None:
    parser.add_argument("bag", nargs="?", default=None, help="scene bag with ground truth (default: generate one)")
    parser.add_argument("--model", default=None, help="object model (.npz); default: built from --capture")
    parser.add_argument("--capture", default=None, help="capture bag to build the model from (default: generate one)")
    parser.add_argument("--params", default=None, help="the node's parameter YAML (frontend.* and ecc.* are used)")
    parser.add_argument("--object", default=None, help="object of the generated bags (default: the generator's)")
    parser.add_argument("--frames", type=int, default=30, help="frames of the generated scene bag (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the generated bags (default 0)")
    parser.add_argument("--max-rre-deg", type=float, default=10.0, help="hit: rotation error below this (default 10 deg)")
    parser.add_argument("--max-rte", type=float, default=0.02, help="hit: translation error below this (default 0.02 m)")
    parser.add_argument("--min-visibility", type=float, default=0.25,
                        help="instances less visible than this are not counted as present (default 0.25)")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")


def generate_bags(workdir: Path, object_name, frames: int, seed: int) -> tuple[Path, Path]:
    """A scene bag and a capture bag from the synthetic generator."""
    from ..synthetic import bags as synth_bags

    scene = workdir / "scene"
    capture = workdir / "capture"
    synth_bags.write_scene_bag(scene, **synth_bags_kwargs(object_name, frames, seed))
    synth_bags.write_capture_bag(capture, **synth_bags_kwargs(object_name, None, seed))
    return scene, capture


def synth_bags_kwargs(object_name, frames, seed) -> dict:
    kw = {"seed": seed}
    if object_name:
        kw["object_name"] = object_name
    if frames:
        kw["frames"] = frames
    return kw


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
        f"latency per frame: p50 {lat['total']['p50']:.1f} ms  p95 {lat['total']['p95']:.1f} ms",
        "stages (p50 / p95 ms): " + "  ".join(f"{s} {lat[s]['p50']:.1f} / {lat[s]['p95']:.1f}"
                                            for s in ("sift", "matching", "lifting", "ecc", "refinement")),
    ]
    return "\n".join(lines)


def run(args) -> int:
    from ..rgbd.model import load_model, save_model
    from .build_model import views_from_bag
    from .offline import load_config, metrics_dict, replay

    config = load_config(args.params)
    with tempfile.TemporaryDirectory(prefix="mireg_bench_frames_") as tmp:
        tmp = Path(tmp)
        bag, capture = args.bag, args.capture
        if bag is None or (args.model is None and capture is None):
            print("generating synthetic bags ...", file=sys.stderr)
            gen_scene, gen_capture = generate_bags(tmp, args.object, args.frames, args.seed)
            bag = bag or gen_scene
            capture = capture or gen_capture
        if args.model:
            model = load_model(args.model)
        else:
            from ..rgbd.model import BuildSettings, build_model
            from .build_model import register_view_with_ecc

            views, description = views_from_bag(capture, None, None)
            model = build_model(views, BuildSettings(), name=(description or {}).get("name", ""),
                                register_view=register_view_with_ecc)
            save_model(model, tmp / "model.npz")
            print(f"model: {model.num_keypoints} keypoints from {len(views)} view(s) of {capture}", file=sys.stderr)
        result = replay(bag, model, config, None, args.max_rre_deg, args.max_rte, progress=sys.stderr.isatty(),
                        min_visibility=args.min_visibility)
    if not result.scores:
        raise InputError(f"bag {bag} has no ground truth (/ground_truth/poses); the benchmark needs it")
    metrics = metrics_dict(result, args.max_rre_deg, args.max_rte, args.min_visibility)
    print(format_report(metrics))
    if args.json:
        Path(args.json).write_text(json.dumps(metrics, indent=2))
    return 0
