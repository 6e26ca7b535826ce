"""ECC parameters. Defaults are the paper's (ModelNet units); ``metric()`` is for RGB-D in metres."""
from __future__ import annotations

from dataclasses import dataclass, replace

from ..params import param


@dataclass(frozen=True)
class ECCConfig:
    # Compatibility (paper Sec. 3.1). spatial_sigma > 0 multiplies G by the authors' code's
    # spatial weight max(0, 1 - ((d + d')/2)^2 / sigma^2); 0 gives the paper's plain G.
    spatial_sigma: float = param(0.0, "spatial weight radius on the compatibility matrix (0 = off, the paper's G); same units as the points", 0.0, 1e6)
    # Clustering (Sec. 3.2).
    min_dist_thresh: float = param(0.2, "stop merging when the smallest Tanimoto distance exceeds this", 0.0, 1.0)
    # Refinement (Sec. 3.3-3.4).
    inlier_thresh: float = param(0.3, "residual |R x + t - y| below which a correspondence is an inlier; same units as the points", 1e-9, 1e6)
    alpha0: int = param(3, "alpha schedule: first minimum cluster size for fitting", 0, 100000)
    theta: float = param(3.0, "alpha schedule growth: alpha = min(alpha0 * theta^(n-1), round(N/100))", 1.0, 100.0)
    alpha_floor: int = param(0, "lower bound on alpha (0 = the paper's schedule; 3 stops fits to one or two points)", 0, 100000)
    iou_thresh: float = param(0.8, "merge two transforms whose inlier sets have at least this IoU", 0.0, 1.0)
    max_refine_iters: int = param(10, "refinement rounds at most (it usually converges in about 3)", 1, 1000)
    refine_scope: str = param("sample", "which correspondences the refinement fits and re-assigns: sample (refine the sampled clusters, then assign all N; our reading of the paper) or all (assign all N to the sampled clusters first, then refine on all N with alpha's N = all; the authors' code)", choices=("sample", "all"))
    # Selection (Sec. 3.5).
    min_cluster_size: int = param(10, "keep clusters with more than this many inliers", 0, 100000)
    gamma_thresh: float = param(0.5, "drop instances from the first k whose inliers / best inliers fall to this (see gamma_rule)", 0.0, 1.0)
    gamma_counts: str = param("clusters", "which inlier counts gamma compares: clusters (the refined clusters' sizes, as the authors' code) or fitted (each candidate cluster's transform fitted, all N re-assigned, its inliers counted: our reading of the paper's 'transformations by their inlier numbers')", choices=("fitted", "clusters"))
    gamma_rule: str = param("at_or_below", "where gamma_thresh cuts: at_or_below (the paper: gamma_k <= gamma_thresh is dropped) or below (the authors' code: gamma_k < gamma_thresh; an instance with exactly that share is kept)", choices=("at_or_below", "below"))
    covered_instances: str = param("keep", "selected instances whose inliers all lie within inlier_thresh of the model as a stronger selected instance places it: keep (the paper) or drop (it explains no target point the stronger one's object does not occupy: the model turned over in place, collecting chance matches on the surface; core/placement.py)", choices=("keep", "drop"))
    # Large inputs (Sec. 3.6).
    max_correspondences: int = param(1024, "cluster at most this many correspondences; the rest are assigned afterwards (0 = all)", 0, 10_000_000)
    lost_clusters: str = param("drop", "with sampling (N > max_correspondences), clusters of 3 or more sampled correspondences that the refinement dropped whole (their size in the sample understates an under-drawn instance): drop (the paper) or test (fit each, count its inliers among all N, keep it as a candidate if that count is more than chance: a-contrario, number of false alarms below 1; core/significance.py)", choices=("drop", "test"))
    sampling: str = param("uniform", "how to choose them: uniform (the paper) or consistency (keep those whose distances to spatial neighbours are preserved)", choices=("uniform", "consistency"))
    sampling_score: str = param("chance", "consistency sampling: score each correspondence by its agreeing neighbours in excess of chance (chance: a z-score against the agreement rate of randomly re-paired correspondences) or by their raw number (count: crowded outlier regions score high)", choices=("chance", "count"))
    sampling_exponent: float = param(6.0, "consistency sampling: draw with weights (score + 1)^exponent; 0 = uniform", 0.0, 100.0)
    sampling_tolerance: float = param(0.1, "consistency sampling: | |x_i - x_j| - |y_i - y_j| | below this counts as agreement; same units as the points (neighbourhood radius = spatial_sigma)", 0.0, 1e6)
    seed: int = param(0, "random seed for the sampling; results are deterministic for a seed", 0, 2**31 - 1)

    @staticmethod
    def paper() -> "ECCConfig":
        """Exactly the paper's settings (ModelNet units)."""
        return ECCConfig()

    @staticmethod
    def modelnet() -> "ECCConfig":
        """The project's defaults for the synthetic benchmark (ModelNet units)."""
        return replace(ECCConfig(), spatial_sigma=2.0, alpha_floor=3, sampling="consistency", sampling_exponent=3.0,
                       gamma_counts="fitted", gamma_rule="below", covered_instances="drop",
                       lost_clusters="test")

    @staticmethod
    def metric() -> "ECCConfig":
        """RGB-D in metres: tabletop objects of 5-30 cm, D455 depth noise of a few mm."""
        return replace(ECCConfig(), spatial_sigma=0.25, inlier_thresh=0.015, alpha_floor=3,
                       min_cluster_size=5, gamma_thresh=0.1, sampling="consistency", sampling_exponent=3.0,
                       sampling_tolerance=0.005)
