"""One-to-many descriptor matching: every scene keypoint to its nearest model descriptor.

Several instances in a scene map to the same model keypoints, so there is no mutual check.
The ratio test compares the best model descriptor with the best one whose 3D point is more
than ``separation`` away from the best one's: a model merged from several views holds the
same physical point several times, and a textbook best-vs-second test rejects exactly the
points seen best (NOTES.md section 9).
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ...threads import submit_in_chunks

MATCHERS = ("flann", "brute_force")


def flann_index(desc: np.ndarray, trees: int, seed: int):
    """Randomised kd-trees over ``desc`` (float32). FLANN draws its trees from OpenCV's global
    generator: seeded, so that the same descriptors give the same index, and matches, in
    every run."""
    cv2.setRNGSeed(int(seed))
    return cv2.flann_Index(desc, {"algorithm": 1, "trees": int(trees)})


def nearest_and_second(idx: np.ndarray, dist: np.ndarray, neighbour_xyz: np.ndarray, separation: float,
                       mine: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ratio test's two distances on k-nearest-neighbour rows (``idx``, ``dist``: (Q, k),
    nearest first; ``neighbour_xyz``: (Q, k, 3), each neighbour's model point). Per row,
    among the neighbours where ``mine`` (all when None): the nearest one's index and distance,
    and the distance of the next one whose model point lies more than ``separation`` from
    the nearest one's (NaN when there is none among them)."""
    first = np.zeros((len(idx), 1), np.int64) if mine is None else mine.argmax(axis=1)[:, None]
    best = np.take_along_axis(idx, first, axis=1)[:, 0]
    gap = np.linalg.norm(neighbour_xyz - np.take_along_axis(neighbour_xyz, first[:, :, None], axis=1), axis=2)
    distinct = (gap > separation) & (np.arange(idx.shape[1])[None, :] > first)
    if mine is not None:
        distinct &= mine
    second = np.where(distinct.any(axis=1), np.take_along_axis(dist, distinct.argmax(axis=1)[:, None], axis=1)[:, 0],
                      np.nan)
    return best, np.take_along_axis(dist, first, axis=1)[:, 0], second


def prepare_descriptors(desc: np.ndarray, root_sift: bool = True) -> np.ndarray:
    """(K, 128) float32 descriptors ready for L2 matching; RootSIFT (L1-normalise, square
    root) when asked, which makes the L2 distance a Hellinger distance."""
    d = np.asarray(desc, dtype=np.float32).reshape(-1, 128)
    if root_sift and len(d):
        d = np.sqrt(np.maximum(d, 0) / (d.sum(axis=1, keepdims=True) + 1e-7))
    return np.ascontiguousarray(d, dtype=np.float32)


