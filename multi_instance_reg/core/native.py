"""The core's compiled loops: built ahead of time by ``make install``, else numba's JIT.

Each stage module marks its loops with ``@compiled(...)`` instead of ``@numba.njit(...)``:
- ``@compiled("RET(ARGS)", ...)``: an entry point called from Python, with its numba
  signature (arrays as ``f4[:, ::1]``, C-contiguous);
- ``@compiled(...)`` without a signature: a helper called only from other compiled loops.

Why: a fresh process that loads numba's cached kernels pays, before the first registration
finishes, for importing numba (~0.3 s), initialising its compiler (~0.4-0.7 s: the first
cached kernel loaded) and loading each kernel (10-40 ms each, 10 entry points), 1-2 s in all
on this 2-core machine; the registration itself takes 30-100 ms. ``make install`` therefore
compiles the entry points once into an extension module (``_kernels_aot*.so``, numba's
ahead-of-time compiler, for this machine's CPU): importing it takes under a millisecond and
does not import numba at all. Without it (a clone without ``make install``, a colcon build,
or after a kernel's source changed) the same functions run through numba's JIT with
``cache=True`` as before: the first call in a fresh checkout compiles them (about 40 s),
later processes load the cache from ``__pycache__`` next to the sources (or
``NUMBA_CACHE_DIR``).

Ahead-of-time code is serial (numba compiles ``prange`` loops ahead of time as plain loops),
but it releases the GIL: the row-parallel kernels take a range [lo, hi) of their rows and
``split_rows`` runs the parts on this process's cores from Python threads (the main thread
takes the first part). Threads that wait in ``Future.result`` sleep, unlike OpenMP's
spinning workers, which on this shared 2-core machine made the JIT's parallel kernels 2-30x
slower when other jobs held the cores. Through the JIT, the kernels' own ``prange`` does it
and ``split_rows`` makes one call. Threads are off (1) unless a tool calls ``set_threads``
(``mireg register --threads``); ``MIREG_KERNELS=jit`` forces the JIT (tests compare both).

Build: ``python -m multi_instance_reg.core.build_native`` (run by ``make install``).
"""
from __future__ import annotations

import importlib
import os
import threading
import zlib
from pathlib import Path

import numpy as np

# Modules whose @compiled loops are built ahead of time; their sources (and this file)
# make the hash that tells a current build from a stale one.
KERNEL_MODULES = ("clustering", "compatibility", "refinement", "sampling")
_AOT_NAME = "_kernels_aot"
_HERE = Path(__file__).resolve().parent

# (module, name, signature, njit options) of every entry point, in definition order.
ENTRY_POINTS: list[tuple[str, str, str, dict]] = []


def source_hash() -> int:
    """A 62-bit checksum of the kernel modules' sources and this file's (CRC-32 and length:
    cheap enough to check at every start; a numba upgrade reinstalls, which rebuilds)."""
    crc, size = 0, 0
    for name in KERNEL_MODULES + ("native",):
        data = (_HERE / f"{name}.py").read_bytes()
        crc, size = zlib.crc32(data, crc), size + len(data)
    return (crc << 30) | (size & (2**30 - 1))


def _load_aot():
    """The ahead-of-time module if it is built and matches the sources, else None (and why)."""
    if os.environ.get("MIREG_KERNELS", "auto") in ("jit", "build"):
        return None, "MIREG_KERNELS=" + os.environ["MIREG_KERNELS"]
    try:
        module = importlib.import_module(f"{__package__}.{_AOT_NAME}")
    except ImportError:
        return None, "not built (run make install)"
    if module.source_hash() != source_hash():
        return None, "stale: kernel sources changed since it was built (run make install)"
    return module, "ahead-of-time"


_BUILDING = os.environ.get("MIREG_KERNELS") == "build"
_AOT, KERNELS = _load_aot()   # KERNELS: which kernels this process runs, said in benches
if _AOT is None:
    from numba import prange  # noqa: F401  (the stage modules' parallel loops)
else:
    prange = range  # the Python bodies never run: the compiled module has them


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


# Threads for split_rows: 1 unless a tool asks for more (set_threads). The RGB-D pipeline
# keeps 1: its ECC shares the cores with SIFT's threads and the node's other work.
THREADS = 1
_pool = None
_pool_lock = threading.Lock()


def set_threads(count: int) -> int:
    """Run the ahead-of-time kernels' row ranges on ``count`` threads (0 = every available
    core); returns the count in effect (always 1 through the JIT, whose prange threads)."""
    global THREADS, _pool
    count = available_cores() if count <= 0 else int(count)
    with _pool_lock:
        if _AOT is None:
            count = 1
        if count != THREADS and _pool is not None:
            _pool.shutdown(wait=True)
            _pool = None
        THREADS = count
    return THREADS


def _executor():
    global _pool
    with _pool_lock:
        if _pool is None:
            from concurrent.futures import ThreadPoolExecutor
            _pool = ThreadPoolExecutor(THREADS - 1, thread_name_prefix="mireg-core")
        return _pool


def split_rows(kernel, bounds, *args) -> None:
    """kernel(*args, lo, hi) for every part [bounds[k], bounds[k + 1]), the parts on
    THREADS threads at once (ahead-of-time kernels, which release the GIL); the kernel
    writes its rows into arrays among args. One call over everything with the JIT."""
    bounds = [int(b) for b in bounds]
    if THREADS == 1 or len(bounds) <= 2:
        kernel(*args, bounds[0], bounds[-1])
        return
    futures = [_executor().submit(kernel, *args, lo, hi) for lo, hi in zip(bounds[1:-1], bounds[2:]) if hi > lo]
    try:
        kernel(*args, bounds[0], bounds[1])
    finally:
        for f in futures:
            f.result()


