"""ECC: one rigid transform per object instance from a noisy set of 3D correspondences.

``ECC.register`` reads like the paper: preprocess (drop invalid rows, sample when N is
large), compatibility matrix, agglomerative clustering, recursive refinement, upsampling to
all correspondences, selection.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .clustering import cluster_compatibility_vectors
from .compatibility import compatibility_matrix
from .config import ECCConfig
from .sampling import choose_sample
from .refinement import assign, assign_nearest, fit_transforms, instance_scores, merge_duplicates, relabel, residuals
from .placement import covered_by_stronger
from .significance import meaningful


@dataclass
class RegistrationResult:
    transforms: np.ndarray      # (M, 4, 4) float64, source -> target, by inlier count, descending
    labels: np.ndarray          # (N,) int64: index into transforms, -1 for outliers
    inlier_counts: np.ndarray   # (M,) int64
    scores: np.ndarray          # (M,) float64: mean of 1 - residual / inlier_thresh over inliers
    n_invalid: int = 0          # rows dropped for NaN / inf
    n_clustered: int = 0        # correspondences that went through clustering (after sampling)
    timings_ms: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.transforms)

    def inliers(self, m: int) -> np.ndarray:
        return np.flatnonzero(self.labels == m)


def principal_coordinate(points: np.ndarray) -> np.ndarray:
    """Each point's coordinate along the points' axis of largest spread, the axis pointing
    to the farthest point, so that a rigid motion of the points changes nothing."""
    centred = points - points.mean(0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    coordinate = centred @ vectors[:, -1]
    return -coordinate if -coordinate.min() > coordinate.max() else coordinate


def _as_points(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) array of points, got shape {a.shape}")
    return a


class ECC:
    def __init__(self, config: ECCConfig | None = None):
        self.config = config or ECCConfig()

    def register(self, src, tgt) -> RegistrationResult:
        """Multi-instance registration of correspondences src[i] <-> tgt[i]."""
        cfg = self.config
        src, tgt = _as_points("src", src), _as_points("tgt", tgt)
        if len(src) != len(tgt):
            raise InputError(f"src and tgt must have the same number of rows ({len(src)} != {len(tgt)})")
        timings = {}
        t0 = time.perf_counter()
        valid = np.isfinite(src).all(1) & np.isfinite(tgt).all(1)
        x, y = src[valid], tgt[valid]
        n = len(x)
        if n < 3:
            return self._empty(len(src), int((~valid).sum()), n)
        sample = self.sample(x, y)
        xs, ys = x[sample], y[sample]
        t1 = time.perf_counter()
        G = compatibility_matrix(xs, ys, cfg.spatial_sigma)
        t2 = time.perf_counter()
        labels = cluster_compatibility_vectors(G, cfg.min_dist_thresh, overwrite=True)  # G is not needed after
        t3 = time.perf_counter()
        if len(sample) < n and cfg.refine_scope == "all":
            # The authors' order: the sampled clusters' members keep their labels, the rest
            # start as outliers; the first round fits each cluster to its sampled members and
            # assigns all N, later rounds fit to (and count) inliers among all N.
            labels_all = -np.ones(n, dtype=np.int64)
            labels_all[sample] = labels
            labels = self.refine(x, y, labels_all)
        elif len(sample) < n:
            labels = self.upsample(xs, ys, self.refine(xs, ys, labels), x, y, clusters=labels)
        else:  # the sample is every row, in another order
            labels_all = np.empty(n, dtype=np.int64)
            labels_all[sample] = self.refine(xs, ys, labels)
            labels = labels_all
        T, labels_valid, counts, scores = self.select(x, y, labels)
        t4 = time.perf_counter()
        timings.update(sampling=(t1 - t0) * 1e3, compatibility=(t2 - t1) * 1e3,
                       clustering=(t3 - t2) * 1e3, refinement=(t4 - t3) * 1e3, total=(t4 - t0) * 1e3)
        full_labels = -np.ones(len(src), dtype=np.int64)
        full_labels[valid] = labels_valid
        return RegistrationResult(T, full_labels, counts, scores, int((~valid).sum()), len(sample), timings)

    # -- stages ---------------------------------------------------------------------------
    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Indices of the correspondences to cluster (all, or a seeded sample of them), in
        spatial order: along the targets' principal axis, so that compatible pairs, which
        are close in space, lie near the diagonal of G and the clustering's sparse product
        skips the rest. The order changes no result but ties (broken by index)."""
        cfg = self.config
        sample = choose_sample(len(x), cfg.max_correspondences, cfg.sampling,
                               np.random.default_rng(cfg.seed), x, y,
                               radius=cfg.spatial_sigma, tolerance=cfg.sampling_tolerance,
                               exponent=cfg.sampling_exponent, score=cfg.sampling_score)
        return sample[np.lexsort((principal_coordinate(x[sample]), principal_coordinate(y[sample])))]

    def refine(self, x: np.ndarray, y: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Fit, merge duplicates, re-assign; repeat until the partition stops changing."""
        cfg = self.config
        n = len(x)
        labels, _ = relabel(labels)
        for it in range(1, cfg.max_refine_iters + 1):
            alpha = max(cfg.alpha_floor, min(cfg.alpha0 * cfg.theta ** (it - 1), round(n / 100)))
            counts = np.bincount(labels[labels >= 0], minlength=1)
            big = np.flatnonzero(counts > alpha)
            if len(big) == 0:
                return -np.ones(n, dtype=np.int64)
            remap = -np.ones(len(counts), dtype=np.int64)
            remap[big] = np.arange(len(big))
            fit_labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
            T = fit_transforms(x, y, fit_labels, len(big))
            errors = residuals(x, y, T)
            keep = merge_duplicates(errors <= cfg.inlier_thresh, cfg.iou_thresh)
            new_labels, _ = relabel(assign(errors[:, keep], cfg.inlier_thresh))
            if np.array_equal(new_labels, labels):
                break
            labels = new_labels
        return labels

    def upsample(self, xs, ys, sample_labels, x, y, clusters=None) -> np.ndarray:
        """Assign every correspondence to the transforms found on the sample (Sec. 3.6).

        With lost_clusters test (and ``clusters``, the sample's clustering), the clusters of
        at least 3 that the refinement dropped whole are fitted too and judged on all N: an
        instance whose inliers the sample under-drew shows up in the sample only as such
        small clusters (alpha there reaches round(1024 / 100) = 10), while among all N it
        has its full support. Each is kept if its inliers among all N are more than chance
        (significance.py); the rest go, and selection judges the survivors as any other."""
        cfg = self.config
        n_clusters = int(sample_labels.max()) + 1 if (sample_labels >= 0).any() else 0
        T = fit_transforms(xs, ys, sample_labels, n_clusters) if n_clusters else np.zeros((0, 4, 4))
        testing = cfg.lost_clusters == "test" and clusters is not None
        extra = self._lost_clusters(xs, ys, clusters, sample_labels) if testing else np.zeros((0, 4, 4))
        T = np.concatenate([T, extra])
        if len(T) == 0:
            return -np.ones(len(x), dtype=np.int64)
        labels, errors = assign_nearest(x, y, T, cfg.inlier_thresh)
        if len(extra) == 0:
            return labels
        counts = np.bincount(labels[labels >= 0], minlength=len(T))
        # Only those that could pass selection's size cut are tested (the rest go anyway);
        # the number of tests counts every lost cluster looked at.
        tested = np.flatnonzero(counts[n_clusters:] > cfg.min_cluster_size) + n_clusters
        keep = np.ones(len(T), dtype=bool)
        keep[n_clusters:] = False
        keep[tested] = meaningful(x, y, T, labels, errors, tested, np.random.default_rng(cfg.seed), hypotheses=len(extra))
        if keep.all():
            return labels
        return assign_nearest(x, y, T[keep], cfg.inlier_thresh)[0]

    @staticmethod
    def _lost_clusters(xs, ys, clusters, refined) -> np.ndarray:
        """Transforms fitted to the clusters (of at least 3: a rigid fit) none of whose
        members the refinement kept."""
        lost = clusters.copy()
        lost[np.isin(clusters, clusters[refined >= 0])] = -1
        lost, count = relabel(lost)
        if count:
            small = np.bincount(lost[lost >= 0], minlength=count) < 3
            lost[(lost >= 0) & small[np.maximum(lost, 0)]] = -1
            lost, count = relabel(lost)      # the same order: relabel numbers by first appearance
        return fit_transforms(xs, ys, lost, count) if count else np.zeros((0, 4, 4))

    def select(self, x, y, labels):
        """Clusters larger than min_cluster_size, by inlier count; stop at the first whose
        count falls to gamma_thresh of the best (Sec. 3.5; gamma_rule: at or below, or only
        below it); with covered_instances drop, without those whose inliers all lie on a
        stronger instance's placed model (placement.py). Final fits use all inliers."""
        cfg = self.config
        n = len(x)
        counts = np.bincount(labels[labels >= 0], minlength=1)
        if cfg.gamma_counts == "fitted":
            # Count each candidate transform's inliers among all N before the cut: a
            # cluster's size can differ from its fitted transform's inliers by a few.
            big = np.flatnonzero(counts > cfg.min_cluster_size)
            if len(big):
                remap = -np.ones(len(counts), dtype=np.int64)
                remap[big] = np.arange(len(big))
                big_labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
                labels = assign_nearest(x, y, fit_transforms(x, y, big_labels, len(big)), cfg.inlier_thresh)[0]
                counts = np.bincount(labels[labels >= 0], minlength=1)
        cand = np.flatnonzero(counts > cfg.min_cluster_size)
        cand = cand[np.argsort(-counts[cand], kind="stable")]
        if len(cand) == 0:
            return self._no_instances(n)
        ratios = counts[cand] / counts[cand[0]]
        dropped = ratios[1:] < cfg.gamma_thresh if cfg.gamma_rule == "below" else ratios[1:] <= cfg.gamma_thresh
        cut = np.flatnonzero(dropped)
        if len(cut):
            cand = cand[: cut[0] + 1]
        remap = -np.ones(len(counts), dtype=np.int64)
        remap[cand] = np.arange(len(cand))
        sel_labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
        T = fit_transforms(x, y, sel_labels, len(cand))
        final, best_errors = assign_nearest(x, y, T, cfg.inlier_thresh)
        if cfg.covered_instances == "drop":
            # An instance whose inliers all lie on the model as a stronger one places it
            # (placement.py); its correspondences go to the nearest kept transform or out.
            keep = covered_by_stronger(x, y, T, final, cfg.inlier_thresh)
            if not keep.all():
                T = T[keep]
                final, best_errors = assign_nearest(x, y, T, cfg.inlier_thresh)
        counts = np.bincount(final[final >= 0], minlength=len(T))
        scores = instance_scores(final, best_errors, cfg.inlier_thresh, len(T))
        # Sort by inlier count and renumber the labels to match; empty transforms go.
        order = np.argsort(-counts, kind="stable")
        order = order[counts[order] > 0]
        rank = -np.ones(len(T) + 1, dtype=np.int64)
        rank[order] = np.arange(len(order))
        final = rank[final]  # -1 maps through rank[-1] = -1
        return T[order], final, counts[order].astype(np.int64), scores[order]

    # -- empty results ---------------------------------------------------------------------
    @staticmethod
    def _no_instances(n):
        return np.zeros((0, 4, 4)), -np.ones(n, dtype=np.int64), np.zeros(0, np.int64), np.zeros(0)

    def _empty(self, n_rows, n_invalid, n_clustered):
        T, _, counts, scores = self._no_instances(0)
        return RegistrationResult(T, -np.ones(n_rows, dtype=np.int64), counts, scores, n_invalid, n_clustered)


def register(src, tgt, config: ECCConfig | None = None) -> RegistrationResult:
    """Functional form of ``ECC(config).register(src, tgt)``."""
    return ECC(config).register(src, tgt)
