"""``mireg bench scale``: throughput of ``mireg bop run`` against the number of Ray workers.

Generates a synthetic BOP set (``--scenes`` scenes of ``--frames`` images, fixed seeds) and
runs it serially, on a local Ray with each of ``--workers`` workers, and on a simulated
cluster of ``--nodes`` Ray nodes on this machine (``ray.cluster_utils.Cluster``, ``--node-cpus``
each). Prints per run the images per second over the run (Ray's start and the models'
building left out), the CPU seconds per image, and whether its poses equal the serial run's.
The shape search runs without its CPU-time budget (``frontend.shape_deadline_ms: 0``): with
it, an image that is a worker's first is cut where a later one is not.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

HELP = "images/s of `mireg bop run` serial, on 1, 2 local Ray workers and a simulated multi-node Ray cluster"


def add_arguments(parser) -> None:
    parser.add_argument("--scenes", type=int, default=6, help="synthetic scenes (default 6)")
    parser.add_argument("--frames", type=int, default=2, help="images per scene (default 2)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="local Ray workers to time (default 1 2)")
    parser.add_argument("--nodes", type=int, default=3, help="nodes of the simulated cluster (default 3; 0 = none)")
    parser.add_argument("--node-cpus", type=int, default=2, help="CPUs each simulated node offers (default 2)")
    parser.add_argument("--seed", type=int, default=100, help="seed of the first scene (default 100)")
    parser.add_argument("--keep", default=None, help="keep the data set and runs in this folder")


def _poses(csv_path):
    from ...datasets.bop import read_results_csv

    return [(r.scene_id, r.im_id, r.obj_id, round(r.score, 6), [round(v, 6) for v in r.T_m.reshape(-1)])
            for r in read_results_csv(csv_path)]


def run(args) -> int:
    import ray

    from ...errors import InputError
    from ...synthetic.scene import make_tabletop_scene, write_scene_bag
    from ..cli import main

    if args.scenes < 1 or args.frames < 1 or min(args.workers) < 1 or args.nodes < 0 or args.node_cpus < 1:
        raise InputError("--scenes, --frames, --workers and --node-cpus must be at least 1, --nodes at least 0")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="mireg_scale_"))
    data = root / "bop"
    if not data.exists():
        t0 = time.perf_counter()
        for k in range(args.scenes):
            scene = make_tabletop_scene(["snack_box"], frames=args.frames, seed=args.seed + k)
            write_scene_bag(scene, root / "bags" / f"scene{k + 1}", imu=False, bop_dir=data, bop_scene=k + 1)
        print(f"bench scale: {args.scenes * args.frames} images generated in {time.perf_counter() - t0:.0f} s "
              f"({data})", file=sys.stderr)
    params = root / "no_deadline.yaml"
    params.write_text("instance_registration:\n  ros__parameters:\n    frontend.shape_deadline_ms: 0.0\n")

    def one(name, extra):
        out = root / name
        t0 = time.perf_counter()
        code = main(["bop", "run", str(data), "-o", str(out), "--quiet", "--params", str(params), "--overlays", "0",
                     "--csv", str(out / "results.csv"), *extra])
        total = time.perf_counter() - t0
        if code != 0:
            raise InputError(f"the {name} run failed (exit {code})")
        summary = json.loads((out / "summary.json").read_text())
        n = len(summary["images"])
        return {"run": name, "workers": summary["run"]["workers"], "images": n,
                "images_per_s": n / summary["run"]["wall_seconds"], "command_s": total,
                "cpu_s_per_image": summary["cpu_seconds_per_image"]["mean"], "poses": _poses(out / "results.csv")}

    rows = [one("serial", [])]
    for w in args.workers:
        rows.append(one(f"ray_{w}", ["--workers", str(w)]))
        ray.shutdown()
    if args.nodes:
        from ray.cluster_utils import Cluster

        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": args.node_cpus, "include_dashboard": False})
        try:
            for _ in range(args.nodes - 1):
                cluster.add_node(num_cpus=args.node_cpus)
            cluster.wait_for_nodes()
            rows.append(one(f"cluster_{args.nodes}x{args.node_cpus}", ["--address", cluster.address]))
        finally:
            ray.shutdown()
            cluster.shutdown()
    serial = rows[0]
    print(f"\nmireg bop run on {serial['images']} synthetic images ({args.scenes} scenes x {args.frames}; "
          f"{len(serial['poses'])} poses serially)")
    print(f"{'run':<16}{'workers':>8}{'images/s':>10}{'x serial':>10}{'command s':>11}{'CPU s/image':>13}  same poses")
    for r in rows:
        print(f"{r['run']:<16}{r['workers']:>8}{r['images_per_s']:>10.3f}{r['images_per_s'] / serial['images_per_s']:>10.2f}"
              f"{r['command_s']:>11.1f}{r['cpu_s_per_image']:>13.3f}  {'yes' if r['poses'] == serial['poses'] else 'NO'}")
    print(f"images/s: over the run, Ray's start and the models' building left out (they are in 'command s'); "
          f"each worker starts its own process, loads the models and warms up inside the run. Load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs: with more runnable processes than cores, workers "
          f"cannot run side by side.")
    return 0 if all(r["poses"] == serial["poses"] for r in rows) else 1
