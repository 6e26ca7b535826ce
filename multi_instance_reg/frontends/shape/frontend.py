"""The shape front end of the per-frame pipeline: pose hypotheses from depth alone, each
refined by ICP and explained against the frame (explain.py), and the instances chosen
jointly. No ROS; colour only for its seams and its appearance.

    shape = ShapeFrontEnd(model, frontend_config)
    cloud = shape.frame_cloud(depth_m, intrinsics, search_mask)    # points off the supports, segments
    src, tgt = shape.correspondences(cloud)                         # point-pair votes: model -> scene points
    ... ECC on (src, tgt) (with ``shape.ecc_config(base)``) ...
    view = FrameView.of(depth_m, intrinsics, rgb)
    candidates = shape.refine_all(transforms, cloud, view)          # [Explanation], best first
    chosen = shape.choose(candidates, cloud, view, conflicts)       # the instances
"""
from __future__ import annotations

import os
import threading
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ...core import ECCConfig
from ...errors import InputError
from ...messages import CameraIntrinsics
from ...search_clock import search_time
from ...symmetry import detect_symmetries
from ...models.model import ObjectModel
from ...threads import shared_pool, submit_each
from ...tracking.icp import align_projective
from .explain import (APPEARANCE_BASE, APPEARANCE_WEIGHT, FREE_WEIGHT, MIN_SEEN, Explanation, FrameView,
                      crease_distances, explain, select, symmetric_greys)
from ...rgbd.depth_noise import measure_depth_noise
from ...rgbd.verify import facing_camera
from .faces import Faces, frame_patches, matches, model_faces, nearest_face_pose, patch_poses
from .geometry import (PointGrid, ShapeMatcher, depth_support, describe, icp_point_to_plane, is_convex, normal_radius,
                       scene_cloud, surface_normals, voxel_downsample)
from .ppf import ANGLE_BINS as ANGLE_STEPS, PPFModel, cluster_poses
from .segments import (connected_segments, level_supports, segment_members, segment_pairs, segments_within_reach,
                       support_mask)


# ICP pairs a model point with a scene point at most this many voxels away.
ICP_REACH = 2.0
# A refined pose with more than this share of its points in space seen empty is aligned again
# by projective ICP, for this many rounds.
OVERHANG = 0.02
PROJECTIVE_ROUNDS = 30
# A pose ICP slid off its flat patch, one of several pieces of one plane in depth, goes back
# onto it unless the depth check's support - free is better off it by more than this
# (``refine_one``; flush cartons: 0.02-0.05 gained 2-3 cm off; with no bound, ICP's better
# fits were undone too).
PATCH_SLACK = 0.1
# Voxels: how far from a crease a sample's distance to it is told (``crease_distances``; the
# seams that mark an outline are widened by about two voxels at 1.5 m).
CREASE_REACH = 4.0
# A model placed by its faces' outlines (a box) is looked for out to where the depth's
# tolerance (3 sigma) is this share of its thinnest extent, the least step its faces' edges
# show above what it stands on (``resolvable_depth``; realistic-sensor cartons at 1.7-2.0 m,
# k 0.006, were beyond the diameter's share).
FACE_STEP_SHARE = 0.5
# Points closer than this many voxels are in one segment.
SEGMENT_LINK = 2.0
# ``joined_poses``: each group's best this many clusters, from every this many times
# ``shape_ref_step``-th point (on generated brackets and channels, the same hypotheses as
# from six clusters and every point the segments' votes take, at half the CPU time).
JOINED_CLUSTERS = 2
JOINED_REF_SPACING = 2
# A non-convex model checks this many times shape_pose_clusters of the frame's vote clusters
# (``correspondences``).
NON_CONVEX_CLUSTERS = 2
# An instance needs at least this many model points seen on valid depth (explain.MIN_JUDGED
# for the verification; here for the cheap check before ICP).
MIN_VISIBLE = 20
# sigma_z / z^2 (per metre) where a frame gives too few smooth patches to measure it, and the
# least a measurement is taken for (shape_depth_noise 0): a D4xx's. The 7 x 7 plane fits see
# the pixel-to-pixel part of the noise only; a real camera's error is also correlated over
# tens of pixels, which the depth check over an object's extent meets too: the IC-BIN frames
# measure 0.0010-0.0014, and at that k the noise-share cut searched the room out to 2.4 m
# (15-17 s CPU on the bin of cartons, 3.5 s at 0.002; the cut was set there with 0.002).
NOMINAL_DEPTH_NOISE = 0.002


@dataclass
class FrameCloud:
    points: np.ndarray        # (M, 3) camera frame, voxel-downsampled
    normals: np.ndarray       # (M, 3) towards the camera
    salient: np.ndarray       # (S,) indices of the points that are matched
    descriptors: np.ndarray   # (S, 33) their FPFH
    tree: cKDTree | None
    segments: np.ndarray | None = None    # (M,) segment label per point (-1: none), ppf only
    poses: np.ndarray | None = None       # (K, 4, 4) pose hypotheses clustered from the votes, ppf only
    up: np.ndarray | None = None          # (3,) the support plane's normal (the largest, or the largest level
                                          # one given gravity), towards the camera, ppf only
    up_offset: float | None = None        # that plane: up . p + up_offset = 0 on it
    planes: tuple = ()                    # the supports: removed planes level with ``up`` (normal, offset)
    grid: PointGrid | None = None         # the points and normals for ICP's nearest-point search
    patches: Faces | None = None          # the segments' flat patches shaped as a model face (ppf, shape_faces)
    patch_fits: np.ndarray | None = None  # (J, F) bool: patch j has model face f's outline
    compact: np.ndarray | None = None     # ids of the segments within the object's diameter (``compact_segments``)


