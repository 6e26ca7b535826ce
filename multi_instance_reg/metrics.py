"""Multi-instance registration metrics (ECC paper, appendix; NOTES.md section 2).

Per scene: match K ground-truth to M estimated transforms with the Hungarian method on the
Frobenius distance of the 4x4 matrices; a matched pair is a hit when RRE < max_rre_deg and
RTE < max_rte. MHR = hits / K, MHP = hits / M, MHF1 = per-scene F1. Over scenes, MHR, MHP and
MHF1 are averaged; MF is the F1 of the averaged precision and recall, as later papers report.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .transforms import rotation_angle_deg


def _f1(precision: float, recall: float) -> float:
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


@dataclass
class SceneScore:
    n_gt: int
    n_est: int
    hits: int
    pairs: list[tuple[int, int]] = field(default_factory=list)   # (gt index, est index)
    rre_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per pair
    rte: np.ndarray = field(default_factory=lambda: np.zeros(0))      # per pair
    hit: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @property
    def recall(self) -> float:
        # A scene with nothing to find and nothing found is perfect; with nothing to find
        # and something found, recall is vacuous (1) and precision carries the penalty.
        return 1.0 if self.n_gt == 0 else self.hits / self.n_gt

    @property
    def precision(self) -> float:
        return (1.0 if self.n_gt == 0 else 0.0) if self.n_est == 0 else self.hits / self.n_est

    @property
    def f1(self) -> float:
        return _f1(self.precision, self.recall)


def evaluate_scene(T_gt, T_est, max_rre_deg: float = 20.0, max_rte: float = 0.5, symmetries=None) -> SceneScore:
    """Score one scene. T_gt (K,4,4), T_est (M,4,4); either may be empty.

    ``symmetries`` (a multi_instance_reg.symmetry.Symmetries in the frame the poses map
    from): each pair is scored against the symmetric ground-truth pose nearest to the
    estimate, as the BOP benchmark does; None (or none found) is the plain comparison."""
    T_gt = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    K, M = len(T_gt), len(T_est)
    if K == 0 or M == 0:
        return SceneScore(K, M, 0)
    if symmetries is not None and not symmetries.is_trivial:
        from .symmetry import closest_symmetric_pose

        variants = np.array([[closest_symmetric_pose(g, e, symmetries) for e in T_est] for g in T_gt])  # (K, M, 4, 4)
        cost = np.linalg.norm(variants - T_est[None], axis=(2, 3))
        gi, ei = linear_sum_assignment(cost)
        matched = [variants[g, e] for g, e in zip(gi, ei)]
        rre = np.array([rotation_angle_deg(T_est[e, :3, :3].T @ V[:3, :3]) for V, e in zip(matched, ei)])
        rte = np.array([np.linalg.norm(V[:3, 3] - T_est[e, :3, 3]) for V, e in zip(matched, ei)])
        hit = (rre < max_rre_deg) & (rte < max_rte)
        return SceneScore(K, M, int(hit.sum()), list(zip(gi.tolist(), ei.tolist())), rre, rte, hit)
    cost = np.linalg.norm(T_gt[:, None] - T_est[None], axis=(2, 3))
    gi, ei = linear_sum_assignment(cost)
    rre = np.array([rotation_angle_deg(T_est[e, :3, :3].T @ T_gt[g, :3, :3]) for g, e in zip(gi, ei)])
    rte = np.linalg.norm(T_gt[gi, :3, 3] - T_est[ei, :3, 3], axis=1)
    hit = (rre < max_rre_deg) & (rte < max_rte)
    return SceneScore(K, M, int(hit.sum()), list(zip(gi.tolist(), ei.tolist())), rre, rte, hit)


def combine_scores(scores: list[SceneScore]) -> SceneScore:
    """One scene's score from the scores of disjoint parts of it (e.g. one per object, each
    matched on its own): counts and per-pair errors added up; the pairs' indices, which
    refer to each part's own arrays, are not kept (a single part is returned as it is)."""
    if len(scores) == 1:
        return scores[0]
    return SceneScore(sum(s.n_gt for s in scores), sum(s.n_est for s in scores), sum(s.hits for s in scores), [],
                      np.concatenate([np.zeros(0)] + [s.rre_deg for s in scores]),
                      np.concatenate([np.zeros(0)] + [s.rte for s in scores]),
                      np.concatenate([np.zeros(0, bool)] + [s.hit for s in scores]))


