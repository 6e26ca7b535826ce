"""The ECC core on one generated scene: what it found against the truth.

Run as ``python -m multi_instance_reg.tools.demo_core [--band 50-70] [--seed 1]``.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ..core import ECC, ECCConfig
from ..metrics import evaluate_scene
from ..synthetic.correspondences import BANDS, make_band
from ..threads import limit_blas_threads


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--band", choices=list(BANDS), default="50-70")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    limit_blas_threads(1)  # see multi_instance_reg.threads
    scene = make_band(args.band, 1, args.seed)[0]
    ecc = ECC(ECCConfig.modelnet())
    ecc.register(scene.src[:300], scene.tgt[:300])  # load the compiled kernels first
    result = ecc.register(scene.src, scene.tgt)
    score = evaluate_scene(scene.T_gt, result.transforms)
    print(f"Scene: {len(scene.T_gt)} instances of '{scene.shape}', {len(scene.src)} correspondences, "
          f"{scene.outlier_ratio:.0%} outliers (band {args.band})")
    print(f"ECC found {len(result)} instance(s) in {result.timings_ms['total']:.1f} ms "
          f"(clustered {result.n_clustered} sampled correspondences)")
    matched = dict((e, g) for g, e in score.pairs)
    rre = dict((e, r) for (g, e), r in zip(score.pairs, score.rre_deg))
    rte = dict((e, t) for (g, e), t in zip(score.pairs, score.rte))
    for m in range(len(result)):
        if m in matched:
            print(f"  #{m:2d} inliers {result.inlier_counts[m]:4d} -> truth #{matched[m]:2d}: "
                  f"RRE {rre[m]:5.2f} deg, RTE {rte[m]:.3f}")
        else:
            print(f"  #{m:2d} inliers {result.inlier_counts[m]:4d} -> no ground-truth instance")
    hit_truth = {g for (g, _), h in zip(score.pairs, score.hit) if h}
    missed = sorted(set(range(len(scene.T_gt))) - hit_truth)
    print(f"Hits {score.hits}/{len(scene.T_gt)}: recall {score.recall:.2f}, precision {score.precision:.2f}, "
          f"F1 {score.f1:.2f}" + (f"; missed truth #{missed}" if missed else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
