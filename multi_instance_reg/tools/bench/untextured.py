"""``mireg bench frames --untextured PRESET``: the shape front end on untextured scenes.

Per preset (pallet, cylinders, bracket, channel, stairs, tee; ``all`` = the first three in turn): the object's mesh is written
and timed into a model (``mireg build-model --mesh``), ``--scenes`` scenes of ``--frames``
frames are generated (seeds seed+200, ...; 4 to 12 instances; ``--sensor``, ``--randomise``:
the depth's sensor profile, as ``mireg synth``'s), plus as many distractor-only scenes (no
instance). Printed: MHF1 (hits over the object's symmetries), median RTE/RRE, the
instances reported on distractor-only frames, latency p50/p95, the model build time.
"""
from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .scenes import INSTANCES_PER_SCENE, write_scenes_bag


def generate_untextured_bag(path: Path, preset: str, scenes: int, frames: int, seed: int, instances=None,
                            depth_noise_correlation_px: float = 0.0, sensor: str = "d455",
                            randomise: bool = False) -> Path:
    from ...synthetic.untextured import make_untextured_scene

    def scene(k):
        n = INSTANCES_PER_SCENE[k % len(INSTANCES_PER_SCENE)] if instances is None else instances
        return make_untextured_scene(preset, n, 3, frames, seed + 200 + k).set_sensor(sensor, randomise)
    return write_scenes_bag(path, (scene(k) for k in range(scenes)), depth_noise_correlation_px)


def run_untextured(args, config) -> int:
    from ...meshes import load_mesh, save_mesh
    from ...models.mesh_model import build_model_from_mesh
    from ...synthetic.objects import get_object, object_mesh
    from ...synthetic.untextured import BENCH_ALL, PRESETS
    from ..offline import format_report, metrics_dict, replay

    presets = list(BENCH_ALL) if args.untextured == "all" else [args.untextured]
    if args.correspondences:
        config = replace(config, frontend=replace(config.frontend, correspondences=args.correspondences))
    results = {}
    for preset in presets:
        name = PRESETS[preset]
        with tempfile.TemporaryDirectory(prefix="mireg_bench_untextured_") as tmp:
            tmp = Path(tmp)
            mesh_path = save_mesh(object_mesh(get_object(name)), tmp / f"{name}.stl", "mm")
            t0 = time.perf_counter()
            model = build_model_from_mesh(load_mesh(mesh_path, "mm"), name)
            build_s = time.perf_counter() - t0
            print(f"[{preset}] generating {args.scenes} scenes + {args.scenes} distractor-only scenes of "
                  f"{args.frames} frames (seed {args.seed}) ...", file=sys.stderr)
            camera = dict(sensor=args.sensor, randomise=args.randomise,
                          depth_noise_correlation_px=args.depth_noise_correlation)
            bag = generate_untextured_bag(tmp / "scenes", preset, args.scenes, args.frames, args.seed, **camera)
            empty = generate_untextured_bag(tmp / "empty", preset, args.scenes, args.frames, args.seed + 50, instances=0,
                                            **camera)
            gravity = not args.no_gravity
            r = replay(bag, model, config, None, args.max_rre_deg, args.max_rte, progress=sys.stderr.isatty(),
                       min_visibility=args.min_visibility, gravity=gravity)
            r_empty = replay(empty, model, config, None, args.max_rre_deg, args.max_rte, progress=sys.stderr.isatty(),
                             gravity=gravity)
        metrics = metrics_dict(r, args.max_rre_deg, args.max_rte, args.min_visibility)
        metrics["load_average"] = float(__import__("os").getloadavg()[0])
        fp = int(sum(r_empty.found))
        metrics.update(model_build_s=build_s, distractor_frames=len(r_empty.frames), distractor_false_positives=fp,
                       gravity_frames=r.gravity_frames + r_empty.gravity_frames,
                       preset=preset, symmetries=model.symmetries.describe() if model.symmetries else "none")
        results[preset] = metrics
        print(f"== untextured {preset} ({name}; symmetries: {metrics['symmetries']}; "
              f"correspondences: {config.frontend.correspondences}; seed {args.seed}; "
              f"sensor {args.sensor}{', randomised' if args.randomise else ''})")
        print(format_report(metrics))
        print(f"distractor-only frames: {len(r_empty.frames)}, instances reported there (false positives): {fp}; "
              f"model from a mesh of {len(load_mesh_vertices(name))} vertices built in {build_s:.2f} s; "
              f"gravity from the IMU on {metrics['gravity_frames']} of {len(r.frames) + len(r_empty.frames)} frames")
    if args.json:
        import json
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


def load_mesh_vertices(name: str) -> np.ndarray:
    from ...synthetic.objects import get_object, object_mesh

    return object_mesh(get_object(name)).vertices
