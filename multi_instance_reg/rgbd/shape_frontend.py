"""The shape front end of the per-frame pipeline: correspondences from depth alone, and the
refinement and depth check of the poses ECC finds from them. No ROS, no colour.

    shape = ShapeFrontEnd(model, frontend_config)
    cloud = shape.frame_cloud(depth_m, intrinsics, search_mask)    # search-region points, normals, FPFH
    src, tgt = shape.correspondences(cloud)                         # model points -> scene points
    ... ECC on (src, tgt) (with ``shape.ecc_config(base)``) ...
    kept = shape.refine_and_check(transforms, cloud, depth_m, intrinsics)   # [(T, support, agreeing points)]
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..core import ECCConfig
from ..errors import InputError
from ..messages import CameraIntrinsics
from .model import ObjectModel
from .shape import ShapeMatcher, depth_support, describe, icp_point_to_plane, scene_cloud, voxel_downsample


@dataclass
class FrameCloud:
    points: np.ndarray        # (M, 3) camera frame, voxel-downsampled
    normals: np.ndarray       # (M, 3) towards the camera
    salient: np.ndarray       # (S,) indices of the points that are matched
    descriptors: np.ndarray   # (S, 33) their FPFH
    tree: cKDTree | None


class ShapeFrontEnd:
    def __init__(self, model: ObjectModel, fe):
        if not model.has_shape:
            raise InputError("the object model has no shape data (frontend.correspondences shape/both); "
                             "build it from a mesh with `mireg build-model --mesh FILE`")
        self.model = model
        self.fe = fe
        self.voxel = float(model.shape_voxel)
        keep = np.flatnonzero(model.shape_variation >= fe.shape_min_variation)
        if len(keep) < 3:
            keep = np.arange(len(model.shape_points))
        self._model_idx = keep
        self._model_pts = model.shape_points.astype(np.float64)
        # The surface once (the descriptors hold a point once per view that sees it): for ICP
        # and the depth check.
        surface = voxel_downsample(self._model_pts, self.voxel)
        _, j = cKDTree(self._model_pts).query(surface, k=1)
        self._surface = surface
        self._surface_normals = model.shape_normals[j].astype(np.float64)
        self._matcher = ShapeMatcher(model.shape_descriptors[keep], k=fe.shape_neighbours)
        self.diameter = float(np.linalg.norm(model.extent))

    def ecc_config(self, base: ECCConfig) -> ECCConfig:
        """ECC for shape matches: thresholds no finer than the voxel they are sampled at, and
        compatibility only between points that one object can hold (spatial weight)."""
        return replace(base, inlier_thresh=max(base.inlier_thresh, 1.5 * self.voxel),
                       sampling_tolerance=max(base.sampling_tolerance, 0.6 * self.voxel),
                       spatial_sigma=1.2 * self.diameter, sampling="consistency")

    def frame_cloud(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics, search: np.ndarray) -> FrameCloud:
        # Every second pixel is plenty: the voxel is several pixel footprints wide.
        pts = scene_cloud(depth_m, intrinsics, search, self.voxel, stride=2)
        if len(pts) > self.fe.shape_max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), self.fe.shape_max_points, replace=False)]
        if len(pts) < 10:
            return FrameCloud(pts, np.zeros_like(pts), np.zeros(0, np.int64), np.zeros((0, 33), np.float32), None)
        normals, variation, desc = describe(pts, self.voxel, toward=np.zeros(3))
        salient = np.flatnonzero(variation >= self.fe.shape_min_variation)
        return FrameCloud(pts, normals, salient, desc[salient], cKDTree(pts))

    def correspondences(self, cloud: FrameCloud) -> tuple[np.ndarray, np.ndarray]:
        """(model points (N, 3), scene points (N, 3)): each salient scene point with its
        ``shape_neighbours`` nearest model descriptors."""
        s, m = self._matcher.match(cloud.descriptors)
        return self._model_pts[self._model_idx[m]], cloud.points[cloud.salient[s]]

    def refine_and_check(self, transforms, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics
                         ) -> list[tuple[np.ndarray, float, int]]:
        """Each transform refined by ICP against the frame's points and kept when the depth
        image agrees with the model's visible surface: (T, support share, agreeing points)."""
        fe = self.fe
        out = []
        if cloud.tree is None:
            return out
        tol = max(fe.shape_depth_tolerance, 0.8 * self.voxel)
        first = min(3, fe.shape_icp_iterations)
        for T in transforms:
            # A few rounds first: a hypothesis the depth hardly supports then is dropped
            # without paying for the rest (most of ECC's clusters on shape matches are wrong).
            T, _ = icp_point_to_plane(T, self._surface, cloud.points, cloud.normals, cloud.tree,
                                      max_dist=2.0 * self.voxel, iterations=first)
            support, free, n = depth_support(T, self._surface, self._surface_normals, depth_m, intrinsics, tol)
            if support < 0.5 * fe.shape_min_support:
                continue
            T, _ = icp_point_to_plane(T, self._surface, cloud.points, cloud.normals, cloud.tree,
                                      max_dist=1.5 * self.voxel, iterations=fe.shape_icp_iterations - first)
            support, free, n = depth_support(T, self._surface, self._surface_normals, depth_m, intrinsics, tol)
            if n >= fe.shape_min_visible and support >= fe.shape_min_support and free <= fe.shape_max_free:
                out.append((T, support, int(round(support * n))))
        return out


def resolve_correspondences(choice: str, model: ObjectModel) -> str:
    """``auto``: what the model allows (texture and shape: both; shape only: shape; else sift)."""
    has_sift = model.num_keypoints >= 3
    if choice == "auto":
        if model.has_shape:
            return "both" if has_sift else "shape"
        return "sift"
    if choice in ("shape", "both") and not model.has_shape:
        raise InputError(f"frontend.correspondences={choice} needs shape data in the model; build it from a mesh "
                         f"with `mireg build-model --mesh FILE`, or use sift")
    if choice in ("sift", "both") and not has_sift:
        raise InputError(f"frontend.correspondences={choice} needs SIFT keypoints, and this model has "
                         f"{model.num_keypoints} (built from a mesh alone); use shape or auto, or build the model "
                         f"with capture bags as well")
    return choice


__all__ = ["ShapeFrontEnd", "FrameCloud", "resolve_correspondences"]