class ShapeFrontEnd:
    def __init__(self, model: ObjectModel, fe):
        self._deadline = None         # set_deadline's search_time() bound, or None
        self.deadline_cut = False     # whether past_deadline turned work away since set_deadline
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
        self._surface, self._surface_normals = oriented_downsample(self._model_pts, model.shape_normals, self.voxel)
        self._creases = crease_distances(self._surface, self._surface_normals, CREASE_REACH * self.voxel)
        # The mesh's grey level at each sample under each pose the shape cannot tell apart,
        # for the verification's appearance (None: no colour). Those are the model's
        # symmetries, or where it declares none (BOP declares those of the textured object:
        # a printed can has none) the shape's own.
        self._surface_grey = None
        if model.shape_grey is not None:
            _, j = cKDTree(self._model_pts).query(self._surface, k=1)
            alike = model.symmetries if model.symmetries is not None and not model.symmetries.is_trivial \
                else detect_symmetries(self._model_pts, self.voxel)
            self._surface_grey = symmetric_greys(self._surface, np.asarray(model.shape_grey, np.float64)[j], alike)
        self.diameter = float(np.linalg.norm(model.extent))
        self._thinnest = float(np.min(model.extent))
        # sigma_z / z^2 of the frame being registered: shape_depth_noise, or measured on each
        # frame when that is 0 (``measure_noise``, called by ``frame_cloud``).
        self.depth_noise = fe.shape_depth_noise if fe.shape_depth_noise > 0 else NOMINAL_DEPTH_NOISE
        # The radius of the smallest ball about a point of the surface that holds the whole
        # object (0.49-0.61 of the box diagonal for the cartons, cylinders, brackets, channels,
        # tees and stairs): what a reference in a segment of several objects pairs with
        # (``partner_reach``).
        self.central_reach = central_radius(self._surface)
        # A non-convex object (an L bracket) hides parts of itself that face the camera: the
        # depth check draws its own surface first (each sample a disc of about the samples'
        # spacing) and leaves those parts out. On a convex one nothing is hidden (0: not drawn;
        # the downsampled surfaces of boxes and cylinders stand at most 0.6 voxel in front of
        # their own tangent planes, the bracket's 20 voxels).
        self._self_hiding = 0.0 if is_convex(self._surface, self._surface_normals, self.voxel) \
            else 0.75 * self.voxel
        self._box_centre = np.asarray(model.box_centre, np.float64)
        self.features = fe.shape_features
        self._faces = None
        if self.features == "ppf":
            self._ppf = PPFModel(self._surface, self._surface_normals, self.diameter, self.voxel, model.symmetries,
                                 bucket_cap=fe.shape_ppf_bucket)
            # The largest flat piece the object can show: its two largest box sides.
            e = np.sort(np.asarray(model.extent, np.float64))
            self._max_face_area = float(e[1] * e[2])
            # Where flush tops of such objects would lie above their support (support_mask).
            self._face_heights = object_face_heights(self._surface, self._surface_normals, self.voxel)
            # The model's flat faces with a long axis (a carton's six): a frame patch with
            # the same outline moments places the pose (frontends/shape/faces.py). Convex models only:
            # a non-convex one hides parts of its own faces (the bracket's upright, its base
            # plate), and a plate's outline does not say on which side the rest lies
            # (bracket MHF1 seed 0 / 5: 0.925 / 0.833 -> 0.901 / 0.828 with them).
            self._faces = model_faces(self._surface, self._surface_normals, self.voxel) \
                if fe.shape_faces and self._self_hiding == 0 else None
        else:
            self._matcher = ShapeMatcher(model.shape_descriptors[keep], k=fe.shape_neighbours)

    def measure_noise(self, depth_m: np.ndarray) -> float:
        """Set and return ``depth_noise`` for this frame: ``shape_depth_noise`` when > 0, else
        measured on the frame (``rgbd/depth_noise.py``, 3-5 ms at 640x480; a fixed k is too
        strict on a noisier camera: a realistic-sensor pallet, k 0.004, gave no pose with
        0.002), never below ``NOMINAL_DEPTH_NOISE`` (also when the frame has too few smooth
        patches)."""
        k = self.fe.shape_depth_noise
        if k <= 0:
            k = max(measure_depth_noise(depth_m) or 0.0, NOMINAL_DEPTH_NOISE)
        self.depth_noise = float(k)
        return self.depth_noise

    @property
    def resolvable_depth(self) -> float:
        """Metres: the farthest the depth check can tell the object's shape from any surface
        there: its tolerance (3 sigma of the depth noise, sigma = ``depth_noise`` x z^2) at
        most shape_max_noise_share of the object's diameter. Beyond, every surface of its size
        agrees (IC-BIN, a room 2-3 m behind a bin of cups: 30-56 mm against a cup's 45 mm
        radius, support 0.8-1.0 on clutter). No points from there."""
        k, share = self.depth_noise, self.fe.shape_max_noise_share
        if k <= 0 or share <= 0:
            return np.inf
        reach = share * self.diameter
        if self._faces is not None and len(self._faces):
            # A box is placed by a face's outline (``face_poses``), which the depth's noise
            # does not blur: its shape is told where the step at the face's edges is, its
            # thinnest extent at least twice the tolerance.
            reach = max(reach, FACE_STEP_SHARE * self._thinnest)
        return float(np.sqrt(reach / (3.0 * k)))

    @property
    def depth_tolerance(self) -> float:
        """Metres: a model point agrees with the depth image within this."""
        return max(self.fe.shape_depth_tolerance, 0.8 * self.voxel)

    @property
    def judges_appearance(self) -> bool:
        """Whether the verification compares the model's colour with the image's (a mesh
        with colour)."""
        return self._surface_grey is not None

    @property
    def non_convex(self) -> bool:
        """Whether the model hides parts of itself (an L bracket; ``_self_hiding``)."""
        return self._self_hiding > 0

    def tolerance_at(self, T: np.ndarray) -> float:
        """Metres: agreement with the depth image for an instance at pose T, within the depth
        noise at its distance (3 sigma; 2.4 cm at 2 m, where a fixed 1.2 cm left true cartons
        at 0.88 support and 0.1 "free")."""
        return max(self.depth_tolerance, 3.0 * self.depth_noise * float(T[2, 3]) ** 2)

    def _visible_surface(self, T: np.ndarray, normals: bool = False):
        """The model's surface samples at pose T (camera frame) that face the camera; with
        ``normals``, (samples, their normals)."""
        p = self._surface @ T[:3, :3].T + T[:3, 3]
        n = self._surface_normals @ T[:3, :3].T
        facing = facing_camera(p, n)
        return (p[facing], n[facing]) if normals else p[facing]

    def surface_normals_at(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) the outward normal of the model surface nearest each model-frame point."""
        if len(points) == 0:
            return np.zeros((0, 3))
        _, j = cKDTree(self._surface).query(np.asarray(points, np.float64), k=1)
        return self._surface_normals[j]

    def warm_up_frame(self) -> tuple[np.ndarray, CameraIntrinsics, np.ndarray]:
        """A small made-up depth frame of the object in front of a wall, for ``warm_up``: the
        shape path's kernels (support planes, normals, votes, ICP, depth and outline checks)
        compile on their first call, seconds on a new checkout's first frame otherwise. The
        model's camera-facing surface at an oblique pose, each sample drawn as a square of
        its voxel's footprint in its tangent plane (not at one depth: the steps of a tilted
        face, a few mm, would be no depth a sensor gives), nearest first. Returns the depth,
        its intrinsics and the pose drawn."""
        f, w, h = 120.0, 160, 120
        z = max(1.6 * f * self.diameter / w, self.fe.depth_min + self.diameter)
        c, s = np.cos(0.5), np.sin(0.5)
        T = np.eye(4)
        T[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        T[:3, 3] = [0.0, 0.0, z]
        depth = np.full((h, w), np.float32(z + self.diameter))       # the wall behind it
        p, n = self._visible_surface(T, normals=True)
        u = np.rint(f * p[:, 0] / p[:, 2] + w / 2).astype(int)
        v = np.rint(f * p[:, 1] / p[:, 2] + h / 2).astype(int)
        r = int(np.ceil(f * self.voxel / z / 2))
        for k in np.argsort(-p[:, 2]):                                # far first: the nearest stays
            rows = np.arange(max(v[k] - r, 0), max(min(v[k] + r + 1, h), 0))
            cols = np.arange(max(u[k] - r, 0), max(min(u[k] + r + 1, w), 0))
            if len(rows) == 0 or len(cols) == 0:
                continue
            # Each pixel's ray (x, y, 1) meets the sample's plane n . (ray t - p) = 0 at depth t.
            den = n[k, 0] * (cols[None, :] - w / 2) / f + n[k, 1] * (rows[:, None] - h / 2) / f + n[k, 2]
            depth[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1] = float(n[k] @ p[k]) / den
        K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
        return depth, CameraIntrinsics(K, w, h), T

    def ecc_config(self, base: ECCConfig) -> ECCConfig:
        """ECC for shape matches: thresholds no finer than the voxel they are sampled at, and
        compatibility only between points that one object can hold (spatial weight)."""
        return replace(base, inlier_thresh=max(base.inlier_thresh, 1.5 * self.voxel),
                       sampling_tolerance=max(base.sampling_tolerance, 0.6 * self.voxel),
                       spatial_sigma=1.2 * self.diameter, sampling="consistency")

    def frame_cloud(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics, search: np.ndarray | None,
                    gravity: np.ndarray | None = None, within: np.ndarray | None = None) -> FrameCloud:
        """The frame's points where objects can be, no farther than the depth where the
        object's shape can be told (``resolvable_depth``). ``search``: (H, W) bool, the
        pipeline's search region (fpfh: its planes removed, inside the workspace); None: the
        depth within [depth_min, depth_max] (ppf: it removes the planes itself,
        ``segment_cloud``). ``within``: (H, W) bool, the workspace's pixels (or None: no
        workspace), kept of what is left once the planes are removed. ``gravity``: see
        ``segment_cloud``."""
        self.measure_noise(depth_m)
        if search is None:
            search = (depth_m >= self.fe.depth_min) & (depth_m <= self.fe.depth_max)
        if self.features == "ppf":
            # The supports are sought up to an object's size beyond the resolvable depth, where
            # an object there stands (a floor past it, seen only in pieces nearer, was fitted
            # across those, the pallet's top and the cartons' tops: 12 deg off level); the
            # points are kept only nearer.
            if np.isfinite(self.resolvable_depth):
                search = search & (depth_m <= self.resolvable_depth + self.diameter)
            return self.segment_cloud(depth_m, intrinsics, search, gravity, within)
        if np.isfinite(self.resolvable_depth):
            search = search & (depth_m <= self.resolvable_depth)
        if within is not None:
            search = search & within
        # Every second pixel is plenty: the voxel is several pixel footprints wide.
        pts = scene_cloud(depth_m, intrinsics, search, self.voxel, stride=2)
        if len(pts) > self.fe.shape_max_points:
            pts = pts[np.random.default_rng(0).choice(len(pts), self.fe.shape_max_points, replace=False)]
        if len(pts) < 10:
            return FrameCloud(pts, np.zeros_like(pts), np.zeros(0, np.int64), np.zeros((0, 33), np.float32), None)
        normals, variation, desc = describe(pts, self.voxel, toward=np.zeros(3))
        salient = np.flatnonzero(variation >= self.fe.shape_min_variation)
        return FrameCloud(pts, normals, salient, desc[salient], cKDTree(pts),
                          grid=PointGrid(pts, normals, ICP_REACH * self.voxel))

    def segment_cloud(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics, valid: np.ndarray,
                      gravity: np.ndarray | None = None, within: np.ndarray | None = None) -> FrameCloud:
        """The ``valid`` pixels' points minus the large pieces of dominant planes (floor,
        pallet top, table), those of them ``within`` the workspace (pixels; None: all),
        voxel-downsampled, with normals, cut into connected segments. ``gravity``
        (unit "up", camera frame; None: not known): the support "below" the objects
        (``cloud.up``) is the largest removed plane within ``shape_gravity_tolerance_deg`` of
        it, not a larger wall (``support_mask``)."""
        fe = self.fe
        ground, planes, rest = [], [], []
        # Every second pixel's point off the supports (lifted once, in support_mask).
        support_mask(depth_m, intrinsics, valid, fe.shape_support_area * self._max_face_area,
                     fe.shape_plane_thresh, self.depth_noise, stride=2, ground=ground, planes=planes,
                     up=gravity, up_tolerance_deg=fe.shape_gravity_tolerance_deg, rest=rest,
                     face_heights=self._face_heights, min_width=self._thinnest)
        pts = rest[0]
        if within is not None:
            pts = pts[within[rest[1][:, 0], rest[1][:, 1]]]
        if np.isfinite(self.resolvable_depth):
            pts = pts[pts[:, 2] <= self.resolvable_depth]
        pts = voxel_downsample(np.asarray(pts, np.float64), self.voxel)
        empty = FrameCloud(pts, np.zeros_like(pts), np.zeros(0, np.int64), np.zeros((0, 33), np.float32), None,
                           np.full(len(pts), -1, np.int64))
        if len(pts) < 10:
            return empty
        # The segments on the other core while the normals are estimated here (neither
        # needs the other; both searches release the GIL and share one tree), and the ICP
        # grid built here while the segments, the longer of the two, are finished.
        tree = cKDTree(pts)
        segments = submit_each(lambda p: connected_segments(p, SEGMENT_LINK * self.voxel,
                                                            fe.shape_min_segment, tree=tree), [pts])[0]
        z = float(np.median(pts[:, 2]))
        normals = surface_normals(pts, self.voxel, toward=np.zeros(3), tree=tree,
                                  radius=normal_radius(self.voxel, self.depth_noise * z * z))
        grid = PointGrid(pts, normals, ICP_REACH * self.voxel)
        labels = segments.result()
        # Of the planes removed, those level with the support below are supports: a pose may
        # not sink into them (``explain``'s sunk samples). The others are walls, a bin's sides:
        # what lies behind one is hidden, not sunk (IC-BIN: cups inside the bin had 114-159
        # samples "sunk" into its side, and none of them was found).
        supports = level_supports(planes, ground[0] if ground else None)
        return FrameCloud(pts, normals, np.zeros(0, np.int64), np.zeros((0, 33), np.float32), tree, labels,
                          up=ground[0] if ground else None, up_offset=ground[1] if ground else None,
                          planes=supports, grid=grid)

    def correspondences(self, cloud: FrameCloud, on_poses=None, on_matches=None,
                        view: FrameView | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(model points (N, 3), scene points (N, 3)). ppf: each reference point of a
        segment with the model point its pair votes choose (over the symmetries); fpfh: each
        salient scene point with its ``shape_neighbours`` nearest model descriptors.
        ``on_poses()`` is called as soon as ``cloud.poses`` (ppf) is set (to start their
        refinement); ``on_matches(src, tgt)`` (ppf) as soon as the correspondences are made,
        before the vote clusters' poses, which they do not depend on (to start ECC on them).
        ``view``: the frame's seams cut flat patches (``face_poses``)."""
        if self.features == "ppf":
            if cloud.segments is None or not np.any(cloud.segments >= 0):
                return np.zeros((0, 3)), np.zeros((0, 3))
            reach = self.partner_reach(cloud)
            s, m, poses, share = self._ppf.vote(cloud.points, cloud.normals, cloud.segments,
                                                self.fe.shape_ref_step, self.fe.shape_max_partners, reach=reach)
            poses = self._ppf.canonical_poses(poses)
            src, matched = self._ppf.correspondences(s, poses, cloud.points, canonical=True, tree=cloud.tree)
            tgt = cloud.points[matched]
            if on_matches is not None:
                on_matches(src, tgt)
            if self.fe.shape_pose_clusters > 0:
                # The references' own poses, clustered: an instance whose references ECC
                # does not group (too few agree among the rest) still gets a hypothesis.
                # More of them for a non-convex model: its wrong poses rarely pass the
                # verification (a part stands in space seen empty, or sinks into what is
                # there), so more cost only search time; a convex one's extra clusters (boxes
                # slid along their faces, cans turned about their axis) can pass. IC-BIN's
                # cups: the right clusters ranked 31st-52nd.
                k = self.fe.shape_pose_clusters * (NON_CONVEX_CLUSTERS if self.non_convex else 1)
                cloud.poses = cluster_poses(poses, share, 360.0 / ANGLE_STEPS, 0.1 * self.diameter, k)
                if self.non_convex and self.fe.shape_segment_clusters > 0:
                    # Non-convex models only: a convex one's segment is one surface whose
                    # votes agree (pallet and cylinders seeds 0 / 5: the same results with
                    # them, for 12-20 ms more refinement a pallet frame).
                    cloud.poses = np.concatenate([cloud.poses, self.segment_poses(poses, share, cloud.segments[s],
                                                                                  cloud.poses)])
                    # And what segmentation split off an instance, voted with it.
                    cloud.poses = np.concatenate([cloud.poses, self.joined_poses(cloud, cloud.poses)])
                if self._faces is not None and len(self._faces):
                    # The face poses first; a vote cluster that one of them would be refined
                    # for (``distinct``) is left out: moved onto the same patch, it would be
                    # the same pose, refined twice.
                    faces = self.face_poses(cloud, view)
                    near = _within(cloud.poses, faces, 360.0 / ANGLE_STEPS, 0.1 * self.diameter)
                    cloud.poses = np.concatenate([faces, cloud.poses[~near]])
            if on_poses is not None:
                on_poses()
            return src, tgt
        s, m = self._matcher.match(cloud.descriptors)
        return self._model_pts[self._model_idx[m]], cloud.points[cloud.salient[s]]

    def partner_reach(self, cloud: FrameCloud) -> np.ndarray | None:
        """(M,) metres: how far from each point of the cloud, as a reference, its vote
        partners may lie, by segment; None: the
        object's diameter everywhere. In a segment larger than the
        object (two points farther apart than its diameter),
        ``central_reach``: touching instances form one segment (channels side by side, their
        tops flush), and partners spread over the diameter lay mostly on the neighbours
        (open-side-down channels merged in pairs or fours: 0-5 right references of 70-100
        each; voted over their own points alone, 10-60). A reference near its instance's
        middle still pairs with all of it."""
        labels = cloud.segments
        if labels is None:
            return None
        compact = self.compact_segments(cloud)
        reach = np.full(len(cloud.points), np.inf)
        reach[(labels >= 0) & ~np.isin(labels, compact)] = self.central_reach
        return reach if np.isfinite(reach).any() else None

    def compact_segments(self, cloud: FrameCloud) -> np.ndarray:
        """``segments_within_reach`` of the cloud's segments and the object's diameter, found
        once a frame (3-4 ms a channel frame)."""
        if cloud.compact is None:
            cloud.compact = segments_within_reach(cloud.points, cloud.segments, self.diameter)
        return cloud.compact

    def face_poses(self, cloud: FrameCloud, view: FrameView | None = None) -> np.ndarray:
        """(K, 4, 4) pose hypotheses from the segments' flat patches whose outline moments are
        a model face's (``faces.patch_poses``; a carton seen from above shows its top alone,
        and its references' votes are blurred in the plane of it), one per pose the object's
        symmetries tell apart. Also keeps those patches (``cloud.patches``, ``patch_fits``) for
        ``_refine``. ``view``: with colour, its seams cut a plane where the depth shows no
        gap (cartons packed flush)."""
        patches = frame_patches(cloud.points, cloud.normals, cloud.segments, self.diameter,
                                SEGMENT_LINK * self.voxel,
                                lambda z: max(self.depth_tolerance, 3.0 * self.depth_noise * z * z),
                                across_seams=None if view is None else view.across_seams)
        fits = matches(self._faces, patches, self.voxel)
        shaped = fits.any(axis=1)
        cloud.patches, cloud.patch_fits = patches.take(shaped), fits[shaped]
        poses = patch_poses(self._faces, cloud.patches, cloud.patch_fits)
        if len(poses) <= 1:
            return poses
        # One pose per patch and face the symmetries tell apart (a box's top on either sign
        # of its axis, or its bottom's face: one pose, up to the faces' sampling).
        poses = self._ppf.canonical_poses(poses)
        keep = cluster_poses(poses, np.ones(len(poses)), 5.0, self.voxel, len(poses), min_members=1, indices=True)
        return poses[np.sort(keep)]

    def segment_poses(self, poses: np.ndarray, share: np.ndarray, labels: np.ndarray, taken: np.ndarray,
                      k: int | None = None) -> np.ndarray:
        """(K, 4, 4) each segment's best ``shape_segment_clusters`` (``k``) clusters of its own
        references' poses (``labels``: each reference's segment), those not already among
        ``taken`` (the frame-wide clusters). Ranked over the whole frame, an instance whose
        segment is small or whose references mostly vote wrong poses (a bracket's plate seen
        alone: blurred and turned-over votes) loses to the larger segments' second and third
        clusters: its right cluster ranked 33rd-96th of 50-130, yet 1st-3rd in its segment."""
        k = self.fe.shape_segment_clusters if k is None else k
        angle, shift = 360.0 / ANGLE_STEPS, 0.1 * self.diameter
        out = []
        for label in np.unique(labels[labels >= 0]):
            mine = np.flatnonzero(labels == label)
            if len(mine) >= 2:
                out.append(cluster_poses(poses[mine], share[mine], angle, shift, k))
        if not out:
            return np.zeros((0, 4, 4))
        out = np.concatenate(out)
        out = out[~_within(out, taken, angle, shift)]
        # One of each group the refinement would take as one pose (two segments of one
        # bracket, its upright and base plate, vote the same): the rest would be refined
        # ahead of ECC for nothing.
        return out[np.sort(self.distinct(out))] if len(out) > 1 else out

    def joined_poses(self, cloud: FrameCloud, taken: np.ndarray) -> np.ndarray:
        """(K, 4, 4) non-convex models: poses voted over what segmentation split off an
        instance, the best JOINED_CLUSTERS clusters of each group's references (every
        JOINED_REF_SPACING x ``shape_ref_step``-th point), those not already among ``taken``:
        - each pair of segments that together fit within the object's diameter, voted as
          one: a part in front can hide the corner that joins it to the rest (a bracket seen
          from behind its upright is two segments; generated brackets, seed 5: 0-1 right
          references of 33-57 on each such bracket, none found);
        - each segment within the diameter, its references paired with every point within
          the diameter of its centre: a part touching another object joins that object's
          segment (generated brackets, seed 3: 0-3 right references on each such bracket).
        A plate voted alone is ambiguous."""
        labels = cloud.segments
        ids, members = segment_members(labels)
        groups = segment_pairs(cloud.points, labels, self.diameter, members)
        leads = [len(g) for g in groups]
        for label in self.compact_segments(cloud):
            mine = members[int(np.searchsorted(ids, label))]
            around = np.asarray(cloud.tree.query_ball_point(cloud.points[mine].mean(axis=0), self.diameter), np.int64)
            others = around[(labels[around] >= 0) & (labels[around] != label)]
            if len(mine) >= 2 and len(others):
                groups.append(np.concatenate([mine, others]))
                leads.append(len(mine))
        if not groups:
            return np.zeros((0, 4, 4))
        _, _, poses, share, group = self._ppf.vote_groups(cloud.points, cloud.normals, groups,
                                                          JOINED_REF_SPACING * self.fe.shape_ref_step,
                                                          self.fe.shape_max_partners, leads=leads)
        return self.segment_poses(self._ppf.canonical_poses(poses), share, group, taken, k=JOINED_CLUSTERS)

    def refine_all(self, transforms, cloud: FrameCloud, view: FrameView, started: "Prefetch | None" = None,
                   offset: int = 0) -> list[Explanation]:
        """Each hypothesis refined by ICP and explained (``refine_one``), those the depth
        hardly supports dropped. Hypotheses that are one pose (ECC's and the vote clusters'
        for one instance) are refined once: the first of each group, in the order given
        (``distinct``: best first, so that the frame's deadline leaves the weakest), except
        that one centred on an instance already verified waits for the rest (``Deferring``).
        On each worker of the shared thread pool (the kernels, k-d tree queries and OpenCV
        calls release the GIL). ``started``: a ``Prefetch`` (``start_refining``) of
        ``transforms[offset:]`` already under way; what it has taken on is used. The
        explanations in the order given, whatever order they were refined in."""
        if cloud.grid is None:
            return []
        order = self.distinct(transforms)
        claimed = started.stop() if started is not None else set()
        missing = [k for k in order if k - offset not in claimed]
        hypotheses = {k: np.array(transforms[k], np.float64) for k in missing}
        queue = Deferring(missing, {k: self.centre(T) for k, T in hypotheses.items()}, 0.5 * self._thinnest)
        for e in (started.finished() if started is not None else []):
            if self.verified(e):
                queue.verified(self.centre(e.T))
        refined = {}

        def work(_):
            while (k := queue.next()) is not None:
                refined[k] = e = self.refine_one(hypotheses[k], cloud, view)
                if self.verified(e):
                    queue.verified(self.centre(e.T))

        for worker in submit_each(work, range(os.cpu_count() or 1)):
            worker.result()
        out = [refined[k] if k in refined else started.result(k - offset) for k in order]
        return [e for e in out if e is not None]

    def centre(self, T: np.ndarray) -> np.ndarray:
        """The centre of the model's box at pose T (camera frame)."""
        return T[:3, :3] @ self._box_centre + T[:3, 3]

    def verified(self, e: Explanation | None) -> bool:
        """Whether explanation ``e`` passes as an instance on its own (nothing claimed)."""
        return e is not None and e.support >= self.fe.shape_min_support and e.evidence >= self.fe.shape_min_evidence

    def start_refining(self, transforms, cloud: FrameCloud, view: FrameView) -> "Prefetch | None":
        """The vote clusters' poses refined on one worker of the shared thread pool while
        ECC runs on this thread, the weakest first: the strongest are the ones most often
        duplicated by an ECC transform (and then not needed); ``refine_all(...,
        started=)`` stops it and takes its results. None on a single core."""
        if cloud.grid is None or len(transforms) == 0:
            return None
        first = self.distinct(transforms)
        rest = sorted(set(range(len(transforms))) - set(first))
        return Prefetch(lambda T0: self.refine_one(T0, cloud, view),
                        [np.array(T, np.float64) for T in transforms], sorted(first, reverse=True) + rest[::-1])

    def distinct(self, transforms) -> list[int]:
        """Indices of the transforms to refine: the first of each group of near-identical
        ones (within the vote clusters' 24 deg and a tenth of the diagonal), in the order
        the groups are refined."""
        if len(transforms) <= 1:
            return list(range(len(transforms)))
        return list(cluster_poses(np.stack([np.asarray(T, np.float64) for T in transforms]),
                                  -np.arange(len(transforms), dtype=np.float64), 360.0 / ANGLE_STEPS,
                                  0.1 * self.diameter, len(transforms), min_members=1, indices=True))

    def refine_one(self, T0: np.ndarray, cloud: FrameCloud, view: FrameView) -> Explanation | None:
        """Hypothesis T0 refined by ICP and explained against the frame, nothing claimed
        (``explain``); None past the frame's deadline or where the depth hardly supports it.
        Reads only the frame's data: safe in several threads at once."""
        fe = self.fe
        if self.past_deadline():
            return None
        depth_m, intrinsics = view.depth, view.intrinsics
        fit = lambda T: self.depth_check(T, depth_m, intrinsics)
        first = min(3, fe.shape_icp_iterations)
        # The depth check first (a projection, no search), then a few rounds of ICP: a
        # hypothesis the depth hardly supports is dropped without paying for the rest
        # (most of ECC's clusters are wrong).
        start = fit(T0)
        if cloud.patches is not None:
            # On a frame patch shaped as one of its faces (a carton's top seen whole): placed
            # by the patch's outline, which holds what ICP on the face alone does not (its
            # turn and shift in the plane), if the depth agrees at least as well.
            on_patch = nearest_face_pose(self._faces, cloud.patches, cloud.patch_fits, T0,
                                         0.1 * self.diameter + self.voxel)
            if on_patch is not None and (moved := fit(on_patch))[0] >= start[0]:
                T0, start = on_patch, moved
        if start[1] < 0.25 * fe.shape_min_support:
            return None
        T = self._icp(T0, cloud, depth_m, intrinsics, ICP_REACH * self.voxel, first)
        best = max([start + (T0,), fit(T) + (T,)], key=lambda c: c[0])
        if best[1] < 0.5 * fe.shape_min_support:
            return None
        T = self._icp(best[3], cloud, depth_m, intrinsics, 1.5 * self.voxel, fe.shape_icp_iterations - first)
        # ICP can slide a box seen by one face alone: whichever pose the depth supports better.
        best = max([best, fit(T) + (T,)], key=lambda c: c[0])
        if best[2] > OVERHANG:
            # Overhanging space seen empty: nearest-point ICP paired points across a
            # non-convex object's parts (or onto a neighbour). Projective ICP pairs each
            # model point with the depth on its ray instead.
            T = align_projective(best[3], self._surface, self._surface_normals, depth_m, intrinsics,
                                 PROJECTIVE_ROUNDS, 1.5 * self.voxel, 0.75 * self.voxel).T
            best = max([best, fit(T) + (T,)], key=lambda c: c[0])
        if cloud.patches is not None:
            # A face that is a piece of a larger plane in depth (cartons packed flush) is
            # held in that plane by nothing but its patch's outline, and ICP slides it there
            # for a little more support (its hidden sides paired with a neighbour's top,
            # 0.02-0.05 more, 2-3 cm off): put back on its patch in its plane, unless the
            # depth supports ICP's pose by more than PATCH_SLACK. Where gaps show in depth,
            # ICP's place is the better one (a noisy patch's outline is off by a few mm and deg).
            fits = cloud.patch_fits & cloud.patches.joined[:, None]
            on_patch = nearest_face_pose(self._faces, cloud.patches, fits, best[3],
                                         0.1 * self.diameter + self.voxel, keep_plane=True)
            if on_patch is not None and not _within(on_patch[None], best[3][None], 1.0, 0.25 * self.voxel)[0] \
                    and (moved := fit(on_patch))[0] >= best[0] - PATCH_SLACK:
                best = moved + (on_patch,)
        # The most its appearance could add (a model with colour): the bound stays a bound.
        looks = APPEARANCE_WEIGHT * (1.0 - APPEARANCE_BASE) if self._surface_grey is not None else 0.0
        # Not worth an explanation: not even were everything that hides it explained
        # (``explain.select``'s ``possible``, by the cheap check).
        worth = lambda c: c[1] - FREE_WEIGHT * c[2] >= (0.9 * fe.shape_min_evidence - looks) * (c[1] + c[2])
        # The depth check that guides ICP does not see an outline: ICP can carry a pose off
        # a box whose faces are flush with its neighbours' (onto half of each, for a little
        # more support). Where it moved the pose farther than two hypotheses that are one
        # (``distinct``) and the moved pose fails, its start is explained too, the better kept.
        carried = not _within(best[3][None], T0[None], 360.0 / ANGLE_STEPS, 0.1 * self.diameter)[0]
        tries = [c for c in [best] + ([start + (T0,)] if carried else []) if worth(c)]
        if not tries:
            return None
        first = self.explain(tries[0][3], cloud, view, needed=fe.shape_min_evidence)
        if len(tries) == 1 or first.evidence >= fe.shape_min_evidence:
            return first
        return max([first, self.explain(tries[1][3], cloud, view, needed=fe.shape_min_evidence)],
                   key=lambda e: e.evidence)

    def depth_check(self, T, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[float, float, float]:
        """(support - free, support, free) of the model's surface at pose T
        (``geometry.depth_support``, compiled: the cheap look that guides ICP), over the
        points seen but no fewer than ``MIN_SEEN`` of all, as ``explain`` judges a pose;
        (-1, 0, 1) with fewer than ``MIN_VISIBLE`` points judged."""
        support, free, n = depth_support(T, self._surface, self._surface_normals, depth_m, intrinsics,
                                         self.tolerance_at(T), self._self_hiding)
        if n < MIN_VISIBLE:
            return -1.0, 0.0, 1.0
        judged = max(support + free, MIN_SEEN)
        return (support - free) / judged, support / judged, free / judged

    def explain(self, T, cloud: FrameCloud, view: FrameView, claimed: np.ndarray | None = None,
                needed: float | None = None) -> Explanation:
        """``explain.explain`` of pose T with this model's surface, tolerance and support."""
        return explain(T, self._surface, self._surface_normals, view, self.tolerance_at(T), self.voxel,
                       self._same_surface(T), claimed, up=cloud.up, planes=cloud.planes,
                       sigma=self.depth_noise * float(T[2, 3]) ** 2, span=self.diameter, grey=self._surface_grey,
                       creases=self._creases, needed=needed)

    def choose(self, candidates: list[Explanation], cloud: FrameCloud, view: FrameView, conflicts) -> list[Explanation]:
        """The instances among the refined ``candidates``, chosen jointly (``explain.select``);
        ``conflicts(e, chosen)``: whether two explanations' model volumes overlap."""
        K = view.intrinsics.K
        z = float(np.median([e.T[2, 3] for e in candidates])) if candidates else 1.0
        px = K[0, 0] * self.voxel / max(z, 1e-3)        # a voxel in pixels at the candidates' distance
        return select(candidates, lambda e, claimed: self.explain(e.T, cloud, view, claimed), conflicts,
                      self.fe.shape_min_support, self.fe.shape_min_evidence, max(1, int(round(0.75 * px))),
                      int(np.ceil(2.0 * px)), view.depth.shape, self.past_deadline)

    def _same_surface(self, T) -> float:
        """Metres: depth differences within the noise (3 sigma) at pose T's distance, at least
        2 mm and half a voxel: "the same surface" for the outline. The floor in voxels is the
        model's own: its downsampled samples near an edge stand up to about half a voxel off
        their face's plane, and on noiseless depth (measured k 0) a board's top went on past a
        carton's outline in 6 % of the band at 2 mm, 75 % at half a voxel (99.6 % at k 0.002)."""
        return max(3.0 * self.depth_noise * float(T[2, 3]) ** 2, 0.002, 0.5 * self.voxel)

    def set_deadline(self, at: float | None) -> None:
        """Refine no further hypothesis once ``search_time()`` passes ``at`` (None: no
        bound); ``deadline_cut`` says afterwards whether that turned any away. CPU time less
        the kernels' one-off compilation (``search_clock``), not the clock's: what the frame
        costs, whatever else the host runs (on a host of its own the two agree), so that a
        replay or a benchmark finds the same instances at any load."""
        self._deadline, self.deadline_cut = at, False

    def past_deadline(self) -> bool:
        """Whether the frame's deadline has passed (and so work is turned away: counted)."""
        if self._deadline is None or search_time() < self._deadline:
            return False
        self.deadline_cut = True
        return True

    def _icp(self, T, cloud: FrameCloud, depth_m, intrinsics, max_dist: float, iterations: int) -> np.ndarray:
        """Point-to-plane ICP of the model's surface facing the camera, paired as
        ``shape_icp_association`` says: with the frame cloud's nearest points, or with the
        depth pixels the model points project to (the tracker's ICP)."""
        if self.fe.shape_icp_association == "projective":
            return align_projective(T, self._surface, self._surface_normals, depth_m, intrinsics, iterations,
                                    max_dist, 0.5 * max_dist).T
        return icp_point_to_plane(T, self._surface, cloud.grid, max_dist=max_dist, iterations=iterations,
                                  model_normals=self._surface_normals)[0]


class Prefetch:
    """``function`` of items, in the given order, on one worker of the shared thread pool,
    until ``stop``; the results by item index (``result``). Nothing is run on a single core."""

    def __init__(self, function, items, order):
        self._function, self._items, self._order = function, items, list(order)
        self._lock = threading.Lock()
        self._stopped = False
        self._claimed: set[int] = set()
        self._done: dict = {}
        pool = shared_pool()
        self._future = pool.submit(self._run) if pool is not None else None

    def _run(self) -> None:
        for k in self._order:
            with self._lock:
                if self._stopped:
                    return
                self._claimed.add(k)
            result = self._function(self._items[k])
            with self._lock:
                self._done[k] = result

    def stop(self) -> set[int]:
        """Takes on no more items; returns those it has taken on (done, or under way)."""
        with self._lock:
            self._stopped = True
            return set(self._claimed)

    def finished(self) -> list:
        """The results done so far."""
        with self._lock:
            return list(self._done.values())

    def result(self, k: int):
        """Item k's result (one taken on), once it is done."""
        if self._future is not None:
            self._future.result()      # the worker's exception, if any, is raised here
        return self._done[k]


class Deferring:
    """Items handed out in a given order to whichever worker asks (``next``), except that
    one whose place lies within ``reach`` of an instance verified so far (``verified``)
    waits until only such items are left. Two objects cannot fill one space: a hypothesis
    centred within half the object's thinnest extent of a verified instance's centre is
    mostly that instance again (IC-BIN, 80 clusters: 39 of the 45 refinements that landed
    on a cup found before began within 45 mm of it, none of the 27 that found a new cup
    began nearer than 75 mm). With a deadline the budget goes to the rest of the frame
    first; without one the same items are refined."""

    def __init__(self, order, places: dict, reach: float):
        self._order = list(order)
        self._places = np.array([places[k] for k in self._order], np.float64).reshape(-1, 3)
        self._reach = float(reach)
        self._taken = np.zeros(len(self._order), bool)
        self._near = np.zeros(len(self._order), bool)    # within reach of a verified instance
        self._lock = threading.Lock()

    def verified(self, place: np.ndarray) -> None:
        with self._lock:
            self._near |= np.linalg.norm(self._places - np.asarray(place, np.float64), axis=1) < self._reach

    def next(self):
        """The next item (None when none is left)."""
        with self._lock:
            left = ~self._taken
            if not left.any():
                return None
            free = left & ~self._near
            i = int(np.argmax(free if free.any() else left))
            self._taken[i] = True
            return self._order[i]


def _within(poses: np.ndarray, others: np.ndarray, max_angle_deg: float, max_shift: float) -> np.ndarray:
    """(len(poses),) bool: within ``max_angle_deg`` and ``max_shift`` of any of ``others``."""
    if len(poses) == 0 or len(others) == 0:
        return np.zeros(len(poses), bool)
    cos = (np.einsum("aij,bij->ab", poses[:, :3, :3], others[:, :3, :3]) - 1.0) / 2.0
    shift = np.linalg.norm(poses[:, None, :3, 3] - others[None, :, :3, 3], axis=2)
    return np.any((cos >= np.cos(np.radians(max_angle_deg))) & (shift < max_shift), axis=1)


# ``object_face_heights``: model surface samples facing this close to up (degrees) ...
FACE_UP_DEG = 10.0
# ... at least this many within half a voxel of one height make a face there.
FACE_MIN_POINTS = 10


def object_face_heights(surface: np.ndarray, normals: np.ndarray, voxel: float) -> np.ndarray:
    """The heights (metres, ascending) above its support at which the model, resting on a
    side of its box, shows a flat face facing up: the channel lying open side down its back
    at 5 cm, open side up its floor at 8 mm and its rims at 5 cm, on a side its wall at 10
    cm. Surface samples (model frame, box axes) facing up within FACE_UP_DEG, binned by
    half a voxel."""
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            s = sign * surface[:, axis]
            up = sign * normals[:, axis] >= np.cos(np.radians(FACE_UP_DEG))
            h = s[up] - s.min()
            binned = np.rint(h / (0.5 * voxel)).astype(np.int64)
            bins, counts = np.unique(binned, return_counts=True)
            out.extend(float(np.mean(h[binned == b])) for b in bins[counts >= FACE_MIN_POINTS])
    return np.unique(np.round(np.asarray([x for x in out if x > 0.5 * voxel]), 4))


def central_radius(points: np.ndarray) -> float:
    """The least, over the points, of the largest distance from one to any other: the radius
    of the smallest ball about one of them that holds them all. The farthest point from any
    point is a vertex of their convex hull."""
    from scipy.spatial import ConvexHull, QhullError
    from scipy.spatial.distance import cdist

    points = np.asarray(points, np.float64)
    try:
        far = points[ConvexHull(points).vertices]
    except QhullError:          # flat or too few points: every point is a candidate
        far = points
    return float(cdist(points, far).max(axis=1).min())


def oriented_downsample(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The mean point and normal per voxel and normal direction (the nearest of +-x, +-y,
    +-z): the two sides of a plate thinner than two voxels stay apart, each with its own
    outward normal (a visible side is matched, ICP'd and checked against its own side)."""
    normals = np.asarray(normals, np.float64)
    side = np.argmax(np.abs(normals), axis=1) * 2 + (normals[np.arange(len(normals)), np.argmax(np.abs(normals), axis=1)] < 0)
    keys = np.floor(np.asarray(points, np.float64) / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = ((keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]) * 6 + side
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    out_p = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)], 1)
    out_n = np.stack([np.bincount(inverse, weights=normals[:, k], minlength=len(counts)) for k in range(3)], 1)
    out_n /= np.maximum(np.linalg.norm(out_n, axis=1, keepdims=True), 1e-12)
    return out_p / counts[:, None], out_n


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


__all__ = ["ShapeFrontEnd", "FrameCloud", "FrameView", "resolve_correspondences", "oriented_downsample"]
