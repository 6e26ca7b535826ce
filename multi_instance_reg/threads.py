"""Thread pools of the BLAS libraries loaded in this process.

numpy, scipy and OpenCV each bring their own OpenBLAS. After every call its worker threads
busy-wait for more work; on a 2-core machine they then compete with OpenCV's SIFT threads.
Measured on the synthetic scenes, 2 cores shared with other work: 259 ms per frame with the
default pools, 137 ms with one BLAS thread (SIFT alone went from 134 to 73 ms). The matrix
products of the pipeline are small, so one BLAS thread costs nothing measurable. The ECC
core's numba kernels suffer the same way (their OpenMP threads against BLAS's): the core
tools set one BLAS thread too.

Setting OPENBLAS_NUM_THREADS works only before numpy is first imported; this works at any
time, through the libraries' own ``*_set_num_threads`` entry points (as threadpoolctl does).
"""
from __future__ import annotations

import ctypes
import os
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
            "openblas_set_num_threads64_")


def loaded_openblas_libraries() -> list[str]:
    """Paths of the OpenBLAS shared libraries mapped into this process (Linux)."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if line.strip()}
    except OSError:
        return []
    return sorted(p for p in paths if "openblas" in p.lower() and ".so" in p)


def limit_blas_threads(count: int = 1) -> int:
    """Set the thread count of every loaded OpenBLAS; returns how many libraries were set."""
    done = 0
    for path in loaded_openblas_libraries():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter.argtypes = [ctypes.c_int]
                setter(int(count))
                done += 1
                break
    return done


_POOL: ThreadPoolExecutor | None = None

# Seconds a thread holding the GIL runs before another waiting for it is let in (Python's
# default 5 ms). The pool's tasks are compiled kernels of tens of microseconds between
# Python steps: each kernel releases the GIL and, returning while the other thread runs
# Python, waited up to the whole interval for it. At 1 ms the bracket's frame latency fell
# 4-13 % (paired runs); at 0.3 and 0.1 ms the switches cost what the waits saved.
GIL_SWITCH_INTERVAL = 0.001


def shared_pool() -> ThreadPoolExecutor | None:
    """The shared thread pool (one worker per core), or None on a single core. Creating it
    shortens the interpreter's GIL switch interval to ``GIL_SWITCH_INTERVAL`` (never lengthens it)."""
    global _POOL
    cores = os.cpu_count() or 1
    if cores <= 1:
        return None
    if _POOL is None:
        if sys.getswitchinterval() > GIL_SWITCH_INTERVAL:
            sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        _POOL = ThreadPoolExecutor(cores, thread_name_prefix="mireg")
    return _POOL


def submit_each(function, items) -> list:
    """``function(item)`` started for each item in the shared thread pool (in order; run
    at once, in this thread, on a single core); returns one future-like object per item,
    whose ``result()`` waits. For independent tasks whose time is mostly in calls that
    release the GIL (nogil numba kernels, k-d tree queries, OpenCV)."""
    pool = shared_pool()
    if pool is None:
        return [_Done(function, item) for item in items]
    return [pool.submit(function, item) for item in items]


_BESIDE: ThreadPoolExecutor | None = None


def run_beside(function, *args):
    """``function(*args)`` started on a thread of its own, beside the caller's work; returns
    a future-like object whose ``result()`` waits (run at once, in this thread, on a single
    core). Not the shared pool: a task that itself waits on the shared pool's tasks, run
    inside it, could hold both workers while its own tasks queue behind it."""
    global _BESIDE
    if (os.cpu_count() or 1) <= 1:
        return _Done(lambda a: function(*a), args)
    if _BESIDE is None:
        shared_pool()                      # the same GIL switch interval
        _BESIDE = ThreadPoolExecutor(1, thread_name_prefix="mireg-beside")
    return _BESIDE.submit(function, *args)


def map_each(function, items) -> list:
    """``function(item)`` for each item, in the shared thread pool; the results in order."""
    return [f.result() for f in submit_each(function, items)]


class _Done:
    """A task run at once (no pool): its result, or its exception, kept for ``result()``."""

    def __init__(self, function, item):
        try:
            self._value, self._error = function(item), None
        except BaseException as exc:  # re-raised in result(), as a Future does
            self._value, self._error = None, exc

    def result(self):
        if self._error is not None:
            raise self._error
        return self._value

    def cancel(self) -> bool:
        return False


def submit_in_chunks(function, rows: np.ndarray, min_chunk: int = 256):
    """``function`` started on consecutive chunks of ``rows``, one per core, in a shared
    thread pool; returns a callable that waits and gives the results in order. The caller
    can do other work meanwhile (several models' searches queued at once, one model's
    clustering while the next one's search runs)."""
    cores = os.cpu_count() or 1
    parts = int(min(cores, max(1, len(rows) // min_chunk)))
    if parts <= 1:
        result = [function(rows)]
        return lambda: result
    pool = shared_pool()
    bounds = np.linspace(0, len(rows), parts + 1).astype(int)
    futures = [pool.submit(function, rows[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
    return lambda: [f.result() for f in futures]


def map_in_chunks(function, rows: np.ndarray, min_chunk: int = 256) -> list:
    """``function`` applied to consecutive chunks of ``rows``, one per core, in a shared
    thread pool; the results in order. For calls that release the GIL and use one core
    (OpenCV's FLANN search): on 2 cores, half the time."""
    return submit_in_chunks(function, rows, min_chunk)()
