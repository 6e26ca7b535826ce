"""mireg bench table1: the ECC paper's Table 1 on generated shapes, ECC next to sequential RANSAC.

Both methods see the very same correspondence sets (NOTES.md section 2 protocol). A hit is
RRE < 20 deg and RTE < 0.5 (the paper's thresholds, ModelNet units). MHF1 is the mean of
per-scene F1; MF, the F1 of the mean precision and recall, is printed too.

``--hard`` generates the harder set (partial views, near-neighbour confusion, up to 30
instances; synthetic/correspondences.py). ``--reference DIR`` runs ECC on correspondence
sets made by others instead (DIR/<set>/<band>_<i>.npz with src, tgt, gt, band) and prints,
per set and band, the result of the authors' code on the same samples from
DIR/authors_ecc.json when it is there.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ...core import ECC
from ...core.baseline import sequential_ransac
from ...metrics import evaluate_scene, summarize
from ...errors import InputError
from ...synthetic.correspondences import BANDS, HARD, PLAIN, CorrespondenceScene, make_band
from ...threads import limit_blas_threads
from ..register import add_ecc_arguments, ecc_config_from_args

PAPER_TABLE1 = {"10-50": (96.08, 99.73, 97.03, 0.62), "50-70": (93.99, 99.49, 95.51, 0.55),
                "70-90": (60.39, 94.42, 69.36, 0.50), "90-99": (14.70, 65.20, 22.75, 0.47)}


def add_arguments(parser) -> None:
    parser.add_argument("--samples-per-band", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bands", nargs="+", choices=list(BANDS), default=list(BANDS))
    parser.add_argument("--no-baseline", action="store_true", help="skip sequential RANSAC")
    parser.add_argument("--baseline-max-iters", type=int, default=1000,
                        help="GC-RANSAC iterations per fit in the baseline")
    parser.add_argument("--hard", action="store_true",
                        help="the hard set: partial views (30-100 %%), a quarter of the matches on a near neighbour, up to 30 instances")
    parser.add_argument("--reference", metavar="DIR",
                        help="run on the reference sets in DIR (DIR/<set>/<band>_<i>.npz; DIR/authors_ecc.json for comparison) instead of generated ones")
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


def load_reference(directory) -> dict[str, dict[str, list[tuple[str, CorrespondenceScene]]]]:
    """{set: {band: [(file name, scene)]}} from DIR/<set>/*.npz (sets and files sorted)."""
    root = Path(directory)
    if not root.is_dir():
        raise InputError(f"{root} is not a directory; give the folder that holds the reference sets (e.g. ../shared/reference/core)")
    sets = {}
    for set_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for path in sorted(set_dir.glob("*.npz")):
            with np.load(path, allow_pickle=False) as d:
                if not {"src", "tgt", "gt", "band"} <= set(d.files):
                    raise InputError(f"{path} lacks src, tgt, gt or band; it is not a reference sample")
                scene = CorrespondenceScene(d["src"].astype(np.float64), d["tgt"].astype(np.float64),
                                            d["gt"].astype(np.float64), np.zeros(0, bool), np.zeros(0, np.int64),
                                            float(d["outlier_ratio"]) if "outlier_ratio" in d.files else float("nan"), "")
                band = str(d["band"])
            sets.setdefault(set_dir.name, {}).setdefault(band, []).append((path.name, scene))
    if not sets:
        raise InputError(f"{root} holds no <set>/*.npz reference samples")
    return sets


def run_reference(args, ecc) -> int:
    sets = load_reference(args.reference)
    authors_path = Path(args.reference) / "authors_ecc.json"
    authors = json.loads(authors_path.read_text()) if authors_path.exists() else {}
    print(f"Reference sets in {args.reference}: hit = RRE < 20 deg and RTE < 0.5; ECC preset '{args.preset}'; "
          f"authors' code from {authors_path.name if authors else '(no authors_ecc.json)'}")
    header = f"{'set':>6} {'band':>7} {'n':>3}  {'ECC MHR':>7} {'MHP':>6} {'MHF1':>6} {'MF':>6} {'time (s)':>9}   {'authors MHF1':>12} {'MF':>6} {'time (s)':>9}"
    print(header)
    print("-" * len(header))
    results = {}
    for set_name, bands in sets.items():
        for band, items in sorted(bands.items(), key=lambda kv: list(BANDS).index(kv[0]) if kv[0] in BANDS else 99):
            r = _evaluate(lambda s: ecc.register(s.src, s.tgt).transforms, [scene for _, scene in items])
            a = authors.get(set_name, {}).get("bands", {}).get(band)
            results.setdefault(set_name, {})[band] = {"ECC": r, "authors": a}
            auth = f"{a['MHF1']:12.2f} {a['MF']:6.2f} {a['time_s_median']:9.2f}" if a else f"{'-':>12}"
            print(f"{set_name:>6} {band:>7} {len(items):>3}  {100 * r['MHR']:7.2f} {100 * r['MHP']:6.2f} {100 * r['MHF1']:6.2f} "
                  f"{100 * r['MF']:6.2f} {r['median_time_s']:9.4f}   {auth}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": dataclasses.asdict(ecc.config), "reference": str(args.reference),
                                               "sets": results}, indent=2))
    return 0


def run(args) -> int:
    limit_blas_threads(1)  # see multi_instance_reg.threads: spinning BLAS threads slow the kernels
    config = ecc_config_from_args(args)
    ecc = ECC(config)
    warm = make_band("50-70", 1, seed=12345)[0]
    ecc.register(warm.src, warm.tgt)  # compile / load numba kernels outside the timing
    if args.reference:
        return run_reference(args, ecc)
    difficulty = HARD if args.hard else PLAIN
    methods = {"ECC (this package)": lambda s: ecc.register(s.src, s.tgt).transforms}
    if not args.no_baseline:
        methods["Sequential GC-RANSAC"] = lambda s: sequential_ransac(
            s.src, s.tgt, config.inlier_thresh, min_inliers=config.min_cluster_size,
            max_iters=args.baseline_max_iters)
    print(f"Table 1 protocol{' (hard set)' if args.hard else ''}: {args.samples_per_band} samples per band, seed {args.seed}, "
          f"hit = RRE < 20 deg and RTE < 0.5; ECC preset '{args.preset}'")
    header = f"{'band':>7}  {'method':<22} {'MHR':>6} {'MHP':>6} {'MHF1':>6} {'MF':>6} {'time (s)':>9}  {'N (median)':>10}"
    print(header)
    print("-" * len(header))
    results = {}
    for band in args.bands:
        scenes = make_band(band, args.samples_per_band, args.seed, difficulty)
        n_med = int(np.median([len(s.src) for s in scenes]))
        results[band] = {"median_N": n_med}
        for name, method in methods.items():
            r = _evaluate(method, scenes)
            results[band][name] = r
            print(f"{band:>7}  {name:<22} {100 * r['MHR']:6.2f} {100 * r['MHP']:6.2f} {100 * r['MHF1']:6.2f} "
                  f"{100 * r['MF']:6.2f} {r['median_time_s']:9.4f}  {n_med:>10}")
        if args.hard:
            continue  # the paper has no such set
        mhr, mhp, mhf1, t = PAPER_TABLE1[band]
        print(f"{band:>7}  {'ECC paper (6-core CPU)':<22} {mhr:6.2f} {mhp:6.2f} {mhf1:6.2f} {'':>6} {t:9.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": dataclasses.asdict(config), "hard": args.hard, "samples_per_band": args.samples_per_band,
                                               "seed": args.seed, "bands": results}, indent=2))
    return 0
