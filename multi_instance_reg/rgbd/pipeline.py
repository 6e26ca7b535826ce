"""The per-frame pipeline: one RGB-D frame in, one pose per visible instance out. No ROS.

It reads like the method::

    reg = InstanceRegistration(load_model("mug.npz"), PipelineConfig())
    result = reg.register_frame(rgb, depth_m, intrinsics)
    for inst in result.instances:       # sorted by inlier count, descending
        inst.T                          # (4, 4) model frame -> camera optical frame, metres

search region (depth in range, off the table and walls) -> detect (SIFT on that region) ->
lift (window-median depth, undistortion) -> match (one-to-many, ratio test against another
physical point) -> cluster (ECC in metres) -> recover small instances ECC left out ->
refine (optional) and select (size, fit score, no two instances in one place).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numba
import numpy as np
from scipy.spatial.distance import cdist

from ..core import ECC, ECCConfig
from ..core.refinement import instance_scores, residuals
from ..errors import InputError
from ..messages import CameraIntrinsics, no_depth_reason
from ..params import param
from ..transforms import apply_transform, refine_transform, rigid_fit
from ..frontends.sift.features import SiftSettings, extract_sift_in_region
from .lifting import backproject, lookup_depth, off_planes, support_planes, undistort_pixels
from ..frontends.sift.matching import DescriptorMatcher, prepare_descriptors
from ..models.model import ObjectModel
from ..frontends.sift.guided import GuidedMatcher, guide_instances
from .shape_frontend import ShapeFrontEnd, best_per_place, resolve_correspondences
from .verify import free_space_share, surface_samples, texture_agreement
from .workspace import Workspace, WorkspaceConfig
from ..threads import limit_blas_threads, map_each, submit_each

STAGES = ("sift", "matching", "lifting", "ecc", "refinement", "total")
# The most of a pose's agreeing points a later acceptance pass lets lie on the surface of an
# instance found before it (``ShapeFrontEnd.found_shares``): beyond it, its evidence is theirs.
FOUND_SHARE_MAX = 0.5


@dataclass(frozen=True)
class FrontEndConfig:
    """Settings of everything around the ECC core: detection, matching, lifting, refinement."""
    # Detection.
    sift_nfeatures: int = param(0, "SIFT: keep at most this many keypoints per frame (0 = all)", 0, 100000)
    sift_contrast_threshold: float = param(0.02, "SIFT contrast threshold (OpenCV default 0.04; lower finds more keypoints on weak texture)", 0.001, 0.5)
    sift_edge_threshold: float = param(10.0, "SIFT edge threshold (OpenCV default 10)", 1.0, 100.0)
    sift_octave_layers: int = param(3, "SIFT scales per octave (Lowe: 3; 2 is faster, finds fewer keypoints)", 1, 6)
    sift_upsample: float = param(1.0, "scale the image by this before SIFT (1 = off; > 1 finds more keypoints on small objects, < 1 is faster)", 0.25, 4.0)
    # Matching.
    ratio: float = param(0.8, "ratio test: best descriptor distance / second-best (second among model points more than ratio_separation away in 3D) must be below this", 0.1, 1.0)
    ratio_separation: float = param(0.01, "metres: model points closer than this to the best match count as the same physical point in the ratio test", 0.0, 1.0)
    matcher: str = param("flann", "descriptor search: flann (approximate kd-trees, about twice as fast) or brute_force (exact)", choices=("flann", "brute_force"))
    flann_checks: int = param(32, "flann: leaves the kd-tree search visits per query (each model has its own index); fewer is faster and finds fewer of the exact nearest neighbours", 1, 4096)
    multi_model_index: str = param("joint", "several models (flann): joint (one index over every model's descriptors, each knowing its model, searched once a frame; the ratio test within each model) or per_model (each model's own index, searched as with that model alone). joint is faster with several models, at a small loss of matches for objects with few keypoints", choices=("joint", "per_model"))
    joint_flann_checks: int = param(48, "flann, multi_model_index joint: leaves the search visits per query over all models' descriptors (it needs more than one model's index for the same matches: 32 lost the can's matches)", 1, 4096)
    root_sift: bool = param(True, "compare descriptors as RootSIFT (Hellinger kernel) instead of plain L2")
    # Lifting.
    depth_window: int = param(5, "side in pixels of the window whose median valid depth lifts a keypoint (odd)", 1, 31)
    depth_min: float = param(0.1, "metres: ignore depth below this", 0.0, 100.0)
    depth_max: float = param(4.0, "metres: ignore depth beyond this", 0.0, 100.0)
    remove_planes: int = param(2, "search no keypoints on (or behind) up to this many dominant planes of the depth image: the table, then a wall (0 = search everywhere); of two parallel planes nearer to each other than the object's size (the tops of several objects lying flat make one) only the farther counts", 0, 3)
    plane_thresh: float = param(0.01, "metres: keypoints closer than this to a removed plane are dropped", 0.001, 0.1)
    plane_min_share: float = param(0.2, "a plane is removed only if it holds at least this share of the valid depth pixels", 0.01, 1.0)
    depth_max_spread: float = param(0.02, "metres: drop a keypoint whose window depths spread more than this around the median (a depth edge); 0 = keep all", 0.0, 10.0)
    # Process.
    blas_threads: int = param(1, "threads of the BLAS libraries in this process (0 = leave as they are); 1 stops their busy-waiting threads from competing with SIFT on 2 cores", 0, 64)
    # Per-instance refinement.
    refine: bool = param(False, "refine each instance by least squares on its correspondences re-selected with refine_thresh (measured on the synthetic scenes: no change in median RTE/RRE, so off by default)")
    refine_iterations: int = param(3, "refinement rounds per instance", 1, 50)
    refine_thresh: float = param(0.008, "metres: residual below which a correspondence joins an instance during refinement", 0.0005, 1.0)
    # Guided matching (frontends/sift/guided.py), after the selection.
    guided: bool = param(True, "SIFT: after the selection, pair each instance's unassigned nearby scene keypoints with the model keypoints its pose puts within guided_radius of them (nearest descriptor among those, below guided_max_distance: texture repeated on the object fails the global ratio test but not this one), refit the pose on its inliers and these, and count them as its inliers")
    guided_radius: float = param(0.006, "metres: guided matching pairs a scene keypoint only with model keypoints this close to it at the instance's pose, and refits the pose on the correspondences this close to it", 0.001, 0.1)
    guided_max_distance: float = param(0.6, "guided matching: largest descriptor distance of a pair (RootSIFT: Hellinger distance, 0 to 1.41; plain L2 of unit SIFT vectors otherwise)", 0.0, 2.0)
    guided_max_inliers: int = param(50, "guided matching only for instances with at most this many inliers (the others are kept as they are)", 0, 100000)
    guided_rounds: int = param(1, "guided matching: rounds of pairing and refitting per instance (each from the pose the previous one refitted)", 1, 10)
    # Selection.
    recover: bool = param(True, "after ECC, look for small instances among the unassigned correspondences with a hard pairwise-distance test (the clustering misses clusters of 4-10 in hundreds of outliers)")
    recover_min_inliers: int = param(5, "a recovered instance needs at least this many mutually consistent correspondences", 4, 1000)
    recover_tolerance: float = param(0.01, "metres: two correspondences are consistent when their model and scene distances differ by less than this", 0.001, 0.1)
    min_score: float = param(0.7, "drop an instance whose score (mean of 1 - residual / ecc.inlier_thresh over its inliers) is below this; mirrored fits score 0.6-0.65, true ones 0.8-0.95 on the synthetic scenes (0 = keep all)", 0.0, 1.0)
    max_overlap: float = param(0.3, "drop an instance when more than this share of its box volume lies inside a stronger instance's box (1 = keep all)", 0.0, 1.0)
    max_free: float = param(0.15, "SIFT instances: drop one when more than this share of its visible model surface (the model's dense cloud at its pose, facing the camera, on valid depth) lies in front of the measured depth by more than free_tolerance + tan(free_tilt_deg) x its distance from the inliers' centre: space the camera sees to be empty (1 = off)", 0.0, 1.0)
    free_tolerance: float = param(0.008, "metres: max_free's margin at the inliers (depth noise)", 0.0, 0.2)
    free_tilt_deg: float = param(10.0, "degrees: max_free's margin grows by tan(this) per metre from the inliers, so that a pose a few close matches tilt by up to this is not taken for one in empty space", 0.0, 60.0)
    # Correspondences from shape (rgbd/shape_frontend.py; models built from a mesh).
    correspondences: str = param("auto", "where correspondences come from: sift (texture), shape (depth: point-pair votes, see shape_features), both (each through its own ECC; the SIFT instances, plus shape instances where no SIFT instance is), or auto (what the model has: shape data and keypoints -> both, shape data only -> shape, else sift)", choices=("auto", "sift", "shape", "both"))
    shape_min_variation: float = param(0.02, "shape: match only points whose surface variation (smallest / summed PCA eigenvalue over the descriptor radius) is at least this; flat faces (~0) give only outliers", 0.0, 0.34)
    shape_neighbours: int = param(3, "shape: each scene point is matched to this many nearest model descriptors (one-to-many)", 1, 20)
    shape_max_points: int = param(30000, "shape: at most this many voxel-downsampled search-region points per frame (a random subset beyond, which thins the cloud and weakens the descriptors)", 100, 1000000)
    shape_icp_iterations: int = param(15, "shape: point-to-plane ICP rounds per instance", 0, 100)
    shape_icp_association: str = param("nearest", "shape: how ICP pairs model and scene points: nearest (the nearest point of the frame's downsampled cloud within 2 voxels, then 1.5) or projective (the depth pixel each model point projects to, within the same distance shrinking to half: the tracker's ICP, tracking/icp.py, no search)", choices=("nearest", "projective"))
    shape_depth_tolerance: float = param(0.008, "metres: a model point agrees with the depth image when within this (or 0.8 voxel, whichever is larger)", 0.001, 0.2)
    shape_min_support: float = param(0.75, "shape: keep an instance when at least this share of its visible model surface agrees with the depth image", 0.0, 1.0)
    shape_min_evidence: float = param(0.8, "shape: keep an instance when support - free - 2 x outline continuation is at least this (support and free as in shape_min_support / shape_max_free; outline continuation: share of the depth pixels in a band just outside the model's outline where its nearest face continues within 3 sigma of the depth noise: a piece of a larger surface)", 0.0, 1.0)
    shape_outline_rounds: int = param(1, "shape: a pose the depth supports (shape_min_support) but that is rejected (free space, outline continuation) is moved up to this many times onto the patch of depth surface its outline bounds, along the directions its visible normals leave ICP free (a face seen alone: along its plane, and turned about its normal to the patch's long axis), ICP'd and judged again; 0 = off", 0, 10)
    shape_min_in_view: float = param(0.5, "shape: drop an instance when less than this share of its model surface facing the camera projects inside the image: the depth and outline checks judge only that part, and a pose mostly outside the image fits a strip of wall at its edge as well as an object. A true instance cut by the image edge can fall below it. 0 = off", 0.0, 1.0)
    shape_max_free: float = param(0.15, "shape: drop an instance when more than this share of its visible model surface lies in front of the measured depth (space seen to be empty)", 0.0, 1.0)
    shape_recover_max: int = param(0, "shape: look for small consistent groups among at most this many matches no ECC transform explains (a random subset; quadratic in it); 0 = off. Measured on a 2-frame grey-cylinder bag: 1500 lifts recall 0 -> 0.30 at precision 1.0 but latency 240 -> 1120 ms", 0, 100000)
    shape_features: str = param("ppf", "shape: ppf (point pairs voted per connected segment of the depth off large planes; Drost et al. 2010) or fpfh (FPFH on the search region, one-to-many)", choices=("ppf", "fpfh"))
    shape_ppf_bucket: int = param(50, "shape ppf: at most this many model pairs per quantised feature (a random subset; a box has thousands of coplanar pairs per distance)", 10, 100000)
    shape_ref_step: int = param(5, "shape ppf: every this-many-th point of a segment is a reference point that votes", 1, 100)
    shape_max_partners: int = param(60, "shape ppf: each reference point is paired with at most this many points of its segment within the object's diameter (evenly spread)", 5, 100000)
    shape_pose_clusters: int = param(30, "shape ppf: besides ECC's transforms, check this many pose hypotheses clustered straight from the reference points' votes (Drost et al.; 24 deg, a tenth of the object's diagonal); 0 = ECC's only", 0, 1000)
    shape_segment_clusters: int = param(6, "shape ppf, non-convex models only: besides the frame's best shape_pose_clusters, each connected segment's best this-many clusters of its own references' poses are checked too (those not among the frame's): an instance in a small segment, or whose votes are mostly blurred or turned over, ranks low over the frame yet high in its segment; 0 = off", 0, 100)
    shape_merged_reach: bool = param(True, "shape ppf: in a segment that holds more than one object (two of its points farther apart than the object's diameter: touching instances whose surfaces meet within the segment link), each reference point pairs only with points within the radius of the smallest ball about a point of the object's surface that holds the whole object, not the whole diameter, so that most of its partners lie on its own instance; off: the diameter, as in a segment of one object")
    shape_merged_clusters: int = param(6, "shape ppf, non-convex models, with shape_merged_reach: the segments of several objects are voted over the whole diameter as well, and each one's best this-many clusters of those votes are checked too (those not among the frame's and the segments' own): a plate's pose is told by pairs reaching the other plate, farther than the short reach; 0 = off", 0, 100)
    shape_support_area: float = param(3.0, "shape ppf: a connected piece of a dominant plane is a support surface (floor, pallet, table) and removed when its area exceeds this many times the object's largest box side", 1.0, 1000.0)
    shape_keep_object_tops: bool = param(True, "shape ppf, with shape_support_area: a large plane piece stays in the cloud when its points stand, above a larger removed plane, at a height where the object resting on it shows a flat face up, and nothing stands on it within its outline: the flush tops of objects lying side by side, larger together than shape_support_area faces, not a support (a pallet's top, as high as a carton, carries the cartons)", None, None)
    shape_deadline_ms: float = param(180.0, "shape: the search's budget, milliseconds from when the pose hypotheses are taken up (after the frame's points, votes and ECC): no further hypothesis is refined nor acceptance pass run once it is spent. The hypotheses are refined best first (ECC's clusters by size, then the vote clusters by their votes), so a cluttered frame returns the instances verified by then instead of taking seconds (IC-BIN frames with a room behind the bin: refinement 10-36 s on a loaded host). The process's CPU time, not the clock's: the same instances at any load of the host. FrameResult.deadline_cut (mireg offline: metrics.json deadline_cut_frames) says when it did; 0 = no deadline", 0.0, 100000.0)
    shape_max_noise_share: float = param(0.125, "shape: look for the object only where the depth check's tolerance there, 3 sigma of the depth noise (shape_depth_noise), is at most this share of its diameter (its box diagonal): z <= sqrt(this x diameter / (3 shape_depth_noise)). Beyond, any surface of the object's size agrees with it: IC-BIN frames (a room 2-3 m behind a bin of cups) gave 46-60 poses a frame on clutter at 2.0-3.1 m, support 0.8-1.0 at tolerances of 30-56 mm against a cup's 45 mm radius. 0.125 with the D4xx noise: cup (17 cm diagonal) 1.9 m, grey cylinder 1.65 m, bracket 1.8 m, carton 2.85 m; 0 = no limit", 0.0, 1.0)
    shape_depth_noise: float = param(0.002, "shape ppf: depth noise sigma per squared metre of distance (stereo: sigma_z = this x z^2; D4xx about 0.002); plane points lie within plane_thresh + 3 sigma_z", 0.0, 0.1)
    both_min_shown_keypoints: int = param(10, "both: a shape instance whose pose shows at least this many of the model's SIFT keypoints (facing the camera, not hidden) is a textured view, and kept only with both_min_agreeing matches; fewer: plain faces, kept on the depth evidence alone", 0, 100000)
    both_min_agreeing: int = param(3, "both: SIFT matches that must agree with a shape instance showing textured faces", 0, 100000)
    shape_plane_thresh: float = param(0.004, "shape ppf: metres: a point is on a support plane within this + 3 sigma_z of it (the SIFT path's plane_thresh, 1 cm, would take the top of a 12 mm plate lying on the table for the table); a point in that band is still off the plane where the band points of the 5 x 5 sampled pixels about it lie on average more than this + 3 sigma of such means off it (sigma measured on the plane): a tray's or a channel's thin floor is not the table", 0.0, 0.1)
    shape_segment_link: float = param(2.0, "shape ppf: points closer than this many voxels are in one segment", 1.0, 10.0)
    shape_min_segment: int = param(15, "shape ppf: segments with fewer voxel points are ignored", 3, 100000)
    shape_hidden_by_instances: bool = param(True, "shape: a pose rejected for too little support is judged again with its model points hidden behind the instances found in the frame left out (not those inside a found instance's box; at least shape_min_in_view of its points must remain), and added where no instance is", None, None)
    shape_joined_clusters: int = param(1, "shape ppf, non-convex models only (an L bracket; boxes and cylinders show one connected surface): two segments side by side in the image across a depth step, that one object could span, also vote together, and their best this-many pose clusters are checked as hypotheses (not given to ECC); 0 = off", 0, 100)
    shape_rejected_pairs: bool = param(True, "shape (with shape_hidden_by_instances), non-convex models only: poses still rejected after that are judged again two at a time, each with the other taken as found besides the instances found (its pixels hide the other's points and leave its outline band); a pair is added when both pass and neither overlaps an instance kept: two instances hiding each other or lying flush, neither found alone. Not for convex models: two carton-sized distractor boxes, one flush against the other, pass as a pair too", None, None)
    shape_rejected_groups: bool = param(True, "shape, with shape_rejected_pairs (non-convex models only): the poses still rejected after the pairs, clear of every instance kept, are judged in groups of three or more whose pixels meet one another (a row of touching instances with flush tops, each rejected on its outline unless its neighbours on both sides are taken as found), each member with all the others taken as found; those that fail leave the group and the rest are judged again; added when three or more pass", None, None)
    shape_hidden_by_any: bool = param(True, "shape (with shape_hidden_by_instances): poses still rejected after that (and shape_rejected_pairs) are judged again with every point behind a nearer measured surface left out, whatever it is, when the depth steps clearly in front of them where they go out of sight (in the depth image: at the hidden points next to the agreeing ones the depth at least 2 tolerances nearer than at those, median), and added where no instance is: an instance behind a distractor that is not found. Where a pose is sunk into a surface, that surface goes on smoothly instead", None, None)
    shape_residual_votes: bool = param(True, "shape ppf, non-convex models only: after the acceptance passes, the segments the instances found touch are voted again without those instances' points (cut into connected segments anew), and each new segment's best shape_segment_clusters clusters are refined and judged (also with the instances found hiding them), added where no instance is: an instance in one segment with its neighbours pairs most of its references with their points", None, None)
    shape_outline_by_instances: bool = param(True, "shape (with shape_hidden_by_instances): a pose rejected by the free-space or outline check is judged again too, its outline band's pixels on the instances found left out (a neighbour flush with it continues its face there: no larger surface), and added where no instance is", None, None)
    shape_faces: bool = param(True, "shape ppf, convex models with a face that has a long axis (a box; not a cylinder): the segments' flat patches whose outline (second moments) is that of a model face (a carton's top seen whole) give pose hypotheses, and a hypothesis near such a patch is moved onto it before ICP (a face seen alone holds ICP in its plane nowhere, and its point pairs differ only in their distance; rgbd/faces.py)", None, None)
    shape_rescues_per_place: int = param(3, "shape: of the refined poses the checks reject (none of them on a kept pose's place), only this many on one place (their boxes overlapping beyond max_overlap; those overhanging space seen empty, free >= 0.02, and the others each this many), the best fits (support - free), get the further tries (moved onto their outline's patch; for non-convex models the second look, turned starts and held look); 0 = all. Several hypotheses refined onto one distractor, or onto one instance they all miss, find there what the best of them finds", 0, 1000)
    shape_second_look: bool = param(True, "shape, non-convex models only (an L bracket): a refined pose rejected while overhanging space seen empty (free >= 0.02, support and support - free >= 0.6) is aligned again by projective point-to-plane ICP (each model point with the depth pixel on its ray: no pairs across the two plates where they meet, which leave nearest-point ICP a few degrees off), judged again when the depth agrees better, and added where no instance is", None, None)
    shape_residual_rejected: bool = param(True, "shape ppf, with shape_residual_votes: the residual votes also leave out the points of the rejected poses the depth supports (shape_min_support), the most evident first, each clear of those before it (max_overlap): an instance in one segment with flush neighbours that were all rejected (on their outlines onto it) has no hypothesis otherwise, its references paired with the neighbours' points. Voted besides the votes over the found instances' leftovers, not instead", None, None)
    shape_climbed_pairs: bool = param(True, "shape ppf, with shape_residual_rejected and shape_rejected_pairs: of the poses the residual votes give beside a supported rejected pose that does not overhang space seen empty (free < 0.02: rejected for what a neighbour explains), refined and rejected, the best fit on each place with that pose's pixels hiding them, when those hide some of it and the rest agrees or overhangs (the held look's gate), is climbed by turned starts (shape_turned_starts, halved twice when none is better; within the vote clusters' bounds) while the depth agrees better with it so hidden, then judged in a pair with that pose: an instance half hidden by its flush neighbour has fits a few degrees off about its top's normal that nearest-point ICP neither turns nor holds along its length", None, None)
    shape_turned_starts: float = param(10.0, "shape, with shape_second_look (non-convex models): a pose still rejected after its second look, though the depth supports it (shape_min_support), is started again from itself turned by +- this many degrees about each of the model's axes (through its visible surface's centre), 3 ICP rounds each; the start the depth agrees with best gets the remaining rounds, is judged and added where no instance is; 0 = off", 0.0, 90.0)
    shape_reject_through_support: bool = param(True, "shape ppf: drop a pose whose model reaches more than 2 voxels through the frame's largest support plane (the plane piece with the largest area removed, taken as unbounded: the table or floor): the depth check counts what lies behind the table's surface as hidden, so a bracket turned over with its upright plate sunk into the table would pass it. Off where the largest plane is not what objects stand on and objects lie beyond its extension", None, None)
    shape_pierce_every_plane: bool = param(True, "shape ppf, with shape_reject_through_support: the model may reach through none of the support planes a large piece of which the frame shows (the floor and a pallet's top on it, a table and a wall), not only the largest: a carton fitted onto a crate's top on a pallet can reach through the pallet's top while the largest plane is the floor", None, None)
    shape_min_noise_agreement: float = param(0.5, "shape: of the model points that agree with the depth (within the depth tolerance, whose floor of shape_depth_tolerance or 0.8 voxel is many sigma near the camera), at least this share must agree within the depth noise (3 sigma at the object's distance, at least 2 mm): the object's surface is where the depth is, not a shape that passes near it; 0 = off", 0.0, 1.0)
    shape_min_visible: int = param(20, "shape: an instance needs at least this many model points visible in the image with valid depth", 3, 100000)
    shape_gravity_tolerance_deg: float = param(20.0, "shape ppf, when the frame comes with the direction of gravity (the camera's accelerometer, or TF): the support \"below\" the objects (the outline check leaves out what lies no higher than an object's lowest point; shape_reject_through_support without every plane) is the largest removed plane whose normal is within this of up, not a larger wall; none within it: the largest, as without gravity. A hand-held camera's accelerometer averaged over 0.1 s is a few degrees off, more on a sharp turn; level supports lie within a degree or two, walls 70-90 deg off", 1.0, 60.0)


def rgbd_ecc_config() -> ECCConfig:
    """ECCConfig.metric() tuned on the synthetic tabletop scenes: no gamma cut. A far or
    partly hidden instance gives 6-15 correspondences while a near one gives 150-200, so the
    paper's "drop clusters under gamma x the largest" loses exactly the small ones; spurious
    clusters are removed by the front end's overlap and score tests instead, which also lets
    min_cluster_size drop to 3 (more than 3 inliers). The spatial weight is off: the plain
    compatibility of the paper found slightly more of the small clusters here."""
    return replace(ECCConfig.metric(), gamma_thresh=0.0, min_cluster_size=3, spatial_sigma=0.0)


@dataclass(frozen=True)
class PipelineConfig:
    """All settings of the per-frame pipeline; the ROS node declares one parameter per leaf."""
    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    ecc: ECCConfig = field(default_factory=rgbd_ecc_config)
    workspace: WorkspaceConfig = field(default_factory=WorkspaceConfig)


@dataclass
class Instance:
    """One found instance of the object in a frame."""
    id: int                 # index in this frame's result, 0 = most inliers (not tracked over frames)
    T: np.ndarray           # (4, 4) float64, model frame -> camera optical frame, metres
    inliers: int            # number of inlier correspondences
    score: float            # in [0, 1]: mean of 1 - residual / ecc.inlier_thresh over the inliers
    object: str = ""        # name of the model it is an instance of


@dataclass
class SceneKeypoints:
    """One frame's SIFT keypoints that have a 3D point (``InstanceRegistration.detect``)."""
    uv: np.ndarray              # (K, 2) float32 pixel coordinates
    descriptors: np.ndarray     # (K, 128) float32, ready for matching (RootSIFT when configured)
    xyz: np.ndarray             # (K, 3) float32 camera optical frame, metres
    detected: int               # SIFT keypoints found before lifting
    depth_m: np.ndarray | None = None                   # the frame's depth image (the free-space check)
    intrinsics: CameraIntrinsics | None = None


