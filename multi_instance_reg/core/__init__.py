"""ECC: multi-instance point cloud registration by efficient correspondence clustering.

Plain numpy/scipy (plus numba kernels); no ROS. Usage::

    from multi_instance_reg.core import ECC, ECCConfig
    result = ECC(ECCConfig.metric()).register(src, tgt)   # src, tgt: (N, 3), row i = one correspondence
    result.transforms      # (M, 4, 4) float64, source -> target, sorted by inlier count, descending
    result.labels          # (N,) int64: index into transforms, or -1 for an outlier
    result.inlier_counts   # (M,) int64
    result.scores          # (M,) float64 in [0, 1]: mean of 1 - residual / inlier_thresh over inliers
    result.inliers(m)      # indices of instance m's inliers
"""
from .config import ECCConfig
from .ecc import ECC, RegistrationResult, register

__all__ = ["ECC", "ECCConfig", "RegistrationResult", "register"]
