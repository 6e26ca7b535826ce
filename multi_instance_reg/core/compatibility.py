"""Distance-invariance (compatibility) matrix G of the ECC paper, Sec. 3.1.

G_ij = s_ij^2 with s_ij = min(d_ij / d'_ij, d'_ij / d_ij), d = |x_i - x_j|, d' = |y_i - y_j|,
G_ii = 1. Optionally multiplied by the spatial weight of the authors' code,
max(0, 1 - ((d + d') / 2)^2 / sigma^2), which zeroes pairs too far apart to lie on one object.
"""
from __future__ import annotations

import numba
import numpy as np

# Pairs closer than this in both clouds are the same correspondence repeated: fully compatible.
_COINCIDENT = np.float32(1e-9)
_NEGLIGIBLE = np.float32(1e-6)


@numba.njit(cache=True, parallel=True, fastmath=True)
def _compatibility_kernel(src, tgt, inv_sigma2):
    # Full rows (not a triangle mirrored by columns): contiguous writes vectorise well and
    # cost less than the strided mirror writes would save.
    n = src.shape[0]
    G = np.empty((n, n), dtype=np.float32)
    for i in numba.prange(n):
        for j in range(n):
            dx = src[i, 0] - src[j, 0]
            dy = src[i, 1] - src[j, 1]
            dz = src[i, 2] - src[j, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            ex = tgt[i, 0] - tgt[j, 0]
            ey = tgt[i, 1] - tgt[j, 1]
            ez = tgt[i, 2] - tgt[j, 2]
            e = np.sqrt(ex * ex + ey * ey + ez * ez)
            hi = max(d, e)
            lo = min(d, e)
            s = lo / hi if hi > _COINCIDENT else 1.0
            g = s * s
            if inv_sigma2 > 0.0:
                m = 0.5 * (d + e)
                w = 1.0 - m * m * inv_sigma2
                g = g * max(w, 0.0)
            # Flush negligible compatibilities to 0: they change no decision, and their
            # products would be denormal floats, which are ~100x slower to multiply.
            G[i, j] = g if g > _NEGLIGIBLE else 0.0
        G[i, i] = 1.0
    return G


def compatibility_matrix(src: np.ndarray, tgt: np.ndarray, spatial_sigma: float = 0.0) -> np.ndarray:
    """(N, N) float32 symmetric compatibility matrix for N correspondences src[i] <-> tgt[i]."""
    src = np.ascontiguousarray(src, dtype=np.float32)
    tgt = np.ascontiguousarray(tgt, dtype=np.float32)
    inv_sigma2 = 1.0 / (spatial_sigma * spatial_sigma) if spatial_sigma > 0 else 0.0
    return _compatibility_kernel(src, tgt, np.float32(inv_sigma2))
