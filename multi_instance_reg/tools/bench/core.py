"""mireg bench core: median wall time and peak memory of ECC at N = 256, 1024, 4096, 16384.

Inputs follow the Table 1 protocol at a fixed size: 10 instances, 60 % outliers (noise and
distractor shapes), one-to-many correspondences; N > max_correspondences is downsampled as
in the paper. Peak memory is the rise of the process's peak RSS during the calls (VmHWM,
reset through /proc/self/clear_refs), so it includes numpy and numba allocations. The median
CPU time (one thread: the library's default) is the steadier figure on a shared machine.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ...core import ECC
from ...synthetic.correspondences import make_sized_scene
from ...threads import limit_blas_threads
from ..register import add_ecc_arguments, ecc_config_from_args


def add_arguments(parser) -> None:
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024, 4096, 16384])
    parser.add_argument("--repeats", type=int, default=15, help="timed runs per size (distinct scenes)")
    parser.add_argument("--outlier-ratio", type=float, default=0.6)
    parser.add_argument("--instances", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    add_ecc_arguments(parser)


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def _reset_peak_rss() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def run(args) -> int:
    limit_blas_threads(1)  # see multi_instance_reg.threads: spinning BLAS threads slow the kernels
    config = ecc_config_from_args(args)
    ecc = ECC(config)
    rng = np.random.default_rng(args.seed)
    warm = make_sized_scene(rng, 300, args.outlier_ratio, args.instances)
    ecc.register(warm.src, warm.tgt)  # numba compiles (or loads its cache) here, not in the timing
    rows = []
    print(f"ECC core, {args.instances} instances, {args.outlier_ratio:.0%} outliers, "
          f"max_correspondences={config.max_correspondences}, {args.repeats} runs per size")
    print(f"{'N':>7} {'clustered':>9} {'median ms':>10} {'p90 ms':>8} {'CPU ms':>7} {'sample':>7} {'compat':>7} {'cluster':>8} {'refine':>7} {'peak MiB':>9}")
    for n in args.sizes:
        scenes = [make_sized_scene(rng, n, args.outlier_ratio, args.instances) for _ in range(args.repeats)]
        times, cpu_times, stages, peaks = [], [], [], []
        for s in scenes:
            base = _rss_kib("VmRSS")
            can_reset = _reset_peak_rss()
            c0, t0 = time.process_time(), time.perf_counter()
            r = ecc.register(s.src, s.tgt)
            times.append((time.perf_counter() - t0) * 1e3)
            cpu_times.append((time.process_time() - c0) * 1e3)
            stages.append(r.timings_ms)
            if can_reset:
                peaks.append((_rss_kib("VmHWM") - base) / 1024)
        med = lambda k: float(np.median([st[k] for st in stages]))
        row = {"N": n, "clustered": r.n_clustered, "median_ms": float(np.median(times)),
               "p90_ms": float(np.percentile(times, 90)), "cpu_ms": float(np.median(cpu_times)),
               "sampling_ms": med("sampling"),
               "compatibility_ms": med("compatibility"),
               "clustering_ms": med("clustering"), "refinement_ms": med("refinement"),
               "peak_mib": float(np.max(peaks)) if peaks else None}
        rows.append(row)
        peak = f"{row['peak_mib']:9.1f}" if peaks else "      n/a"
        print(f"{n:>7} {row['clustered']:>9} {row['median_ms']:>10.1f} {row['p90_ms']:>8.1f} {row['cpu_ms']:>7.1f} "
              f"{row['sampling_ms']:>7.1f} {row['compatibility_ms']:>7.1f} {row['clustering_ms']:>8.1f} {row['refinement_ms']:>7.1f} {peak}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": dataclasses.asdict(config), "rows": rows}, indent=2))
    return 0