class DescriptorMatcher:
    """Matcher against a fixed set of model keypoints: "brute_force" (exact, one matrix
    product) or "flann" (randomised kd-trees built once: about half the time on a few
    thousand model keypoints, and the same matches for all but a fraction of a percent)."""

    def __init__(self, model_desc: np.ndarray, model_xyz: np.ndarray, ratio: float = 0.8, separation: float = 0.01,
                 method: str = "brute_force", neighbours: int = 8, flann_trees: int = 4, flann_checks: int = 32,
                 seed: int = 0):
        if method not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {method!r}")
        self.method = method
        self.neighbours = int(neighbours)
        self.flann_checks = int(flann_checks)
        self.desc = np.ascontiguousarray(model_desc, dtype=np.float32)
        self.xyz = np.asarray(model_xyz, dtype=np.float32).reshape(-1, 3)
        self._flann = None
        if method == "flann" and len(self.desc) > self.neighbours:
            self._flann = flann_index(self.desc, flann_trees, seed)
        self.sq = np.einsum("ij,ij->i", self.desc, self.desc)
        self.ratio = float(ratio)
        self.separation = float(separation)
        xyz = np.asarray(model_xyz, dtype=np.float64).reshape(-1, 3)
        # For each model point, the model points that are the same physical point (CSR arrays),
        # itself included. From the pairs within reach: a model merged from 32 views holds each
        # point ~70 times, and per-point lists cost 0.1 s a model there.
        n = len(xyz)
        pairs = cKDTree(xyz).query_pairs(separation, output_type="ndarray") if n else np.zeros((0, 2), np.int64)
        own = np.arange(n, dtype=np.int64)
        rows = np.concatenate([pairs[:, 0], pairs[:, 1], own]).astype(np.int64)
        cols = np.concatenate([pairs[:, 1], pairs[:, 0], own]).astype(np.int64)
        self._group_ptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).astype(np.int64)
        self._group_idx = cols[np.argsort(rows, kind="stable")]

    def match(self, scene_desc: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(scene indices, model indices, distance ratios) of the accepted matches, (N,) each.

        Accepted when best / second < ratio, "second" being the nearest descriptor whose model
        point lies more than ``separation`` from the best one's (accepted too when there is none).
        """
        return self.match_later(scene_desc, chunk)()

    def match_later(self, scene_desc: np.ndarray, chunk: int = 4096):
        """``match``, started: returns a callable that gives its result. The FLANN search runs
        in the shared thread pool meanwhile; brute force runs when called."""
        q_all = np.ascontiguousarray(scene_desc, dtype=np.float32)
        n_q, n_m = len(q_all), len(self.desc)
        if n_q == 0 or n_m == 0:
            return lambda: (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        if self._flann is not None:
            search = submit_in_chunks(lambda rows: self._flann.knnSearch(rows, self.neighbours,
                                                                         params={"checks": self.flann_checks}), q_all)
            return lambda: self._accept_knn(search())
        return lambda: self._match_brute_force(q_all, chunk)

    def _match_brute_force(self, q_all: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n_q = len(q_all)
        best_all = np.zeros(n_q, np.int64)
        ratio_all = np.zeros(n_q, np.float32)
        for start in range(0, n_q, chunk):
            q = q_all[start:start + chunk]
            # |q|^2 is the same along a row: it does not change the order, only the distances.
            d2 = self.sq[None, :] - 2.0 * (q @ self.desc.T)
            rows = np.arange(len(q))
            best = d2.argmin(axis=1)
            q_sq = np.einsum("ij,ij->i", q, q)
            d_best = np.sqrt(np.maximum(d2[rows, best] + q_sq, 0.0))
            # Blank out the best one's physical point, then the row minimum is the second.
            lo, hi = self._group_ptr[best], self._group_ptr[best + 1]
            counts = hi - lo
            rep_rows = np.repeat(rows, counts)
            offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
            d2[rep_rows, self._group_idx[np.repeat(lo, counts) + offs]] = np.inf
            d2_second = d2.min(axis=1)
            d_second = np.sqrt(np.maximum(d2_second + q_sq, 0.0))
            r = np.where(np.isfinite(d2_second), d_best / np.maximum(d_second, 1e-12), 0.0)
            best_all[start:start + len(q)] = best
            ratio_all[start:start + len(q)] = r
        accept = np.nonzero(ratio_all < self.ratio)[0]
        return accept.astype(np.int64), best_all[accept], ratio_all[accept]

    def _accept_knn(self, parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The same test on the approximate k nearest neighbours (FLANN's results per chunk of
        queries); when all of them are the best one's physical point, the match is unambiguous."""
        idx = np.concatenate([p[0] for p in parts]).astype(np.int64)
        d2 = np.concatenate([p[1] for p in parts])
        dist = np.sqrt(np.maximum(d2, 0.0))          # FLANN's L2 gives squared distances
        best, nearest, second = nearest_and_second(idx, dist, self.xyz[idx], self.separation)
        ratio = np.where(np.isnan(second), 0.0, nearest / np.maximum(second, 1e-12)).astype(np.float32)
        accept = np.flatnonzero(ratio < self.ratio)
        return accept.astype(np.int64), best[accept], ratio[accept]


class JointMatcher:
    """One FLANN index over several models' descriptors, each knowing its model: a frame's
    keypoints are searched once, not once per model (``MultiModelRegistration``).

    Per keypoint and per model among its ``neighbours`` nearest descriptors: that model's
    nearest is its match when the ratio test of ``DescriptorMatcher`` passes within that
    model (the second is the model's next descriptor more than ``separation`` away in 3D, so
    a keypoint that two objects share still matches both; the selection across models decides
    which object a region is). When that second is not among the neighbours, the farthest
    neighbour's distance stands in for it: the true second is at least that far, so the
    ratio used is never below the true one (a match accepted here, the model's own index
    would accept too, up to the search's approximation).

    The search spends its checks over all models' descriptors, so it needs more of them than
    one model's index for the same matches (``frontend.joint_flann_checks``)."""

    def __init__(self, model_descs: list, model_xyzs: list, ratio: float = 0.8, separation: float = 0.01,
                 neighbours: int = 16, flann_trees: int = 4, flann_checks: int = 48, seed: int = 0):
        descs = [np.ascontiguousarray(d, dtype=np.float32).reshape(-1, 128) for d in model_descs]
        self.models = len(descs)
        self.owner = np.concatenate([np.full(len(d), k, np.int64) for k, d in enumerate(descs)])
        self.first = np.concatenate([[0], np.cumsum([len(d) for d in descs])]).astype(np.int64)
        self.xyz = np.concatenate([np.asarray(x, np.float32).reshape(-1, 3) for x in model_xyzs])
        self.desc = np.concatenate(descs)
        self.neighbours = int(min(neighbours, len(self.desc)))
        self.flann_checks = int(flann_checks)
        self.ratio = float(ratio)
        self.separation = float(separation)
        self._flann = flann_index(self.desc, flann_trees, seed) if len(self.desc) else None

    def match_later(self, scene_desc: np.ndarray):
        """The search started in the shared thread pool; returns a callable that gives, per
        model, (scene indices, that model's keypoint indices, distance ratios)."""
        q = np.ascontiguousarray(scene_desc, dtype=np.float32)
        if len(q) == 0 or self._flann is None or self.neighbours < 2:
            none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
            return lambda: [none] * self.models
        search = submit_in_chunks(lambda rows: self._flann.knnSearch(rows, self.neighbours,
                                                                     params={"checks": self.flann_checks}), q)
        return lambda: self._accept(search())

    def _accept(self, parts: list) -> list:
        idx = np.concatenate([p[0] for p in parts]).astype(np.int64)
        dist = np.sqrt(np.maximum(np.concatenate([p[1] for p in parts]), 0.0))
        owner, neighbour_xyz = self.owner[idx], self.xyz[idx]
        out = []
        for k in range(self.models):
            mine = owner == k
            best, nearest, second = nearest_and_second(idx, dist, neighbour_xyz, self.separation, mine)
            second = np.where(np.isnan(second), dist[:, -1], second)     # unseen: at least the farthest
            ratio = (nearest / np.maximum(second, 1e-12)).astype(np.float32)
            accept = np.flatnonzero(mine.any(axis=1) & (ratio < self.ratio))
            out.append((accept, best[accept] - self.first[k], ratio[accept]))
        return out
