"""``mireg bench bop``: BOP's AR and the project's MHF1, with the latency, per data set.

Each synthetic data set is generated in the BOP layout by ``mireg synth ... --bop`` (seeds
``--seed`` and ``--seed`` + 1000: the second is never tuned on), run by ``mireg bop run`` and
scored by ``mireg bop score``, the commands a user runs, in processes of their own. The real
IC-BIN frames in ``../shared/foreign/icbin`` (no ground truth) are run too when present: the
poses found and the time, for the eye to check against the overlays the run leaves.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HELP = "BOP AR (VSD, MSSD, MSPD), MHF1 and seconds per image on synthetic BOP sets and the foreign real frames"

HELD_OUT_OFFSET = 1000
FOREIGN_ICBIN = Path("../shared/foreign/icbin")      # beside the repository, as make bench runs it
# name -> (what it is, mireg synth arguments)
DATASETS = {
    "table": ("snack boxes and cans on a table, hand-held sweep",
              ["scene", "--object", "snack_box", "--object", "can", "--instances", "3"]),
    "bin": ("cans dropped into a bin, seen from above, clutter behind",
            ["scene", "--object", "can", "--layout", "bin", "--motion", "overhead", "--background", "clutter"]),
    "pallet": ("plain cartons on a pallet from above (mesh model, depth only)",
               ["untextured", "--preset", "pallet"]),
}


def add_arguments(parser) -> None:
    parser.add_argument("--datasets", default=",".join(DATASETS),
                        help=f"comma-separated, of {', '.join(DATASETS)} (default all)")
    parser.add_argument("--frames", type=int, default=4, help="images per data set and seed (default 4)")
    parser.add_argument("--seed", type=int, default=0, help=f"tuned seed; seed + {HELD_OUT_OFFSET} is the held-out one")
    parser.add_argument("--foreign", type=Path, default=FOREIGN_ICBIN,
                        help="the real IC-BIN frames (BOP layout, no ground truth); skipped when absent")
    parser.add_argument("--keep", type=Path, default=None, help="keep data sets, runs and overlays here")


def _mireg(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", *args],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mireg {' '.join(args)} failed ({done.returncode}): {done.stderr.strip()[-600:]}")


def _run_and_score(dataset: Path, out: Path, with_truth: bool) -> dict:
    _mireg("bop", "run", str(dataset), "-o", str(out), "--quiet")
    summary = json.loads((out / "summary.json").read_text())
    row = {"images": len(summary["images"]), "poses": sum(e["poses"] for e in summary["images"]),
           "p50_s": summary["seconds_per_image"]["p50"], "max_s": summary["seconds_per_image"]["max"],
           "cpu_s": summary["cpu_seconds_per_image"]["p50"], "cut": summary.get("deadline_cut_images", 0)}
    if with_truth:
        _mireg("bop", "score", summary["csv"], "--dataset", str(dataset), "--quiet", "-o", str(out / "scores.json"))
        scores = json.loads((out / "scores.json").read_text())
        row.update({k: scores[k] for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "MHP", "MHF1")})
    return row


def _line(name: str, seed: str, row: dict) -> str:
    acc = ("   ".join(f"{row[k]:.3f}" for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "MHP", "MHF1"))
           if "AR" in row else "   ".join(["  -  "] * 6))
    return (f"  {name:<8} {seed:<10} {row['images']:>3} {row['poses']:>5}   {acc}   "
            f"{row['p50_s']:5.2f} {row['max_s']:5.2f} {row['cpu_s']:5.2f} {row['cut']:>3}")


def run(args) -> int:
    names = [n.strip() for n in args.datasets.split(",") if n.strip()]
    unknown = [n for n in names if n not in DATASETS]
    if unknown:
        print(f"mireg bench bop: error: unknown data set(s) {', '.join(unknown)} (known: {', '.join(DATASETS)})",
              file=sys.stderr)
        return 2
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="mireg-bench-bop-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"mireg bench bop: {args.frames} images per data set and seed, realistic sensor, scenes randomised; "
          f"seed {args.seed} tuned on, {args.seed + HELD_OUT_OFFSET} held out")
    print("  data     seed       img poses     AR     VSD    MSSD    MSPD     MHP    MHF1    p50 s max s cpu s cut")
    rows = {}
    for name in names:
        what, synth_args = DATASETS[name]
        for seed, label in ((args.seed, f"{args.seed} tuned"), (args.seed + HELD_OUT_OFFSET, f"{args.seed + HELD_OUT_OFFSET} held")):
            base = work / f"{name}_{seed}"
            bop_dir = base / "bop"
            if not bop_dir.exists():
                _mireg("synth", *synth_args, "-o", str(base / "bag"), "--bop", str(bop_dir), "--frames", str(args.frames),
                       "--seed", str(seed), "--sensor", "realistic", "--randomise", "--no-imu")
            rows[(name, seed)] = row = _run_and_score(bop_dir, base / "run", with_truth=True)
            print(_line(name, label, row), flush=True)
    if args.foreign and Path(args.foreign, "camera.json").is_file():
        row = _run_and_score(Path(args.foreign), work / "icbin_run", with_truth=False)
        print(_line("icbin", "real", row) + "   (no ground truth: see the overlays)")
    if rows:
        ar = np.array([r["AR"] for r in rows.values()])
        f1 = np.array([r["MHF1"] for r in rows.values()])
        print(f"  mean over {len(rows)} runs: AR {ar.mean():.3f}, MHF1 {f1.mean():.3f}; "
              f"'cut' = images whose shape search the deadline stopped (frontend.shape_deadline_ms)")
    if args.keep:
        print(f"  data sets, runs and overlays in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0