def summarize(scores: list[SceneScore]) -> dict:
    """Averages over scenes: MHR, MHP, MHF1 (mean of per-scene F1), MF (F1 of the means),
    and the median RRE / RTE of the hits."""
    if not scores:
        return {"scenes": 0, "MHR": 0.0, "MHP": 0.0, "MHF1": 0.0, "MF": 0.0,
                "median_rre_deg": None, "median_rte": None, "hits": 0, "gt": 0, "est": 0}
    mhr = float(np.mean([s.recall for s in scores]))
    mhp = float(np.mean([s.precision for s in scores]))
    rre = np.concatenate([s.rre_deg[s.hit] for s in scores])
    rte = np.concatenate([s.rte[s.hit] for s in scores])
    return {
        "scenes": len(scores),
        "MHR": mhr, "MHP": mhp,
        "MHF1": float(np.mean([s.f1 for s in scores])),
        "MF": _f1(mhp, mhr),
        "median_rre_deg": float(np.median(rre)) if len(rre) else None,
        "median_rte": float(np.median(rte)) if len(rte) else None,
        "hits": int(sum(s.hits for s in scores)),
        "gt": int(sum(s.n_gt for s in scores)),
        "est": int(sum(s.n_est for s in scores)),
    }


class IdentityScore:
    """Identity over a sequence (NOTES.md section 11): CLEAR MOT's MOTA and ID switches,
    and IDF1 (Ristani et al. 2016).

    Feed it frame by frame with the matched (ground-truth identity, track id) pairs of that
    frame (the hits of ``evaluate_scene``'s one-to-one matching) and the counts of ground
    truth and of estimates. An ID switch is a ground-truth object matched to another track
    than the one it was last matched to. IDF1 assigns ground-truth objects to tracks one-to-
    one over the whole sequence so as to maximise the frames they are matched in; those
    frames are the IDTP, every other ground-truth frame an IDFN and every other estimate an
    IDFP. (Co-occurrence is counted on the per-frame matches, not on every pair within the
    gate: a close, conservative variant of the definition.)
    """

    def __init__(self):
        self.gt = 0
        self.est = 0
        self.hits = 0
        self.switches = 0
        self._last: dict = {}
        self._together: dict = {}

    def add_frame(self, matches, n_gt: int, n_est: int) -> None:
        self.gt += int(n_gt)
        self.est += int(n_est)
        for gt_key, track in matches:
            self.hits += 1
            if gt_key in self._last and self._last[gt_key] != track:
                self.switches += 1
            self._last[gt_key] = track
            self._together[(gt_key, track)] = self._together.get((gt_key, track), 0) + 1

    def merge(self, other: "IdentityScore", sequence) -> None:
        """Add another sequence's counts; its identities are kept apart by ``sequence``."""
        self.gt += other.gt
        self.est += other.est
        self.hits += other.hits
        self.switches += other.switches
        for (g, t), n in other._together.items():
            self._together[((sequence, g), (sequence, t))] = n

    def summary(self) -> dict:
        idtp = 0
        if self._together:
            gts = sorted({g for g, _ in self._together})
            tracks = sorted({t for _, t in self._together})
            count = np.zeros((len(gts), len(tracks)))
            gi, ti = {g: i for i, g in enumerate(gts)}, {t: i for i, t in enumerate(tracks)}
            for (g, t), n in self._together.items():
                count[gi[g], ti[t]] = n
            rows, cols = linear_sum_assignment(-count)
            idtp = int(count[rows, cols].sum())
        idfn, idfp = self.gt - idtp, self.est - idtp
        fn, fp = self.gt - self.hits, self.est - self.hits
        return {
            "IDF1": 2 * idtp / (2 * idtp + idfp + idfn) if idtp or idfp or idfn else 1.0,
            "IDP": idtp / self.est if self.est else 1.0,
            "IDR": idtp / self.gt if self.gt else 1.0,
            "id_switches": self.switches,
            "id_switches_per_1000": 1000.0 * self.switches / self.gt if self.gt else 0.0,
            "MOTA": 1.0 - (fn + fp + self.switches) / self.gt if self.gt else 1.0,
            "object_frames": self.gt, "estimates": self.est, "matched": self.hits, "FN": fn, "FP": fp,
        }
