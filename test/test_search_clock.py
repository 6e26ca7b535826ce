"""The shape search's deadline runs on CPU time less numba's one-off kernel builds."""
import time

import numba
import numpy as np

from multi_instance_reg.search_clock import kernel_build_seconds, search_time


def test_compiling_a_kernel_is_not_search_time():
    @numba.njit                       # not cached: compiled on the first call below
    def sum_of_squares(x):
        s = 0.0
        for v in x:
            s += v * v
        return s

    built, searched, spent = kernel_build_seconds(), search_time(), time.process_time()
    assert sum_of_squares(np.arange(10.0)) == 285.0
    built = kernel_build_seconds() - built
    spent = time.process_time() - spent
    assert built > 0.02 and built <= spent + 1e-3
    assert search_time() - searched < 0.2 * spent
    # Once built, a call costs search time again and no build time.
    before = kernel_build_seconds()
    sum_of_squares(np.arange(1e6))
    assert kernel_build_seconds() == before
