"""Is a transform's support more than chance? An a-contrario test (as in Moisan and Stival's
AC-RANSAC), used for the small clusters that the refinement of a sample dropped (ecc.py).

Under the null hypothesis the pairing of sources and targets carries no information, so a
correspondence lies within eps of transform T with probability p_T(eps) = P(|T x_a - y_b|
<= eps) for a random pair a != b. p_T is measured on the data itself, from random
re-pairings, so that it includes the density of targets where T puts the model: a crowded
patch of clutter gives any transform laid over it hundreds of inliers, and a high p_T.
With its inlier residuals r_(1) <= ... <= r_(k), a transform is meaningful when, for some k,
the number of false alarms

    NFA = n_tests * P(Binomial(N, p_T(r_(k))) >= k)

is below 1 (fewer than one false detection expected over all the tests; n_tests =
transforms tested x N, the possible k). Real inliers crowd near zero residual, chance ones
spread over the whole ball, so the best k is what separates them. The binomial tail is the
Chernoff bound exp(-N KL(k/N || p)), which only overestimates it: the test is conservative.
No threshold is fitted: NFA < 1 is the a-contrario convention.
"""
from __future__ import annotations

import numpy as np

from .refinement import residuals

# Random re-pairings: p_T(inlier_thresh) is typically 0.002-0.02 on the synthetic sets, so
# this gives 30-300 null hits per transform, for one residual pass over 16,384 pairs.
NULL_PAIRS = 16384


def log_binomial_tail_bound(n: int, p, k) -> np.ndarray:
    """Chernoff bound on log P(Binomial(n, p) >= k): -n KL(k/n || p) where k/n > p, else 0."""
    q = np.asarray(k, dtype=np.float64) / n
    p = np.asarray(p, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rest = np.where(q < 1.0, (1.0 - q) * np.log((1.0 - q) / (1.0 - p)), 0.0)
        kl = q * np.log(q / p) + rest
    return np.where(q > p, -n * kl, 0.0)


def meaningful(x: np.ndarray, y: np.ndarray, transforms: np.ndarray, labels: np.ndarray,
               errors: np.ndarray, tested: np.ndarray, rng: np.random.Generator,
               hypotheses: int | None = None) -> np.ndarray:
    """For each transform index in ``tested``: whether its inliers (labels == index, with
    residuals ``errors``) are more than chance, NFA < 1 with n_tests = hypotheses x N
    (hypotheses: the transforms considered, len(tested) unless given)."""
    n = len(x)
    tested = np.asarray(tested, dtype=np.int64)
    out = np.zeros(len(tested), dtype=bool)
    if len(tested) == 0 or n < 2:
        return out
    a = rng.integers(0, n, NULL_PAIRS)
    b = (a + rng.integers(1, n, NULL_PAIRS)) % n   # a != b: re-paired, never a pair itself
    null = residuals(x[a], y[b], transforms[tested])
    log_tests = np.log(max(hypotheses or len(tested), len(tested)) * n)
    for i, m in enumerate(tested):
        r = np.sort(errors[labels == m])
        if len(r) == 0:
            continue
        # The chance rate at each inlier's residual (only null residuals up to the largest
        # inlier's matter: sorting those alone is ~50x less work); +1 / +1: never 0.
        column = null[:, i]
        column = np.sort(column[column <= r[-1]])
        p = (np.searchsorted(column, r, side="right") + 1.0) / (NULL_PAIRS + 1.0)
        out[i] = log_tests + log_binomial_tail_bound(n, p, np.arange(1, len(r) + 1)).min() < 0.0
    return out
