"""mireg register IN.npz -o OUT.npz: multi-instance registration of one correspondence set.
mireg register A.npz B.npz ... -o OUTDIR/: several in one process (OUTDIR/A.npz, ...), so that
the kernels are loaded once.

Public contract. IN holds ``src`` (N,3) and ``tgt`` (N,3), row i one correspondence.
OUT holds ``T`` (M,4,4) float64 source->target sorted by inlier count (descending),
``labels`` (N,) int64 (index into T, -1 = outlier), ``inlier_counts`` (M,) int64, ``time_s``
(float64 scalar); also, as extensions, ``scores`` (M,) and ``n_invalid`` (rows dropped for
NaN/inf).
"""
from __future__ import annotations

import argparse
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from ..core import ECC, ECCConfig, native
from ..errors import InputError
from ..files import require_npz_archive
from ..threads import limit_blas_threads
from ..params import param_specs, read_params_yaml, with_overrides

PRESETS = {"paper": ECCConfig.paper, "modelnet": ECCConfig.modelnet, "metric": ECCConfig.metric}


def add_ecc_arguments(parser: argparse.ArgumentParser, default_preset: str = "modelnet") -> None:
    """--preset, --params FILE and one --flag per ECC parameter (e.g. --inlier-thresh).

    A parameter whose flag the tool already has (benches have their own --seed for the
    data) is left to the preset and the parameter file."""
    parser.add_argument("--preset", choices=sorted(PRESETS), default=default_preset,
                        help=f"parameter set to start from (default {default_preset}: "
                             "paper = the paper's settings, modelnet = synthetic units, metric = RGB-D metres)")
    parser.add_argument("--params", metavar="FILE.yaml",
                        help="ROS 2 parameter file; its ecc.* entries override the preset")
    taken = set(parser._option_string_actions)
    for spec in param_specs(ECCConfig()):
        if "--" + spec.name.replace("_", "-") in taken:
            continue
        parser.add_argument("--" + spec.name.replace("_", "-"), dest="ecc_" + spec.name,
                            type=spec.type, default=None, metavar=spec.type.__name__.upper(),
                            help=f"{spec.description} (paper: {spec.default})")


def ecc_config_from_args(args) -> ECCConfig:
    config = PRESETS[args.preset]()
    if args.params:
        yaml_params = read_params_yaml(args.params)
        ecc_params = {k[len("ecc."):]: v for k, v in yaml_params.items() if k.startswith("ecc.")}
        config = with_overrides(config, ecc_params)
    overrides = {spec.name: getattr(args, "ecc_" + spec.name) for spec in param_specs(config)
                 if getattr(args, "ecc_" + spec.name, None) is not None}
    return with_overrides(config, overrides)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="IN.npz", nargs="+",
                        help="npz with src (N,3) and tgt (N,3); several: each is written to OUTDIR/<its name>")
    parser.add_argument("-o", "--output", metavar="OUT.npz|OUTDIR/", required=True,
                        help="output file for one input; a directory (existing, or ending in /) for several")
    parser.add_argument("--threads", type=int, default=0, metavar="N",
                        help="threads for each registration's row-parallel kernels (default 0 = every core "
                             "this process may use; 1 = serial; results are the same)")
    add_ecc_arguments(parser)


def load_correspondences(path) -> tuple[np.ndarray, np.ndarray]:
    require_npz_archive(path, "correspondence file", "write it with numpy.savez(FILE, src=(N, 3) array, tgt=(N, 3) array)")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("src", "tgt") if k not in data.files]
            if missing:
                raise InputError(f"{path} has no array(s) {', '.join(missing)}; it needs src (N,3) and tgt (N,3)")
            src, tgt = data["src"], data["tgt"]
    except FileNotFoundError:
        raise InputError(f"{path} does not exist") from None
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path} is not a readable .npz file ({exc})") from None
    for name, a in (("src", src), ("tgt", tgt)):
        if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.number):
            raise InputError(f"{path}: {name} must be a numeric (N, 3) array, got {a.dtype} {a.shape}")
    if len(src) != len(tgt):
        raise InputError(f"{path}: src has {len(src)} rows but tgt has {len(tgt)}")
    return src.astype(np.float64), tgt.astype(np.float64)


def output_paths(inputs: list[str], output: str) -> list[Path]:
    """Where each input's result goes: the file itself for one input (the original form),
    OUTDIR/<input's name> when the output is a directory."""
    out = Path(output)
    if len(inputs) == 1 and not (output.endswith(("/", os.sep)) or out.is_dir()):
        return [out]
    if out.exists() and not out.is_dir():
        raise InputError(f"{output} is a file; with several inputs -o must name a directory (e.g. -o out/)")
    names = [Path(p).name for p in inputs]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InputError(f"several inputs are named {repeated[0]}; their results would overwrite each other in {output}")
    out.mkdir(parents=True, exist_ok=True)
    return [out / n for n in names]


def save_result(path, result, elapsed: float) -> None:
    # Through a file handle so the name is kept exactly (np.savez would append .npz).
    with open(path, "wb") as fh:
        np.savez(fh, T=result.transforms.astype(np.float64), labels=result.labels.astype(np.int64),
                 inlier_counts=result.inlier_counts.astype(np.int64), time_s=np.float64(elapsed),
                 scores=result.scores.astype(np.float64), n_invalid=np.int64(result.n_invalid))


def run(args) -> int:
    limit_blas_threads(1)  # see multi_instance_reg.threads: spinning BLAS threads slow the kernels
    if args.threads < 0:
        raise InputError(f"--threads must be 0 (every core) or more, got {args.threads}")
    native.set_threads(args.threads)
    config = ecc_config_from_args(args)
    outputs = output_paths(args.input, args.output)
    ecc = ECC(config)
    for path, out in zip(args.input, outputs):
        src, tgt = load_correspondences(path)
        c0, t0 = time.process_time(), time.perf_counter()
        result = ecc.register(src, tgt)
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
        save_result(out, result, elapsed)
        # The CPU time too: on a shared machine it varies far less than the wall time.
        print(f"{len(result)} instance(s) from {len(src)} correspondences "
              f"({result.n_invalid} invalid rows dropped) in {elapsed * 1e3:.1f} ms (CPU {cpu * 1e3:.1f} ms) -> {out}")
    return 0
