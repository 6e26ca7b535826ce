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
from ..search_clock import search_time
from ..transforms import apply_transform, refine_transform, rigid_fit
from ..frontends.sift.features import SiftSettings, extract_sift_in_region
from .lifting import backproject, lookup_depth, off_planes, support_planes, undistort_pixels
from ..frontends.sift.matching import DescriptorMatcher, prepare_descriptors
from ..models.model import ObjectModel
from ..frontends.sift.guided import GuidedMatcher, guide_instances
from ..frontends.shape.frontend import FrameView, ShapeFrontEnd, resolve_correspondences
from .verify import free_space_share, surface_samples, texture_agreement
from .workspace import Workspace, WorkspaceConfig
from ..threads import limit_blas_threads, run_beside, submit_each

STAGES = ("sift", "matching", "lifting", "ecc", "refinement", "total")
# The share of frontend.shape_deadline_ms the shape path's refinement may take; the joint
# choice has the rest (past the whole, it chooses on the scores it has: bracket seed 5 lost
# neighbours whose outlines a chosen instance explains, not scored again).
REFINE_SHARE = 0.8


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
    # Correspondences from shape (frontends/shape/frontend.py; models built from a mesh).
    correspondences: str = param("auto", "where correspondences come from: sift (texture), shape (depth: point-pair votes, see shape_features), both (each through its own ECC; the SIFT instances, plus shape instances where no SIFT instance is), or auto (what the model has: shape data and keypoints -> both, shape data only -> shape, else sift)", choices=("auto", "sift", "shape", "both"))
    shape_min_variation: float = param(0.02, "shape: match only points whose surface variation (smallest / summed PCA eigenvalue over the descriptor radius) is at least this; flat faces (~0) give only outliers", 0.0, 0.34)
    shape_neighbours: int = param(3, "shape: each scene point is matched to this many nearest model descriptors (one-to-many)", 1, 20)
    shape_max_points: int = param(30000, "shape: at most this many voxel-downsampled search-region points per frame (a random subset beyond, which thins the cloud and weakens the descriptors)", 100, 1000000)
    shape_icp_iterations: int = param(15, "shape: point-to-plane ICP rounds per instance", 0, 100)
    shape_icp_association: str = param("nearest", "shape: how ICP pairs model and scene points: nearest (the nearest point of the frame's downsampled cloud within 2 voxels, then 1.5) or projective (the depth pixel each model point projects to, within the same distance shrinking to half: the tracker's ICP, tracking/icp.py, no search)", choices=("nearest", "projective"))
    shape_depth_tolerance: float = param(0.008, "metres: a model sample agrees with the depth image when within this (or 0.8 voxel, or 3 sigma of the depth noise at its distance, shape_depth_noise, whichever is largest)", 0.001, 0.2)
    shape_min_support: float = param(0.75, "shape: an instance needs at least this share of its judged model samples (facing the camera, on valid depth, not behind an instance chosen before it nor an occluder, but no fewer than 60 % of those and the ones behind an occluder; those behind the surface the pose agrees with, running on, count half) to agree with the depth: within the depth tolerance and, where the depth gives a normal, with the normal within 45 deg (frontends/shape/explain.py)", 0.0, 1.0)
    shape_min_evidence: float = param(0.8, "shape: an instance needs support - 2 x free - 2 x outline at least this (shares of its judged samples; free: samples in space the camera saw through; outline: share of a band just outside its drawn outline where its nearest face continues in the depth, a piece of a larger surface, unless a seam in colour or a chosen instance's pixels break it). The instances are chosen best gain first (evidence x samples no chosen one explains); each choice claims its pixels and its neighbours are judged again", 0.0, 1.0)
    shape_features: str = param("ppf", "shape: ppf (point pairs voted per connected segment of the depth off large planes; Drost et al. 2010) or fpfh (FPFH on the search region, one-to-many)", choices=("ppf", "fpfh"))
    shape_ppf_bucket: int = param(50, "shape ppf: at most this many model pairs per quantised feature (a random subset; a box has thousands of coplanar pairs per distance)", 10, 100000)
    shape_ref_step: int = param(5, "shape ppf: every this-many-th point of a segment is a reference point that votes", 1, 100)
    shape_max_partners: int = param(60, "shape ppf: each reference point is paired with at most this many points of its segment within the object's diameter (evenly spread)", 5, 100000)
    shape_pose_clusters: int = param(30, "shape ppf: besides ECC's transforms, check this many pose hypotheses clustered straight from the reference points' votes (Drost et al.; 24 deg, a tenth of the object's diagonal), twice this many for a non-convex model; 0 = ECC's only", 0, 1000)
    shape_segment_clusters: int = param(6, "shape ppf, non-convex models only: besides the frame's best shape_pose_clusters, each connected segment's best this-many clusters of its own references' poses are checked too (those not among the frame's): an instance in a small segment, or whose votes are mostly blurred or turned over, ranks low over the frame yet high in its segment; and what segmentation split off an instance gives its best two: each pair of segments that together fit within the object's diameter voted as one (a part in front hides the corner that joins it to the rest), each segment within it voted with every point around it (a part touching another object joins that object's segment); 0 = neither", 0, 100)
    shape_support_area: float = param(3.0, "shape ppf: a connected piece of a dominant plane is a support surface (floor, pallet, table) and removed when its area exceeds this many times the object's largest box side; a large piece stays when it stands above a larger removed plane at the height of an object's face (flush tops of objects side by side)", 1.0, 1000.0)
    shape_deadline_ms: float = param(180.0, "shape: the search's budget, milliseconds from when the pose hypotheses are taken up (after the frame's points, votes and ECC): no further hypothesis is refined once it is spent, and the joint choice then uses the scores it has instead of scoring neighbours again. The hypotheses are refined best first (ECC's clusters by size, then the vote clusters by their votes), so a cluttered frame returns the instances verified by then instead of taking seconds. The process's CPU time, not the clock's: the same instances at any load of the host. FrameResult.deadline_cut (mireg offline: metrics.json deadline_cut_frames) says when it did; 0 = no deadline", 0.0, 100000.0)
    shape_max_noise_share: float = param(0.125, "shape: look for the object only where the depth check's tolerance there, 3 sigma of the depth noise (shape_depth_noise, measured or given), is at most this share of its diameter (its box diagonal): z <= sqrt(this x diameter / (3 k)). Beyond, any surface of the object's size agrees with it: IC-BIN frames (a room 2-3 m behind a bin of cups) gave 46-60 poses a frame on clutter at 2.0-3.1 m, support 0.8-1.0 at tolerances of 30-56 mm against a cup's 45 mm radius. 0.125 with the D4xx noise (k 0.002): cup (17 cm diagonal) 1.9 m, grey cylinder 1.65 m, bracket 1.8 m, carton 2.85 m. A model placed by its faces' outlines (shape_faces: a box) is looked for out to where the tolerance is half its thinnest extent, the least step at its faces' edges, if that is farther (the carton: 3.5 m); 0 = no limit", 0.0, 1.0)
    shape_depth_noise: float = param(0.0, "shape: depth noise sigma per squared metre of distance (stereo: sigma_z = this x z^2; D4xx about 0.002, other cameras and surfaces up to 0.005): the depth check's tolerance, the outline's \"same surface\", the support planes' band (plane_thresh + 3 sigma_z) and shape_max_noise_share's cut take it; 0 = measured on each frame (plane fits of 7 x 7 pixel patches, rgbd/depth_noise.py), never below 0.002: those fits see only the pixel-to-pixel part of the noise (real IC-BIN frames measure 0.0010-0.0014, yet the checks tuned there need 0.002)", 0.0, 0.1)
    both_min_shown_keypoints: int = param(10, "both: a shape instance whose pose shows at least this many of the model's SIFT keypoints (facing the camera, not hidden) is a textured view, and kept only with both_min_agreeing matches; fewer: plain faces, kept on the depth evidence alone", 0, 100000)
    both_min_agreeing: int = param(3, "both: SIFT matches that must agree with a shape instance showing textured faces", 0, 100000)
    shape_plane_thresh: float = param(0.004, "shape ppf: metres: a point is on a support plane within this + 3 sigma_z of it (the SIFT path's plane_thresh, 1 cm, would take the top of a 12 mm plate lying on the table for the table); a point in that band is still off the plane where the band points of the 5 x 5 sampled pixels about it lie on average more than this + 3 sigma of such means off it (sigma measured on the plane): a tray's or a channel's thin floor is not the table", 0.0, 0.1)
    shape_min_segment: int = param(15, "shape ppf: segments with fewer voxel points are ignored", 3, 100000)
    shape_faces: bool = param(True, "shape ppf, convex models with a face that has a long axis (a box; not a cylinder): the segments' flat patches whose outline (second moments) is that of a model face (a carton's top seen whole) give pose hypotheses, and a hypothesis near such a patch is moved onto it before ICP (a face seen alone holds ICP in its plane nowhere, and its point pairs differ only in their distance; frontends/shape/faces.py)", None, None)
    shape_gravity_tolerance_deg: float = param(20.0, "shape ppf, when the frame comes with the direction of gravity (the camera's accelerometer, or TF): the support \"below\" the objects (the outline leaves out what lies no higher than an object's lowest point) is the largest removed plane whose normal is within this of up, not a larger wall; none within it: the largest, as without gravity. A hand-held camera's accelerometer averaged over 0.1 s is a few degrees off, more on a sharp turn; level supports lie within a degree or two, walls 70-90 deg off. With or without gravity, the removed planes parallel to that support within 5 deg are supports an instance may not sink into; the others are walls (a bin's sides), which hide what lies behind them", 1.0, 60.0)


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
                       gravity: np.ndarray | None = None, keypoints=None) -> FrameResult:
        """rgb (H, W, 3) uint8, depth_m (H, W) float metres (0 = invalid), aligned to colour.
        ``gravity``: "up" in the colour optical frame (any length; the accelerometer's mean
        reading at rest), or None when not known; the shape path takes the support below the
        objects along it (``shape_gravity_tolerance_deg``). ``keypoints``: the frame's SIFT
        keypoints when several models share one detection (``detect``'s, or a future-like
        object of them); None: detected here."""
        check_frame(rgb, depth_m, intrinsics)
        gravity = unit_up(gravity)
        if self.correspondences == "shape":
            return self._register_frame_shape(depth_m, intrinsics, gravity=gravity, rgb=rgb)
        if self.correspondences == "both":
            return self._register_frame_both(rgb, depth_m, intrinsics, gravity, keypoints)
        return self._register_frame_sift(rgb, depth_m, intrinsics, keypoints)

    def _register_frame_sift(self, rgb, depth_m, intrinsics, keypoints=None) -> FrameResult:
        """SIFT matches -> ECC -> refinement and checks on the matches."""
        t = {s: 0.0 for s in STAGES}
        t0 = time.perf_counter()
        if keypoints is None:
            keypoints = self.detect(rgb, depth_m, intrinsics, t)
        elif hasattr(keypoints, "result"):
            keypoints = keypoints.result()
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

    def _register_frame_shape(self, depth_m, intrinsics, search=None, gravity=None, rgb=None,
                              beside=None) -> FrameResult:
        """Shape correspondences -> ECC (and the vote clusters' poses) -> each hypothesis
        refined by ICP and explained against the frame -> the instances chosen jointly
        (``frontends/shape/explain.py``: hypotheses on the same pixels compete; two whose
        boxes overlap cannot both be, which also reports a symmetric object once). ``rgb``:
        its edges mark outlines the depth does not show (flush-packed cartons). ``beside``:
        work started beside this path (``run_beside``), waited for before the search, whose
        deadline is the process's CPU time."""
        fe = self.config.frontend
        t = {s: 0.0 for s in STAGES}
        t0 = time.perf_counter()
        within = None
        if fe.shape_features == "ppf":
            within = self.workspace_pixels(depth_m, intrinsics)     # ppf removes its own planes first
        elif search is None:
            search = self._search_mask(depth_m, intrinsics)
        view = FrameView.of(depth_m, intrinsics, rgb)
        t3 = time.perf_counter()
        t["lifting"] = (t3 - t0) * 1e3
        cloud = self._shape.frame_cloud(depth_m, intrinsics, None if search is None else search > 0, gravity, within)
        t4 = time.perf_counter()
        # ECC does not need the vote clusters' poses (ppf): it runs in the shared pool as
        # soon as the correspondences are made, while those poses are made; they do not
        # depend on ECC either: they are refined on the other core until ECC is done.
        # "matching" then holds the pose clusters too, and "ecc" the wait for ECC after them.
        started, solving = [], []

        def start_ecc(s, g):
            if len(s) >= 3:
                solving.extend(submit_each(lambda pair: self._shape_ecc.register(*pair), [(s, g)]))

        src, tgt = self._shape.correspondences(cloud, on_poses=lambda: started.append(
            self._shape.start_refining(list(cloud.poses), cloud, view)), on_matches=start_ecc, view=view)
        started = started[0] if started else None
        t5 = time.perf_counter()
        t["shape"] = (t4 - t3) * 1e3
        t["matching"] = (t5 - t4) * 1e3
        hypotheses = [] if cloud.poses is None else list(cloud.poses)
        if len(src) >= 3:
            reg = solving[0].result() if solving else self._shape_ecc.register(src, tgt)
            hypotheses = [np.asarray(T, np.float64) for T in reg.transforms] + hypotheses
        offset = len(hypotheses) - (0 if cloud.poses is None else len(cloud.poses))
        if beside is not None:
            beside.result()
        t6 = time.perf_counter()
        t["ecc"] = (t6 - t5) * 1e3
        # The search's budget: from here, where the hypotheses are taken up best first; the
        # refinement stops at REFINE_SHARE of it, the joint choice (scoring the neighbours of
        # each instance chosen again) has the rest.
        budget = fe.shape_deadline_ms / 1e3 if fe.shape_deadline_ms > 0 else None
        start = search_time()
        self._shape.set_deadline(start + REFINE_SHARE * budget if budget else None)
        candidates = self._shape.refine_all(hypotheses, cloud, view, started, offset)
        cut = self._shape.deadline_cut
        self._shape.set_deadline(start + budget if budget else None)
        chosen = self._shape.choose(candidates, cloud, view,
                                    lambda e, c: bool(self._overlapping([e.T], [c.T])[0, 0]))
        cut = cut or self._shape.deadline_cut
        self._shape.set_deadline(None)
        instances = [Instance(i, e.pose, int(round(e.agree)), e.support, self.model.name) for i, e in enumerate(chosen)]
        labels, _ = assign_nearest(src, tgt, [e.pose for e in chosen], self._shape_ecc.config.inlier_thresh)
        t["refinement"] = (time.perf_counter() - t6) * 1e3
        t["total"] = (time.perf_counter() - t0) * 1e3
        uv = project_points(tgt, intrinsics)
        return FrameResult(instances, t, uv, src.astype(np.float32), tgt.astype(np.float32), labels, 0,
                           deadline_cut=cut)

    def _overlapping(self, transforms, poses) -> np.ndarray:
        """(len(transforms), len(poses)) bool: whether each transform's box and each pose's
        overlap beyond ``max_overlap`` (either way)."""
        limit = self.config.frontend.max_overlap
        n = len(poses)
        if n == 0 or len(transforms) == 0:
            return np.zeros((len(transforms), n), bool)
        overlap = box_overlaps(self.model, list(poses) + list(transforms), self._box_grid)
        return (overlap[n:, :n] > limit) | (overlap[:n, n:].T > limit)

    def _register_frame_both(self, rgb, depth_m, intrinsics, gravity=None, keypoints=None) -> FrameResult:
        """Texture and shape, each through its own ECC; every SIFT instance is kept as the
        SIFT path finds it, and a shape instance is added where no SIFT instance is. (Joining
        the two correspondence sets before one ECC and judging every instance by the depth
        checks lost textured instances that lean on or hide behind others: seed 0 MHF1 0.88
        against 0.98 for SIFT alone.)"""
        fe = self.config.frontend
        # The two paths share nothing until here: SIFT runs beside the shape path's cloud and
        # votes (IC-BIN frames, paired runs: p50 248-262 -> 239-254 ms, the same poses).
        sift = run_beside(self._register_frame_sift, rgb, depth_m, intrinsics, keypoints)
        shaped = self._register_frame_shape(depth_m, intrinsics, gravity=gravity, rgb=rgb, beside=sift)
        textured = sift.result()
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
                # also pick which of its symmetric poses it is). Once: where the mesh has
                # colour, the verification judged the pose's appearance already, densely
                # (IC-BIN: the cups' shape poses met 0-6 of the frame's 40-70 matches).
                T, agree, shown = texture_agreement(inst.T, self._keypoints_xyz, self._keypoint_normals,
                                                    self.model.symmetries, match_model, match_scene, depth_m,
                                                    intrinsics, self.config.ecc.inlier_thresh,
                                                    self._shape.depth_tolerance)
                if not self._shape.judges_appearance and shown >= fe.both_min_shown_keypoints \
                        and agree < fe.both_min_agreeing:
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
