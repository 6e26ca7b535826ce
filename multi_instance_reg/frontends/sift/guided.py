"""Guided matching: a second look, with each instance's pose, at the frame's keypoints near it.

The global matcher's ratio test compares a keypoint's nearest model descriptor with the
nearest one of another physical point anywhere on the model. On texture repeated over the
object (the same print on two faces, a row of letters) the two are alike and the match is
rejected, although the instance's pose tells which of them it is. So a partly visible
instance is found with 4-10 matches, and its pose is as noisy as so few matches make it.

With a pose, a scene keypoint can only be one of the model keypoints the pose puts near it.
``GuidedMatcher.pairs`` pairs it with the nearest in descriptor space among the model
keypoints within ``radius`` of it (the scene keypoint taken into the model frame) and keeps
the pair when that descriptor distance is below ``max_distance``; ``guide_instances`` refits
each instance's pose on its inliers and these pairs (least squares, re-selected around the
pose: ``transforms.refine_transform``) and counts them as its inliers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ...core.refinement import residuals
from ...transforms import refine_transform


@dataclass
class GuidedPairs:
    """Pairs found for one pose: scene keypoint ``scene[i]`` to model keypoint ``model[i]``."""
    scene: np.ndarray           # (P,) int64 indices into the frame's lifted keypoints
    model: np.ndarray           # (P,) int64 indices into the model's keypoints
    distance: np.ndarray        # (P,) float32 descriptor distance of each pair


class GuidedMatcher:
    """Pairs a frame's keypoints with the model keypoints a pose puts near them."""

    def __init__(self, model_xyz: np.ndarray, model_desc: np.ndarray, box_centre, extent, radius: float,
                 max_distance: float, neighbours: int = 16):
        self.xyz = np.asarray(model_xyz, dtype=np.float64).reshape(-1, 3)
        self.desc = np.ascontiguousarray(model_desc, dtype=np.float32)
        self.tree = cKDTree(self.xyz)
        self.centre = np.asarray(box_centre, dtype=np.float64)
        self.half = np.asarray(extent, dtype=np.float64) / 2.0
        self.radius = float(radius)
        self.max_distance = float(max_distance)
        self.neighbours = int(neighbours)
        self.sq = np.einsum("ij,ij->i", self.desc, self.desc)

    def pairs(self, T: np.ndarray, scene_xyz: np.ndarray, scene_desc: np.ndarray,
              candidates: np.ndarray) -> GuidedPairs:
        """For the scene keypoints ``candidates`` (indices): each one's model keypoint within
        ``radius`` of it at pose T (model frame -> camera frame) whose descriptor is nearest,
        when nearer than ``max_distance``."""
        candidates = np.asarray(candidates, dtype=np.int64)
        R, t = T[:3, :3], T[:3, 3]
        local = (np.asarray(scene_xyz, np.float64)[candidates] - t) @ R          # into the model frame
        # Only keypoints in (or just around) the instance's box can pair: a cheap cut first.
        near = np.all(np.abs(local - self.centre) <= self.half + self.radius, axis=1)
        candidates, local = candidates[near], local[near]
        none = GuidedPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        if len(candidates) == 0:
            return none
        # The nearest model keypoints in 3D (a fixed number, so that everything stays in
        # arrays: a model merged from many views holds 10-40 within 6 mm of a point).
        gap, near_idx = self.tree.query(local, k=self.neighbours, distance_upper_bound=self.radius)
        inside = np.isfinite(gap)
        near_idx = np.where(inside, near_idx, 0)
        q = np.asarray(scene_desc, np.float32)[candidates]
        d = self.desc[near_idx]                                                      # (C, k, 128)
        dist2 = (np.einsum("ij,ij->i", q, q)[:, None] + self.sq[near_idx]
                 - 2.0 * np.einsum("ikj,ij->ik", d, q))
        dist2 = np.where(inside, dist2, np.inf)
        best = dist2.argmin(axis=1)
        rows = np.arange(len(candidates))
        dist = np.sqrt(np.maximum(dist2[rows, best], 0.0))
        keep = dist < self.max_distance
        return GuidedPairs(candidates[keep], near_idx[rows, best][keep], dist[keep].astype(np.float32))


