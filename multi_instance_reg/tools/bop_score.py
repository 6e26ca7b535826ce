"""``mireg bop score RESULTS.csv --dataset DIR [--split test] [-o SCORES.json] [--vsd-thetas 0.3]``: a BOP results
CSV scored as the BOP challenge scores the ViVo task (AR over VSD, MSSD, MSPD) and with the
project's MHR / MHP / MHF1 at 10 deg / 2 cm; the scoring itself is ``evaluation.bop_scoring``.
Prints the figures overall and per object and writes them as JSON (default: beside the CSV,
``<csv name>.scores.json``)."""
from __future__ import annotations

import json
import sys
from pathlib import Path


def add_arguments(p) -> None:
    p.add_argument("results", help="BOP results CSV (scene_id,im_id,obj_id,score,R,t,time), e.g. from `mireg bop run`")
    p.add_argument("-o", "--output", default=None, help="scores JSON (default: RESULTS with .scores.json)")
    p.add_argument("--vsd-delta-mm", type=float, default=15.0,
                   help="VSD visibility tolerance in mm (default 15; BOP uses 5 for ITODD)")
    p.add_argument("--vsd-thetas", default=None, metavar="0.3",
                   help="VSD correctness thresholds, comma-separated (default BOP 2019-2022's 0.05,0.10,...,0.50; "
                        "BOP 2018 used 0.3)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args) -> int:
    from ..datasets.bop import BopDataset, read_results_csv
    from ..errors import InputError
    from ..evaluation.bop_scoring import ScoreSettings, score_results

    if not args.vsd_delta_mm > 0:
        raise InputError(f"--vsd-delta-mm must be positive, got {args.vsd_delta_mm}")
    settings = ScoreSettings(vsd_delta_m=args.vsd_delta_mm / 1000.0)
    if args.vsd_thetas is not None:
        try:
            thetas = tuple(float(v) for v in args.vsd_thetas.split(",") if v.strip())
        except ValueError:
            thetas = ()
        if not thetas or not all(0 < t <= 1 for t in thetas):
            raise InputError(f"--vsd-thetas must be comma-separated numbers in (0, 1] like 0.3, got '{args.vsd_thetas}'")
        settings = ScoreSettings(vsd_delta_m=args.vsd_delta_mm / 1000.0, vsd_thetas=thetas)
    estimates = read_results_csv(args.results)
    dataset = BopDataset(args.dataset, args.split)
    out = Path(args.output) if args.output else Path(args.results).with_suffix(".scores.json")

    def progress(done, total):
        if not args.quiet and (done == total or done % 10 == 0):
            print(f"\rscored {done}/{total} images", end="\n" if done == total else "", file=sys.stderr, flush=True)

    report = score_results(dataset, estimates, settings, progress)
    report["results"] = str(args.results)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")

    print(f"mireg bop score: {Path(args.results).name} on {dataset.name}/{dataset.split}: {report['images']} images, "
          f"{report['targets']} targets ({report['targets_from']}), {report['instances']} instances counted "
          f"(visib_fract >= 0.1), {report['estimates_evaluated']} of {report['estimates_in_file']} estimates evaluated")
    if report["images_skipped"]:
        print(f"  {report['images_skipped']} images skipped: "
              + "; ".join(f"{n} x {r}" for r, n in report["skip_reasons"].items()))
    print(f"  AR {report['AR']:.3f}   AR_VSD {report['AR_VSD']:.3f}   AR_MSSD {report['AR_MSSD']:.3f}   "
          f"AR_MSPD {report['AR_MSPD']:.3f}")
    print(f"  MHR {report['MHR']:.3f}   MHP {report['MHP']:.3f}   MHF1 {report['MHF1']:.3f}   "
          f"(10 deg / 2 cm over symmetries, every estimate of the target images)")
    print(f"  {'object':>6} {'inst':>5} {'AR':>6} {'VSD':>6} {'MSSD':>6} {'MSPD':>6} {'MHR':>6} {'MHP':>6} {'MHF1':>6}")
    for obj, r in report["per_object"].items():
        print(f"  {obj:>6} {r['instances']:>5} {r['AR']:6.3f} {r['AR_VSD']:6.3f} {r['AR_MSSD']:6.3f} "
              f"{r['AR_MSPD']:6.3f} {r['MHR']:6.3f} {r['MHP']:6.3f} {r['MHF1']:6.3f}")
    t = report["average_time_per_image_s"]
    print(f"  method time per image (the CSV's): {'unknown' if t < 0 else f'{t:.3f} s'}; scoring took "
          f"{report['scoring_seconds']:.1f} s; written {out}")
    return 0
