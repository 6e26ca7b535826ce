"""How noisy is this depth image? sigma_z / z^2, measured from the frame itself. No ROS.

A stereo or structured-light camera's depth noise grows with the square of the distance
(sigma_z = k z^2), and k differs by camera, by unit, by projector power and by surface: a
D455 about 0.002 /m, another renderer's model 0.004 /m, a worn Primesense more. Every depth
check that uses a fixed k is too strict on a noisier camera (it rejects the true surface) or
too lax on a quieter one. So k is measured on each frame: small patches of the depth image
are fitted by a plane; on a patch that lies on one smooth surface what is left is the noise,
on a patch across an edge or a fold it is more. The lower quartile of residual / z^2 over all
patches is k (corrected for the quartile of a chi distribution), since most surfaces in a
scene are smooth at the scale of a few pixels.
"""
from __future__ import annotations

import numpy as np

PATCH_PX = 7                # patch side; the plane fit leaves PATCH_PX^2 - 3 degrees of freedom
STRIDE_PX = 12              # patches on a grid this far apart (about 2,000 at 640x480)
MIN_PATCHES = 50            # fewer full patches than this: no measurement
QUANTILE = 0.25
# Sample standard deviation over 46 degrees of freedom at its lower quartile: sigma x
# (1 - 0.674 / sqrt(2 x 46)) to first order.
_DOF = PATCH_PX * PATCH_PX - 3
QUANTILE_BIAS = 1.0 - 0.674 / np.sqrt(2.0 * _DOF)


def _plane_residual_projector() -> np.ndarray:
    """(P, P) matrix taking a patch's depths (row-major) to their residuals from the least-
    squares plane over pixel offsets."""
    v, u = np.mgrid[0:PATCH_PX, 0:PATCH_PX]
    A = np.column_stack([np.ones(PATCH_PX * PATCH_PX), u.ravel() - PATCH_PX // 2, v.ravel() - PATCH_PX // 2])
    return np.eye(len(A)) - A @ np.linalg.pinv(A)


_PROJECTOR = _plane_residual_projector()


def measure_depth_noise(depth_m: np.ndarray, min_z: float = 0.2, max_z: float = 4.0) -> float | None:
    """k in sigma_z = k z^2 (per metre) from one depth image (metres; 0 or non-finite = no
    depth), or None when fewer than ``MIN_PATCHES`` patches lie wholly on measured depth
    within [min_z, max_z]."""
    d = np.asarray(depth_m, np.float64)
    h, w = d.shape
    rows = np.arange(0, h - PATCH_PX + 1, STRIDE_PX)
    cols = np.arange(0, w - PATCH_PX + 1, STRIDE_PX)
    if len(rows) == 0 or len(cols) == 0:
        return None
    offsets = np.arange(PATCH_PX)
    # (R, C, P, P) patches gathered by index: a few thousand of 49 pixels.
    patches = d[(rows[:, None, None, None] + offsets[None, None, :, None]),
                (cols[None, :, None, None] + offsets[None, None, None, :])]
    patches = patches.reshape(-1, PATCH_PX * PATCH_PX)
    with np.errstate(invalid="ignore"):
        full = np.all(np.isfinite(patches) & (patches >= min_z) & (patches <= max_z), axis=1)
    patches = patches[full]
    if len(patches) < MIN_PATCHES:
        return None
    residual = patches @ _PROJECTOR.T
    sigma = np.sqrt((residual ** 2).sum(axis=1) / _DOF)
    z = patches.mean(axis=1)
    return float(np.quantile(sigma / (z * z), QUANTILE) / QUANTILE_BIAS)
