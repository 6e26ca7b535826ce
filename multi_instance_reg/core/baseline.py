"""Sequential RANSAC: the multi-instance baseline users reach for (NOTES.md section 7).

Fit one rigid transform with GC-RANSAC (pygcransac), take its inliers out, repeat until a fit
has too few inliers. Inliers are counted from our own residuals: the library's mask is not
per-correspondence in this use.
"""
from __future__ import annotations

import numpy as np

from .refinement import residuals


def sequential_ransac(src, tgt, inlier_thresh: float, min_inliers: int = 10,
                      max_instances: int = 30, max_iters: int = 1000) -> np.ndarray:
    """(M, 4, 4) source -> target transforms, in the order they were found."""
    import pygcransac

    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    remaining = np.arange(len(src))
    found = []
    while len(remaining) >= max(min_inliers, 3) and len(found) < max_instances:
        corr = np.ascontiguousarray(np.hstack([src[remaining], tgt[remaining]]))
        T, _ = pygcransac.findRigidTransform(
            corr, np.zeros(0), threshold=inlier_thresh, conf=0.99, max_iters=max_iters,
            use_space_partitioning=False, sampler=0, neighborhood=0)
        if T is None:
            break
        T = np.asarray(T, dtype=np.float64).T  # the library returns the transpose
        inl = residuals(src[remaining], tgt[remaining], T[None])[:, 0] <= inlier_thresh
        if inl.sum() < min_inliers:
            break
        found.append(T)
        remaining = remaining[~inl]
    return np.array(found).reshape(-1, 4, 4)
