"""Capture views placed in a mesh's frame by shape: texture and shape in one model without
ground truth.

A model built from a CAD mesh has the mesh's frame; SIFT keypoints from capture views can join
it only once each view's object pose in that frame is known. A synthetic capture has it as
ground truth; a real one does not. Here the shape path itself finds the object in each view
(the mesh model, ``frontend.correspondences: shape``): that pose is the view's, up to the
mesh's symmetries, which shape cannot tell apart. The texture tells them apart: the first
view (the one with the most keypoints) is placed as found, and every other view in the
symmetric pose where its keypoints land on the same keypoints of the views placed before it
(a match agrees within ``AGREE_M``; continuous symmetry: the turn most matches agree on,
refined by least squares).
A view is placed only when one symmetric pose has clearly the most agreeing matches. A view
where the shape finds nothing is placed by its texture alone (ECC on its matches to the views
placed so far, then fitted to the surface) when enough matches agree and its object points lie
on the mesh; views the texture cannot decide are left out.

Why not register the views to each other by their texture and place the whole capture once:
that chain carries each view's registration error to the next (a can's curved label: 7-24
deg) and the shape's per-view poses are better (0.1-1.8 deg on the same views).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ..symmetry import best_symmetry
from ..transforms import apply_transform, invert_transform
from .model import CaptureView, ObjectModel, RegisteredView
from ..rgbd.pipeline import project_points
from ..frontends.shape.geometry import apply_twist

AGREE_M = 0.005             # a keypoint agrees with a placed one of its descriptor this close
MIN_AGREEING = 8            # matches that must agree before a view is placed ...
DECISIVE = 2.0              # ... and at least this many times the next-best symmetric pose's
ON_SURFACE = 0.8            # a view placed by texture alone: share of its object points on the mesh


@dataclass
class CaptureAlignment:
    poses: list                     # per view: object pose (mesh frame -> view optical frame), None = not placed
    found_by_shape: list            # per view: the shape path found the object in it

    @property
    def found(self) -> int:
        return sum(self.found_by_shape)

    @property
    def placed(self) -> int:
        """Views placed (the texture decided their symmetric pose)."""
        return sum(T is not None for T in self.poses)

    @property
    def by_texture_alone(self) -> int:
        """Views placed that the shape did not find (by ECC on their matches)."""
        return sum(T is not None and not f for T, f in zip(self.poses, self.found_by_shape))


def view_pose_by_shape(registration, view: CaptureView, mask: np.ndarray, model: ObjectModel):
    """The object's pose in one capture view (mesh frame -> view optical frame) by the shape
    path, or None: of the instances found, the best supported one whose box centre projects
    onto the object's pixels (the table and a wall hold none, but a false fit on them could)."""
    result = registration.register_frame(view.rgb, view.depth_m, view.intrinsics)
    h, w = mask.shape
    best = None
    for inst in result.instances:
        c = apply_transform(inst.T, model.box_centre[None, :])
        u, v = np.rint(project_points(c, view.intrinsics)[0]).astype(int)
        if c[0, 2] > 0 and 0 <= u < w and 0 <= v < h and mask[v, u] and (best is None or inst.inliers > best.inliers):
            best = inst
    return None if best is None else np.asarray(best.T, np.float64)


