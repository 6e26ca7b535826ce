"""``mireg bench NAME``: benchmarks that print figures (run by ``make bench``), one module each
(``BENCHES`` below), and ``scenes``: the generated bags and models they share."""
from __future__ import annotations

import importlib

# name -> (module, one-line help)
BENCHES = {
    "core": ("multi_instance_reg.tools.bench.core", "median time and peak memory of the ECC core at N = 256 ... 16384"),
    "node": ("multi_instance_reg.tools.bench.node", "the ROS node: end-to-end latency at 30 Hz, latency under overload, memory over a long replay"),
    "frames": ("multi_instance_reg.tools.bench.frames", "per-frame RGB-D pipeline on synthetic scene bags: MHF1, RTE/RRE, latency by stage"),
    "table1": ("multi_instance_reg.tools.bench.table1", "the paper's Table 1: MHR/MHP/MHF1 per outlier band, ECC vs sequential RANSAC"),
    "tracking": ("multi_instance_reg.tools.bench.tracking", "the tracker on generated sequences: IDF1, ID switches, MOTA, MHF1 with and without it, jitter"),
    "register-startup": ("multi_instance_reg.tools.bench.startup", "mireg register in fresh processes: first-call time_s, process wall/CPU time, batch median"),
    "synth": ("multi_instance_reg.tools.bench.synth", "frames/s of the synthetic D455 bag generator at 640x480 and 1280x720"),
    "bop": ("multi_instance_reg.tools.bench.bop", "BOP AR, MHF1 and seconds per image on synthetic BOP sets (tuned and held-out seeds) and the foreign real frames"),
    "scale": ("multi_instance_reg.tools.bench.scale", "images/s of `mireg bop run` serial, on 1, 2 local Ray workers and a simulated multi-node Ray cluster"),
    "bop-score": ("multi_instance_reg.tools.bench.bop_score", "seconds per image of BOP scoring (VSD, MSSD, MSPD, MHF1) on a generated dataset"),
}


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, (module_name, help_text) in BENCHES.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module_name).add_arguments(p)
        p.set_defaults(_bench_module=module_name)


def run(args) -> int:
    return importlib.import_module(args._bench_module).run(args)