@dataclass
class FrameResult:
    """Everything one frame produced; the node's debug image draws keypoints_uv with labels."""
    instances: list[Instance]
    timings_ms: dict[str, float]        # keys: STAGES
    keypoints_uv: np.ndarray            # (N, 2) float32 pixel coordinates of the lifted matches
    model_xyz: np.ndarray               # (N, 3) float32 matched model keypoints, model frame
    scene_xyz: np.ndarray               # (N, 3) float32 lifted scene keypoints, camera frame
    labels: np.ndarray                  # (N,) int64: instance id or -1 (outlier)
    num_keypoints: int = 0              # SIFT keypoints detected in the frame
    deadline_cut: bool = False          # the shape search stopped at frontend.shape_deadline_ms

    @staticmethod
    def empty(timings_ms: dict[str, float], num_keypoints: int = 0) -> "FrameResult":
        return FrameResult([], timings_ms, np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32),
                           np.zeros((0, 3), np.float32), np.zeros(0, np.int64), num_keypoints)


def check_frame(rgb: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> None:
    """Raise InputError if the frame cannot be registered (shapes, dtypes, sizes)."""
    if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8):
        raise InputError(f"colour image must be (H, W, 3) uint8 RGB, got {getattr(rgb, 'shape', None)} "
                         f"{getattr(rgb, 'dtype', type(rgb).__name__)}")
    if not (isinstance(depth_m, np.ndarray) and depth_m.ndim == 2 and np.issubdtype(depth_m.dtype, np.floating)):
        raise InputError(f"depth image must be (H, W) float metres, got {getattr(depth_m, 'shape', None)} "
                         f"{getattr(depth_m, 'dtype', type(depth_m).__name__)}")
    if depth_m.shape != rgb.shape[:2]:
        raise InputError(f"depth image is {depth_m.shape[1]}x{depth_m.shape[0]} but colour is "
                         f"{rgb.shape[1]}x{rgb.shape[0]}; register depth to colour (aligned_depth_to_color)")
    if not np.any(depth_m > 0):
        raise InputError(f"depth image has no valid pixel ({no_depth_reason(depth_m)}); "
                         "is the depth stream running and aligned to colour?")
    if (intrinsics.width, intrinsics.height) != (rgb.shape[1], rgb.shape[0]):
        raise InputError(f"camera_info is for {intrinsics.width}x{intrinsics.height} but the image is "
                         f"{rgb.shape[1]}x{rgb.shape[0]}; use the colour stream's camera_info")


