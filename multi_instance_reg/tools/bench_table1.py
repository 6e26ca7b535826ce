"""mireg bench table1: the ECC paper's Table 1 on generated shapes, ECC next to sequential RANSAC.

Both methods see the very same correspondence sets (NOTES.md section 2 protocol). A hit is
RRE < 20 deg and RTE < 0.5 (the paper's thresholds, ModelNet units). MHF1 is the mean of
per-scene F1; MF, the F1 of the mean precision and recall, is printed too.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ..core import ECC
from ..core.baseline import sequential_ransac
from ..metrics import evaluate_scene, summarize
from ..synthetic.correspondences import BANDS, make_band
from ..threads import limit_blas_threads
from .register import add_ecc_arguments, ecc_config_from_args

PAPER_TABLE1 = {"10-50": (96.08, 99.73, 97.03, 0.62), "50-70": (93.99, 99.49, 95.51, 0.55),
                "70-90": (60.39, 94.42, 69.36, 0.50), "90-99": (14.70, 65.20, 22.75, 0.47)}


def add_arguments(parser) -> None:
    parser.add_argument("--samples-per-band", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bands", nargs="+", choices=list(BANDS), default=list(BANDS))
    parser.add_argument("--no-baseline", action="store_true", help="skip sequential RANSAC")
    parser.add_argument("--baseline-max-iters", type=int, default=1000,
                        help="GC-RANSAC iterations per fit in the baseline")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    add_ecc_arguments(parser)


def _evaluate(method, scenes):
    scores, times = [], []
    for s in scenes:
        t0 = time.perf_counter()
        T = method(s)
        times.append(time.perf_counter() - t0)
        scores.append(evaluate_scene(s.T_gt, T, max_rre_deg=20.0, max_rte=0.5))
    summary = summarize(scores)
    summary["median_time_s"] = float(np.median(times))
    return summary


def run(args) -> int:
    limit_blas_threads(1)  # see multi_instance_reg.threads: spinning BLAS threads slow the kernels
    config = ecc_config_from_args(args)
    ecc = ECC(config)
    warm = make_band("50-70", 1, seed=12345)[0]
    ecc.register(warm.src, warm.tgt)  # compile / load numba kernels outside the timing
    methods = {"ECC (this package)": lambda s: ecc.register(s.src, s.tgt).transforms}
    if not args.no_baseline:
        methods["Sequential GC-RANSAC"] = lambda s: sequential_ransac(
            s.src, s.tgt, config.inlier_thresh, min_inliers=config.min_cluster_size,
            max_iters=args.baseline_max_iters)
    print(f"Table 1 protocol: {args.samples_per_band} samples per band, seed {args.seed}, "
          f"hit = RRE < 20 deg and RTE < 0.5; ECC preset '{args.preset}'")
    header = f"{'band':>7}  {'method':<22} {'MHR':>6} {'MHP':>6} {'MHF1':>6} {'MF':>6} {'time (s)':>9}  {'N (median)':>10}"
    print(header)
    print("-" * len(header))
    results = {}
    for band in args.bands:
        scenes = make_band(band, args.samples_per_band, args.seed)
        n_med = int(np.median([len(s.src) for s in scenes]))
        results[band] = {"median_N": n_med}
        for name, method in methods.items():
            r = _evaluate(method, scenes)
            results[band][name] = r
            print(f"{band:>7}  {name:<22} {100 * r['MHR']:6.2f} {100 * r['MHP']:6.2f} {100 * r['MHF1']:6.2f} "
                  f"{100 * r['MF']:6.2f} {r['median_time_s']:9.4f}  {n_med:>10}")
        mhr, mhp, mhf1, t = PAPER_TABLE1[band]
        print(f"{band:>7}  {'ECC paper (6-core CPU)':<22} {mhr:6.2f} {mhp:6.2f} {mhf1:6.2f} {'':>6} {t:9.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": dataclasses.asdict(config), "samples_per_band": args.samples_per_band,
                                               "seed": args.seed, "bands": results}, indent=2))
    return 0