@dataclass
class GuidedResult:
    """Every instance's pose and correspondences after guided matching."""
    transforms: list            # (4, 4) per instance, refitted
    scene: list                 # per instance: (n,) int64 scene keypoint indices of its inliers
    model: list                 # per instance: (n,) int64 model keypoint indices paired with them
    residual: list              # per instance: (n,) float64 3D residual of each inlier at its pose


def guide_instances(matcher: GuidedMatcher, transforms: list, own_scene: list, own_model: list,
                    scene_xyz: np.ndarray, scene_desc: np.ndarray, inlier_thresh: float, fit_thresh: float,
                    rounds: int = 1, fit_iterations: int = 3, max_inliers: int | None = None) -> GuidedResult:
    """Guided matching for every instance, strongest first (the order given).

    ``own_scene[i]`` / ``own_model[i]``: the instance's inlier correspondences from the global
    matching (scene and model keypoint indices). A scene keypoint belongs to one instance only:
    those of the instances before it and the inliers of every other one are not offered to an
    instance, nor are its own inliers (they keep their pairing). Per round, the pairs of its
    pose join its own correspondences and the pose is refitted on those within ``fit_thresh``
    of it (``refine_transform``); a further round looks for pairs again from the new pose. Its
    inliers are then its correspondences within ``inlier_thresh`` of the final pose. Instances
    with more than ``max_inliers`` inliers are kept as they are (their keypoints stay theirs).
    """
    scene_xyz64 = np.asarray(scene_xyz, np.float64)
    n = len(scene_xyz64)
    owner = np.full(n, -1, np.int64)
    for i, s in enumerate(own_scene):
        owner[np.asarray(s, np.int64)] = i
    out = GuidedResult([], [], [], [])
    for i, T in enumerate(transforms):
        T = np.asarray(T, np.float64)
        mine_s, mine_m = np.asarray(own_scene[i], np.int64), np.asarray(own_model[i], np.int64)
        if max_inliers is not None and len(mine_s) > max_inliers:
            res = residuals(matcher.xyz[mine_m], scene_xyz64[mine_s], T)[:, 0]
            out.transforms.append(T)
            out.scene.append(mine_s)
            out.model.append(mine_m)
            out.residual.append(res)
            continue
        # Offered: keypoints no other instance holds, less its own inliers (their pairs stay).
        free = np.flatnonzero(owner == -1)
        scene_idx, model_idx = mine_s, mine_m
        for _ in range(max(int(rounds), 1)):
            found = matcher.pairs(T, scene_xyz64, scene_desc, free)
            scene_idx = np.concatenate([mine_s, found.scene])
            model_idx = np.concatenate([mine_m, found.model])
            T_new = refine_transform(T, matcher.xyz[model_idx], scene_xyz64[scene_idx], fit_thresh, fit_iterations)
            moved = float(np.abs(T_new - T).max()) > 1e-6
            T = T_new
            if not moved:
                break
        res = residuals(matcher.xyz[model_idx], scene_xyz64[scene_idx], T)[:, 0]
        keep = res < inlier_thresh
        scene_idx, model_idx, res = scene_idx[keep], model_idx[keep], res[keep]
        # Keypoints this instance took are no longer offered to the weaker ones; those it
        # let go are.
        owner[mine_s] = -1
        owner[scene_idx] = i
        out.transforms.append(T)
        out.scene.append(scene_idx)
        out.model.append(model_idx)
        out.residual.append(res)
    return out


__all__ = ["GuidedMatcher", "GuidedPairs", "GuidedResult", "guide_instances"]
