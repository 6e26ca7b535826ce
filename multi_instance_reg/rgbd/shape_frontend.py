"""The shape front end of the per-frame pipeline: correspondences from depth alone, and the
refinement and depth check of the poses ECC finds from them. No ROS, no colour.

    shape = ShapeFrontEnd(model, frontend_config)
    cloud = shape.frame_cloud(depth_m, intrinsics, search_mask)    # search-region points, normals, FPFH
                                                                    # (gravity=up: which support is "below")
    src, tgt = shape.correspondences(cloud)                         # model points -> scene points
    ... ECC on (src, tgt) (with ``shape.ecc_config(base)``) ...
    kept = shape.refine_and_check(transforms, cloud, depth_m, intrinsics)   # [(T, support, agreeing points, evidence)]
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..core import ECCConfig
from ..errors import InputError
from ..messages import CameraIntrinsics
from ..models.model import ObjectModel
from .ppf import ANGLE_BINS as ANGLE_STEPS, PPFModel, cluster_poses
from .faces import Faces, frame_patches, matches, model_faces, nearest_face_pose, patch_poses
from .segments import (connected_segments, pairs_across_steps, segments_within_reach, support_mask,
                       within_reach)
from .verify import facing_camera, image_pixels, in_view_share, outline_continuation, outline_shift
from ..threads import map_each, shared_pool, submit_each
from ..tracking.icp import align_projective
from ..transforms import rotation_angle_deg
from .shape import (PointGrid, ShapeMatcher, apply_twist, depth_support, describe, icp_point_to_plane, is_convex,
                    noise_agreement, scene_cloud, surface_normals, voxel_downsample)


# ICP pairs a model point with a scene point at most this many voxels away.
ICP_REACH = 2.0
# The second look (``_refine``) is tried on a rejected pose at least this far along: its
# support and support - free, and at least this share of it in front of the depth (it
# overhangs space seen empty: off, not hidden behind something).
SECOND_LOOK_MIN = 0.6
SECOND_LOOK_MIN_FREE = 0.02
# Its projective ICP's rounds (the pairing distance shrinks over them from 1.5 to 0.75 voxel;
# 0.3-0.5 ms for 10): bracket seed 1947, from a pose ICP left 29 deg / 9 mm off 10 rounds stop
# where it was and 30 reach 0.1 deg / 2 mm (frame 4); from another 10 rounds stop 1.6 deg / 17
# mm off (rejected), 30 reach 0.2 deg / 2 mm (frame 5).
SECOND_LOOK_ITERATIONS = 30
# ... and for this many: the pairing distance narrows over the rounds, so from a near start the
# rounds can also carry a pose past the fit (channel seed 5 frame 9: a channel at support - free
# 0.85 after 10 rounds, 0.74 after 30, rejected); the look keeps whichever fits better.
SECOND_LOOK_SHORT = 10
# A pose is rejected when the model reaches more than this many voxels through the frame's
# largest support plane (``pierces``).
PIERCE_VOXELS = 2.0
# ... where the depth does not reach past the plane on the rays of at least this share of them.
PIERCE_SHARE = 0.3
PIERCE_MIN_POINTS = 3
# ``judge_hidden``: the depth steps at least this many tolerances forward from the agreeing
# points to the hidden points next to them.
HIDDEN_STEP = 2.0
# ``turned_over_starts``: a rejected pose of a non-convex model is judged again turned over when
# at least this share of its visible surface lies in front of the depth (what it shows towards
# the camera, the object hides: an open channel's walls and rims standing up from its floor,
# fitted onto the top of one lying open side down).
TURNED_OVER_MIN = 0.15
# ``near_twins``: a half turn of the model (about a box axis or the bisector of two) is a near
# symmetry when at least this share of its surface samples then lies within a voxel of its own
# surface (shifted to fit best). The L bracket's swap of its two plates (half a turn about the
# bisector of its corner): 0.58; every other half turn of it 0.28 at most. The channel's and the
# stairs' turn over (about x, y): 0.60-0.65 (the channel's about z is a symmetry); the tee's 0.49.
NEAR_SYMMETRY_MIN = 0.5
# ``_held_look``: a rejected pose of a non-convex model is refined again with held ICP when at
# least this share of its visible surface agrees with the depth (and the rest lies in front of
# it), and moved by its outline when the held pose's does. The poses it set right on channel
# seeds 1607 / 631 had 0.52-0.93 before and after; half the calls, the same hits, for ~30 %
# less of its CPU.
HELD_LOOK_MIN = 0.5
# Rejected poses this close (degrees; and half a voxel) are one pose for ``judge_pairs``.
SAME_POSE_DEG = 3.0
# A direction holds ICP when at least this share of the visible normals' weight lies along it.
UNHELD_SHARE = 0.1
# The segments of several objects are voted over the whole diameter too (non-convex models,
# ``shape_merged_clusters``) with every this-many-th reference of the short-reach votes: the
# same hits on channel seeds 5 / 311 and bracket 0 / 9 / 13 / 33 / 47 / 113 as with every one
# (channel 9 one more, 307 one fewer), for ~30 ms less CPU a busy channel frame.
MERGED_REF_STRIDE = 2
# ``residual_poses``: a frame point within this many voxels of a found instance's surface is
# that instance's, and left out of the votes again.
RESIDUAL_VOXELS = 1.5
# The least evidence (support - free - 2 x outline), as a share of shape_min_evidence, of a
# rejected pose whose points the residual votes leave out (``supported_evidence``): channels
# rejected on their outlines onto an unfound flush neighbour had 0.66-0.82 (channel seeds
# 2251 / 2141); a fit at the image's edge with a third of its outline on a larger surface
# (0.23, channel 2396 frame 6) left a distractor's remnant that voted a wrong pose which passed.
SUPPORTED_EVIDENCE_SHARE = 0.5
# ``climbed``: at most this many turned starts a pose (improvements and halvings of the turn:
# channel seed 2141 frames 0-2 took 3-9).
CLIMB_STEPS = 12


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
    planes: tuple = ()                    # every support plane with a large piece removed: (normal, offset)
    grid: PointGrid | None = None         # the points and normals for ICP's nearest-point search
    patches: Faces | None = None          # the segments' flat patches shaped as a model face (ppf, shape_faces)
    patch_fits: np.ndarray | None = None  # (J, F) bool: patch j has model face f's outline
    compact: np.ndarray | None = None     # ids of the segments within the object's diameter (``compact_segments``)


class ShapeFrontEnd:
    def __init__(self, model: ObjectModel, fe):
        self._frame_memo = None       # keep_frame's (depth, intrinsics, {poses: image}, {(pose, occluders): check})
        self._found_test = None       # _on_found's last (poses' bytes, test)
        self._deadline = None         # set_deadline's time.perf_counter() bound, or None
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
        self.diameter = float(np.linalg.norm(model.extent))
        # Metres: the farthest the depth check can tell the object's shape from any surface
        # there: its tolerance (3 sigma of the depth noise, sigma = shape_depth_noise x z^2)
        # at most shape_max_noise_share of the object's diameter. Beyond, every surface of
        # its size agrees (IC-BIN, a room 2-3 m behind a bin of cups: 30-56 mm against a
        # cup's 45 mm radius, support 0.8-1.0 on clutter). No points from there.
        k, share = fe.shape_depth_noise, fe.shape_max_noise_share
        self.resolvable_depth = float(np.sqrt(share * self.diameter / (3.0 * k))) if k > 0 and share > 0 else np.inf
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
        # ``_turned_over``'s half turns, per model axis standing up (for the channel and tee, whose
        # half turn about z maps them onto themselves, one: the turns about x and y are alike).
        self._half_turns = self._flip_axes() if self._self_hiding > 0 else [[], [], []]
        # ``near_twins``' maps (model frame, 4 x 4; made at the first call: 60-90 ms, wanted
        # only when the turned-over pass accepts a pose).
        self._near_symmetries = None
        self.features = fe.shape_features
        if self.features == "ppf":
            self._ppf = PPFModel(self._surface, self._surface_normals, self.diameter, self.voxel, model.symmetries,
                                 bucket_cap=fe.shape_ppf_bucket)
            # The largest flat piece the object can show: its two largest box sides.
            e = np.sort(np.asarray(model.extent, np.float64))
            self._max_face_area = float(e[1] * e[2])
            # Where flush tops of such objects would lie above their support (support_mask).
            self._face_heights = object_face_heights(self._surface, self._surface_normals, self.voxel)
            # The model's flat faces with a long axis (a carton's six): a frame patch with
            # the same outline moments places the pose (rgbd/faces.py). Convex models only:
            # a non-convex one hides parts of its own faces (the bracket's upright, its base
            # plate), and a plate's outline does not say on which side the rest lies
            # (bracket MHF1 seed 0 / 5: 0.925 / 0.833 -> 0.901 / 0.828 with them).
            self._faces = model_faces(self._surface, self._surface_normals, self.voxel) \
                if fe.shape_faces and self._self_hiding == 0 else None
        else:
            self._matcher = ShapeMatcher(model.shape_descriptors[keep], k=fe.shape_neighbours)

    @property
    def depth_tolerance(self) -> float:
        """Metres: a model point agrees with the depth image within this."""
        return max(self.fe.shape_depth_tolerance, 0.8 * self.voxel)

    @property
    def non_convex(self) -> bool:
        """Whether the model hides parts of itself (an L bracket; ``_self_hiding``)."""
        return self._self_hiding > 0

    def tolerance_at(self, T: np.ndarray) -> float:
        """Metres: agreement with the depth image for an instance at pose T, within the depth
        noise at its distance (3 sigma; 2.4 cm at 2 m, where a fixed 1.2 cm left true cartons
        at 0.88 support and 0.1 "free")."""
        return max(self.depth_tolerance, 3.0 * self.fe.shape_depth_noise * float(T[2, 3]) ** 2)

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
        if search is None:
            search = (depth_m >= self.fe.depth_min) & (depth_m <= self.fe.depth_max)
        if np.isfinite(self.resolvable_depth):
            search = search & (depth_m <= self.resolvable_depth)
        if self.features == "ppf":
            return self.segment_cloud(depth_m, intrinsics, search, gravity, within)
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
                     fe.shape_plane_thresh, fe.shape_depth_noise, stride=2, ground=ground, planes=planes,
                     up=gravity, up_tolerance_deg=fe.shape_gravity_tolerance_deg, rest=rest,
                     face_heights=self._face_heights if fe.shape_keep_object_tops else None)
        pts = rest[0]
        if within is not None:
            pts = pts[within[rest[1][:, 0], rest[1][:, 1]]]
        pts = voxel_downsample(np.asarray(pts, np.float64), self.voxel)
        empty = FrameCloud(pts, np.zeros_like(pts), np.zeros(0, np.int64), np.zeros((0, 33), np.float32), None,
                           np.full(len(pts), -1, np.int64))
        if len(pts) < 10:
            return empty
        # The segments on the other core while the normals are estimated here (neither
        # needs the other; both searches release the GIL and share one tree), and the ICP
        # grid built here while the segments, the longer of the two, are finished.
        tree = cKDTree(pts)
        segments = submit_each(lambda p: connected_segments(p, fe.shape_segment_link * self.voxel,
                                                            fe.shape_min_segment, tree=tree), [pts])[0]
        normals = surface_normals(pts, self.voxel, toward=np.zeros(3), tree=tree)
        grid = PointGrid(pts, normals, ICP_REACH * self.voxel)
        labels = segments.result()
        return FrameCloud(pts, normals, np.zeros(0, np.int64), np.zeros((0, 33), np.float32), tree, labels,
                          up=ground[0] if ground else None, up_offset=ground[1] if ground else None,
                          planes=tuple(planes), grid=grid)

    def correspondences(self, cloud: FrameCloud, on_poses=None, on_matches=None) -> tuple[np.ndarray, np.ndarray]:
        """(model points (N, 3), scene points (N, 3)). ppf: each reference point of a
        segment with the model point its pair votes choose (over the symmetries); fpfh: each
        salient scene point with its ``shape_neighbours`` nearest model descriptors.
        ``on_poses()`` is called as soon as ``cloud.poses`` (ppf) is set (to start their
        refinement); ``on_matches(src, tgt)`` (ppf) as soon as the correspondences are made,
        before the vote clusters' poses, which they do not depend on (to start ECC on them)."""
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
                cloud.poses = cluster_poses(poses, share, 360.0 / ANGLE_STEPS, 0.1 * self.diameter,
                                            self.fe.shape_pose_clusters)
                if self._self_hiding > 0 and self.fe.shape_segment_clusters > 0:
                    # Non-convex models only: a convex one's segment is one surface whose
                    # votes agree (pallet and cylinders seeds 0 / 5: the same results with
                    # them, for 12-20 ms more refinement a pallet frame).
                    cloud.poses = np.concatenate([cloud.poses, self.segment_poses(poses, share, cloud.segments[s],
                                                                                  cloud.poses)])
                if self._self_hiding > 0 and self.fe.shape_joined_clusters > 0:
                    cloud.poses = np.concatenate([cloud.poses, self.joined_poses(cloud)])
                if self._self_hiding > 0 and self.fe.shape_merged_clusters > 0 and reach is not None:
                    # Non-convex models: the segments of several objects voted over the whole
                    # diameter too, their best clusters added: a plate's pose is told by pairs
                    # reaching to the other plate, farther than ``partner_reach`` (touching
                    # brackets: seed 0 89 -> 86 hits without them, 88 with). Every other
                    # reference is enough for those few clusters.
                    merged = np.where(np.isfinite(reach), cloud.segments, -1)
                    s2, _, far, far_share = self._ppf.vote(cloud.points, cloud.normals, merged,
                                                           MERGED_REF_STRIDE * self.fe.shape_ref_step,
                                                           self.fe.shape_max_partners)
                    cloud.poses = np.concatenate([cloud.poses, self.segment_poses(
                        self._ppf.canonical_poses(far), far_share, merged[s2], cloud.poses,
                        self.fe.shape_merged_clusters)])
                if self._faces is not None and len(self._faces):
                    # The face poses first; a vote cluster that one of them would be refined
                    # for (``distinct``) is left out: moved onto the same patch, it would be
                    # the same pose, refined twice.
                    faces = self.face_poses(cloud)
                    near = _within(cloud.poses, faces, 360.0 / ANGLE_STEPS, 0.1 * self.diameter)
                    cloud.poses = np.concatenate([faces, cloud.poses[~near]])
            if on_poses is not None:
                on_poses()
            return src, tgt
        s, m = self._matcher.match(cloud.descriptors)
        return self._model_pts[self._model_idx[m]], cloud.points[cloud.salient[s]]

    def partner_reach(self, cloud: FrameCloud, labels: np.ndarray | None = None) -> np.ndarray | None:
        """(M,) metres: how far from each point of the cloud, as a reference, its vote
        partners may lie, by segment (``labels``; default ``cloud.segments``); None: the
        object's diameter everywhere. In a segment larger than the
        object (two points farther apart than its diameter), with ``shape_merged_reach``,
        ``central_reach``: touching instances form one segment (channels side by side, their
        tops flush), and partners spread over the diameter lay mostly on the neighbours
        (open-side-down channels merged in pairs or fours: 0-5 right references of 70-100
        each; voted over their own points alone, 10-60). A reference near its instance's
        middle still pairs with all of it."""
        own = labels is None
        labels = cloud.segments if own else labels
        if not self.fe.shape_merged_reach or labels is None:
            return None
        compact = self.compact_segments(cloud) if own else segments_within_reach(cloud.points, labels, self.diameter)
        reach = np.full(len(cloud.points), np.inf)
        reach[(labels >= 0) & ~np.isin(labels, compact)] = self.central_reach
        return reach if np.isfinite(reach).any() else None

    def compact_segments(self, cloud: FrameCloud) -> np.ndarray:
        """``segments_within_reach`` of the cloud's segments and the object's diameter, found
        once a frame (``partner_reach`` and ``joined_poses`` both ask: 3-4 ms a channel frame)."""
        if cloud.compact is None:
            cloud.compact = segments_within_reach(cloud.points, cloud.segments, self.diameter)
        return cloud.compact

    def face_poses(self, cloud: FrameCloud) -> np.ndarray:
        """(K, 4, 4) pose hypotheses from the segments' flat patches whose outline moments are
        a model face's (``faces.patch_poses``; a carton seen from above shows its top alone,
        and its references' votes are blurred in the plane of it), one per pose the object's
        symmetries tell apart. Also keeps those patches (``cloud.patches``, ``patch_fits``) for
        ``_refine``."""
        fe = self.fe
        patches = frame_patches(cloud.points, cloud.normals, cloud.segments, self.diameter,
                                fe.shape_segment_link * self.voxel,
                                lambda z: max(self.depth_tolerance, 3.0 * fe.shape_depth_noise * z * z))
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

    def joined_poses(self, cloud: FrameCloud) -> np.ndarray:
        """(K, 4, 4) pose hypotheses from segments voted together in pairs: for a non-convex
        object, two segments side by side across a depth step that one object could span
        (``pairs_across_steps``; an L bracket seen from behind: its upright plate, and its
        base plate past the step; or one of them joined with a neighbour), each pair's best
        ``shape_joined_clusters`` clusters of its references' poses voted over both (of a
        segment larger than the object, its points within the object's reach of the
        other). Not given to ECC: its correspondences stay those of each segment alone
        (voting across segments everywhere cost the others their references)."""
        fe = self.fe
        pairs = pairs_across_steps(cloud.points, cloud.segments, self.diameter, fe.shape_segment_link * self.voxel,
                                   small=self.compact_segments(cloud))
        if not pairs:
            return np.zeros((0, 4, 4))
        groups = []
        for a, b in pairs:
            # b's points within reach of a's centre: all of b when both fit in the reach (the
            # centre lies among a's points), else (b joins a neighbour) the part near a.
            group = np.flatnonzero((cloud.segments == a) | (cloud.segments == b))
            centre = cloud.points[cloud.segments == a].mean(axis=0)
            groups.append(group[np.linalg.norm(cloud.points[group] - centre, axis=1) <= self.diameter])
        # All pairs in one call (its references split over the two cores).
        _, _, poses, share, which = self._ppf.vote_groups(cloud.points, cloud.normals, groups, fe.shape_ref_step,
                                                          fe.shape_max_partners)
        poses = self._ppf.canonical_poses(poses)
        out = []
        for k in range(len(groups)):
            mine = which == k
            if mine.sum() >= 2:
                # Seeded by the densest pose: a pair's references are few (40-60), and those
                # on a flat plate spread about the right pose; the strongest was 25-30 deg
                # off on standing brackets seen from above, which ICP does not turn back.
                out.append(cluster_poses(poses[mine], share[mine], 360.0 / ANGLE_STEPS, 0.1 * self.diameter,
                                         fe.shape_joined_clusters, densest=True))
        return np.concatenate(out) if out else np.zeros((0, 4, 4))

    def residual_poses(self, cloud: FrameCloud, found, taken, depth_m: np.ndarray | None = None,
                       intrinsics: CameraIntrinsics | None = None, kept=(), supported=()) -> np.ndarray:
        """(K, 4, 4) hypotheses voted again over what the instances ``found`` leave of the
        segments they touch: their points (within ``RESIDUAL_VOXELS`` of a found pose's
        surface) taken out, the rest cut into connected segments again, each one's best
        ``shape_segment_clusters`` clusters of its references' poses (those not among
        ``taken``, the hypotheses already refined). A bracket in a segment with its
        neighbours pairs its references with their points: missed brackets that pass every
        check at their true pose had 0-3 right references of 40-60 in the frame's votes,
        11-32 voted over their own points alone (seed 157). With the frame (``depth_m``,
        ``intrinsics``), also ``bridged_poses``. ``kept``: more poses whose segments are voted
        again, their points kept in the votes. ``supported``: rejected poses the depth supports
        (``shape_min_support``), their points left out as the found ones' are, and only the
        segments they lie in voted again: flush neighbours rejected on their outlines onto an
        instance with no hypothesis leave its points to vote alone (channel seed 2251 frame 6:
        2 of 64 references right in a segment of four channels, 12 of 65 over its own points)."""
        empty = np.zeros((0, 4, 4))
        if cloud.segments is None or not (len(found) or len(kept) or len(supported)) or cloud.tree is None:
            return empty
        explained = self._on_found(found)(cloud.points) if len(found) else np.zeros(len(cloud.points), bool)
        touching = explained
        if len(supported):
            # Only the segments those poses lie in: the others are voted without the found
            # instances' points alone (``supported`` not given) as they would be here.
            touching = self._on_found(supported, keep=False)(cloud.points)
            explained = explained | touching
        if len(kept):
            touching = touching | self._on_found(kept)(cloud.points)
        labels = cloud.segments
        touched = np.unique(labels[touching & (labels >= 0)])
        rest = np.flatnonzero(~explained & np.isin(labels, touched))
        fe = self.fe
        new = np.full(len(cloud.points), -1, np.int64)
        if len(rest) >= fe.shape_min_segment:
            new[rest] = connected_segments(cloud.points[rest], fe.shape_segment_link * self.voxel,
                                           fe.shape_min_segment)
        taken = np.asarray(taken).reshape(-1, 4, 4)
        out = empty
        if np.any(new >= 0):
            s, _, poses, share = self._ppf.vote(cloud.points, cloud.normals, new, fe.shape_ref_step,
                                                fe.shape_max_partners, reach=self.partner_reach(cloud, new))
            if len(poses) >= 2:
                out = self.segment_poses(self._ppf.canonical_poses(poses), share, new[s], taken)
        if depth_m is None:
            return out
        # The pieces: those new segments, and the segments no instance found touches.
        pieces = new.copy()
        whole = (labels >= 0) & ~np.isin(labels, touched)
        pieces[whole] = labels[whole] + new.max() + 1
        bridged = self.bridged_poses(cloud, found, pieces, np.concatenate([taken, out]), depth_m, intrinsics)
        return np.concatenate([out, bridged]) if len(bridged) else out

    def bridged_poses(self, cloud: FrameCloud, found, pieces: np.ndarray, taken, depth_m: np.ndarray,
                      intrinsics: CameraIntrinsics) -> np.ndarray:
        """(K, 4, 4) pose hypotheses from pieces of the frame's points that a found instance
        splits apart, voted together: two pieces (``pieces``: label per point, -1 none) that
        both meet the pixels of one instance of ``found`` in the image (within the segments'
        link of them) and that one object could span. An instance lying across a bracket
        (in front of it, or on it in one segment) cuts its points into pieces, each voting
        alone: a plate's piece votes blurred and turned-over poses (bracket seed 5 frames
        9-11: a bracket's upright and base plate on either side of one found in front of it,
        40 and 127 points, no right pose among their clusters; voted together, 12 right
        references of 34, and its pose passes behind that one). Each pair's best
        ``shape_joined_clusters`` clusters of its references' poses (as ``joined_poses``),
        those not among ``taken``."""
        fe = self.fe
        seen = np.flatnonzero(pieces >= 0)
        if len(seen) < 2 or not len(found):
            return np.zeros((0, 4, 4))
        K = intrinsics.K
        p = cloud.points[seen]
        uv = np.column_stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]])
        groups, pairs = [], set()
        for F in found:
            # Its pixels (the visible model points the depth agrees with), and the pieces
            # within the segments' link of them in the image (the depth lost along its edge
            # lies between); a k-d tree of those pixels, not the image grown around them
            # (11 ms a frame on seed 0).
            q = self._visible_surface(F)
            u, v, inside = image_pixels(q, intrinsics, depth_m.shape)
            d = depth_m[v[inside], u[inside]]
            tol = self.tolerance_at(F)
            on = np.abs(d - q[inside, 2]) < tol
            if on.sum() < 3:
                continue
            reach = (fe.shape_segment_link + 0.75) * self.voxel * K[0, 0] / float(np.median(d[on]))
            meet = np.isfinite(cKDTree(np.column_stack([u[inside][on], v[inside][on]])).query(
                uv, distance_upper_bound=reach)[0])
            if not meet.any():
                continue
            ids = np.unique(pieces[seen[meet]])
            for i, a in enumerate(ids):
                for b in ids[i + 1:]:
                    if (a, b) in pairs:
                        continue
                    pairs.add((a, b))
                    both = np.flatnonzero((pieces == a) | (pieces == b))
                    if within_reach(cloud.points[both], self.diameter):
                        groups.append(both)
        if not groups:
            return np.zeros((0, 4, 4))
        _, _, poses, share, which = self._ppf.vote_groups(cloud.points, cloud.normals, groups, fe.shape_ref_step,
                                                          fe.shape_max_partners)
        poses = self._ppf.canonical_poses(poses)
        angle, shift = 360.0 / ANGLE_STEPS, 0.1 * self.diameter
        # As ``joined_poses``' pairs: few references, seeded by the densest pose.
        out = [cluster_poses(poses[which == k], share[which == k], angle, shift, fe.shape_joined_clusters,
                             densest=True) for k in range(len(groups)) if np.sum(which == k) >= 2]
        if not out:
            return np.zeros((0, 4, 4))
        out = np.concatenate(out)
        out = out[~_within(out, taken, angle, shift)]
        return out[np.sort(self.distinct(out))] if len(out) > 1 else out

    def refine_and_check(self, transforms, cloud: FrameCloud, depth_m: np.ndarray,
                         intrinsics: CameraIntrinsics, started: "Prefetch | None" = None, offset: int = 0,
                         rejected: list | None = None, second: list | None = None, overlaps=None
                         ) -> list[tuple[np.ndarray, float, int, float]]:
        """Each transform refined by ICP against the frame's points and kept when the depth
        image agrees with the model's visible surface: (T, support share, agreeing points, evidence).
        Hypotheses that are one pose (ECC's and the vote clusters' for one instance) are
        refined once: the first of each group, in the order given (``distinct``); with
        ``second``, where that one fails, the group's next from ``offset`` on as well
        (``_next_of_failed``; kept ones go to ``second``). Each is
        refined and judged on its own (``refine_one``), so they run in the shared thread
        pool, two at a time on two cores (the compiled kernels, k-d tree queries and OpenCV
        calls release the GIL); the results in the order of ``distinct``, the same as one
        at a time. ``started``: a ``Prefetch`` (``start_refining``) of ``transforms[offset:]``
        already under way; what it has taken on is used, the rest is refined here.
        ``rejected``: receives the refined poses rejected for too little support (yet enough
        to be judged: at least half ``shape_min_support``), and with
        ``shape_outline_by_instances`` those rejected by the later checks too, for
        ``judge_behind``. ``second``: receives the poses kept at their second look
        (``shape_second_look``) and the groups' second tries; without it they are not
        returned (nor tried). ``overlaps(Ts, poses)``: (len(Ts), len(poses)) bool, whether each
        pose of Ts takes the place of each of the poses (``poses`` left out: of Ts); None: never.
        A rejected pose that takes a kept one's place gets no further tries (``_rescue``), nor
        do all but the ``shape_rescues_per_place`` best fits of the rejected poses on one place
        (``best_per_place``; those overhanging space seen empty and the others apart)."""
        if cloud.grid is None:
            return []
        order = self.distinct(transforms)
        claimed = started.stop() if started is not None else set()

        def judged(indices):
            tasks = [_Claimed(started, k - offset) if k - offset in claimed else None for k in indices]
            missing = [k for k, task in zip(indices, tasks) if task is None]
            new = iter(submit_each(lambda T0: self._refine_plain(T0, cloud, depth_m, intrinsics),
                                   [np.array(transforms[k], np.float64) for k in missing]))
            return [(task if task is not None else next(new)).result() for task in tasks]

        def refined(indices, kept_before=()):
            # Every pose judged first; the further tries then only for the rejected ones
            # clear of every pose kept (``overlaps``): beside a kept one, what they find is
            # that instance again, or added only where no instance is. Of the rejected poses
            # on one place (several hypotheses refined onto one distractor, or onto one
            # instance they all miss), only the best few fits: what the tries add there
            # is added once (bracket seed 0: 36 tries a frame on 7 places; their CPU a frame
            # 48 -> 38 ms, channel seed 1607 179 -> 158 ms, no result changed).
            plain = judged(indices)
            kept = list(kept_before) + [p.kept[0] for p in plain if isinstance(p, _Plain) and p.kept is not None]
            tries = [p for p in plain if self.wants_rescue(p)]
            if overlaps is not None and tries and kept:
                tries = [p for p, row in zip(tries, overlaps([p.T for p in tries], kept)) if not row.any()]
            if overlaps is not None and len(tries) > self.fe.shape_rescues_per_place > 0:
                # A pose overhanging space seen empty gets looks the others do not (the
                # second look, turned starts): those on a place have their own few (channel
                # seed 2141 frame 11: the one overhanging fit of a channel, its look keeping
                # it, was 4th by the fit after three rejected lying flush, free 0).
                overhang = np.array([p.free >= SECOND_LOOK_MIN_FREE for p in tries])
                same = overlaps([p.T for p in tries]) & (overhang[:, None] == overhang[None, :])
                tries = best_per_place(tries, same, self.fe.shape_rescues_per_place)
            rescued = iter(submit_each(lambda p: self._rescue(p, cloud, depth_m, intrinsics), tries))
            tried = {id(p) for p in tries}
            return [next(rescued).result() if id(p) in tried else _unrescued(p) for p in plain]

        results = refined(order)
        # A group whose first went wrong (an ECC transform ICP slid off, or one the checks
        # turn down) is tried once more from its next hypothesis after ``offset`` (a vote
        # cluster's pose: often refined already, ahead of ECC): seed 157 frame 2 lost a
        # bracket whose vote pose, refined, was right. Those kept go with ``second`` (added
        # only where no instance is): ranked with the rest, a wrong one (91 deg off, passing
        # every check) took a bracket's place from its right pose (seed 0 frame 6).
        again = self._next_of_failed(transforms, order, [k for k, r in zip(order, results) if r[0] is None], offset)
        retried = refined(again, [r[0][0] for r in results if r[0] is not None]) if again and second is not None else []
        if rejected is not None:
            rejected.extend(T for kept, T, support, _ in results + retried if kept is None and T is not None and (
                support < self.fe.shape_min_support or self.fe.shape_outline_by_instances))
        if second is not None:
            second.extend(s for _, _, _, s in results + retried if s is not None)
            second.extend(kept for kept, _, _, _ in retried if kept is not None)
        return [kept for kept, _, _, _ in results if kept is not None]

    def start_refining(self, transforms, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics
                       ) -> "Prefetch | None":
        """The vote clusters' poses refined on one worker of the shared thread pool while
        ECC runs on this thread, the weakest first: the strongest are the ones most often
        duplicated by an ECC transform (and then not needed); ``refine_and_check(...,
        started=)`` stops it and takes its results. None on a single core."""
        if cloud.grid is None or len(transforms) == 0:
            return None
        # Those a pose before them in this list duplicates last: ``refine_and_check`` refines
        # only the first of each group, so they are wanted only where ECC's transforms take
        # that first one away (channel seed 0: of 10-17 taken on in a busy frame, 10-15 were
        # not used, 40-70 ms of the other core's time). The order changes no result.
        first = self.distinct(transforms)
        rest = sorted(set(range(len(transforms))) - set(first))
        return Prefetch(lambda T0: self._refine_plain(T0, cloud, depth_m, intrinsics),
                        [np.array(T, np.float64) for T in transforms], sorted(first, reverse=True) + rest[::-1])

    def _next_of_failed(self, transforms, order, failed, offset: int) -> list[int]:
        """Of each group of near-identical transforms (``distinct``: ``order`` its firsts)
        whose first is among ``failed``, the next member at or after ``offset``; a member
        belongs to the earliest first within ``distinct``'s bounds (as its greedy grouping)."""
        if not failed or len(order) == len(transforms):
            return []
        P = np.stack([np.asarray(T, np.float64) for T in transforms])
        firsts = np.sort(np.asarray(order, np.int64))
        cos = (np.einsum("aij,bij->ab", P[offset:, :3, :3], P[firsts, :3, :3]) - 1.0) / 2.0
        shift = np.linalg.norm(P[offset:, None, :3, 3] - P[firsts][None, :, :3, 3], axis=2)
        near = (cos >= np.cos(np.radians(360.0 / ANGLE_STEPS))) & (shift < 0.1 * self.diameter)
        wanted, out = set(failed), []
        for j in range(offset, len(transforms)):
            g = np.flatnonzero(near[j - offset])
            if len(g) and firsts[g[0]] != j and firsts[g[0]] in wanted:
                wanted.discard(firsts[g[0]])
                out.append(j)
        return out

    def distinct(self, transforms) -> list[int]:
        """Indices of the transforms to refine: the first of each group of near-identical
        ones (within the vote clusters' 24 deg and a tenth of the diagonal), in the order
        the groups are refined."""
        if len(transforms) <= 1:
            return list(range(len(transforms)))
        return list(cluster_poses(np.stack([np.asarray(T, np.float64) for T in transforms]),
                                  -np.arange(len(transforms), dtype=np.float64), 360.0 / ANGLE_STEPS,
                                  0.1 * self.diameter, len(transforms), min_members=1, indices=True))

    def refine_one(self, T0: np.ndarray, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """One hypothesis refined by ICP and judged: (T, support share, agreeing points, evidence), or
        None. Reads only the frame's data: safe to run in several threads at once."""
        return self._refine(T0, cloud, depth_m, intrinsics)[0]

    def _refine(self, T0: np.ndarray, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """``refine_one``'s result, the refined pose it judged and its support (None, 0 when
        dropped before), and the pose of its second look (or None)."""
        return self._rescue(self._refine_plain(T0, cloud, depth_m, intrinsics), cloud, depth_m, intrinsics)

    def _fit(self, T, depth_m, intrinsics, occluders: np.ndarray | None = None):
        """(support - free, support, free, judged points) of pose T (``depth_check``; with
        ``occluders``, its points behind the depth where they are set taken as hidden)."""
        support, free, n = self.depth_check(T, depth_m, intrinsics, occluders)
        return support - free, support, free, n

    def _refine_plain(self, T0: np.ndarray, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """ICP and the judgement, without the further tries for a pose the depth supports
        yet the checks reject (``_rescue``): ``_Plain``, or ``_refine``'s result when dropped
        before the judgement."""
        fe = self.fe
        if self.past_deadline():
            # Hypotheses are refined best first (ECC's clusters by size, then the vote
            # clusters by their votes): past the frame's deadline the rest are left.
            return None, None, 0.0, None
        first = min(3, fe.shape_icp_iterations)
        fit = lambda T: self._fit(T, depth_m, intrinsics)

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
            if on_patch is not None:
                moved = fit(on_patch)
                if moved[0] >= start[0]:
                    T0, start = on_patch, moved
        if start[1] < 0.25 * fe.shape_min_support:
            return None, None, 0.0, None
        T = self._icp(T0, cloud, depth_m, intrinsics, ICP_REACH * self.voxel, first)
        cand = max([start + (T0,), fit(T) + (T,)], key=lambda c: c[0])
        if cand[1] < 0.5 * fe.shape_min_support:
            return None, None, 0.0, None
        T = self._icp(cand[4], cloud, depth_m, intrinsics, 1.5 * self.voxel, fe.shape_icp_iterations - first)
        # ICP can slide a box seen by one face alone: keep whichever pose the depth
        # image supports better.
        _, support, free, n, T = max([cand, fit(T) + (T,)], key=lambda c: c[0])
        return _Plain(self._judge(T, support, free, n, cloud, depth_m, intrinsics), T, support, free, T0, start)

    def wants_rescue(self, plain) -> bool:
        """Whether ``_rescue`` would try more for this ``_refine_plain`` result."""
        return isinstance(plain, _Plain) and plain.kept is None

    def _rescue(self, plain, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """``_refine``'s result from ``_refine_plain``'s: a pose the depth supports but the
        checks reject is moved onto its outline's patch, and a non-convex model's looked at
        again (projective ICP, turned starts)."""
        if not isinstance(plain, _Plain):
            return plain
        fe = self.fe
        first = min(3, fe.shape_icp_iterations)
        fit = lambda T: self._fit(T, depth_m, intrinsics)
        kept, T, support, free, T0, start = plain
        if kept is not None or self.past_deadline():
            return _unrescued(plain)
        support0, free0 = support, free
        if support >= fe.shape_min_support:
            # The depth confirms it, but it overhangs empty space or stops short of its
            # face's edge: off along a face seen alone, where ICP cannot hold it. Moved
            # onto the patch its outline bounds, ICP'd back onto the depth, judged again.
            T1 = T
            for _ in range(fe.shape_outline_rounds):
                unheld, axis, centre = self._unheld(T1)
                if not unheld.any():
                    break       # the normals hold every direction: ICP has placed it
                move = self._outline_move(T1, unheld, axis, depth_m, intrinsics)
                if move is None:
                    break
                shift, turn = move
                if np.linalg.norm(shift) < 0.25 * self.voxel and abs(turn) * self.diameter < 0.25 * self.voxel:
                    break
                T1 = _moved(T1, shift, turn, axis, centre)
                T1 = self._icp(T1, cloud, depth_m, intrinsics, 1.5 * self.voxel, first)
                _, support, free, n = fit(T1)
                kept = self._judge(T1, support, free, n, cloud, depth_m, intrinsics)
                if kept is not None:
                    break
        second = None
        if (kept is None and fe.shape_second_look and self._self_hiding > 0 and support0 >= SECOND_LOOK_MIN
                and support0 - free0 >= SECOND_LOOK_MIN and free0 >= SECOND_LOOK_MIN_FREE):
            # A non-convex model (an L bracket) rejected while overhanging empty space: where
            # its two plates meet, the nearest-point ICP pairs model points with scene points
            # on the other plate and stops a few degrees off. Projective pairing (each model
            # point with the depth pixel on its own ray, the tracker's ICP) has no such
            # pairs; its pose, if the depth agrees better, is judged again. Returned apart
            # (``refine_and_check(second=)``): the selection adds it only where no instance is.
            T2, (score, support, free, n) = self._projective_look(T, depth_m, intrinsics)
            T_look, support_look = T, support0
            if score > support0 - free0:
                second = self._judge(T2, support, free, n, cloud, depth_m, intrinsics)
                T_look, support_look = T2, support
            if second is None and fe.shape_turned_starts > 0 and support0 >= fe.shape_min_support:
                # Still overhanging, though the depth confirms it: ICP may sit in a local
                # minimum a turn away (a standing bracket seen from above, 4-12 deg off in its
                # base plate's plane). Started again from the pose turned both ways about each
                # of the model's axes through its visible surface's centre; the start the
                # depth agrees with best is judged when it beats the pose the refinement left.
                best = self._turned_start(T, fe.shape_turned_starts, fit, cloud, depth_m, intrinsics)
                if best[0] > max(score, support0 - free0):
                    second = self._judge(best[4], best[1], best[2], best[3], cloud, depth_m, intrinsics)
                    T_look, support_look = best[4], best[1]
            if second is None:
                # Still rejected: the later passes (judged with points hidden) are handed the
                # pose the depth agrees with best. A bracket half behind a distractor: ICP 11.5
                # deg off (support - free 0.75), the projective look 0.3 deg off (0.78, all but
                # its hidden points), rejected on the evidence by its hidden points alone; the
                # pose ICP left then passed with them hidden (seed 5 frame 7).
                T, support0 = T_look, support_look
        elif (kept is None and fe.shape_second_look and self._self_hiding > 0 and free0 >= SECOND_LOOK_MIN_FREE
              and T is T0):
            # Overhanging, and no ICP round bettered the start (``_refine_plain`` kept T0): the
            # nearest-point pairs led away from it, however far along it is. The projective
            # look is the other way of aligning it; its pose is kept only where it passes
            # (bracket seed 2462: four brackets 4-24 deg / 8-10 mm off, support - free 0.21-0.58,
            # each set within 0.4 deg / 1 mm by the look).
            T2, (score, support, free, n) = self._projective_look(T, depth_m, intrinsics)
            if score > support0 - free0:
                second = self._judge(T2, support, free, n, cloud, depth_m, intrinsics)
        if (kept is None and second is None and self._self_hiding > 0 and support0 >= HELD_LOOK_MIN
                and support0 + free0 >= fe.shape_min_support and self._unheld(T0)[0].any()):
            # Still rejected, though most of it agrees with the depth and the rest overhangs
            # (off along what it shows, not through anything): refined once more from its
            # start with ICP held to what the visible surface holds, then placed by its
            # outline (``_held_look``); returned apart, as the second look's poses are. Only
            # where its start leaves a direction unheld: elsewhere held ICP is ICP, and the
            # look would redo the refinement (bracket seed 0: 990 -> 342 looks, the same hits).
            second = self._held_look(T0, start, fit, cloud, depth_m, intrinsics)
        return kept, T, support0, second

    def _projective_look(self, T, depth_m, intrinsics) -> tuple[np.ndarray, tuple]:
        """Pose T aligned by the second look's projective ICP (each model point paired with the
        depth pixel on its own ray), run for ``SECOND_LOOK_SHORT`` and for
        ``SECOND_LOOK_ITERATIONS`` rounds; of the two, the pose the depth agrees with better,
        and its ``_fit``."""
        looks = [align_projective(T, self._surface, self._surface_normals, depth_m, intrinsics, rounds,
                                  1.5 * self.voxel, 0.75 * self.voxel).T
                 for rounds in (SECOND_LOOK_SHORT, SECOND_LOOK_ITERATIONS)]
        fits = [self._fit(L, depth_m, intrinsics) for L in looks]
        best = max(range(len(looks)), key=lambda k: fits[k][0])
        return looks[best], fits[best]

    def look_again(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
        """Pose T after the second look's projective ICP, judged: (T, support, agreeing points,
        evidence) or None."""
        T2, (_, support, free, n) = self._projective_look(T, depth_m, intrinsics)
        return self._judge(T2, support, free, n, cloud, depth_m, intrinsics)

    def _turned_start(self, T, degrees: float, fit, cloud: FrameCloud, depth_m, intrinsics):
        """Pose T turned by +-``degrees`` about each of the model's axes (camera frame,
        through the centre of its surface facing the camera), each given ``_refine``'s first
        ICP rounds; the one ``fit`` ranks best gets the rest. Returns ``fit``'s tuple and the
        pose. (All rounds for every start cost the bracket's frame 20 ms of refinement.)"""
        p = self._visible_surface(T)
        centre = p.mean(axis=0) if len(p) else T[:3, 3].copy()
        first = min(3, self.fe.shape_icp_iterations)
        starts = []
        for k in range(3):
            for sign in (1.0, -1.0):
                twist = np.zeros(6)
                twist[:3] = sign * np.radians(degrees) * T[:3, k]
                T0 = apply_twist(T, twist, centre)
                T3 = self._icp(T0, cloud, depth_m, intrinsics, ICP_REACH * self.voxel, first)
                # As in ``_refine_plain``: ICP can slide a face seen alone off the start the
                # depth agrees with better (onto a flush neighbour), so the start itself competes.
                starts.append(max([fit(T0) + (T0,), fit(T3) + (T3,)], key=lambda c: c[0]))
        best = max(starts, key=lambda c: c[0])
        T3 = self._icp(best[4], cloud, depth_m, intrinsics, 1.5 * self.voxel, self.fe.shape_icp_iterations - first)
        return max([best, fit(T3) + (T3,)], key=lambda c: c[0])

    def overhangs(self, T, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> bool:
        """Whether pose T overhangs space the depth shows empty (free share at least
        ``SECOND_LOOK_MIN_FREE``, nothing taken as hidden): off along what it shows. An
        instance in front can hide a pose's points and explain its outline, not that."""
        return self._fit(T, depth_m, intrinsics)[2] >= SECOND_LOOK_MIN_FREE

    def climb_fit(self, T, hiding: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> float | None:
        """``_fit``'s support - free at pose T, ``hiding`` its occluders, when ``climbed`` is worth a try from it,
        else None: ``hiding`` hides some of it, and with those points hidden it passes the
        held look's gate (``_rescue``: at least ``HELD_LOOK_MIN`` agrees and the rest
        overhangs, support + free at least ``shape_min_support``: off along what it shows,
        not through anything). Most of the fits the residual votes give beside a rejected
        pose lie through it or the table (support 0.38-0.52 with its pixels hiding them,
        free 0.31-0.61: channel seeds 2141 / 1607 / 2402)."""
        score, support, free, n = self._fit(T, depth_m, intrinsics, hiding)
        if support < HELD_LOOK_MIN or support + free < self.fe.shape_min_support:
            return None
        return score if n < self._fit(T, depth_m, intrinsics)[3] else None

    def climbed(self, T, hiding: np.ndarray, cloud: FrameCloud, depth_m: np.ndarray,
                intrinsics: CameraIntrinsics) -> np.ndarray:
        """Pose T moved by turned starts (``_turned_start``) for as long as one agrees better
        with the depth, its points behind ``hiding`` taken as hidden (``_fit``), the
        turn halved twice when none does; no further than the vote clusters' bounds from T
        (``distinct``: a hypothesis is that close at best). For a pose half hidden by its
        neighbour: nearest-point ICP cannot turn a channel lying flush beside another about
        its top's normal (the top, seen alone, holds no turn in its plane, and the
        neighbour's top goes on in that plane), and the support gate keeps the turned starts
        of ``_rescue`` from it (channel seed 2141 frames 0-2: its fits voted over the
        leftovers of the neighbour's rejected pose 2-12 deg off, support 0.55-0.63 with its
        other half behind that neighbour; climbed with that neighbour's pixels hiding it,
        1.0-2.9 deg and 3 mm off)."""
        fit = lambda P: self._fit(P, depth_m, intrinsics, hiding)
        best, score = T, fit(T)[0]
        max_turn, max_shift = 360.0 / ANGLE_STEPS, 0.1 * self.diameter
        degrees = self.fe.shape_turned_starts
        for _ in range(CLIMB_STEPS):
            moved = self._turned_start(best, degrees, fit, cloud, depth_m, intrinsics)
            P = moved[4]
            within = (rotation_angle_deg(P[:3, :3].T @ T[:3, :3]) <= max_turn
                      and np.linalg.norm(P[:3, 3] - T[:3, 3]) <= max_shift)
            if within and moved[0] > score:
                best, score = P, moved[0]
            elif degrees > 0.3 * self.fe.shape_turned_starts:
                degrees *= 0.5
            else:
                break
        return best

    def found_shares(self, poses, found, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> list[float]:
        """Per pose: of the model's visible points there that agree with the depth, the share
        within ``RESIDUAL_VOXELS`` of a found pose's surface (``found``: poses): the evidence
        those instances explain already. A flush neighbour shares a strip along its edge at
        most (0.00-0.05 for the poses the later passes add right, bracket seeds 5 / 911)."""
        if not len(found):
            return [0.0] * len(poses)
        on_found = self._on_found(found)
        out = []
        for T in poses:
            p = self._visible_surface(T)
            u, v, inside = image_pixels(p, intrinsics, depth_m.shape)
            p = p[inside]
            d = depth_m[v[inside], u[inside]]
            agree = p[(d > 0) & (np.abs(p[:, 2] - d) <= self.tolerance_at(T))]
            out.append(float(np.mean(on_found(agree))) if len(agree) else 0.0)
        return out

    def _on_found(self, found, keep: bool = True):
        """A test (points (N, 3) -> (N,) bool) of lying within ``RESIDUAL_VOXELS`` of the
        surface of one of the poses ``found`` (a k-d tree of them, built once). The last
        one is kept (unless not ``keep``: poses asked once): a frame asks it of the same
        instances two or three times (``found_shares``, ``residual_poses``; 1-4 ms a tree of
        4-11 poses' surfaces)."""
        key = b"".join(np.asarray(F, np.float64).tobytes() for F in found)
        kept = self._found_test
        if kept is not None and kept[0] == key:
            return kept[1]
        tree = cKDTree(np.concatenate([self._surface @ np.asarray(F)[:3, :3].T + np.asarray(F)[:3, 3]
                                       for F in found]))

        def test(points):
            # The frame's whole cloud (2,500-5,000 points) on both cores; a pose's few
            # hundred points are not worth the threads.
            workers = -1 if len(points) >= 2000 else 1
            return np.isfinite(tree.query(points, distance_upper_bound=RESIDUAL_VOXELS * self.voxel,
                                          workers=workers)[0])

        if keep:
            self._found_test = (key, test)
        return test

    def instance_pixels(self, transforms, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        """(H, W) uint8: 1 where the depth image shows one of these instances (a visible
        model point within the depth tolerance there, drawn over its voxel's footprint).
        Read-only while ``keep_frame`` holds this depth image (the frame being registered):
        the acceptance passes ask for the same poses' pixels several times a frame (the
        instances found, each rejected pose of ``_meeting`` and ``judge_groups``), so they are
        drawn once, kept by the poses' bytes."""
        memo = self._frame_memo
        if memo is None or memo[0] is not depth_m or memo[1] is not intrinsics:
            return self._instance_pixels(transforms, depth_m, intrinsics)
        key = b"".join(np.asarray(T, np.float64).tobytes() for T in transforms)
        out = memo[2].get(key)
        if out is None:
            out = self._instance_pixels(transforms, depth_m, intrinsics)
            out.flags.writeable = False
            memo[2][key] = out
        return out

    def set_deadline(self, at: float | None) -> None:
        """Refine no further hypothesis once ``time.process_time()`` passes ``at`` (None: no
        bound); ``deadline_cut`` says afterwards whether that turned any away. CPU time, not
        the clock's: what the frame costs, whatever else the host runs (on a host of its own
        the two agree), so that a replay or a benchmark finds the same instances at any load."""
        self._deadline, self.deadline_cut = at, False

    def past_deadline(self) -> bool:
        """Whether the frame's deadline has passed (and so work is turned away: counted)."""
        if self._deadline is None or time.process_time() < self._deadline:
            return False
        self.deadline_cut = True
        return True

    def keep_frame(self, depth_m: np.ndarray | None, intrinsics: CameraIntrinsics | None = None) -> None:
        """``instance_pixels``, ``every_pixel`` and ``depth_check`` of this depth image (and
        intrinsics; the same objects) kept until the next call (None: none kept); the image
        must not change meanwhile."""
        self._frame_memo = None if depth_m is None else (depth_m, intrinsics, {}, {})

    def every_pixel(self, depth_m: np.ndarray) -> np.ndarray:
        """(H, W) uint8 ones: occluders everywhere (every point behind the measurement hidden);
        read-only, one a frame while ``keep_frame`` holds this image."""
        memo = self._frame_memo
        if memo is None or memo[0] is not depth_m:
            return np.ones(depth_m.shape, np.uint8)
        out = memo[2].get(b"every")
        if out is None:
            out = np.ones(depth_m.shape, np.uint8)
            out.flags.writeable = False
            memo[2][b"every"] = out
        return out

    def depth_check(self, T, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                    occluders: np.ndarray | None = None) -> tuple[float, float, int]:
        """``depth_support`` of the model's surface at pose T (at its tolerance there, hiding
        itself if non-convex): (support, free, judged points). Kept for the frame
        (``keep_frame``) by the pose's bytes and the occluders (only read-only ones, whose
        pixels cannot change: ``instance_pixels``, ``every_pixel``): the passes judge one
        pose again and again (bracket seed 0: 100 of 520 checks a frame were repeats)."""
        memo = self._frame_memo
        kept = memo is not None and memo[0] is depth_m and memo[1] is intrinsics and (
            occluders is None or not occluders.flags.writeable)
        if kept:
            key = (np.asarray(T, np.float64).tobytes(), id(occluders))
            hit = memo[3].get(key)
            # The entry holds the occluders: no other array can have their id meanwhile.
            if hit is not None and hit[0] is occluders:
                return hit[1]
        out = depth_support(T, self._surface, self._surface_normals, depth_m, intrinsics, self.tolerance_at(T),
                            self._self_hiding, occluders)
        if kept:
            memo[3][key] = (occluders, out)
        return out

    def _instance_pixels(self, transforms, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        out = np.zeros(depth_m.shape, np.uint8)
        K = intrinsics.K
        for T in transforms:
            p = self._visible_surface(T)
            u, v, inside = image_pixels(p, intrinsics, depth_m.shape)
            p, u, v = p[inside], u[inside], v[inside]
            on = np.abs(depth_m[v, u] - p[:, 2]) < self.tolerance_at(T)
            out[v[on], u[on]] = 1
        if not out.any():
            return out
        r = max(1, int(round(0.75 * self.voxel * K[0, 0] / float(np.median([T[2, 3] for T in transforms])))))
        return cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))

    def judge_behind(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                     occluders: np.ndarray, found) -> tuple | None:
        """A refined pose the checks rejected, judged again with its points hidden behind the
        instances ``found`` (poses; ``occluders`` the pixels showing them, ``instance_pixels``)
        left out: (T, support, agreeing points, evidence) or None. Only an instance in front explains
        the occlusion: a pose sunk into a distractor or the table, or reaching into a found
        instance's box, is still judged by those points. At least ``shape_min_in_view`` of its
        judged points must remain (as for the image's edge)."""
        fe = self.fe
        tol_T = self.tolerance_at(T)
        support, free, n = self.depth_check(T, depth_m, intrinsics, occluders)
        # What follows only lowers the support and support - free: most are dropped here.
        if support < fe.shape_min_support or support - free < fe.shape_min_evidence:
            return None
        _, _, n_all = self.depth_check(T, depth_m, intrinsics)
        if n >= n_all:
            # Nothing hidden: only the outline may judge it otherwise, where its band meets
            # an instance found (a neighbour flush with it, not a larger surface).
            if not self.fe.shape_outline_by_instances or not self._band_meets(T, occluders, intrinsics):
                return None
            return self._judge(T, support, free, n, cloud, depth_m, intrinsics, explained=occluders)
        support, free, n = self._inside_found(T, found, depth_m, intrinsics, occluders, tol_T, support, free, n)
        if n < fe.shape_min_in_view * n_all:
            return None
        return self._judge(T, support, free, n, cloud, depth_m, intrinsics,
                           explained=occluders if fe.shape_outline_by_instances else None)

    def _inside_found(self, T, found, depth_m, intrinsics, occluders, tol, support, free, n) -> tuple:
        """(support, free, n) with the model's visible points at pose T that were taken as
        hidden (behind the depth by more than ``tol`` where ``occluders`` is set) but lie
        inside a found instance's box counted back into the judged ones (neither agreeing
        nor free): a pose sunk into a found instance is not behind it."""
        if not len(found):
            return support, free, n
        centre, half = np.asarray(self.model.box_centre, np.float64), 0.5 * np.asarray(self.model.extent, np.float64)
        p = self._visible_surface(T)
        inside = np.zeros(len(p), bool)
        for F in found:
            inside |= np.all(np.abs((p - F[:3, 3]) @ F[:3, :3] - centre) <= half, axis=1)
        if not inside.any():
            return support, free, n
        q = p[inside]
        u, v, ok = image_pixels(q, intrinsics, depth_m.shape)
        d = depth_m[v[ok], u[ok]]
        back = int(np.sum((d > 0) & (d < q[ok, 2] - tol) & (occluders[v[ok], u[ok]] > 0)))
        if not back:
            return support, free, n
        return support * n / (n + back), free * n / (n + back), n + back

    def one_of_each(self, poses) -> list:
        """``poses`` less those refined to the same place as an earlier one (within
        ``SAME_POSE_DEG`` and half a voxel)."""
        if len(poses) <= 1:
            return list(poses)
        same = cluster_poses(np.stack([np.asarray(T, np.float64) for T in poses]),
                             -np.arange(len(poses), dtype=np.float64), SAME_POSE_DEG, 0.5 * self.voxel,
                             len(poses), min_members=1, indices=True)
        return [poses[i] for i in sorted(same)]

    def supported_evidence(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> float | None:
        """Support - free - 2 x outline continuation at pose T (as ``_judge`` ranks, nothing
        taken as hidden) when at least ``shape_min_support`` of its visible surface agrees
        with the depth and that evidence is at least ``SUPPORTED_EVIDENCE_SHARE`` of
        ``shape_min_evidence``, else None."""
        support, free, _ = self.depth_check(T, depth_m, intrinsics)
        if support < self.fe.shape_min_support:
            return None
        outline, _ = outline_continuation(T, self._surface, self._surface_normals, depth_m, intrinsics,
                                          self.voxel, self._same_surface(T), up=cloud.up)
        evidence = support - free - 2.0 * outline
        return evidence if evidence >= SUPPORTED_EVIDENCE_SHARE * self.fe.shape_min_evidence else None

    def judge_pairs(self, rejected, overlap: np.ndarray, limit: float, cloud: FrameCloud, depth_m: np.ndarray,
                    intrinsics: CameraIntrinsics, occluders: np.ndarray, found) -> list[tuple[int, int, tuple, tuple]]:
        """Rejected poses judged two at a time: each of a pair judged again (``judge_behind``)
        with the other taken as found besides ``found`` (``occluders`` their pixels). Two
        brackets that hide each other or lie flush, neither found, each fail alone for what
        the other explains (seed 5: a bracket at support 1.0 whose outline band runs onto
        its flush neighbour, the neighbour at 0.74 for what the first hides); judged with
        the other, both pass. Only pairs whose boxes overlap by at most ``limit`` (``overlap``:
        ``box_overlaps`` of the rejected poses) and whose pixels meet (``_band_ring``).
        Returns (i, j, i's result, j's result) for every pair that passes both ways,
        the strongest first; none for a convex model (below)."""
        if len(rejected) < 2 or not self.non_convex:
            # Non-convex models only: on pallet seed 9's distractor-only frames two
            # carton-sized boxes, one flush against the other and hiding part of it, passed
            # as a pair exactly as two true brackets do (support 0.99 and outline 0.15 -> 0.0;
            # support 0.68 -> 0.98), while no bracket pair appeared on any distractor-only frame.
            return []
        # Poses refined to the same place from several hypotheses: one of each.
        same = sorted(cluster_poses(np.stack([np.asarray(T, np.float64) for T in rejected]),
                                    -np.arange(len(rejected), dtype=np.float64), SAME_POSE_DEG, 0.5 * self.voxel,
                                    len(rejected), min_members=1, indices=True))
        # Only those that can pass with some of their points hidden.
        fe = self.fe
        same = [i for i in same if self._evidence_if_hidden(rejected[i], depth_m, intrinsics) is not None]
        candidates, pixels = self._meeting(rejected, same, overlap, limit, depth_m, intrinsics)

        def supported(T, hiding):
            # ``judge_behind``'s first test, alone: the full judging (the outline) only for
            # pairs where both have the support with the other hiding them (a pose of support
            # 1.0 meets many wrong ones, which the judging then took 20 ms a bracket frame
            # to turn down on the outline).
            support, free, _ = self.depth_check(T, depth_m, intrinsics, hiding)
            return support >= fe.shape_min_support and support - free >= fe.shape_min_evidence

        # Each member also as its second look's projective ICP places it (a channel lying flush
        # beside another, its rims paired by nearest-point ICP with the neighbour's wall: ICP
        # left it 2 deg tilted, its outline 0.08 past the neighbour; the look sets it right,
        # 0.1 deg, with a hair less support, so the refinement kept the tilted pose: channel
        # seed 2187 frames 6 / 7, the pair passing at the true poses, not at the rejected ones).
        # Tried where the pair fails as refined; made (with its pixels) before the threads.
        members = sorted({k for pair in candidates for k in pair})
        looked = dict(zip(members, map_each(lambda k: self._projective_look(rejected[k], depth_m, intrinsics)[0],
                                            members))) if self._self_hiding > 0 else {}
        looked = {k: T for k, T in looked.items() if rotation_angle_deg(T[:3, :3].T @ rejected[k][:3, :3]) >= 0.5
                  or np.linalg.norm(T[:3, 3] - rejected[k][:3, 3]) >= 0.25 * self.voxel}
        look_pixels = {k: self.instance_pixels([T], depth_m, intrinsics) for k, T in looked.items()}

        def judged_pair(Ti, Tj, pi, pj):
            hide_i, hide_j = np.maximum(occluders, pj), np.maximum(occluders, pi)
            if not (supported(Ti, hide_i) and supported(Tj, hide_j)):
                return None
            ri = self.judge_behind(Ti, cloud, depth_m, intrinsics, hide_i, list(found) + [Tj])
            if ri is None:
                return None
            rj = self.judge_behind(Tj, cloud, depth_m, intrinsics, hide_j, list(found) + [Ti])
            return None if rj is None else (ri, rj)

        def both(pair):
            i, j = pair
            ways = [(rejected[i], pixels[i])] + ([(looked[i], look_pixels[i])] if i in looked else [])
            ways_j = [(rejected[j], pixels[j])] + ([(looked[j], look_pixels[j])] if j in looked else [])
            for Ti, pi in ways:
                for Tj, pj in ways_j:
                    r = judged_pair(Ti, Tj, pi, pj)
                    if r is not None:
                        return (i, j) + r
            return None

        # Two at a time in the shared thread pool (as the refinement).
        passed = [r for r in (task.result() for task in submit_each(both, candidates)) if r is not None]
        return sorted(passed, key=lambda r: -(r[2][3] + r[3][3]))

    def _evidence_if_hidden(self, T, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> float | None:
        """Support less free share at pose T when it can pass with some of its points hidden
        (``judge_pairs``, ``judge_groups``), else None: enough support when every point behind
        the depth is taken as hidden, and no more free space than when none is (hiding points
        only raises the free share)."""
        if self.depth_check(T, depth_m, intrinsics, self.every_pixel(depth_m))[0] < self.fe.shape_min_support:
            return None
        support, free, _ = self.depth_check(T, depth_m, intrinsics)
        return support - free if free <= self.fe.shape_max_free else None

    def image_rect(self, T, intrinsics: CameraIntrinsics) -> tuple | None:
        """(top, bottom, left, right) pixels: the image rectangle of the visible surface at
        pose T grown by the outline band's reach (what its checks look at); None when none of
        it faces the camera."""
        p = self._visible_surface(T)
        if len(p) == 0:
            return None
        K = intrinsics.K
        u, v = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        r = 1.5 * self.voxel * K[0, 0] / float(p[:, 2].min()) + 1.0
        return v.min() - r, v.max() + r, u.min() - r, u.max() + r

    def rects_meeting(self, poses, others, intrinsics: CameraIntrinsics) -> np.ndarray:
        """(len(poses), len(others)) bool: whether their image rectangles (``image_rect``)
        meet; False where either has none."""
        mine = [self.image_rect(T, intrinsics) for T in poses]
        theirs = [self.image_rect(T, intrinsics) for T in others]
        return np.array([[a is not None and b is not None and rects_meet(a, b) for b in theirs] for a in mine],
                        bool).reshape(len(mine), len(theirs))

    def _meeting(self, rejected, idx, overlap: np.ndarray, limit: float, depth_m: np.ndarray,
                 intrinsics: CameraIntrinsics) -> tuple[list[tuple[int, int]], dict]:
        """The pairs (i, j) of the rejected poses ``idx`` whose boxes overlap by at most
        ``limit`` and whose pixels meet (one's ``instance_pixels`` on the other's
        ``_band_ring``), and those pixels of each pose in a pair (index -> image)."""
        # Each pose's image rectangle: most pairs lie apart in the image and are not looked
        # at further.
        rects = {i: r for i in idx if (r := self.image_rect(rejected[i], intrinsics)) is not None}
        pixels = {}

        def pixels_of(i):
            if i not in pixels:
                pixels[i] = self.instance_pixels([rejected[i]], depth_m, intrinsics)
            return pixels[i]

        rings = {}

        def ring_of(i):
            if i not in rings:
                rings[i] = self._band_ring(rejected[i], depth_m.shape, intrinsics)
            return rings[i]

        candidates = []
        for a, i in enumerate(idx):
            for j in idx[a + 1:]:
                if i not in rects or j not in rects or overlap[i, j] > limit or overlap[j, i] > limit:
                    continue
                if not rects_meet(rects[i], rects[j]):
                    continue
                if pixels_of(j)[ring_of(i)].any() or pixels_of(i)[ring_of(j)].any():
                    candidates.append((i, j))
        # Every candidate's pixels computed here: threads that judge them only read them.
        for i, j in candidates:
            pixels_of(i)
            pixels_of(j)
        return candidates, pixels

    def judge_groups(self, rejected, overlap: np.ndarray, limit: float, cloud: FrameCloud, depth_m: np.ndarray,
                     intrinsics: CameraIntrinsics, occluders: np.ndarray, found) -> list[tuple]:
        """Rejected poses judged in groups of three or more that meet one another (a row of
        touching instances, flush tops: channel seed 307 frame 9, three side by side, the
        middle one rejected unless both neighbours are taken as found, each neighbour
        unless the middle one is; pairs, ``judge_pairs``, cannot pass them). Of each place one
        pose (the best supported where several overlap); each group (poses joined through
        meeting pairs, ``_meeting``) judged with ``judge_behind``, each member with every
        other taken as found besides ``found``; those that fail leave the group and the rest
        are judged again, until all pass (returned: their results) or fewer than three are
        left. Non-convex models only, as the pairs."""
        if len(rejected) < 3 or not self.non_convex:
            return []
        # As the pairs': only those that can pass with some of their points hidden.
        score = {i: e for i, e in enumerate(self._evidence_if_hidden(T, depth_m, intrinsics) for T in rejected)
                 if e is not None}
        kept = []
        for i in sorted(score, key=lambda i: -score[i]):
            if all(overlap[i, j] <= limit and overlap[j, i] <= limit for j in kept):
                kept.append(i)
        if len(kept) < 3:
            return []
        candidates, pixels = self._meeting(rejected, sorted(kept), overlap, limit, depth_m, intrinsics)
        # Groups: the connected pieces of the meeting pairs.
        group = {i: i for i in kept}

        def root(i):
            while group[i] != i:
                group[i] = group[group[i]]
                i = group[i]
            return i

        for i, j in candidates:
            group[root(i)] = root(j)
        members = {}
        for i in kept:
            members.setdefault(root(i), []).append(i)
        out = []
        for idx in members.values():
            while len(idx) >= 3:
                def judge(a, idx=idx):
                    others = [b for b in idx if b != a]
                    hide = np.maximum.reduce([occluders] + [pixels[b] for b in others])
                    return self.judge_behind(rejected[a], cloud, depth_m, intrinsics, hide,
                                             list(found) + [rejected[b] for b in others])
                results = [task.result() for task in submit_each(judge, idx)]
                if all(r is not None for r in results):
                    out.extend(results)
                    break
                idx = [a for a, r in zip(idx, results) if r is not None]
        return out

    def judge_hidden(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                     explained: np.ndarray | None, found=()) -> tuple | None:
        """A rejected pose judged again with every point behind a nearer measured surface left
        out, whatever that surface is (a distractor in front: bracket seeds 13 / 151, support
        0.65-0.79 at the ground-truth pose, nothing else wrong), when the depth steps in front
        of it where it goes out of sight: the depth at the hidden points next to its agreeing
        ones at least ``HIDDEN_STEP`` tolerances nearer than at those agreeing points (median).
        Where a pose is sunk into a distractor or a neighbour, that surface goes on smoothly
        past its agreeing points (9-15 mm against 23-113 mm for the true poses behind a
        distractor). ``explained``: as ``_judge``'s; ``found``: the instances kept (poses). (T, support, agreeing points, evidence)
        or None."""
        fe = self.fe
        tol = self.tolerance_at(T)
        every = self.every_pixel(depth_m)
        support, free, n = self.depth_check(T, depth_m, intrinsics, every)
        if support < fe.shape_min_support or support - free < fe.shape_min_evidence:
            return None
        _, _, n_all = self.depth_check(T, depth_m, intrinsics)
        # As in ``judge_behind``: what lies inside a found instance's box is not behind it.
        support, free, n = self._inside_found(T, found, depth_m, intrinsics, every, tol, support, free, n)
        if n >= n_all or n < fe.shape_min_in_view * n_all:
            return None
        p = self._visible_surface(T)
        u, v, inside = image_pixels(p, intrinsics, depth_m.shape)
        d = np.zeros(len(p))
        d[inside] = depth_m[v[inside], u[inside]]
        gap = p[:, 2] - d
        # Hidden clearly: behind by more than the self-hiding margin as well (0 for a convex
        # model). Points just past the tolerance are the model's own rims and inner faces seen
        # at a slant (the depth check leaves those to ``_hidden_by_self`` only beyond the
        # margin); their depth is the model's own nearer face, a step of a few mm, and they
        # outnumbered the real occlusion edge: channels behind a distractor (seed 617, support
        # 0.72-0.78 at the truth) had median steps 5-8 mm, 28-58 mm without them.
        hidden = (d > 0) & (gap > tol + self._self_hiding)
        agree = (d > 0) & (np.abs(gap) <= tol)
        if not hidden.any() or not agree.any():
            return None
        # The step is measured in the depth image (an agreeing point's depth less the depth
        # at the hidden point next to it), not between the model and the depth: where the pose
        # is sunk into a curved distractor the model leaves a surface that goes on smoothly
        # (cylinders seed 50's distractor-only frame 11: 19 mm from the model, 15 mm in the
        # depth; the true poses behind a distractor 23-113 mm either way).
        step = self._hidden_step(p, d, hidden, agree)
        if step is None or np.median(step) < HIDDEN_STEP * tol:
            return None
        return self._judge(T, support, free, n, cloud, depth_m, intrinsics, explained=explained)

    def turned_over_starts(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> list:
        """Hypotheses from a rejected pose of a non-convex model: T turned over (``_turned_over``).
        An open channel lying open side down shows the votes and ICP a flat top they fit its
        inner floor to, open side up and 42 mm too high, its walls and rims then in front of
        the depth (channel seeds 631 / 1607 / 1627: the only fits near most such channels in
        segments of several). Only when at least ``TURNED_OVER_MIN`` of T's visible surface lies
        in front of the depth, and each turned pose only when the depth agrees with it better
        than with T and by at least half ``shape_min_evidence`` (a projection each): the caller
        refines and judges them as hypotheses."""
        if cloud.up is None or not self.non_convex:
            return []
        support, free, _ = self.depth_check(T, depth_m, intrinsics)
        if free < TURNED_OVER_MIN:
            return []
        out = []
        for T1 in self._turned_over(T, cloud.up, depth_m, intrinsics):
            s1, f1, _ = self.depth_check(T1, depth_m, intrinsics)
            # Placed this well, ICP moves a start little: one the depth agrees with less than half
            # the evidence asked for is not refined (channel seeds 0 / 631: the starts kept had
            # 0.60-0.94 support - free, those under 0.4 all failed; 1627's lowest kept, 0.43).
            if s1 - f1 > max(support - free, 0.5 * self.fe.shape_min_evidence):
                out.append(T1)
        return out

    def _turned_over(self, T, up: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> list:
        """Pose T turned over: half a turn about each of the model's axes but the one nearest
        ``up`` (through its box centre; ``_half_turns``), then moved along ``up`` until its
        highest point is as high as the surface T agrees with (95th percentile): what T fitted
        its inside to is the turned object's top."""
        p = self._visible_surface(T)
        u, v, inside = image_pixels(p, intrinsics, depth_m.shape)
        d = np.zeros(len(p))
        d[inside] = depth_m[v[inside], u[inside]]
        agree = (d > 0) & (np.abs(p[:, 2] - d) <= self.tolerance_at(T))
        if agree.sum() < 3:
            return []
        top = float(np.percentile(p[agree] @ up, 95))
        R = T[:3, :3]
        centre = R @ self._box_centre + T[:3, 3]
        out = []
        for H in self._half_turns[int(np.argmax(np.abs(R.T @ up)))]:
            T1 = np.eye(4)
            T1[:3, :3] = R @ H
            T1[:3, 3] = R @ (H @ (R.T @ (T[:3, 3] - centre))) + centre
            # The highest point: heights along up are linear in the surface, so the model's
            # points' heights in its own frame at the turned rotation.
            T1[:3, 3] += (top - float(np.max(self._surface @ (T1[:3, :3].T @ up)) + T1[:3, 3] @ up)) * up
            out.append(T1)
        return out

    def _flip_axes(self) -> list:
        """Per model axis (the one standing up): the half turns (model frame, 3 x 3) about the
        other two that no symmetry of the model makes the same as each other or as no turn."""
        sym = self.model.symmetries
        same = [np.eye(3)] if sym is None else [S[:3, :3] for S in np.asarray(sym.discrete, np.float64)]
        out = []
        for standing in range(3):
            kept = [np.eye(3)]
            for k in range(3):
                if k == standing:
                    continue
                H = -np.eye(3)
                H[k, k] = 1.0
                if not any(np.allclose(H, Q @ S, atol=1e-6) for Q in kept for S in same):
                    kept.append(H)
            out.append(kept[1:])
        return out

    def near_twins(self, T) -> list:
        """Pose T's near-symmetric twins (``_near_symmetry_maps``): the model turned half a turn
        onto most of its own surface. An L bracket lying on its long plate with its short one
        standing and the same bracket on its short plate with its long one standing share most
        of what the camera sees of them (bracket seed 1213 frame 6: the one placed by a turn
        over 178 deg and 2.7 cm off the other)."""
        if self._near_symmetries is None:
            self._near_symmetries = self._near_symmetry_maps() if self._self_hiding > 0 else []
        return [T @ M for M in self._near_symmetries]

    def _near_symmetry_maps(self) -> list:
        """The half turns through the box centre about the model's box axes and the bisectors
        of each two of them that map at least ``NEAR_SYMMETRY_MIN`` of its surface onto itself,
        each with the shift that fits it best (nearest points, at most 20 rounds), as 4 x 4 maps in
        the model frame; none a symmetry of the model, nor two alike under one."""
        sym = self.model.symmetries
        same = [np.eye(3)] if sym is None else [S[:3, :3] for S in np.asarray(sym.discrete, np.float64)]
        surface, centre = self._surface, self._box_centre
        tree = cKDTree(surface)
        axes = [np.eye(3)[k] for k in range(3)]
        axes += [(np.eye(3)[i] + sign * np.eye(3)[j]) / np.sqrt(2.0) for i in range(3) for j in range(i + 1, 3)
                 for sign in (1.0, -1.0)]
        kept, out = [np.eye(3)], []
        for a in axes:
            H = 2.0 * np.outer(a, a) - np.eye(3)
            if any(np.allclose(H, Q @ S, atol=1e-6) for Q in kept for S in same):
                continue
            turned = (surface - centre) @ H.T + centre
            shift = np.zeros(3)
            for _ in range(20):
                step = np.mean(surface[tree.query(turned + shift)[1]] - (turned + shift), axis=0)
                shift += step
                if np.linalg.norm(step) < 0.01 * self.voxel:
                    break
            if np.mean(tree.query(turned + shift)[0] < self.voxel) >= NEAR_SYMMETRY_MIN:
                kept.append(H)
                M = np.eye(4)
                M[:3, :3] = H
                M[:3, 3] = centre - H @ centre + shift
                out.append(M)
        return out

    def _hidden_step(self, p: np.ndarray, d: np.ndarray, hidden: np.ndarray, agree: np.ndarray) -> np.ndarray | None:
        """``judge_hidden``'s depth steps: at each hidden point next to an agreeing one (within
        a voxel and a half; ``p`` the model's visible points, ``d`` the depth on their rays, 0:
        none), the agreeing point's depth less the hidden one's; None when there is none. When
        no hidden point is next to an agreeing one, a band with no depth between them is
        stepped across: the depth is lost along an occluder's edge (the spread of the depth
        there, the stereo shadow beside it, both wider the larger the step), and the agreeing
        points' depth is carried over the points with none, hop by hop, to the hidden points
        next to them (bracket seed 5 frames 7 / 8: a bracket behind another, support 0.79,
        its hidden points 2-3 voxels from its agreeing ones, 1 from the band)."""
        reach = 1.5 * self.voxel
        near, nearest = cKDTree(p[agree]).query(p[hidden], distance_upper_bound=reach)
        edge = np.isfinite(near)
        if edge.any():
            return d[agree][nearest[edge]] - d[hidden][edge]
        seen = (d > 0) & ~hidden
        if seen.any() and np.isfinite(cKDTree(p[seen]).query(p[hidden], distance_upper_bound=reach)[0]).any():
            return None
        # Points with no depth reached from the agreeing ones, each with the depth carried to it.
        band = np.flatnonzero(d <= 0)
        src, depth = p[agree], d[agree]
        carried_p, carried_d = [], []
        while len(band):
            near, nearest = cKDTree(src).query(p[band], distance_upper_bound=reach)
            reached = np.isfinite(near)
            if not reached.any():
                break
            src, depth = p[band[reached]], depth[nearest[reached]]
            carried_p.append(src)
            carried_d.append(depth)
            band = band[~reached]
        if not carried_p:
            return None
        near, nearest = cKDTree(np.concatenate(carried_p)).query(p[hidden], distance_upper_bound=reach)
        edge = np.isfinite(near)
        return np.concatenate(carried_d)[nearest[edge]] - d[hidden][edge] if edge.any() else None

    def _band_meets(self, T, pixels: np.ndarray, intrinsics: CameraIntrinsics) -> bool:
        """Whether any of ``pixels`` lies a voxel and a half (the outline band's outer edge)
        from the model's visible surface at pose T, in one of eight directions: a cheap test
        before the outline is looked at again."""
        rows, cols = self._band_ring(T, pixels.shape, intrinsics)
        return bool(pixels[rows, cols].any())

    def _band_ring(self, T, shape, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) inside an image of ``shape``: ``_band_meets``' pixels, a voxel and a
        half from the model's visible surface at pose T in each of eight directions."""
        p = self._visible_surface(T)
        if len(p) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        K = intrinsics.K
        u, v = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        r = 1.5 * self.voxel * K[0, 0] / p[:, 2]
        a = np.arange(8) * np.pi / 4
        uu = np.round(u[None, :] + r[None, :] * np.cos(a)[:, None]).astype(np.int64).ravel()
        vv = np.round(v[None, :] + r[None, :] * np.sin(a)[:, None]).astype(np.int64).ravel()
        h, w = shape
        ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        return vv[ok], uu[ok]

    def _unheld(self, T, cloud=None):
        """(3, 3) projection onto the directions in which the visible surface's normals do not
        hold the model (point-to-plane ICP's weak translations): a face seen alone, its
        plane; a lying cylinder, its axis. Elsewhere ICP places the model, and the outline
        shift must not move it. With it: the one held direction when only one is (a face
        seen alone: turning about it is free too), else None, and the visible surface's
        centre (camera frame). With ``cloud``: the normals of the frame's points within ICP's
        reach of that surface instead of the model's (what the camera shows: a channel's
        walls seen edge on face the camera in the model, and hold nothing in the frame)."""
        R, t = T[:3, :3], T[:3, 3]
        p = self._surface @ R.T + t
        n = self._surface_normals @ R.T
        facing = facing_camera(p, n)
        n = n[facing]
        if len(n) < 3:
            return np.zeros((3, 3)), None, t
        if cloud is not None:
            d, j = cloud.tree.query(p[facing], distance_upper_bound=ICP_REACH * self.voxel)
            j = np.unique(j[np.isfinite(d)])
            if len(j) >= 3:
                n = cloud.normals[j]
        w, V = np.linalg.eigh(n.T @ n / len(n))
        weak = V[:, w < UNHELD_SHARE]
        held = V[:, w >= UNHELD_SHARE]
        return weak @ weak.T, (held[:, 0] if held.shape[1] == 1 else None), p[facing].mean(axis=0)

    def pierces(self, T, cloud: FrameCloud, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> bool:
        """Whether the model at pose T reaches more than two voxels through the frame's
        support plane ``cloud.up`` (the table it would stand on: the largest, or the largest
        level one given gravity) where that plane is there: its
        points behind the table's surface are hidden, so the depth check counts them as
        occluded, not as wrong (a bracket turned over, its upright plate sunk into the table,
        its base plate on the true one's). "There": the depth on those points' rays stops at
        the plane or before it; where it reaches past it, the plane ends before them (the plane
        extended without bound would also cut off objects standing lower beyond its edge: on
        the floor beside a table, on a lower shelf).

        With ``shape_pierce_every_plane``, every support plane a large piece of which the frame
        shows is such a surface, not the largest alone: a carton whose top lay (tilted 2.5
        deg) in a crate's top on a pallet reached 4 cm through the pallet's top, seen there
        (the crate on it) though the floor is the largest plane."""
        if cloud.up is None or cloud.up_offset is None:
            return False
        planes = cloud.planes if self.fe.shape_pierce_every_plane and cloud.planes else ((cloud.up, cloud.up_offset),)
        pts = self._surface @ T[:3, :3].T + T[:3, 3]
        # Heights above every plane at once: most planes have no point below them.
        height = pts @ np.stack([up for up, _ in planes]).T + np.array([offset for _, offset in planes])
        deep = height < -PIERCE_VOXELS * self.voxel
        # No point within PIERCE_VOXELS of the support below (``cloud.up``) reaches through
        # another plane: one that lies that low there is the support itself seen off by a
        # degree (a plane fitted 1 deg off the table, 17 mm above it under channels standing
        # on it, their hidden wall bottoms "through" it: channel seed 631), or a board too thin
        # to tell from it.
        def stood_on(up, offset):
            return offset == cloud.up_offset and np.array_equal(up, cloud.up)
        deep &= (pts @ cloud.up + cloud.up_offset > PIERCE_VOXELS * self.voxel)[:, None] | np.array(
            [stood_on(up, offset) for up, offset in planes])[None, :]
        # Through a plane means on both sides of it: a model wholly below one (up to the depth
        # tolerance) has its top in it, and the plane there is made of object tops, not a
        # support it goes through (touching channels' flush tops 5 cm above the table, larger
        # together than three faces, were found as a plane and every true pose below them
        # rejected: channel seeds 9 / 503). A pose sunk whole into a real support's surface,
        # its top flush with it, is rejected by the outline check (the surface goes on).
        through = deep.any(axis=0) & (height > self.tolerance_at(T)).any(axis=0)
        own = []
        def own_pixels():
            if not own:
                own.append(self.instance_pixels([T], depth_m, intrinsics))
            return own[0]
        # A model on both sides of a plane of object tops (standing brackets' base plates,
        # flush on one table: bracket seed 701) is spared where its own face lies in the
        # plane (``_pierces_plane``), but not on the support the objects stand on
        # (``cloud.up``): nothing stands below it, so a face of the model in it is a pose sunk
        # into it (seed 811 frame 5: an L 8 cm into the table, its face flush with it and half
        # out of view, passed as hidden).
        return any(self._pierces_plane(pts[deep[:, k]], up, offset, depth_m, intrinsics,
                                       None if stood_on(up, offset) else own_pixels, self.tolerance_at(T))
                   for k, (up, offset) in enumerate(planes) if through[k])

    def _pierces_plane(self, below, up, offset, depth_m, intrinsics, own_pixels=None, tol: float = 0.0) -> bool:
        """``pierces`` for one plane (``up`` towards the camera, up . p + offset = 0 on it);
        ``below`` the model's surface points (camera frame) more than ``PIERCE_VOXELS`` below it.
        ``own_pixels()``: the pixels where the depth shows the model itself (``instance_pixels``);
        a ray whose depth lies on the plane (within ``tol``) there shows the model's own face in
        that plane, not a support in front of it: touching objects' tops, flush and larger
        than the support area together, are found as a plane (standing brackets' base plates
        on one table, a plane 11 mm above it: bracket seed 701 frame 4, 9 true poses of 10
        reached "through" it by their plates' thickness). ``pierces`` passes none for the
        support the objects stand on."""
        K = intrinsics.K
        h, w = depth_m.shape
        z = np.maximum(below[:, 2], 1e-6)
        u = np.rint(K[0, 0] * below[:, 0] / z + K[0, 2]).astype(np.int64)
        v = np.rint(K[1, 1] * below[:, 1] / z + K[1, 2]).astype(np.int64)
        inside = (below[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = depth_m[v[inside], u[inside]].astype(np.float64)
        rays = np.stack([(u[inside] - K[0, 2]) / K[0, 0], (v[inside] - K[1, 2]) / K[1, 1], np.ones(len(d))], axis=1)
        # Depth along each ray at which it meets the plane; the plane is there when the depth
        # measured on that ray stops at it or before it (the table, or the object on it),
        # not when it reaches past it (the floor beyond the table's edge).
        along = rays @ up
        plane_depth = np.where(along < 0, -offset / np.where(along < 0, along, -1.0), np.inf)
        there = (d > 0) & (d <= plane_depth + self.voxel)
        need = max(PIERCE_MIN_POINTS, PIERCE_SHARE * len(below))
        if int(there.sum()) < need or own_pixels is None:
            return int(there.sum()) >= need
        on_plane = there & (np.abs(d - plane_depth) <= tol)
        if on_plane.any():
            own = own_pixels()[v[inside], u[inside]] > 0
            there &= ~(on_plane & own)
        return int(there.sum()) >= need

    def _judge(self, T, support, free, n, cloud: FrameCloud, depth_m, intrinsics, explained=None):
        """(T, support, agreeing points, evidence) when the depth and the outline accept pose
        T, else None; evidence: the judged points times support - free - 2 x outline
        continuation (what the selection ranks by). ``explained``: pixels the outline leaves
        out (``outline_continuation``)."""
        fe = self.fe
        if n < fe.shape_min_visible or support < fe.shape_min_support or free > fe.shape_max_free:
            return None
        # The outline's share is at least 0: without the evidence even at 0, no need to look.
        if support - free < fe.shape_min_evidence:
            return None
        if fe.shape_min_in_view > 0 and in_view_share(T, self._surface, self._surface_normals,
                                                      intrinsics) < fe.shape_min_in_view:
            return None
        if fe.shape_reject_through_support and self.pierces(T, cloud, depth_m, intrinsics):
            return None
        # A piece of a larger surface (a carton fitted onto a crate's top) agrees with the
        # depth wherever it covers: what tells is the same surface continuing just past
        # its outline, "same" meaning within the depth noise (3 sigma) at its distance.
        same = self._same_surface(T)
        # The object's own surface is where the depth is up to the noise at most of its
        # points, not only up to the tolerance's floor (another shape that passes near it).
        if fe.shape_min_noise_agreement > 0 and noise_agreement(
                T, self._surface, self._surface_normals, depth_m, intrinsics, self.tolerance_at(T),
                same) < fe.shape_min_noise_agreement:
            return None
        outline, _ = outline_continuation(T, self._surface, self._surface_normals, depth_m, intrinsics,
                                          self.voxel, same, up=cloud.up, explained=explained)
        evidence = support - free - 2.0 * outline
        if evidence >= fe.shape_min_evidence:
            return T, support, int(round(support * n)), evidence * n
        return None

    def _held_look(self, T0, start, fit, cloud: FrameCloud, depth_m, intrinsics):
        """A non-convex model's pose rejected after ``_refine``'s looks, refined again from its
        start ``T0`` (``start``: ``fit(T0)``) by ``_held_icp``, and judged; when what does not
        agree lies in front of the depth (it overhangs: off along what it shows, not through
        anything), moved once onto the patch its outline bounds, in the directions the frame's
        own normals there do not hold (``_unheld`` with the cloud), held ICP'd and judged
        again (only when at least ``HELD_LOOK_MIN`` of it agrees: the outline it lies on is
        its own). (T, support, agreeing points, evidence) or None. A U channel lying open side
        down seen from above shows its top and slivers of its walls: the model's walls and
        edges counted as holding it, while the frame's points held nothing in the top's
        plane; its right hypotheses (4-15 deg, 9-18 mm off) refined away or stayed off
        (channel seed 1607 frames 2 / 4 / 10: set right by this look)."""
        fe = self.fe
        first = min(3, fe.shape_icp_iterations)
        T = self._held_icp(T0, cloud, depth_m, intrinsics, ICP_REACH * self.voxel, first)
        cand = max([start + (T0,), fit(T) + (T,)], key=lambda c: c[0])
        T = self._held_icp(cand[4], cloud, depth_m, intrinsics, 1.5 * self.voxel, fe.shape_icp_iterations - first)
        _, support, free, n, T = max([cand, fit(T) + (T,)], key=lambda c: c[0])
        kept = self._judge(T, support, free, n, cloud, depth_m, intrinsics)
        if kept is not None or support < HELD_LOOK_MIN or support + free < fe.shape_min_support:
            return kept
        unheld, axis, centre = self._unheld(T, cloud)
        if not unheld.any():
            return None
        move = self._outline_move(T, unheld, axis, depth_m, intrinsics)
        if move is None:
            return None
        T = self._held_icp(_moved(T, *move, axis, centre), cloud, depth_m, intrinsics, 1.5 * self.voxel, first)
        _, support, free, n = fit(T)
        return self._judge(T, support, free, n, cloud, depth_m, intrinsics)

    def _same_surface(self, T) -> float:
        """Metres: depth differences within the noise (3 sigma) at pose T's distance, at least
        2 mm: "the same surface" for the outline checks."""
        return max(3.0 * self.fe.shape_depth_noise * float(T[2, 3]) ** 2, 0.002)

    def _outline_move(self, T, unheld, axis, depth_m, intrinsics):
        """(shift, turn) that moves pose T onto the patch its outline bounds (``outline_shift``),
        the shift kept to the ``unheld`` directions and the turn only about the one held
        ``axis`` (0 without one), or None where there is no bounded patch (``_unheld``'s
        figures at T)."""
        moved = outline_shift(T, self._surface, self._surface_normals, depth_m, intrinsics, self.voxel,
                              self._same_surface(T), 0.1 * self.diameter + self.voxel, with_turn=True)
        if moved is None:
            return None
        return unheld @ moved[0], (moved[1] if axis is not None else 0.0)

    def _held_icp(self, T0, cloud: FrameCloud, depth_m, intrinsics, max_dist: float, iterations: int) -> np.ndarray:
        """``_icp`` from T0, its move kept only in the directions the model's visible surface
        at T0 holds (``_unheld``): along the others ICP has nothing to go by. A U channel
        lying open side down seen from above has its length held by its thin end faces
        alone, and from its true pose tilted 6 deg ICP slid it 10-20 mm along it (channel
        seed 1607). Used for ``_held_look`` only: in the first refinement it cost poses ICP
        had set right along such a direction (channel 631: 83 -> 78 hits)."""
        T = self._icp(T0, cloud, depth_m, intrinsics, max_dist, iterations)
        unheld, axis, centre = self._unheld(T0)
        if not unheld.any():
            return T
        # The move as a turn about the visible surface's centre and a shift of it.
        D = T @ np.linalg.inv(T0)
        R = D[:3, :3]
        shift = R @ centre + D[:3, 3] - centre
        shift = shift - unheld @ shift
        if axis is not None:
            # A face seen alone: no turn about its normal either.
            w = cv2.Rodrigues(np.ascontiguousarray(R))[0].ravel()
            R = cv2.Rodrigues((w - (w @ axis) * axis).reshape(3, 1))[0]
        out = np.eye(4)
        out[:3, :3] = R @ T0[:3, :3]
        out[:3, 3] = R @ (T0[:3, 3] - centre) + centre + shift
        return out

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
            self._done[k] = self._function(self._items[k])

    def stop(self) -> set[int]:
        """Takes on no more items; returns those it has taken on (done, or under way)."""
        with self._lock:
            self._stopped = True
            return set(self._claimed)

    def result(self, k: int):
        """Item k's result (one taken on), once it is done."""
        if self._future is not None:
            self._future.result()      # the worker's exception, if any, is raised here
        return self._done[k]


def best_per_place(poses, overlap: np.ndarray, k: int, fit=None) -> list:
    """Of ``poses``, in their order, those among the ``k`` best fits on their place (``fit``,
    one figure a pose, higher better; default each pose's ``.support - .free``, as the
    refinement ranks its poses): taken best first, each unless ``k`` taken already overlap it
    (``overlap``: (n, n) bool, either way). Overlap with the taken ones only, not through
    chains of poses: touching instances' fits link into a row (bracket seed 0: a bracket's
    best fit left out behind a neighbour's). Support alone ranked worse: bracket seed 157
    frame 11, of 12 fits of a bracket, the one whose look keeps it was 4th by support (0.734,
    free 0.077), among the first two by the fit."""
    n = len(poses)
    fit = [p.support - p.free for p in poses] if fit is None else fit
    linked = np.asarray(overlap, bool)
    linked = linked | linked.T
    taken: list[int] = []
    for i in sorted(range(n), key=lambda i: -fit[i]):    # stable: ties in order
        if int(linked[i, taken].sum()) < k:
            taken.append(i)
    keep = set(taken)
    return [p for i, p in enumerate(poses) if i in keep]


class _Plain(NamedTuple):
    """``ShapeFrontEnd._refine_plain``'s result for a pose it judged: what the judgement kept
    (or None), the pose and the depth's support and free share there, and where it started."""
    kept: tuple | None
    T: np.ndarray
    support: float
    free: float
    T0: np.ndarray          # the pose ICP started from, and ``_fit``'s figures there
    start: tuple


def _moved(T, shift, turn, axis, centre):
    """Pose T turned by ``turn`` about the held ``axis`` through ``centre`` and shifted by
    ``shift`` (``ShapeFrontEnd._outline_move``). The turn is measured in the image, u towards
    v: about +z, exact for a face square to the line of sight."""
    T = T.copy()
    if turn != 0.0:
        a = axis if axis[2] >= 0 else -axis
        T = apply_twist(T, np.concatenate([turn * a, np.zeros(3)]), centre)
    T[:3, 3] += shift
    return T


def _unrescued(plain):
    """``_rescue``'s result for a ``_refine_plain`` result not tried further."""
    if not isinstance(plain, _Plain):
        return plain
    return (plain.kept, plain.T, plain.support, None)


class _Claimed:
    """Item k of a Prefetch, as a task with ``result()``."""

    def __init__(self, prefetch: Prefetch, k: int):
        self._prefetch, self._k = prefetch, k

    def result(self):
        return self._prefetch.result(self._k)


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


def rects_meet(a, b) -> bool:
    """Whether two image rectangles (top, bottom, left, right) overlap."""
    return not (a[0] > b[1] or b[0] > a[1] or a[2] > b[3] or b[2] > a[3])


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


__all__ = ["ShapeFrontEnd", "FrameCloud", "resolve_correspondences", "oriented_downsample"]
