"""The CPU clock that search deadlines run on: the process's CPU time less the time spent
compiling numba kernels or reading them from numba's cache.

A kernel is compiled, or loaded from the cache, on its first call in a process. That is a
one-off cost of the process, not of the frame: counted against the shape search's 180 ms
budget it cut the first frames of every new process (a fresh checkout's `mireg offline` on
generated cylinders: MHF1 0.44 on its two frames, 0.75 once the kernels were built).
numba takes its global compiler lock around both (``numba:compiler_lock`` events); the time
inside it is left out.
"""
from __future__ import annotations

import threading
import time

from numba.core import event


class _KernelBuildTime(event.Listener):
    """CPU seconds spent with numba's compiler lock held (outermost acquisitions per thread)."""

    def __init__(self):
        self.seconds = 0.0
        self._local = threading.local()

    def on_start(self, ev):
        depth = getattr(self._local, "depth", 0)
        if depth == 0:
            self._local.started = time.process_time()
        self._local.depth = depth + 1

    def on_end(self, ev):
        self._local.depth -= 1
        if self._local.depth == 0:
            self.seconds += time.process_time() - self._local.started


_BUILDING = _KernelBuildTime()
event.register("numba:compiler_lock", _BUILDING)


def kernel_build_seconds() -> float:
    """CPU seconds this process has spent compiling or loading numba kernels so far."""
    return _BUILDING.seconds


def search_time() -> float:
    """``time.process_time()`` less ``kernel_build_seconds()``: what a deadline on the search's
    own work compares against."""
    return time.process_time() - _BUILDING.seconds
