"""Distance-invariance (compatibility) matrix G of the ECC paper, Sec. 3.1.

G_ij = s_ij^2 with s_ij = min(d_ij / d'_ij, d'_ij / d_ij), d = |x_i - x_j|, d' = |y_i - y_j|,
G_ii = 1. Optionally multiplied by the spatial weight of the authors' code,
max(0, 1 - ((d + d') / 2)^2 / sigma^2), which zeroes pairs too far apart to lie on one object.
"""
from __future__ import annotations

import numpy as np

from .native import compiled, prange, row_parts, split_rows

# Pairs closer than this in both clouds are the same correspondence repeated: fully compatible.
_COINCIDENT = np.float32(1e-9)
_NEGLIGIBLE = np.float32(1e-6)
_ZERO, _HALF, _ONE = np.float32(0.0), np.float32(0.5), np.float32(1.0)


@compiled("i8(f4[::1], f4[::1], f4[::1], f4[::1], f4[::1], f4[::1], f4, f4[:, ::1], i8, i8)", parallel=True, fastmath=True)
def _compatibility_kernel(sx, sy, sz, tx, ty, tz, inv_sigma2, G, lo, hi):
    # Rows lo..hi-1 of G.
    # Coordinates as separate arrays and no branch in the inner loop: it vectorises (8x
    # faster than reading (N, 3) rows). Full rows rather than a mirrored triangle:
    # contiguous writes cost less than the strided mirror writes would save.
    n = sx.shape[0]
    for i in prange(lo, hi):
        row = G[i]
        ax, ay, az, bx, by, bz = sx[i], sy[i], sz[i], tx[i], ty[i], tz[i]
        for j in range(n):
            dx, dy, dz = ax - sx[j], ay - sy[j], az - sz[j]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            ex, ey, ez = bx - tx[j], by - ty[j], bz - tz[j]
            e = np.sqrt(ex * ex + ey * ey + ez * ez)
            hi = max(d, e)
            s = min(d, e) / hi if hi > _COINCIDENT else _ONE
            # The spatial weight is 1 when inv_sigma2 = 0 (off).
            m = _HALF * (d + e)
            g = s * s * max(_ONE - m * m * inv_sigma2, _ZERO)
            # Flush negligible compatibilities to 0: they change no decision, and their
            # products would be denormal floats, which are ~100x slower to multiply.
            row[j] = g if g > _NEGLIGIBLE else _ZERO
        row[i] = _ONE
    return hi - lo


def compatibility_matrix(src: np.ndarray, tgt: np.ndarray, spatial_sigma: float = 0.0) -> np.ndarray:
    """(N, N) float32 symmetric compatibility matrix for N correspondences src[i] <-> tgt[i]."""
    s = np.ascontiguousarray(np.asarray(src, dtype=np.float32).T)
    t = np.ascontiguousarray(np.asarray(tgt, dtype=np.float32).T)
    inv_sigma2 = 1.0 / (spatial_sigma * spatial_sigma) if spatial_sigma > 0 else 0.0
    n = len(s[0])
    G = np.empty((n, n), dtype=np.float32)
    split_rows(_compatibility_kernel, row_parts(n, 128), s[0], s[1], s[2], t[0], t[1], t[2], np.float32(inv_sigma2), G)
    return G