class InstanceRegistration:
    """Finds every instance of one stored object in RGB-D frames."""

    def __init__(self, model: ObjectModel, config: PipelineConfig | None = None):
        self.config = config or PipelineConfig()
        fe = self.config.frontend
        self.correspondences = resolve_correspondences(fe.correspondences, model)
        if self.correspondences in ("sift", "both") and (
                model.num_keypoints < 3 or len(model.descriptors) != model.num_keypoints):
            raise InputError(f"object model has {model.num_keypoints} keypoints and {len(model.descriptors)} descriptors; "
                             f"rebuild it with `mireg build-model`")
        self.model = model
        if fe.blas_threads > 0:
            limit_blas_threads(fe.blas_threads)
        self._sift = SiftSettings(fe.sift_nfeatures, fe.sift_contrast_threshold, fe.sift_edge_threshold, fe.sift_upsample,
                                  fe.sift_octave_layers)
        self._matcher = None
        if self.correspondences != "shape":
            self._matcher = DescriptorMatcher(prepare_descriptors(model.descriptors, fe.root_sift), model.keypoints_xyz,
                                              fe.ratio, fe.ratio_separation, method=fe.matcher,
                                              flann_checks=fe.flann_checks)
        self._guided = None
        if self._matcher is not None and fe.guided:
            self._guided = GuidedMatcher(model.keypoints_xyz, self._matcher.desc, model.box_centre, model.extent,
                                         fe.guided_radius, fe.guided_max_distance)
        self._ecc = ECC(self.config.ecc)
        self._shape = None
        if self.correspondences != "sift":
            self._shape = ShapeFrontEnd(model, fe)
            self._shape_ecc = ECC(self._shape.ecc_config(self.config.ecc))
            if self.correspondences == "both":
                self._keypoints_xyz = model.keypoints_xyz.astype(np.float64)
                self._keypoint_normals = self._shape.surface_normals_at(model.keypoints_xyz)
        self._box_grid = box_grid(model.extent) + np.asarray(model.box_centre, dtype=np.float64)
        # Surface samples for the free-space check of SIFT instances (frontend.max_free).
        self._free_surface = None
        if self.correspondences != "shape" and fe.max_free < 1.0:
            self._free_surface = surface_samples(model.points_xyz, model.extent)
        self._planes: list = []
        # Planes parallel to a support and nearer to it than this are objects' tops, not
        # supports (support_planes); several models searched with one detect: the largest.
        self.object_reach = float(np.linalg.norm(model.extent))
        self._rays, self._rays_key = None, None
        self.workspace = Workspace.from_config(self.config.workspace)
        self._region = None           # workspace_pixels' last (depth, intrinsics, pixels)

    def workspace_pixels(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray | None:
        """(H, W) bool, read-only: the pixels inside the workspace (``rgbd/workspace.py``), or
        None without one. The one place the workspace applies: every front end keeps only
        these of its keypoints and points (after finding the frame's support planes on the
        whole depth range, which a box cut through a table would hide from it), so nothing
        is hypothesised outside it. Kept for the frame (both front ends of ``both`` ask)."""
        if self.workspace is None:
            return None
        kept = self._region
        if kept is not None and kept[0] is depth_m and kept[1] is intrinsics:
            return kept[2]
        inside = self.workspace.pixels(depth_m, intrinsics)
        inside.flags.writeable = False
        self._region = (depth_m, intrinsics, inside)
        return inside

    def _search_mask(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        """(H, W) uint8: pixels with depth in range, inside the workspace, that are not on a removed plane, dilated
        by the depth window so that keypoints next to a hole keep their chance."""
        fe = self.config.frontend
        valid = (depth_m >= fe.depth_min) & (depth_m <= fe.depth_max)
        self._planes = []
        if fe.remove_planes > 0:
            self._planes = support_planes(depth_m, intrinsics, fe.remove_planes, fe.plane_thresh, fe.plane_min_share,
                                          object_reach=self.object_reach)
        if self._planes:
            u, v = self._pixel_rays(intrinsics)
            for n, d in self._planes:
                # n . (u, v, 1) z + d, the ray's dot product separable into a row and a column.
                along = (np.float32(n[0]) * u)[None, :] + (np.float32(n[1]) * v + np.float32(n[2]))[:, None]
                valid &= along * depth_m + np.float32(d) > fe.plane_thresh
        inside = self.workspace_pixels(depth_m, intrinsics)
        if inside is not None:
            valid &= inside
        r = max(fe.depth_window // 2, 1)
        return cv2.dilate(valid.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8))

    def _pixel_rays(self, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Viewing rays (u, v, 1) of the pixels as (W,) u and (H,) v float32, cached per
        camera (distortion ignored: it only shapes the search mask, the keypoints themselves
        are undistorted)."""
        key = (intrinsics.width, intrinsics.height, tuple(np.asarray(intrinsics.K).ravel()))
        if self._rays_key != key:
            K = intrinsics.K
            u = ((np.arange(intrinsics.width) - K[0, 2]) / K[0, 0]).astype(np.float32)
            v = ((np.arange(intrinsics.height) - K[1, 2]) / K[1, 1]).astype(np.float32)
            self._rays, self._rays_key = (u, v), key
        return self._rays

    def warm_up(self) -> None:
        """Run the clustering, the lifting, the free-space check and, with shape data, the
        shape path once on small made-up input, so that one-off costs (compiled kernels) are
        not paid by the first real frame. numba caches its kernels on disk, but a new checkout
        compiles them: 1.8 s on the first SIFT frame (15 s on a pallet's first shape frame), in
        which a live node's detector fell seconds behind a short stream."""
        rng = np.random.default_rng(0)
        src = rng.uniform(-0.05, 0.05, (40, 3))
        tgt = src + np.array([0.0, 0.0, 0.8])
        self._ecc.register(src, tgt)
        if self._shape is not None:
            self._shape_ecc.register(src, tgt)
        fe = self.config.frontend
        # The types of a real frame (float32 depth and pixels): the kernels compile per type.
        depth = np.full((48, 64), 0.6, np.float32)
        intrinsics = CameraIntrinsics(np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]]), 64, 48)
        lookup_depth(depth, np.array([[32.0, 24.0]], np.float32), fe.depth_window, fe.depth_min, fe.depth_max,
                     fe.depth_max_spread)
        if self._free_surface is not None:
            T = np.eye(4)
            T[2, 3] = 0.5
            free_space_share(T, *self._free_surface, depth, intrinsics, T[:3, 3], fe.free_tolerance, 0.1)
        if self._shape is not None:
            depth, intrinsics, _ = self._shape.warm_up_frame()
            workspace, self.workspace = self.workspace, None     # the made-up frame lies anywhere
            try:
                self._register_frame_shape(depth, intrinsics)
            finally:
                self.workspace = workspace

    def register_frame(self, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                       gravity: np.ndarray | None = None) -> FrameResult:
        """rgb (H, W, 3) uint8, depth_m (H, W) float metres (0 = invalid), aligned to colour.
        ``gravity``: "up" in the colour optical frame (any length; the accelerometer's mean
        reading at rest), or None when not known; the shape path takes the support below the
        objects along it (``shape_gravity_tolerance_deg``)."""
        check_frame(rgb, depth_m, intrinsics)
        gravity = unit_up(gravity)
        if self.correspondences == "shape":
            return self._register_frame_shape(depth_m, intrinsics, gravity=gravity)
        if self.correspondences == "both":
            return self._register_frame_both(rgb, depth_m, intrinsics, gravity)
        return self._register_frame_sift(rgb, depth_m, intrinsics)

    def _register_frame_sift(self, rgb, depth_m, intrinsics) -> FrameResult:
        """SIFT matches -> ECC -> refinement and checks on the matches."""
        t = {s: 0.0 for s in STAGES}
        t0 = time.perf_counter()
        keypoints = self.detect(rgb, depth_m, intrinsics, t)
        t3 = time.perf_counter()
        scene_idx, model_idx = self.match(keypoints)
        t["matching"] = (time.perf_counter() - t3) * 1e3
        result = self.solve(keypoints, scene_idx, model_idx)
        t["ecc"], t["refinement"] = result.timings_ms["ecc"], result.timings_ms["refinement"]
        t["total"] = (time.perf_counter() - t0) * 1e3
        result.timings_ms = t
        return result

    def detect(self, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
               t: dict[str, float]) -> "SceneKeypoints":
        """The frame's SIFT keypoints lifted to 3D, descriptors ready for matching; adds the
        time spent to ``t["sift"]`` and ``t["lifting"]``. Depends on the frame and the
        front-end settings only, not on the model (several models share it)."""
        fe = self.config.frontend
        t0 = time.perf_counter()
        # Where an instance can be: valid depth, off the table (and walls). SIFT runs only on
        # the box around that region and keeps keypoints inside it: one pyramid on a crop,
        # descriptors only where they can be used.
        search = self._search_mask(depth_m, intrinsics)
        t1 = time.perf_counter()

        # Detect and describe.
        uv, desc = extract_sift_in_region(rgb, search, self._sift)
        n_kp = len(uv)
        t2 = time.perf_counter()
        t["sift"] += (t2 - t1) * 1e3

        # Lift: window-median depth, undistortion, back-projection; the plane test again on
        # the lifted point (the search mask was dilated).
        z = lookup_depth(depth_m, uv, fe.depth_window, fe.depth_min, fe.depth_max, fe.depth_max_spread)
        ok = z > 0
        scene_xyz = backproject(undistort_pixels(uv[ok], intrinsics), z[ok], intrinsics)
        uv, desc = uv[ok], desc[ok]
        if self._planes:
            keep = off_planes(scene_xyz, self._planes, fe.plane_thresh)
            uv, desc, scene_xyz = uv[keep], desc[keep], scene_xyz[keep]
        desc = prepare_descriptors(desc, fe.root_sift)
        t["lifting"] += (t1 - t0 + time.perf_counter() - t2) * 1e3
        return SceneKeypoints(uv, desc, scene_xyz, n_kp, depth_m, intrinsics)

    def match(self, keypoints: "SceneKeypoints") -> tuple[np.ndarray, np.ndarray]:
        """(scene indices, model indices) of the accepted matches, one-to-many: every scene
        keypoint to its nearest model descriptor."""
        return self.match_later(keypoints)()

    def match_later(self, keypoints: "SceneKeypoints"):
        """``match``, started in the shared thread pool: returns a callable that gives its result."""
        matches = self._matcher.match_later(keypoints.descriptors)
        return lambda: matches()[:2]

    def solve(self, keypoints: "SceneKeypoints", scene_idx: np.ndarray, model_idx: np.ndarray) -> FrameResult:
        """Instances from matches (scene keypoint ``scene_idx[i]`` to model keypoint
        ``model_idx[i]``): ECC, recovery of small instances, selection. Only the ``ecc`` and
        ``refinement`` timings are filled in."""
        fe = self.config.frontend
        t = {s: 0.0 for s in STAGES}
        t4 = time.perf_counter()
        src = self.model.keypoints_xyz[model_idx].astype(np.float64)
        tgt = keypoints.xyz[scene_idx].astype(np.float64)
        kp_uv = keypoints.uv[scene_idx].astype(np.float32)
        if len(src) < 3:
            res = FrameResult.empty(t, keypoints.detected)
            res.keypoints_uv, res.model_xyz, res.scene_xyz = kp_uv, src.astype(np.float32), tgt.astype(np.float32)
            res.labels = np.full(len(src), -1, np.int64)
            return res

        # Cluster.
        reg = self._ecc.register(src, tgt)
        t5 = time.perf_counter()
        t["ecc"] = (t5 - t4) * 1e3

        # Refine each instance, drop duplicates that overlap a stronger one, assign, score.
        transforms = [np.asarray(T, dtype=np.float64) for T in reg.transforms]
        if fe.refine:
            transforms = [refine_transform(T, src, tgt, fe.refine_thresh, fe.refine_iterations) for T in transforms]
        if fe.recover:
            _, res = assign_nearest(src, tgt, transforms, self.config.ecc.inlier_thresh)
            leftover = np.flatnonzero(res >= self.config.ecc.inlier_thresh)
            transforms += recover_small_instances(src, tgt, leftover, float(np.linalg.norm(self.model.extent)),
                                                  fe.recover_tolerance, fe.recover_min_inliers,
                                                  self.config.ecc.inlier_thresh)
        instances, labels = self._finalise(src, tgt, transforms, keypoints.depth_m, keypoints.intrinsics)
        if self._guided is not None and instances:
            instances, scene_idx, model_idx, labels = self._guide(keypoints, instances, scene_idx, model_idx, labels)
            src = self.model.keypoints_xyz[model_idx].astype(np.float64)
            tgt = keypoints.xyz[scene_idx].astype(np.float64)
            kp_uv = keypoints.uv[scene_idx].astype(np.float32)
        t["refinement"] = (time.perf_counter() - t5) * 1e3
        return FrameResult(instances, t, kp_uv, src.astype(np.float32), tgt.astype(np.float32), labels,
                           keypoints.detected)

    def _guide(self, keypoints: "SceneKeypoints", instances: list[Instance], scene_idx: np.ndarray,
               model_idx: np.ndarray, labels: np.ndarray):
        """Guided matching (``frontends/sift/guided.py``) for the selected instances: refitted poses, their
        inliers counted with the guided pairs, ranked again. Returns the instances and the
        frame's correspondences (scene and model keypoint indices, labels): a guided pair
        replaces the global match of its scene keypoint, or is added when it had none."""
        thresh = self.config.ecc.inlier_thresh
        fe = self.config.frontend
        own_s = [scene_idx[labels == i] for i in range(len(instances))]
        own_m = [model_idx[labels == i] for i in range(len(instances))]
        g = guide_instances(self._guided, [inst.T for inst in instances], own_s, own_m, keypoints.xyz,
                            keypoints.descriptors, thresh, fe.guided_radius, fe.guided_rounds,
                            max_inliers=fe.guided_max_inliers)
        counts = np.array([len(s) for s in g.scene])
        order = np.argsort(-counts, kind="stable")           # ids are ranks by inliers
        entry = np.full(len(keypoints.xyz), -1, np.int64)
        entry[scene_idx] = np.arange(len(scene_idx))
        model_idx = model_idx.copy()
        labels = np.full(len(scene_idx), -1, np.int64)
        added_s, added_m, added_l = [], [], []
        out = []
        for rank, i in enumerate(order):
            s, m = g.scene[i], g.model[i]
            e = entry[s]
            model_idx[e[e >= 0]] = m[e >= 0]
            labels[e[e >= 0]] = rank
            added_s.append(s[e < 0])
            added_m.append(m[e < 0])
            added_l.append(np.full(int((e < 0).sum()), rank, np.int64))
            score = float(np.mean(1.0 - g.residual[i] / thresh)) if len(s) else 0.0
            out.append(Instance(rank, g.transforms[i], int(len(s)), score, self.model.name))
        scene_idx = np.concatenate([scene_idx] + added_s)
        model_idx = np.concatenate([model_idx] + added_m)
        labels = np.concatenate([labels] + added_l)
        return out, scene_idx, model_idx, labels

    def _register_frame_shape(self, depth_m, intrinsics, search=None, gravity=None) -> FrameResult:
        """Shape correspondences -> ECC -> per instance ICP and a depth check -> no two
        instances in one place (which also reports a symmetric object once: its symmetric
        fits fill the same box)."""
        fe = self.config.frontend
        t = {s: 0.0 for s in STAGES}
        t["shape"] = 0.0
        t0 = time.perf_counter()
        within = None
        if fe.shape_features == "ppf":
            within = self.workspace_pixels(depth_m, intrinsics)     # ppf removes its own planes first
        elif search is None:
            search = self._search_mask(depth_m, intrinsics)
        t3 = time.perf_counter()
        t["lifting"] = (t3 - t0) * 1e3
        cloud = self._shape.frame_cloud(depth_m, intrinsics, None if search is None else search > 0, gravity, within)
        self._shape.keep_frame(depth_m, intrinsics)        # the acceptance passes redraw the same poses
        t4 = time.perf_counter()
        # ECC does not need the vote clusters' poses (ppf): it runs in the shared pool as
        # soon as the correspondences are made, while those poses are made (whose single-
        # threaded steps left the other core idle); the poses do not depend on ECC either:
        # they are refined on the other core until ECC is done (those an ECC transform turns
        # out to duplicate are not used). "matching" then holds the pose clusters too, and
        # "ecc" the wait for ECC after them.
        started, solving = [], []

        def start_ecc(s, g):
            if len(s) >= 3:
                solving.extend(submit_each(lambda pair: self._shape_ecc.register(*pair), [(s, g)]))

        src, tgt = self._shape.correspondences(cloud, on_poses=lambda: started.append(
            self._shape.start_refining(list(cloud.poses), cloud, depth_m, intrinsics)), on_matches=start_ecc)
        started = started[0] if started else None
        t5 = time.perf_counter()
        t["shape"] = (t4 - t3) * 1e3
        t["matching"] = (t5 - t4) * 1e3
        hypotheses = [] if cloud.poses is None else list(cloud.poses)
        if len(src) >= 3:
            reg = solving[0].result() if solving else self._shape_ecc.register(src, tgt)
            hypotheses = [np.asarray(T, np.float64) for T in reg.transforms] + hypotheses
        offset = len(hypotheses) - (0 if cloud.poses is None else len(cloud.poses))
        t6 = time.perf_counter()
        t["ecc"] = (t6 - t5) * 1e3
        if fe.recover and fe.shape_recover_max > 0 and len(src) >= 3:
            # More hypotheses from the matches no transform explains: the depth check below
            # rejects the wrong ones, while a missed instance is lost for the frame.
            thresh = self._shape_ecc.config.inlier_thresh
            _, res = assign_nearest(src, tgt, hypotheses, thresh)
            leftover = np.flatnonzero(res >= thresh)
            if len(leftover) > fe.shape_recover_max:
                leftover = np.sort(np.random.default_rng(0).choice(leftover, fe.shape_recover_max, replace=False))
            hypotheses += recover_small_instances(src, tgt, leftover, self._shape.diameter, self._shape.voxel,
                                                  fe.recover_min_inliers, thresh)
        rejected, second = [], []
        # The search's budget: from here, where the hypotheses are taken up best first.
        self._shape.set_deadline(time.process_time() + fe.shape_deadline_ms / 1e3 if fe.shape_deadline_ms > 0 else None)
        checked = self._shape.refine_and_check(hypotheses, cloud, depth_m, intrinsics, started, offset, rejected,
                                               second, overlaps=self._overlapping)
        chosen = self._one_per_box(checked, frame=(depth_m, intrinsics))
        if second:
            # Poses kept at their second look (a non-convex model's projective ICP) only where
            # no instance is: ranked with the rest, a wrong one polished onto a bracket took
            # the place of its right pose left 4 deg off (seed 0).
            chosen = self._one_per_box(chosen + second, first=len(chosen), frame=(depth_m, intrinsics))
        if not self._shape.past_deadline():
            chosen = self._accept_rejected(chosen, rejected, hypotheses, cloud, depth_m, intrinsics)
        self._shape.keep_frame(None)
        cut = self._shape.deadline_cut
        self._shape.set_deadline(None)
        instances = [Instance(i, c[0], c[2], float(c[1]), self.model.name) for i, c in enumerate(chosen)]
        labels, _ = assign_nearest(src, tgt, [c[0] for c in chosen], self._shape_ecc.config.inlier_thresh)
        t["refinement"] = (time.perf_counter() - t6) * 1e3
        t["total"] = (time.perf_counter() - t0) * 1e3
        uv = project_points(tgt, intrinsics)
        return FrameResult(instances, t, uv, src.astype(np.float32), tgt.astype(np.float32), labels, 0,
                           deadline_cut=cut)

    def _accept_rejected(self, chosen, rejected, hypotheses, cloud, depth_m, intrinsics) -> list:
        """``chosen`` (the instances the refinement keeps) and what the acceptance passes add
        of the ``rejected`` poses (and of the residual votes over ``hypotheses``' segments)."""
        fe = self.config.frontend
        late = self._shape.past_deadline      # each pass only while the frame's deadline has not passed
        if fe.shape_hidden_by_instances and chosen and rejected:
            # Poses rejected for too little support, perhaps for what the instances found
            # hide of them, or by the outline, where a found one is flush with them: judged
            # again with those points and pixels left out, added where no instance is.
            chosen, rejected = self._accept_behind(chosen, rejected, cloud, depth_m, intrinsics)
        judged_with = {id(c) for c in chosen}
        if fe.shape_hidden_by_instances and fe.shape_rejected_pairs and len(rejected) >= 2 and not late():
            chosen = self._accept_pairs(chosen, rejected, cloud, depth_m, intrinsics)
            if fe.shape_rejected_groups and not late():
                chosen = self._accept_groups(chosen, rejected, cloud, depth_m, intrinsics)
        provisional = []
        if fe.shape_hidden_by_instances and fe.shape_hidden_by_any and rejected and not late():
            before = chosen
            chosen = self._accept_hidden(chosen, rejected, cloud, depth_m, intrinsics)
            provisional = chosen[len(before):]
        if fe.shape_hidden_by_instances and self._shape.non_convex and rejected and not late():
            chosen = self._accept_turned(chosen, rejected, cloud, depth_m, intrinsics)
        if fe.shape_residual_votes and self._shape.non_convex and chosen and not late():
            chosen = self._accept_residual(chosen, hypotheses, cloud, depth_m, intrinsics, provisional, rejected)
        if fe.shape_hidden_by_instances and rejected and any(id(c) not in judged_with for c in chosen) and not late():
            # The rejected poses judged again with the instances the later passes found (those
            # whose checks look where one of them is seen): a channel rejected on its outline
            # onto a flush neighbour found only by the residual votes (channel seed 2251 frames
            # 7 / 8) passes with it.
            meet = self._shape.rects_meeting(rejected, [c[0] for c in chosen if id(c) not in judged_with], intrinsics)
            near = [T for T, row in zip(rejected, meet) if row.any()]
            if near:
                chosen, _ = self._accept_behind(chosen, near, cloud, depth_m, intrinsics)
        return chosen

    def _accept_pairs(self, chosen, rejected, cloud, depth_m, intrinsics) -> list:
        """``chosen`` and the rejected poses accepted two at a time (``ShapeFrontEnd.judge_pairs``:
        each passes with the other taken as found), a pair only when neither overlaps an
        instance kept or a pose accepted before it; the strongest pairs first."""
        if not self._shape.non_convex:
            return chosen
        found = [c[0] for c in chosen]
        limit = self.config.frontend.max_overlap
        free, sub = self._free_block(found, rejected)
        if len(free) < 2:
            return chosen
        occluders = self._shape.instance_pixels(found, depth_m, intrinsics)
        pairs = self._shape.judge_pairs([rejected[k] for k in free], sub, limit, cloud, depth_m, intrinsics,
                                        occluders, found)
        taken: set[int] = set()
        for i, j, ri, rj in pairs:
            if any(sub[i, k] > limit or sub[k, i] > limit or sub[j, k] > limit or sub[k, j] > limit for k in taken):
                continue
            taken |= {i, j}
            chosen = chosen + [ri, rj]
        return chosen

    def _accept_groups(self, chosen, rejected, cloud, depth_m, intrinsics) -> list:
        """``chosen`` and the rejected poses clear of it accepted in groups of three or more
        (``ShapeFrontEnd.judge_groups``: each passes with all the others taken as found)."""
        found = [c[0] for c in chosen]
        free, sub = self._free_block(found, rejected)
        if len(free) < 3:
            return chosen
        occluders = self._shape.instance_pixels(found, depth_m, intrinsics) if found \
            else np.zeros(depth_m.shape, np.uint8)
        return chosen + self._shape.judge_groups([rejected[k] for k in free], sub, self.config.frontend.max_overlap,
                                                 cloud, depth_m, intrinsics, occluders, found)

    def _accept_hidden(self, chosen, rejected, cloud, depth_m, intrinsics) -> list:
        """``chosen`` and the rejected poses that pass with whatever lies in front of them
        taken as hiding them (``ShapeFrontEnd.judge_hidden``), added where no instance is."""
        found = [c[0] for c in chosen]
        free = [rejected[k] for k in self._clear_of(found, rejected)[1]]
        if not free:
            return chosen
        explained = self._shape.instance_pixels(found, depth_m, intrinsics) if found else None
        hidden = [c for c in map_each(lambda T: self._shape.judge_hidden(T, cloud, depth_m, intrinsics, explained,
                                                                                  found),
                                      free) if c is not None]
        if not hidden:
            return chosen
        chosen = self._hidden_over_overhanging(chosen, hidden, depth_m, intrinsics)
        return self._one_per_box(chosen + hidden, first=len(chosen), frame=(depth_m, intrinsics))

    def _hidden_over_overhanging(self, chosen, hidden, depth_m, intrinsics) -> list:
        """``chosen`` without those that overhang space the depth shows empty
        (``ShapeFrontEnd.overhangs``) where one of the ``hidden`` poses (passed with what lies
        in front hiding them) that does not overhang claims the same seen points (more than
        ``FOUND_SHARE_MAX`` of its agreeing points on the chosen one's surface) with more
        evidence: of two poses explaining the same surface, the one whose unseen rest lies
        behind a nearer surface, not out in view. An L bracket whose base plate is hidden
        behind a cylinder, its upright plate seen: the same bracket turned half about the
        vertical, its base on the open table, agrees as well (support 0.91, free 0.06-0.07,
        evidence 175-188), kept first, then kept the right pose (judged hidden, free 0) off
        its place (bracket seed 2465 frames 3 / 5)."""
        shape = self._shape
        level = [c for c in hidden if not shape.overhangs(c[0], depth_m, intrinsics)]
        if not level:
            return chosen
        out = []
        for c in chosen:
            if shape.overhangs(c[0], depth_m, intrinsics) and any(
                    h[3] > c[3] and shape.found_shares([h[0]], [c[0]], depth_m, intrinsics)[0] > FOUND_SHARE_MAX
                    for h in level):
                continue
            out.append(c)
        return out

    def _accept_turned(self, chosen, rejected, cloud, depth_m, intrinsics) -> list:
        """``chosen`` and the rejected poses clear of it turned over (``ShapeFrontEnd.turned_over_starts``),
        those clear of the instances found refined and judged as hypotheses (one of each group
        alike: several fits of one channel turn over onto it), added where no instance is."""
        found = [c[0] for c in chosen]
        free = [rejected[k] for k in self._clear_of(found, rejected)[1]]
        starts = [T1 for S in map_each(lambda T: self._shape.turned_over_starts(T, cloud, depth_m, intrinsics), free)
                  for T1 in S]
        # Most fits on an instance found turn over onto it (a fit sliding between two).
        starts = [starts[k] for k in self._clear_of(found, starts)[1]]
        if not starts:
            return chosen
        second = []
        checked = self._shape.refine_and_check(starts, cloud, depth_m, intrinsics, second=second)
        if not checked and not second:
            return chosen
        # A pose placed by a half turn is a guess the votes did not make: its near-symmetric
        # twin is as near (an L bracket with its plates swapped), and so is a pose a few
        # degrees off the one ICP left; of them the depth agrees with best is kept (bracket
        # seed 1213 frame 6: the turned pose 178 deg off a bracket, evidence 138, its twin
        # refined onto that bracket 181; 1917 frame 2: 10.4 deg off, 171.5, its second look
        # 1.0 deg off, 213).
        accepted = [self._better_twin(c, cloud, depth_m, intrinsics) for c in checked + second]
        return self._one_per_box(chosen + accepted, first=len(chosen), frame=(depth_m, intrinsics))

    def _better_twin(self, kept, cloud, depth_m, intrinsics):
        """Of ``kept`` (T, support, agreeing points, evidence), it after the second look's
        projective ICP (``ShapeFrontEnd.look_again``) and its near-symmetric twins
        (``ShapeFrontEnd.near_twins``) refined, each judged, the one with the most evidence."""
        looked = self._shape.look_again(kept[0], cloud, depth_m, intrinsics)
        candidates = [kept] + ([looked] if looked is not None else [])
        twins = self._shape.near_twins(kept[0])
        if twins:
            second = []
            candidates += self._shape.refine_and_check(twins, cloud, depth_m, intrinsics, second=second) + second
        return max(candidates, key=lambda c: c[3])

    def _accept_residual(self, chosen, hypotheses, cloud, depth_m, intrinsics, provisional=(), rejected=()) -> list:
        """``chosen`` and the poses voted again over what the instances found leave of their
        segments (``ShapeFrontEnd.residual_poses``), refined and judged as the first
        hypotheses, then with the instances found hiding them (``judge_behind``); added
        where no instance is. ``provisional``: those of ``chosen`` passed only with points
        taken as hidden behind whatever is in front (``_accept_hidden``): a pose here with
        more evidence on the place of one takes it (``_one_per_box``), and their segments
        are voted again with their points kept, for poses on their places
        (``_on_place_of``). Bracket seed 157 frame 9: a bracket on the upright plate of
        another, turned half about the vertical, its base plate taken as hidden (evidence
        219), held the place of that bracket's right pose (243), voted over the points it
        had taken."""
        marked = {id(c) for c in provisional}
        firm = [c for c in chosen if id(c) not in marked]
        provisional = [c for c in chosen if id(c) in marked]
        found = [c[0] for c in chosen]
        supported = self._supported(rejected, found, cloud, depth_m, intrinsics) \
            if rejected and self.config.frontend.shape_residual_rejected else []
        poses = self._shape.residual_poses(cloud, found, hypotheses, depth_m, intrinsics)
        if supported:
            # Besides, not instead: a supported pose may lie wrong over an instance that the
            # votes above find (channel seed 0, bracket 2366: hits lost when they replaced them).
            more = self._shape.residual_poses(cloud, found, np.concatenate([np.reshape(hypotheses, (-1, 4, 4)), poses]),
                                              supported=supported)
            poses = np.concatenate([poses, more]) if len(more) else poses
        rejected, second, checked = [], [], []
        if len(poses):
            checked = self._shape.refine_and_check(list(poses), cloud, depth_m, intrinsics, rejected=rejected,
                                                   second=second)
        if provisional:
            placed = [c[0] for c in provisional]
            again = self._shape.residual_poses(cloud, [c[0] for c in firm],
                                               np.concatenate([np.reshape(hypotheses, (-1, 4, 4)), poses]),
                                               depth_m, intrinsics, kept=placed)
            if len(again):
                looked = []
                more = self._shape.refine_and_check(list(again), cloud, depth_m, intrinsics, second=looked) + looked
                # Only to take a provisional pose's place: elsewhere these votes over its
                # points add nothing the votes without them did not (and they vote other
                # clusters over its neighbours: seed 1811 frame 0, a bracket behind a right
                # provisional one).
                checked += [c for c in more if self._on_place_of(c[0], placed, (depth_m, intrinsics))]
        if checked or second:
            chosen = self._one_per_box(firm + provisional + checked + second, first=len(firm),
                                       frame=(depth_m, intrinsics))
        if supported and rejected and self.config.frontend.shape_climbed_pairs and self.config.frontend.shape_rejected_pairs:
            chosen = self._accept_climbed_pairs(chosen, supported, rejected, cloud, depth_m, intrinsics)
        if self.config.frontend.shape_hidden_by_instances and rejected:
            chosen, rejected = self._accept_behind(chosen, rejected, cloud, depth_m, intrinsics)
            # These votes are over what the instances found leave: a channel lying open side
            # down among found ones has its fits here (channel seed 631 frame 11: both misses).
            if rejected:
                chosen = self._accept_turned(chosen, rejected, cloud, depth_m, intrinsics)
        return chosen

    def _accept_climbed_pairs(self, chosen, supported, rejected, cloud, depth_m, intrinsics) -> list:
        """``chosen`` and pairs (``_accept_pairs``) of the ``supported`` rejected poses (those
        not overhanging space seen empty, ``ShapeFrontEnd.overhangs``) and the
        poses the residual votes gave beside them (``rejected``: refined, rejected), each
        of those first climbed (``ShapeFrontEnd.climbed``) with that supported pose's pixels
        and the instances' taken as hiding it: the best fit so hidden on each place beside it
        (its box clear of it, the image rectangles meeting) of those worth the climb
        (``ShapeFrontEnd.climb_fit``). A channel half hidden by its
        flush neighbour, which is rejected on its outline onto it, has no fit ICP sets right
        (channel seed 2141 frames 0-2: 2-12 deg off about its top's normal); the pair, judged
        as ``judge_pairs`` does, passes at the climbed pose."""
        found = [c[0] for c in chosen]
        shape = self._shape
        # Only those rejected for what a neighbour explains: one that overhangs space seen
        # empty is off along what it shows (channel seed 2404 frame 11: slid 27 mm along its
        # length, free 0.07, it passed with a channel climbed beside it; 2141's, free 0.00).
        supported = [supported[k] for k in self._clear_of(found, supported)[1]
                     if not shape.overhangs(supported[k], depth_m, intrinsics)]
        rejected = [rejected[k] for k in self._clear_of(found, rejected)[1]]
        if not supported or not rejected:
            return chosen
        occluders = shape.instance_pixels(found, depth_m, intrinsics) if found \
            else np.zeros(depth_m.shape, np.uint8)
        starts = []
        meet = shape.rects_meeting(supported, rejected, intrinsics)
        for P, beside, meets in zip(supported, self._overlapping(supported, rejected), meet):
            near = np.flatnonzero(meets & ~np.asarray(beside, bool))
            if not len(near):
                continue
            hiding = np.maximum(occluders, shape.instance_pixels([P], depth_m, intrinsics))
            scored = [(rejected[k], f) for k in near
                      if (f := shape.climb_fit(rejected[k], hiding, depth_m, intrinsics)) is not None]
            if not scored:
                continue
            poses = [T for T, _ in scored]
            best = best_per_place(poses, self._overlapping(poses), 1, fit=[f for _, f in scored])
            starts += [(T, hiding) for T in best]
        if not starts:
            return chosen
        climbed = map_each(lambda s: shape.climbed(s[0], s[1], cloud, depth_m, intrinsics), starts)
        return self._accept_pairs(chosen, supported + list(climbed), cloud, depth_m, intrinsics)

    def _supported(self, rejected, found, cloud, depth_m, intrinsics) -> list:
        """Of the ``rejected`` poses clear of the instances ``found``, those the depth
        supports (``shape_min_support``, nothing taken as hidden), the most evident first
        (``supported_evidence``) and each clear of those taken before it (``max_overlap``;
        ``best_per_place`` with one a place), as ``_one_per_box`` takes instances: rejected by their other checks (the outline
        onto an unfound neighbour), their points are theirs all the same. By support alone,
        fits slid along a channel onto its flush neighbour came first (channel seed 2141
        frame 0: support 0.98, outline 0.22, against the right fit's 0.94 and 0.06)."""
        free = self._shape.one_of_each([rejected[k] for k in self._clear_of(found, rejected)[1]])
        scored = [(T, e) for T in free if (e := self._shape.supported_evidence(T, cloud, depth_m, intrinsics))
                  is not None]
        if not scored:
            return []
        poses = [T for T, _ in scored]
        return best_per_place(poses, self._overlapping(poses), 1, fit=[e for _, e in scored])

    def _on_place_of(self, T, poses, frame) -> bool:
        """Whether pose T takes the place of one of ``poses`` in ``_one_per_box``: their
        boxes overlap beyond ``max_overlap``, or more than ``FOUND_SHARE_MAX`` of that one's
        agreeing points lie on T's surface (``_own_evidence``)."""
        return self._overlaps_any([T], poses)[0] or any(not self._own_evidence(P, [T], frame) for P in poses)

    def _accept_behind(self, chosen, rejected, cloud, depth_m, intrinsics) -> tuple[list, list]:
        """``chosen`` and the rejected poses that pass with the instances found hiding them
        (``ShapeFrontEnd.judge_behind``), added where no instance is; and the rejected poses
        clear of the instances found (``_clear_of``), the only ones a later pass can add."""
        found = [c[0] for c in chosen]
        rejected = [rejected[k] for k in self._clear_of(found, rejected)[1]]
        if rejected:
            occluders = self._shape.instance_pixels(found, depth_m, intrinsics)
            # Each on its own, two at a time in the shared thread pool (as the refinement).
            behind = [c for c in map_each(lambda T: self._shape.judge_behind(T, cloud, depth_m, intrinsics,
                                                                             occluders, found), rejected)
                      if c is not None]
            if behind:
                chosen = self._one_per_box(chosen + behind, first=len(chosen), frame=(depth_m, intrinsics))
        return chosen, rejected

    def _clear_of(self, found, rejected) -> tuple[np.ndarray, list[int]]:
        """``box_overlaps`` of ``found`` followed by ``rejected``, and the indices of the
        rejected poses whose box overlaps no found one's beyond ``max_overlap``: the others
        are dropped by the selection whatever a judging says, so they are not judged."""
        limit = self.config.frontend.max_overlap
        overlap = box_overlaps(self.model, list(found) + list(rejected), self._box_grid)
        n = len(found)
        free = [k for k in range(len(rejected))
                if not (np.any(overlap[n + k, :n] > limit) or np.any(overlap[:n, n + k] > limit))]
        return overlap, free

    def _free_block(self, found, rejected) -> tuple[list[int], np.ndarray]:
        """``_clear_of``'s free rejected poses (indices) and the box overlaps among them."""
        overlap, free = self._clear_of(found, rejected)
        n = len(found)
        return free, overlap[np.ix_([n + k for k in free], [n + k for k in free])]

    def _overlaps_any(self, transforms, poses) -> list[bool]:
        """For each of ``transforms``, whether its box and one of ``poses``' overlap beyond
        ``max_overlap`` (either way; ``_clear_of``), as ``_one_per_box`` keeps no two."""
        return [bool(row.any()) for row in self._overlapping(transforms, poses)]

    def _overlapping(self, transforms, poses=None) -> np.ndarray:
        """(len(transforms), len(poses)) bool: whether each transform's box and each pose's
        overlap beyond ``max_overlap`` (either way; ``_clear_of``); ``poses`` None: the
        transforms among themselves (the diagonal True)."""
        limit = self.config.frontend.max_overlap
        if poses is None:
            overlap = box_overlaps(self.model, list(transforms), self._box_grid)
            return (overlap > limit) | (overlap.T > limit) | np.eye(len(transforms), dtype=bool)
        n = len(poses)
        if n == 0 or len(transforms) == 0:
            return np.zeros((len(transforms), n), bool)
        overlap = box_overlaps(self.model, list(poses) + list(transforms), self._box_grid)
        return (overlap[n:, :n] > limit) | (overlap[:n, n:].T > limit)

    def _one_per_box(self, checked, first: int = 0, frame=None) -> list:
        """No two instances in one box: of the checked poses (T, support, agreeing points,
        evidence), the first ``first`` kept as they are, then the rest by their evidence (the
        depth check's net points, ``ShapeFrontEnd._judge``), each kept when it overlaps none
        kept before. By agreeing points alone, a carton fitted lying on its side into a
        standing one's top (its 30 x 15 cm face inside the 30 x 20 top, some of the side
        face showing too) outnumbered the right pose by a few points while overhanging.
        ``frame`` ((depth, intrinsics)): each of the rest is also dropped where most of its
        agreeing points lie on the surfaces of those kept before it (``_own_evidence``)."""
        checked = list(checked[:first]) + sorted(checked[first:], key=lambda c: -c[3])
        overlap = box_overlaps(self.model, [c[0] for c in checked], self._box_grid)
        kept, limit = list(range(first)), self.config.frontend.max_overlap
        for k in range(first, len(checked)):
            if all(overlap[k, j] <= limit and overlap[j, k] <= limit for j in kept) and (
                    frame is None or self._own_evidence(checked[k][0], [checked[j][0] for j in kept], frame)):
                kept.append(k)
        return [checked[k] for k in kept]

    def _own_evidence(self, T, kept, frame) -> bool:
        """Whether at most ``FOUND_SHARE_MAX`` of pose T's agreeing points lie on the surfaces
        of the poses ``kept`` (stronger ones; ``ShapeFrontEnd.found_shares``): beyond it, T is
        one of them seen again. In the first choice, a bracket turned over onto a stronger
        one's plate (its box clear of that one's, 0.87 of its points on it) took the place of
        the bracket it half covered (seed 5 frame 2). In the later passes (poses added only
        where no instance is), an L bracket turned over, one plate on a found bracket's,
        passed by ``judge_behind``: seed 923, share 1.00; the poses those passes add right
        0.00-0.05. Only the kept poses whose boxes can come that near are looked at."""
        centre = np.asarray(self.model.box_centre, np.float64)
        here = T[:3, :3] @ centre + T[:3, 3]
        reach = self.object_reach + 2.0 * self._shape.voxel
        near = [F for F in kept if np.linalg.norm(F[:3, :3] @ centre + F[:3, 3] - here) <= reach]
        return not near or self._shape.found_shares([T], near, *frame)[0] <= FOUND_SHARE_MAX

    def _register_frame_both(self, rgb, depth_m, intrinsics, gravity=None) -> FrameResult:
        """Texture and shape, each through its own ECC; every SIFT instance is kept as the
        SIFT path finds it, and a shape instance is added where no SIFT instance is. (Joining
        the two correspondence sets before one ECC and judging every instance by the depth
        checks lost textured instances that lean on or hide behind others: seed 0 MHF1 0.88
        against 0.98 for SIFT alone.)"""
        fe = self.config.frontend
        textured = self._register_frame_sift(rgb, depth_m, intrinsics)
        shaped = self._register_frame_shape(depth_m, intrinsics, gravity=gravity)
        transforms = [i.T for i in textured.instances] + [i.T for i in shaped.instances]
        overlap = box_overlaps(self.model, transforms, self._box_grid)
        kept = list(range(len(textured.instances)))
        instances = list(textured.instances)
        # The frame's matches, as texture_agreement reads them: converted once, not per instance.
        match_model, match_scene = textured.model_xyz.astype(np.float64), textured.scene_xyz.astype(np.float64)
        for k, inst in enumerate(shaped.instances, start=len(kept)):
            if all(overlap[k, j] <= fe.max_overlap and overlap[j, k] <= fe.max_overlap for j in kept):
                # The texture has its say: a shape pose that shows the model's textured
                # faces is kept only when some of the frame's matches agree with it (they
                # also pick which of its symmetric poses it is).
                T, agree, shown = texture_agreement(inst.T, self._keypoints_xyz, self._keypoint_normals,
                                                    self.model.symmetries, match_model, match_scene, depth_m,
                                                    intrinsics, self.config.ecc.inlier_thresh,
                                                    self._shape.depth_tolerance)
                if shown >= fe.both_min_shown_keypoints and agree < fe.both_min_agreeing:
                    continue
                kept.append(k)
                instances.append(Instance(len(instances), T, inst.inliers, inst.score, self.model.name))
        t = {s: textured.timings_ms.get(s, 0.0) + shaped.timings_ms.get(s, 0.0) for s in textured.timings_ms}
        t["shape"] = shaped.timings_ms.get("shape", 0.0)
        return FrameResult(instances, t, textured.keypoints_uv, textured.model_xyz, textured.scene_xyz,
                           textured.labels, textured.num_keypoints, deadline_cut=shaped.deadline_cut)

    def _finalise(self, src, tgt, transforms, depth_m=None, intrinsics=None) -> tuple[list[Instance], np.ndarray]:
        """Assign correspondences to their nearest instance; drop instances that end up too
        small, fit loosely, fill space the depth image sees to be empty, or overlap a
        stronger one (two instances cannot fill the same space: such a duplicate is usually
        a mirrored fit to texture repeated on two faces)."""
        ecc = self.config.ecc
        thresh = ecc.inlier_thresh
        fe = self.config.frontend
        kept = list(range(len(transforms)))
        overlap = box_overlaps(self.model, transforms, self._box_grid)
        check_free = self._free_surface is not None and depth_m is not None and intrinsics is not None
        free: dict[int, float] = {}
        slope = float(np.tan(np.radians(fe.free_tilt_deg)))
        while True:
            labels, res = assign_nearest(src, tgt, [transforms[k] for k in kept], thresh)
            counts = np.bincount(labels[labels >= 0], minlength=len(kept))
            scores = instance_scores(labels, res, thresh, len(kept))
            # Too small, or too loose (a mirrored pose on texture repeated on two faces) ...
            order = [i for i in np.argsort(-counts, kind="stable")
                     if counts[i] > ecc.min_cluster_size and scores[i] >= fe.min_score]
            # ... or in space the camera sees to be empty (judged once per transform, with
            # the inliers it first has) ...
            if check_free:
                for i in order:
                    if kept[i] not in free:
                        free[kept[i]] = free_space_share(transforms[kept[i]], *self._free_surface, depth_m, intrinsics,
                                                         tgt[labels == i].mean(axis=0), fe.free_tolerance, slope)[0]
                order = [i for i in order if free[kept[i]] <= fe.max_free]
            order = [kept[i] for i in order]
            # ... or in the space of a stronger instance.
            survivors = []
            for k in order:
                if all(overlap[k, j] <= fe.max_overlap for j in survivors):
                    survivors.append(k)
            if survivors == kept:
                break
            kept = survivors
        instances = [Instance(i, transforms[k], int((labels == i).sum()), float(scores[i]), self.model.name)
                     for i, k in enumerate(kept)]
        return instances, labels


def unit_up(gravity) -> np.ndarray | None:
    """A frame's gravity "up" as a unit (3,) float64 vector, or None (not known)."""
    if gravity is None:
        return None
    g = np.asarray(gravity, np.float64)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or float(np.linalg.norm(g)) < 1e-9:
        raise InputError(f"gravity must be a finite, non-zero 3-vector in the camera's optical frame, got {gravity!r}")
    return g / np.linalg.norm(g)


def project_points(xyz: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(N, 2) float32 pixel coordinates of camera-frame points (pinhole, no distortion)."""
    K = intrinsics.K
    z = np.maximum(xyz[:, 2], 1e-6)
    return np.stack([K[0, 0] * xyz[:, 0] / z + K[0, 2], K[1, 1] * xyz[:, 1] / z + K[1, 2]], axis=1).astype(np.float32)


def recover_small_instances(src: np.ndarray, tgt: np.ndarray, candidates: np.ndarray, diameter: float,
                            tolerance: float, min_inliers: int, inlier_thresh: float, max_instances: int = 20
                            ) -> list[np.ndarray]:
    """Rigid transforms for small groups of mutually consistent correspondences.

    Two correspondences are consistent when their model-side and scene-side distances agree
    within ``tolerance`` and both lie within one object (``diameter``). Greedily: take the
    correspondence with the most consistent partners, shrink it and its partners to a set
    where every pair is consistent, fit, re-select inliers, keep the fit if it has at least
    ``min_inliers``; remove them and repeat. A random group of 5 passing 10 pairwise tests at
    1 cm is rare; the caller's score and overlap tests catch the rest.
    """
    idx = np.asarray(candidates, dtype=np.int64)
    if len(idx) < min_inliers:
        return []
    x, y = src[idx], tgt[idx]
    dx, dy = cdist(x, x), cdist(y, y)
    C = (np.abs(dx - dy) < tolerance) & (dy < diameter) & (dx > 0.005) & (dy > 0.005)
    alive = np.ones(len(idx), bool)
    # Consistent partners still alive, kept up to date as correspondences leave (recounting
    # the whole n x n matrix each round cost 5-20 ms a frame per model with many outliers).
    partners = C.sum(axis=1)
    found = []
    for _ in range(max_instances * 3):
        deg = np.where(alive, partners, 0)
        seed = int(np.argmax(deg))
        if deg[seed] < min_inliers - 1:
            break
        group = np.flatnonzero(C[seed] & alive)
        group = np.append(group, seed)
        sub = C[np.ix_(group, group)] | np.eye(len(group), dtype=bool)
        while len(group) >= min_inliers and not sub.all():
            worst = int(np.argmin(sub.sum(axis=1)))
            group = np.delete(group, worst)
            sub = np.delete(np.delete(sub, worst, axis=0), worst, axis=1)
        if len(group) < min_inliers:
            alive[seed] = False
            partners -= C[:, seed]
            continue
        T = rigid_fit(x[group], y[group])
        for _ in range(3):
            inl = alive & (np.linalg.norm(apply_transform(T, x) - y, axis=1) < inlier_thresh)
            if inl.sum() < 3:
                break
            T = rigid_fit(x[inl], y[inl])
        inl = alive & (np.linalg.norm(apply_transform(T, x) - y, axis=1) < inlier_thresh)
        if inl.sum() >= min_inliers:
            found.append(T)
            alive &= ~inl
            partners -= C[:, np.flatnonzero(inl)].sum(axis=1)
            if len(found) >= max_instances:
                break
        else:
            alive[seed] = False
            partners -= C[:, seed]
    return found


def assign_nearest(src, tgt, transforms, thresh) -> tuple[np.ndarray, np.ndarray]:
    """Each correspondence to the transform with the smallest residual, -1 if that is above
    thresh. Returns (labels (N,), residual to the assigned transform (N,))."""
    if not transforms:
        return np.full(len(src), -1, np.int64), np.full(len(src), np.inf)
    res = residuals(src, tgt, np.asarray(transforms, dtype=np.float64))
    best = res.argmin(axis=1)
    r = res[np.arange(len(src)), best]
    return np.where(r < thresh, best, -1).astype(np.int64), r


def box_overlaps(model: ObjectModel, transforms, grid: np.ndarray) -> np.ndarray:
    """(M, M): entry [a, b] is the share of instance b's box volume (``grid``: points inside
    the model's box, model frame) that lies inside instance a's box: near 0 for touching or
    stacked instances, large for two fits to one physical object."""
    T = np.ascontiguousarray(np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4))
    m = len(T)
    if m == 0 or len(grid) == 0:
        return np.zeros((m, m))
    centre = np.asarray(getattr(model, "box_centre", np.zeros(3)), dtype=np.float64)
    return _box_shares(np.ascontiguousarray(grid, np.float64), T, centre,
                       np.asarray(model.extent, dtype=np.float64) / 2.0)


@numba.njit(cache=True, nogil=True)
def _box_shares(grid, T, centre, half):
    # b's grid in a's model frame (R_a^T R_b, R_a^T (t_b - t_a)), pair by pair, compiled: the
    # selection and the acceptance passes call this 50-60 times a bracket frame on one core,
    # where the relative poses as numpy products had cost more than the shares.
    # A pair whose boxes lie apart (most: instances side by side) shares nothing, told from
    # the centres: b's grid lies within ``reach`` of its box centre, a's box within |half| of
    # its own; R_rel's stretch (1 for a rotation, bounded from its deviation from one) counted.
    m = T.shape[0]
    out = np.zeros((m, m))
    reach = 0.0
    for p in range(grid.shape[0]):
        d0, d1, d2 = grid[p, 0] - centre[0], grid[p, 1] - centre[1], grid[p, 2] - centre[2]
        reach = max(reach, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    half_norm = np.sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2])
    R = np.empty((3, 3))
    t = np.empty(3)
    for a in range(m):
        for b in range(m):
            e0, e1, e2 = T[b, 0, 3] - T[a, 0, 3], T[b, 1, 3] - T[a, 1, 3], T[b, 2, 3] - T[a, 2, 3]
            for i in range(3):
                for j in range(3):
                    R[i, j] = T[a, 0, i] * T[b, 0, j] + T[a, 1, i] * T[b, 1, j] + T[a, 2, i] * T[b, 2, j]
                t[i] = T[a, 0, i] * e0 + T[a, 1, i] * e1 + T[a, 2, i] * e2
            off = 0.0
            for i in range(3):
                for j in range(3):
                    g = R[0, i] * R[0, j] + R[1, i] * R[1, j] + R[2, i] * R[2, j] - (1.0 if i == j else 0.0)
                    off = max(off, abs(g))
            c0 = centre[0] * R[0, 0] + centre[1] * R[0, 1] + centre[2] * R[0, 2] + t[0] - centre[0]
            c1 = centre[0] * R[1, 0] + centre[1] * R[1, 1] + centre[2] * R[1, 2] + t[1] - centre[1]
            c2 = centre[0] * R[2, 0] + centre[1] * R[2, 1] + centre[2] * R[2, 2] + t[2] - centre[2]
            if np.sqrt(c0 * c0 + c1 * c1 + c2 * c2) > np.sqrt(1.0 + 3.0 * off) * reach + half_norm + 1e-9:
                continue
            count = 0
            for p in range(grid.shape[0]):
                x, y, z = grid[p, 0], grid[p, 1], grid[p, 2]
                count += ((abs(x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0] - centre[0]) <= half[0])
                          & (abs(x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1] - centre[1]) <= half[1])
                          & (abs(x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2] - centre[2]) <= half[2]))
            out[a, b] = count / grid.shape[0]
    return out


def box_grid(extent, steps: int = 5, fill: float = 0.8) -> np.ndarray:
    """(steps^3, 3) points evenly filling the central ``fill`` of the model's box."""
    axes = [np.linspace(-fill * e / 2.0, fill * e / 2.0, steps) for e in np.asarray(extent, dtype=np.float64)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


__all__ = ["FrontEndConfig", "PipelineConfig", "Instance", "FrameResult", "SceneKeypoints", "InstanceRegistration",
           "check_frame", "recover_small_instances", "assign_nearest", "box_overlaps", "box_grid", "STAGES"]
