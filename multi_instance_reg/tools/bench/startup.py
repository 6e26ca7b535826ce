"""mireg bench register-startup: `mireg register` as a user meets it, in fresh processes.

Per size: --processes fresh `mireg register IN.npz -o OUT.npz` processes, each on its own
input (10 instances, the Table-1 construction of `mireg bench core`), with the median of
the `time_s` they write (the registration's own time, first call in the process), of their
wall time and of their CPU time (user + system, all threads: less sensitive than wall time
to other jobs on a shared machine); then one batch process over all of them
(`mireg register A.npz B.npz ... -o DIR/`): median `time_s` per sample, and median CPU time
per sample (the command prints it; steadier than wall time on a loaded machine). The same
with the kernels on one thread (--threads 1) and through numba's JIT cache
(MIREG_KERNELS=jit), for comparison. The floor: a Python process that only imports numpy.
"""
from __future__ import annotations

import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core import native
from ...synthetic.correspondences import make_sized_scene


def add_arguments(parser) -> None:
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 13000])
    parser.add_argument("--processes", type=int, default=7, help="fresh processes (and batch samples) per size")
    parser.add_argument("--outlier-ratio", type=float, default=0.6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-jit", action="store_true", help="skip the comparison with numba's JIT cache")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")


def _timed(command: list[str], env: dict) -> tuple[float, float, str]:
    """(wall s, CPU s of the child, its stdout) of one process, which must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(command, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(command[:4])} ... failed: {p.stderr.strip()[-500:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), p.stdout


def _time_s(path: Path) -> float:
    with np.load(path) as r:
        return float(r["time_s"])


def _measure(inputs: list[Path], out_dir: Path, env: dict, options: list[str]) -> dict:
    register = [sys.executable, "-m", "multi_instance_reg.tools.cli", "register"] + options
    walls, cpus, firsts = [], [], []
    for i, path in enumerate(inputs):
        out = out_dir / f"single_{i}.npz"
        wall, cpu, _ = _timed(register + [str(path), "-o", str(out)], env)
        walls.append(wall)
        cpus.append(cpu)
        firsts.append(_time_s(out))
    batch_dir = out_dir / "batch"
    batch_wall, _, out = _timed(register + [str(p) for p in inputs] + ["-o", f"{batch_dir}/"], env)
    batch = [_time_s(batch_dir / p.name) for p in inputs]
    batch_cpu = [float(m) / 1e3 for m in re.findall(r"\(CPU ([0-9.]+) ms\)", out)]
    return {"first_time_s": float(np.median(firsts)), "process_wall_s": float(np.median(walls)),
            "process_cpu_s": float(np.median(cpus)), "batch_time_s": float(np.median(batch)),
            "batch_cpu_s": float(np.median(batch_cpu)), "batch_time_s_all": batch,
            "batch_wall_s": batch_wall, "first_time_s_all": firsts, "process_wall_s_all": walls}


def run(args) -> int:
    rng = np.random.default_rng(args.seed)
    # (label, environment, options): the default (every core), then one thread, then the JIT.
    modes = [("ahead-of-time" if native.KERNELS == "ahead-of-time" else f"JIT ({native.KERNELS})", {}, [])]
    if native.KERNELS == "ahead-of-time":
        modes.append(("AOT 1 thread", {}, ["--threads", "1"]))
    if not args.no_jit and native.KERNELS == "ahead-of-time":
        modes.append(("JIT cache", {"MIREG_KERNELS": "jit"}, []))
    rows = []
    with tempfile.TemporaryDirectory(prefix="mireg-startup-") as tmp:
        tmp = Path(tmp)
        floor = [_timed([sys.executable, "-c", "import numpy"], dict(os.environ))[0] for _ in range(args.processes)]
        print(f"`mireg register` in fresh processes, {args.processes} per size, median; "
              f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
        print(f"floor: python -c 'import numpy' {np.median(floor) * 1e3:.0f} ms wall")
        print(f"{'N':>6} {'kernels':>14} {'time_s first':>13} {'process wall':>13} {'process CPU':>12} {'batch time_s':>13} {'batch CPU':>10}")
        for n in args.sizes:
            inputs = []
            for i in range(args.processes):
                s = make_sized_scene(rng, n, args.outlier_ratio, 10)
                inputs.append(tmp / f"n{n}_{i}.npz")
                np.savez(inputs[-1], src=s.src, tgt=s.tgt)
            for label, extra, options in modes:
                out_dir = tmp / f"out_{n}_{len(rows)}"
                out_dir.mkdir()
                r = _measure(inputs, out_dir, dict(os.environ, **extra), options)
                rows.append({"N": n, "kernels": label, **r})
                print(f"{n:>6} {label:>14} {r['first_time_s'] * 1e3:>10.1f} ms {r['process_wall_s'] * 1e3:>10.0f} ms "
                      f"{r['process_cpu_s'] * 1e3:>9.0f} ms {r['batch_time_s'] * 1e3:>10.1f} ms {r['batch_cpu_s'] * 1e3:>7.1f} ms")
    print("targets: time_s first <= 100 ms, process <= 500 ms, batch median <= 40 ms")
    if args.json:
        Path(args.json).write_text(json.dumps({"floor_import_numpy_s": float(np.median(floor)), "rows": rows,
                                               "load_average": os.getloadavg()[0]}, indent=2))
    return 0