def fit_to_surface(T_view_mesh: np.ndarray, cloud: np.ndarray, surface: cKDTree, normals: np.ndarray,
                   voxel: float, rounds: int = 20) -> np.ndarray:
    """Point-to-plane ICP of a view's object points (view frame) onto the mesh's surface
    samples (mesh frame; ``surface`` their k-d tree, built once for all views): the shape
    path fits voxel samples a shape voxel apart, the view's thousands of points settle the
    pose further (its capture keypoints sit on that surface). Pairs beyond 2 voxels, then 1,
    are left out (table remnants at the mask's edge)."""
    tree, points = surface, surface.data
    T = np.asarray(T_view_mesh, np.float64).copy()
    for k in range(rounds):
        q = apply_transform(invert_transform(T), cloud)          # the view's points in the mesh frame
        dist, j = tree.query(q, k=1, distance_upper_bound=2.0 * voxel)
        ok = dist < (2.0 if k < rounds // 2 else 1.0) * voxel
        if ok.sum() < 30:
            break
        p, m, n = q[ok], points[j[ok]], normals[j[ok]]
        # Move the points by a small twist [w, v]: r = n . (p + w x p + v - m).
        A = np.hstack([np.cross(p, n), n])
        b = -np.einsum("ij,ij->i", n, p - m)
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        step = apply_twist(np.eye(4), x, np.zeros(3))          # mesh-frame points: p -> R p + v
        T = T @ invert_transform(step)
        if np.linalg.norm(x) < 1e-7:
            break
    return T


def symmetric_choice(x: np.ndarray, y: np.ndarray, model: ObjectModel) -> tuple[np.ndarray, int, int]:
    """Which symmetry M (model frame) takes a view's keypoints ``x`` (placed as the shape found
    them) onto their matches ``y`` among the keypoints placed before: (M, agreeing matches
    with it, agreeing with the best other discrete symmetry)."""
    return best_symmetry(x, y, model.symmetries, AGREE_M)


def texture_pose(obj: RegisteredView, s_idx: np.ndarray, target: np.ndarray, surface: cKDTree,
                 normals: np.ndarray, voxel: float) -> tuple[np.ndarray | None, int]:
    """A view's pose (mesh frame -> view) from its keypoints' matches to the keypoints placed
    so far (``target``, mesh frame), by ECC, then fitted to the surface: (pose, matches that
    agree with it), or (None, 0). Judged as a shape-found view is, by its agreeing matches,
    and only kept where most of its object points lie on the mesh surface."""
    from ..core import ECC, ECCConfig

    x = obj.keypoints_xyz[s_idx]
    res = ECC(ECCConfig.metric()).register(x, target)
    best, best_agree = None, 0
    for T_mesh_view in res.transforms:
        pose = fit_to_surface(invert_transform(np.asarray(T_mesh_view)), obj.cloud, surface, normals, voxel)
        agree = int(np.sum(np.linalg.norm(apply_transform(invert_transform(pose), x) - target, axis=1) < AGREE_M))
        if agree > best_agree:
            best, best_agree = pose, agree
    if best is None:
        return None, 0
    dist, _ = surface.query(apply_transform(invert_transform(best), obj.cloud), k=1, distance_upper_bound=2.0 * voxel)
    return (best, best_agree) if np.mean(dist < 2.0 * voxel) >= ON_SURFACE else (None, 0)


def place_views(model: ObjectModel, views: list[CaptureView], objects: list[RegisteredView],
                surface: tuple[np.ndarray, np.ndarray] | None = None, config=None) -> CaptureAlignment:
    """Each view's object pose in the mesh frame (see the module docstring). ``model``: the
    mesh's (shape data, symmetries); ``objects``: each view's object in its own frame
    (``model.view_objects``); ``surface``: (points, normals) of the mesh sampled densely
    (default: the model's shape points, a shape voxel apart)."""
    from ..frontends.sift.matching import DescriptorMatcher, prepare_descriptors
    from ..rgbd.pipeline import InstanceRegistration, PipelineConfig

    config = config or PipelineConfig()
    config = replace(config, frontend=replace(config.frontend, correspondences="shape"))
    registration = InstanceRegistration(model, config)
    found = [view_pose_by_shape(registration, v, o.mask, model) if len(o.keypoints_xyz) else None
             for v, o in zip(views, objects)]
    points, normals = surface if surface is not None else (model.shape_points, model.shape_normals)
    tree, normals = cKDTree(np.asarray(points, np.float64)), np.asarray(normals, np.float64)
    found = [None if T is None else fit_to_surface(T, o.cloud, tree, normals, model.shape_voxel)
             for T, o in zip(found, objects)]
    if not any(T is not None for T in found):
        raise InputError(f"the object was not found by its shape in any of the {len(views)} capture view(s), so "
                         f"their texture cannot be placed on the mesh; check that the mesh is this object's and its "
                         f"--units, or give captures with ground-truth poses")
    poses: list = [None] * len(views)
    # Keypoints in the mesh frame as the shape placed them (before any symmetric choice).
    as_found = [None if T is None else apply_transform(invert_transform(T), o.keypoints_xyz)
                for T, o in zip(found, objects)]
    first = max((k for k in range(len(views)) if found[k] is not None), key=lambda k: len(objects[k].keypoints_xyz))
    poses[first] = found[first]
    placed_xyz, placed_desc = [as_found[first]], [objects[first].descriptors]
    progress = True
    while progress:
        progress = False
        matcher = DescriptorMatcher(prepare_descriptors(np.concatenate(placed_desc)),
                                    np.concatenate(placed_xyz).astype(np.float32), ratio=0.8, separation=0.01)
        target = np.concatenate(placed_xyz)
        for k in range(len(views)):
            if poses[k] is not None:
                continue
            s_idx, m_idx, _ = matcher.match(prepare_descriptors(objects[k].descriptors))
            if len(s_idx) < MIN_AGREEING:
                continue
            if found[k] is not None:
                M, agree, second = symmetric_choice(as_found[k][s_idx], target[m_idx], model)
                # Keypoints at M x: the view's pose is found @ M^-1.
                pose = found[k] @ invert_transform(M) if agree >= DECISIVE * second else None
            else:
                # Not found by its shape (a can seen end-on, a face too small to vote): its
                # texture against the views placed so far, settled on the surface.
                pose, agree = texture_pose(objects[k], s_idx, target[m_idx], tree, normals, model.shape_voxel)
            if pose is not None and agree >= MIN_AGREEING:
                poses[k] = pose
                placed_xyz.append(apply_transform(invert_transform(pose), objects[k].keypoints_xyz))
                placed_desc.append(objects[k].descriptors)
                progress = True
        # (Views placed in this round join the reference for the next.)
    return CaptureAlignment(poses, [T is not None for T in found])


def place_capture_keypoints(model: ObjectModel, mesh, views: list[CaptureView], settings) -> CaptureAlignment:
    """The capture views' SIFT keypoints brought into the mesh model's frame by shape (what
    ``build-model --mesh`` does with captures that have no ground truth): each view's object
    (``model.view_objects``), its pose (``place_views``, the ICP onto the mesh sampled at a
    quarter shape voxel), its keypoints added to ``model`` (``add_placed_keypoints``)."""
    from ..meshes import sample_surface
    from .mesh_model import add_placed_keypoints
    from .model import view_objects

    objects = list(view_objects(views, settings))
    align = place_views(model, views, objects, sample_surface(mesh, model.shape_voxel / 4.0, seed=3))
    add_placed_keypoints(model, objects, align.poses)
    return align


__all__ = ["CaptureAlignment", "fit_to_surface", "place_capture_keypoints", "place_views", "symmetric_choice",
           "view_pose_by_shape"]