def row_parts(n: int, min_rows: int, work: str = "even") -> list[int]:
    """Bounds of THREADS parts of rows 0..n with about equal work: ``even`` (the same per
    row) or ``growing`` (row i costs ~i, as a lower triangle); one part below 2 x min_rows."""
    parts = min(THREADS, n // max(min_rows, 1))
    if parts <= 1:
        return [0, n]
    if work == "growing":
        return [int(round(n * np.sqrt(k / parts))) for k in range(parts + 1)]
    return [n * k // parts for k in range(parts + 1)]


def _split_args(signature: str) -> list[str]:
    """The argument types of a numba signature "RET(A, B, ...)", split at top-level commas."""
    depth, end = 0, len(signature) - 1
    assert signature.endswith(")"), signature
    for start in range(end, -1, -1):
        c = signature[start]
        depth += c in ")]"
        depth -= c in "(["
        if depth == 0:
            break
    args, depth, current = [], 0, ""
    for c in signature[start + 1:end]:
        depth += (c in "([") - (c in ")]")
        if c == "," and depth == 0:
            args.append(current.strip())
            current = ""
        else:
            current += c
    return args + ([current.strip()] if current.strip() else [])


_DTYPES = {"f4": np.float32, "f8": np.float64, "i4": np.int32, "i8": np.int64, "b1": np.bool_}


def _arg_checker(name: str, spec: str):
    """A function that returns the argument as the compiled code needs it or raises: the
    ahead-of-time code reads memory as declared, so a wrong dtype or layout would crash."""
    code = spec.split("[")[0]
    dtype = np.dtype(_DTYPES[code])
    if "[" not in spec:
        cast = {"f": float, "i": int, "b": bool}[code[0]]
        return lambda a: cast(a)
    ndim = spec[spec.index("["):].count(",") + 1

    def check(a):
        if not (isinstance(a, np.ndarray) and a.dtype == dtype and a.ndim == ndim and a.flags.c_contiguous):
            got = f"{a.dtype} {a.ndim}-d{'' if a.flags.c_contiguous else ' non-contiguous'}" if isinstance(a, np.ndarray) else type(a).__name__
            raise TypeError(f"{name}: argument needs a C-contiguous {ndim}-d {dtype} array ({spec}), got {got}")
        return a

    return check


def _njit(function, options):
    import numba

    if _BUILDING:  # ahead of time: serial (split_rows threads it), nothing written to the JIT's cache
        return numba.njit(**{k: v for k, v in options.items() if k != "parallel"})(function)
    return numba.njit(cache=True, **options)(function)


def compiled(signature: str | None = None, **options):
    """Decorator for a numba-compilable function; see the module docstring."""
    def decorate(function):
        module = function.__module__.rsplit(".", 1)[-1]
        if signature is None:  # a helper: only other compiled code calls it
            return function if _AOT is not None else _njit(function, options)
        ENTRY_POINTS.append((module, function.__name__, signature, options))
        if _AOT is not None:
            implementation = getattr(_AOT, f"{module}__{function.__name__}")
        else:
            implementation = _njit(function, options)
        checks = [_arg_checker(function.__name__, s) for s in _split_args(signature)]

        def entry(*args):
            return implementation(*[check(a) for check, a in zip(checks, args)])

        entry.__name__, entry.__doc__, entry.__wrapped__ = function.__name__, function.__doc__, function
        entry.implementation = implementation
        return entry
    return decorate


def build(output_dir: Path = _HERE) -> Path:
    """Compile every entry point ahead of time into ``_kernels_aot*.so`` (needs a C compiler)."""
    if not _BUILDING:
        raise RuntimeError("build() must run with MIREG_KERNELS=build (python -m multi_instance_reg.core.build_native does)")
    import inspect
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # numba.pycc is marked for deprecation; the pinned numba has it
        from numba.pycc import CC
        import numba.pycc.compiler as pycc_compiler

    class _ReleasingGil(pycc_compiler.Flags):
        """pycc's wrappers hold the GIL by default; these release it around each call, so
        that split_rows's threads run at once (the kernels touch no Python object)."""
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    pycc_compiler.Flags = _ReleasingGil

    for name in KERNEL_MODULES:
        importlib.import_module(f"{__package__}.{name}")
    cc = CC(_AOT_NAME)
    cc.output_dir = str(output_dir)
    cc.target_cpu = "host"   # built where it runs (make install): use the machine's vector units
    cc.verbose = False
    for module, name, signature, options in ENTRY_POINTS:
        entry = getattr(importlib.import_module(f"{__package__}.{module}"), name)
        # Exported functions get default compiler flags: the body is compiled as a callee
        # with its own options (fastmath), serial (see _njit).
        params = ", ".join(inspect.signature(entry.__wrapped__).parameters)
        scope = {"kernel": entry.implementation}
        exec(f"def trampoline({params}):\n    return kernel({params})\n", scope)
        cc.export(f"{module}__{name}", signature)(scope["trampoline"])
    digest = source_hash()
    scope = {}
    exec(f"def source_hash():\n    return {digest}\n", scope)
    cc.export("source_hash", "i8()")(scope["source_hash"])
    cc.compile()
    return output_dir
