"""Instances that keep their identity over frames. No ROS.

    tracker = InstanceTracker(model, TrackerConfig())
    for frame in frames:                                       # in order, every frame
        out = tracker.step(stamp_ns, depth_m, intrinsics, detections, camera_motion)
        for inst in out:                                       # by track_id
            inst.track_id, inst.state, inst.source, inst.T

Objects rest and the camera moves. Each frame every track is first moved by the camera's
motion, measured where it can be (``camera_motion`` from ``odometry.py``: the static scene's
features; else the tracks' shared velocity), corrected by one ICP of all tracks together
against the depth; then the frame's detections are assigned to the tracks (one to one within
``gate_distance``, after moving the tracks by the camera motion the detections themselves
show where nothing else measured it; a detection left over within a track's volume corrects
that track); then each track is aligned to the depth by projective ICP (``icp.py``). A
detection found on an older frame (the live node's detector runs behind the camera) is fused
with ``add_detections(stamp_ns, detections)`` against each track's pose on that frame.

What is published is what has evidence on the frame: a track the depth confirms (ICP
fitness), or one a detection continues that the depth does not contradict (no more than
``max_free_share`` of its visible model points standing where the camera saw through to a
surface behind them). A prediction is not evidence: a track with neither is kept, coasting,
for its object's next detection, and not published, unless the depth shows it hidden (most
of it behind a surface well in front of it, nothing seen through it) where the camera's
motion was measured: then it is published as coasting. Where the depth vouches for neither a
track's pose nor its detection's, the detection wins. Two tracks whose model volumes overlap
are one object: the one with the better evidence stays. Stamps that go back (a bag played in
a loop, a camera restarted) end every track, and the tracker says so in the log.

Life of a track: born *tentative* from a detection no track claims (published at once where
the depth confirms it); *confirmed* after ``confirm_detections`` detections, or at once when
the depth confirms the detection's pose (``confirm_fitness``); a confirmed track without
evidence on a frame is *coasting*, and ends when that lasts ``coast_s``. A tentative track
ends at its first miss. Ids count up from 0 and are never reused.

A detection whose position matches a track but whose orientation does not is the same object
seen in one of its symmetric poses (a box turned 180 deg looks the same on its plain faces):
the track keeps its orientation, unless ``flip_after`` detections in a row agree with each
other on the other one (the track itself was the wrong one).
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from ..messages import CameraIntrinsics
from ..params import param
from ..transforms import invert_transform, rotation_angle_deg
from ..frontends.shape.geometry import apply_twist as twist_step
from .icp import ProjectiveICP

_log = logging.getLogger(__name__)

TENTATIVE, CONFIRMED, COASTING = "tentative", "confirmed", "coasting"
DETECTION, TRACKING = "detection", "tracking"
RECENT = 0.25                    # weight of the latest residual in the output filter's running mean (about 4 frames)
HISTORY = 90                     # poses kept per track, to fuse detections of older frames


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of the tracker (ROS parameters ``tracking.*``)."""
    gate_distance: float = param(0.03, "m: a detection can continue a track only if its position is within this of the track's (one-to-one assignment among those)", 0.001, 1.0)
    gate_rotation_deg: float = param(30.0, "a detection within the position gate whose orientation differs by more than this is the object in a symmetric pose: the track keeps its own orientation", 1.0, 180.0)
    flip_after: int = param(3, "detections in a row, agreeing with each other but not with their track's orientation, that turn the track to theirs", 1, 1000)
    confirm_detections: int = param(2, "detections that confirm a new (tentative) track; a tentative track ends at its first miss", 1, 100)
    confirm_fitness: float = param(0.9, "a new track is confirmed at once, on its first detection, when the ICP from that detection's pose confirms at least this share of the visible model points not hidden behind something nearer (and icp_min_fitness and icp_min_in_view hold): the depth then vouches for the detection as a second detection would; 0 = off (only detections confirm)", 0.0, 1.0)
    coast_s: float = param(1.0, "s: a confirmed track that is neither detected nor confirmed by the depth for longer than this ends; meanwhile it is kept (coasting, carried by the camera's motion) so that the object's next detection continues it, but not published: a prediction is not evidence", 0.0, 60.0)
    max_undetected_s: float = param(1.5, "s: a track kept by the depth alone, with no detection for longer than this and not found by the last two detection rounds that ran on frames it lived in, ends (0 = never): the detector's verdict, not the clock's (a detector running seconds behind on a loaded host leaves that long between its rounds)", 0.0, 3600.0)
    duplicate_distance: float = param(0.015, "m: two tracks whose positions come closer than this, or than half the object's smallest extent (their model volumes overlap), follow one object: the one with the weaker evidence on this frame ends (published before not, confirmed before tentative, then the older)", 0.0, 1.0)
    min_hidden_share: float = param(0.6, "share of a track's visible model points that must be hidden behind a surface more than icp_max_distance in front of them (an arm, an object in front) for an undetected track whose pose the camera's measured motion carried to be published as hidden (state coasting): the depth agrees with it without confirming it; 1 = never", 0.0, 1.0)
    max_free_share: float = param(0.3, "share of a track's visible model points that may stand where the camera saw through to a surface more than icp_max_distance behind them (space seen empty, which no occlusion explains): above it the depth contradicts the pose and the track has no evidence on that frame, whatever detected it", 0.0, 1.0)
    odometry: bool = param(True, "measure the camera's motion from one frame to the next by the colour image's features with depth (tracking.odometry: ORB, RANSAC; objects rest, so it moves every track) and predict the tracks by it: a shaking or jumping camera is followed exactly where a velocity would guess; where a frame has too little texture, the prediction below is used")
    camera_motion: bool = param(True, "predict every track by one motion shared by all (the camera's: objects rest and the camera moves), corrected on each frame by one ICP of all confirmed and coasting tracks together against the depth (where that is refused or no such track is in view: the median rotation, then the median translation of the steps of the tracks the depth or a detection saw), plus the track's own residual velocity; an occluded (coasting) track follows the shared motion. Off: each track's own constant velocity, an occluded one follows the nearest seen track")
    velocity_decay: float = param(0.5, "share of a track's own velocity (with camera_motion: what the shared motion does not explain) kept per frame the track is updated by the depth alone (no detection): a velocity the depth does not confirm (a box sliding along the table plane it shares with its neighbours) dies out instead of carrying the track away from a resting object; 1 = constant velocity", 0.0, 1.0)
    smoothing: float = param(0.0, "pose smoothing, 0 = off (the published pose is the measured one) to 0.95 (heavy): the published pose is a constant-velocity (alpha-beta) filter of the measured one with gain 1 - smoothing, so a resting object's pose settles and a steadily moving one does not lag (and, with a still camera, the running mean of a resting object's measured poses: rest_frames); a measurement further than icp_max_step / icp_max_step_deg from the filter restarts it", 0.0, 0.95)
    rest_frames: int = param(30, "with smoothing on, while the camera is judged still (needs camera_motion): a track whose measured pose stays near its published one is averaged over up to this many frames, so that the published pose of a resting object converges: it is the running mean of the measured poses (gain 1 / n on its n-th frame at rest, down to 1 / rest_frames), held still in the camera. A measurement rest_sigmas times further from it than usual, a run of them off to one side, or a moving camera brings back the plain filter (gain 1 - smoothing), so a moving object is followed as before. 0 or 1 = off", 0, 100000)
    rest_sigmas: float = param(3.0, "see rest_frames: how many times its usual (RMS) distance from the published pose, in rotation or position, one measurement, or the running mean of the last few, must be for the track to count as moving", 1.0, 100.0)
    detection_gain: float = param(0.3, "with smoothing on: share of an agreeing detection's correction (within icp_max_step and, in orientation, icp_max_step_deg times its spread of a confirmed track, no symmetric flip) that moves a resting track in the steady state, for a detection of detection_gain_inliers inliers (a Kalman gain: the first detections of a track are averaged, weaker ones pull less, stronger ones more); the ICP then re-fits what the depth constrains, so this filters only what it does not (a box seen from its top: its yaw and where it lies on the table), which a detection would otherwise reset with its own noise on every frame. 1 = reset; unused with smoothing 0 (the track is then the measured pose)", 0.01, 1.0)
    detection_gain_inliers: int = param(100, "inliers of the detection that detection_gain refers to; a detection's pose variance is taken as inversely proportional to its inliers", 1, 100000)
    publish_tentative: bool = param(True, "publish a new track (state tentative) on the frame where only its detection vouches for it, the depth not contradicting it (a detection is evidence: the output is then never worse than the detector's); off: only once the depth or a second detection confirms it")
    icp: bool = param(True, "bring every track up to date on every frame by projective point-to-plane ICP of the model against the depth image (off: tracks move only with detections)")
    icp_points: int = param(1000, "model points used by the ICP of one track", 20, 20000)
    icp_iterations: int = param(10, "ICP iterations per track and frame", 1, 100)
    icp_damping: float = param(0.001, "Levenberg damping of each ICP step, relative to the mean eigenvalue of its normal equations (rotation scaled by the object's radius): holds back what the depth barely constrains", 0.0, 10.0)
    icp_min_information: float = param(0.03, "an ICP step moves the pose only in the directions the depth constrains: those whose information (eigenvalue of the normal equations, rotation scaled by the object's radius) is at least this share of the best-constrained one; the others (a box seen from its top: where it lies in that plane) stay at the prediction or the detection. 0 = every direction", 0.0, 1.0)
    icp_min_in_view: float = param(0.25, "share of the model points facing the camera that must project into the image for the depth to count at all (below: a miss; an instance leaving the view is not kept, nor confirmed, by the few points on the image border)", 0.0, 1.0)
    icp_min_measured: float = param(0.5, "share of the model points the depth usually measures on a track (its running mean over the frames it was seen) that must have a depth measurement on a frame for the ICP to count (below: a miss): an arm too close for the depth camera leaves a sliver of the object, which the ICP would tilt the pose to. 0 = off", 0.0, 1.0)
    icp_max_distance: float = param(0.03, "m: depth pairs farther apart than this are ignored in the first ICP iteration (the gate shrinks to icp_inlier_distance by the last)", 0.001, 0.5)
    icp_inlier_distance: float = param(0.006, "m: a model point counts as confirmed by the depth within this distance", 0.0005, 0.1)
    icp_max_step: float = param(0.01, "m: an ICP result that moves the track's pose further than this from its prediction (or from the detection of this frame) is refused: the model slid along a plane it shares with something else", 0.0005, 1.0)
    icp_max_step_deg: float = param(5.0, "deg: the same for the rotation; with smoothing on, a detection further than this times its spread (sqrt(detection_gain_inliers / inliers), at least 1) from a confirmed track is left for the depth to decide, a nearer one is pulled by its gain", 0.1, 180.0)
    icp_min_fitness: float = param(0.35, "share of the visible model points (facing the camera, with a depth measurement) the depth must confirm for the track to count as seen on a frame (below: a miss, e.g. occluded)", 0.0, 1.0)


@dataclass
class TrackedInstance:
    """One published track on one frame."""
    track_id: int           # unique within a run, never reused
    id: int                 # rank in this frame's list by inliers (as the per-frame Instance.id)
    T: np.ndarray           # (4, 4) model frame -> camera optical frame (smoothed when smoothing > 0)
    inliers: int            # correspondences of the last detection of this track
    score: float            # score of the last detection of this track
    state: str              # tentative | confirmed | coasting
    source: str             # detection: a detection updated it since the last output; tracking: depth/prediction only
    age_s: float            # since the track was born
    fitness: float          # share of the visible model points the depth confirmed on this frame (0 without ICP)
    object: str = ""        # name of the object (set by ObjectTrackers, objects.py)


@dataclass
class Track:
    track_id: int
    T: np.ndarray                       # measured (or predicted) pose on the latest frame
    T_out: np.ndarray                   # published pose (filtered when smoothing > 0)
    born_ns: int
    stamp_ns: int                       # frame of T
    last_seen_ns: int
    last_detected_ns: int
    detections: int = 1
    inliers: int = 0
    score: float = 0.0
    fitness: float = 0.0
    measured_ref: float = 0.0           # model points the depth measured on this track, running mean over its seen frames
    state: str = TENTATIVE
    state_before: str = TENTATIVE       # at the start of the latest frame
    detected_since_output: bool = True
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(6))   # twist per second (rotvec, translation)
    out_velocity: np.ndarray = field(default_factory=lambda: np.zeros(6))  # of T_out: rotvec about its origin, translation; per second
    out_count: float = 0.0                    # measurements the published pose averages (rest_frames)
    out_spread: np.ndarray | None = None      # mean square distance (rad^2, m^2) of the measurements from the published pose
    out_mean: np.ndarray | None = None        # running mean of the measurements' residuals from the published pose (RECENT)
    T_out_before: np.ndarray | None = None    # T_out on the frame before, before this frame's prediction
    history: deque = field(default_factory=lambda: deque(maxlen=HISTORY))   # (stamp_ns, T)
    flip_votes: list = field(default_factory=list)                      # recent disagreeing orientations
    T_before_jump: np.ndarray | None = None   # the track's own pose when a detection moved it further than icp_max_step on this frame
    far_detections: int = 0                   # detections in a row that were that far from the track
    pull_variance: float = 1.0                # of the pose where the depth leaves it free, in units of a detection with detection_gain_inliers inliers
    frames_since_pull: int = 0
    pulled: float = 0.0                       # share of the way a detection moved it on this frame (0: none, or reset to it)
    evidence: bool = False                    # a detection or the depth vouched for it on its latest frame (published then)
    missed_rounds: int = 0                    # detection rounds in a row, on frames it lived in, that did not find it

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        for s, T in reversed(self.history):
            if s == stamp_ns:
                return T
            if s < stamp_ns:
                return None
        return None


def proper_pose(T) -> np.ndarray:
    """A copy of T with its rotation made exactly orthonormal (nearest rotation, by SVD):
    poses are composed frame after frame, and a slightly scaled rotation would compound."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return T


_ORIGIN = np.zeros(3)
MISSED_ROUNDS = 2                # detection rounds in a row that must miss a track before max_undetected_s ends it
MAX_CAMERA_TURN_DEG = 45.0       # a camera motion between two frames taken from the detections turns at most this


def smallest_extent(points: np.ndarray) -> float:
    """The object's thickness along its thinnest principal axis (m): two poses of one object
    whose origins are closer than half of it have overlapping volumes."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 4:
        return 0.0
    centred = pts - pts.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]
    spans = np.ptp(centred @ axes.T, axis=0)
    return float(spans.min())


def relative_twist(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(rotvec, translation) of D with T_to = D T_from."""
    D = T_to @ invert_transform(T_from)
    return np.concatenate([Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]])


def apply_twist(T: np.ndarray, twist: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """exp(scale * twist) applied on the left of T, about the camera's origin (a velocity over scale s)."""
    return twist_step(np.asarray(T, np.float64), scale * np.asarray(twist, np.float64), _ORIGIN)


def local_residual(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(rotvec, translation) taking T_from to T_to, the rotation about T_from's own origin
    (so that smoothing a rotation does not swing the position about the camera)."""
    rv = Rotation.from_matrix(T_to[:3, :3] @ T_from[:3, :3].T).as_rotvec()
    return np.concatenate([rv, T_to[:3, 3] - T_from[:3, 3]])


def local_step(T: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """T moved by a local_residual-style twist."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(twist[:3]).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + twist[3:]
    return out


def kalata_beta(alpha: float) -> float:
    """The velocity gain of an alpha-beta filter that goes with position gain alpha for a
    constant-velocity target (Kalata 1984)."""
    return 2.0 * (2.0 - alpha) - 4.0 * np.sqrt(1.0 - alpha)


def icp_for(model, config: TrackerConfig) -> ProjectiveICP | None:
    """The depth alignment the settings ask for (None with icp off)."""
    c = config
    return ProjectiveICP(model.points_xyz, c.icp_points, c.icp_iterations, c.icp_max_distance,
                         c.icp_inlier_distance, c.icp_damping, c.icp_min_information) if c.icp else None


class InstanceTracker:
    """Tracks of the instances of one object over a stream of frames (see the module doc)."""

    def __init__(self, model, config: TrackerConfig | None = None, symmetries=None):
        self.model = model
        self.tracks: list[Track] = []
        self.next_id = 0
        self.ended = 0                   # tracks ended so far
        self.stamp_ns: int | None = None # latest frame
        self.camera_velocity = np.zeros(6)   # shared motion per second (relative_twist form), camera_motion on
        self.camera_correction: np.ndarray | None = None   # this frame's correction of the predicted camera motion
        self._frame_dt = 0.0                 # s since the frame before
        self._camera_step = self._camera_square = self._camera_change = None   # _camera_moves: the last shared step, recent mean squares of the steps and of their changes
        self._camera_moving = True
        self._camera_still = 0                # frames the camera has been judged still in a row
        self.resets = 0                       # times the stamps went back and every track was ended
        self._detections_win = False          # this frame's detections reset their tracks (see _fuse)
        self._predicted_motion = np.eye(4)    # the camera motion the tracks were predicted by on this frame
        self._motion_measured = False         # ... measured (odometry), not extrapolated
        self._merge_distance = 0.5 * smallest_extent(model.points_xyz)
        # Rotations (model frame) under which the object looks the same; identity first.
        self.symmetries = [np.eye(3)] + [np.asarray(S, dtype=np.float64)[:3, :3] for S in (symmetries or [])]
        self.set_config(config or TrackerConfig())

    def set_config(self, config: TrackerConfig) -> None:
        """Settings from the next frame on (the live node's parameter changes); tracks and ids stay."""
        self.config = config
        self._icp = icp_for(self.model, config)

    # ---- per frame -------------------------------------------------------------------
    def step(self, stamp_ns: int, depth_m: np.ndarray | None, intrinsics: CameraIntrinsics | None,
             detections=None, camera_motion: np.ndarray | None = None) -> list[TrackedInstance]:
        """Advance every track to this frame; ``detections`` (Instances found on this very
        frame, or None when the detector did not run on it) correct them before the depth
        alignment; ``camera_motion``: the camera's motion D since the frame stepped before
        (X_now = D X_before; ``odometry.CameraOdometry``), None where it is not known.
        Returns what to publish for this frame."""
        if self.stamp_ns is not None and int(stamp_ns) < self.stamp_ns:
            self.reset(f"the stamps went back by {(self.stamp_ns - int(stamp_ns)) * 1e-9:.3f} s "
                       "(a bag played in a loop, a camera restarted)")
            camera_motion = None
        self._predict(stamp_ns, camera_motion)
        self._align_camera(depth_m, intrinsics)
        if detections is not None:
            self._fuse(stamp_ns, detections)
        self._align(stamp_ns, depth_m, intrinsics)
        return self.output()

    def add_detections(self, stamp_ns: int, detections) -> None:
        """Detections found on an earlier frame (at most HISTORY frames back)."""
        self._fuse(int(stamp_ns), detections)

    def reset(self, why: str) -> None:
        """End every track (ids go on counting): the stream's past is not this frame's."""
        _log.warning("tracking reset, %d track(s) ended: %s", len(self.tracks), why)
        self.ended += len(self.tracks)
        self.tracks = []
        self.resets += 1
        self.stamp_ns = None
        self.camera_velocity = np.zeros(6)
        self._camera_step = self._camera_square = self._camera_change = None
        self._camera_moving, self._camera_still = True, 0

    # ---- stages ----------------------------------------------------------------------
    def _predict(self, stamp_ns: int, camera_motion: np.ndarray | None = None) -> None:
        """Every track moved to this frame: by the camera's measured motion where it is known
        (objects rest), else by the shared velocity; then by its own residual velocity."""
        stamp_ns = int(stamp_ns)
        shared = self.camera_velocity if self.config.camera_motion else np.zeros(6)
        dt_frame = (stamp_ns - self.stamp_ns) * 1e-9 if self.stamp_ns is not None else 0.0
        self._predicted_motion = (proper_pose(camera_motion) if camera_motion is not None
                                  else apply_twist(np.eye(4), shared, max(dt_frame, 0.0)))
        self._motion_measured = camera_motion is not None
        for tr in self.tracks:
            dt = (stamp_ns - tr.stamp_ns) * 1e-9
            if camera_motion is not None:
                tr.T = apply_twist(self._predicted_motion @ tr.T, tr.velocity, max(dt, 0.0))
                tr.T_out_before = tr.T_out
                if self._camera_moving:
                    # (A still camera's measured motion is noise: the published pose of a
                    # resting object is held, as rest_frames averages it.)
                    tr.T_out = proper_pose(self._predicted_motion @ tr.T_out)
                tr.stamp_ns = stamp_ns
            elif dt > 0:
                tr.T = apply_twist(apply_twist(tr.T, shared, dt), tr.velocity, dt)
                tr.T_out_before = tr.T_out
                tr.T_out = local_step(tr.T_out, tr.out_velocity * dt)   # the filter's own velocity
                tr.stamp_ns = stamp_ns
            tr.history.append((stamp_ns, tr.T.copy()))
            tr.state_before = tr.state
            tr.frames_since_pull += 1
        self._frame_dt = (stamp_ns - self.stamp_ns) * 1e-9 if self.stamp_ns is not None else 0.0
        self.stamp_ns = stamp_ns

    def _align_camera(self, depth_m, intrinsics) -> None:
        """With camera_motion: correct the prediction by the one motion that aligns all
        confirmed and coasting tracks to the depth together (the camera's, as the objects
        rest), before the detections and each track's own ICP. Sets camera_correction (None:
        not measured; the median of the tracks' own steps is used then)."""
        c = self.config
        self.camera_correction = None
        anchors = [tr for tr in self.tracks if tr.state != TENTATIVE]
        if not (c.camera_motion and anchors and self._icp is not None and depth_m is not None
                and intrinsics is not None):
            return
        res = self._icp.align_all([tr.T for tr in anchors], depth_m, intrinsics)
        step_m = float(np.linalg.norm(res.T[:3, 3]))
        step_deg = rotation_angle_deg(res.T[:3, :3])
        if res.fitness < c.icp_min_fitness or step_m > c.icp_max_step or step_deg > c.icp_max_step_deg:
            return
        D = proper_pose(res.T)
        self.camera_correction = D
        for tr in self.tracks:
            tr.T = proper_pose(D @ tr.T)
            tr.history[-1] = (tr.history[-1][0], tr.T.copy())

    def _closest_symmetric(self, T_det: np.ndarray, T_ref: np.ndarray) -> tuple[np.ndarray, float]:
        """The detection turned by the model symmetry that brings it closest to T_ref, and
        the remaining rotation angle (deg)."""
        best, best_angle = T_det, np.inf
        for S in self.symmetries:
            T = T_det.copy()
            T[:3, :3] = T_det[:3, :3] @ S
            angle = rotation_angle_deg(T[:3, :3].T @ T_ref[:3, :3])
            if angle < best_angle:
                best, best_angle = T, angle
        return best, best_angle

    def _fuse(self, stamp_ns: int, detections) -> None:
        """Each detection continues the track of its object or starts one. The tracks are first
        moved by the camera's motion that the detections show (``_camera_from_detections``:
        a shaking or jumping camera moves every resting object alike), then assigned one to
        one within ``gate_distance``; a detection left over that lies within a left-over
        track's volume corrects that track (it drifted) rather than starting a second one."""
        c = self.config
        dets = list(detections)
        candidates = [(tr, tr.pose_at(stamp_ns)) for tr in self.tracks]
        candidates = [(tr, T) for tr, T in candidates if T is not None]
        matched_dets: set[int] = set()
        matched_rows: set[int] = set()  # of candidates
        # On this very frame, where neither the colour (odometry) nor the depth measured the
        # camera's motion (a jump beyond the ICP's reach, a gap), the tracks' poses are stale:
        # the detections win.
        self._detections_win = (stamp_ns == self.stamp_ns and self.camera_correction is None
                                and not self._motion_measured)
        if dets and candidates:
            D = self._camera_from_detections([T for _, T in candidates], dets)
            if D is not None and (self._detections_win or stamp_ns != self.stamp_ns):
                if stamp_ns == self.stamp_ns:
                    for tr in self.tracks:       # this very frame: every track moves with the camera
                        tr.T = proper_pose(D @ tr.T)
                        tr.history[-1] = (stamp_ns, tr.T.copy())
                    candidates = [(tr, tr.T.copy()) for tr, _ in candidates]
                else:
                    candidates = [(tr, proper_pose(D @ T)) for tr, T in candidates]
            pos_d = np.array([np.asarray(d.T)[:3, 3] for d in dets])
            pos_t = np.array([T[:3, 3] for _, T in candidates])
            dist = np.linalg.norm(pos_t[:, None] - pos_d[None], axis=2)
            for gate in (c.gate_distance, max(c.gate_distance, self._merge_distance)):
                cost = np.where(dist <= gate, dist, 1e6)
                cost[list(matched_rows), :] = 1e6
                cost[:, list(matched_dets)] = 1e6
                rows, cols = linear_sum_assignment(cost)
                for r, k in zip(rows, cols):
                    if cost[r, k] >= 1e6:
                        continue
                    tr, T_then = candidates[r]
                    self._correct(tr, T_then, dets[k], stamp_ns)
                    matched_dets.add(k)
                    matched_rows.add(r)
        matched_tracks = {candidates[r][0].track_id for r in matched_rows}
        for tr, _ in candidates:
            tr.missed_rounds = 0 if tr.track_id in matched_tracks else tr.missed_rounds + 1
        # A tentative track that a detection round (on a frame it lived in) did not find ends.
        missed = {tr.track_id for tr, _ in candidates if tr.state == TENTATIVE and tr.track_id not in matched_tracks}
        self.ended += len(missed)
        self.tracks = [tr for tr in self.tracks if tr.track_id not in missed]
        for k, det in enumerate(dets):
            if k not in matched_dets:
                self._birth(det, stamp_ns, candidates)

    def _camera_from_detections(self, poses: list[np.ndarray], dets) -> np.ndarray | None:
        """The camera's motion since the tracks' poses ``poses`` (on the detections' frame) as
        the detections show it, or None where they show none. Objects rest, so one rigid
        motion D takes every track onto its object's detection: no motion and each (track,
        detection) pair propose one (the detection turned by the symmetry nearest the track);
        the one that brings most tracks within gate_distance of a detection wins (then the
        nearer), refitted to all it pairs. It must pair at least two tracks (no camera motion
        is made of one pair), and more than the tracks as they are: where those pair, the
        detections correct them one by one."""
        c = self.config
        if len(poses) < 2 or len(dets) < 2:
            return None
        pos_t = np.array([T[:3, 3] for T in poses])
        pos_d = np.array([np.asarray(d.T)[:3, 3] for d in dets])

        def paired(D):
            moved = pos_t @ D[:3, :3].T + D[:3, 3]
            near = np.linalg.norm(moved[:, None] - pos_d[None], axis=2)
            j = near.argmin(axis=1)
            d = near[np.arange(len(poses)), j]
            ok = d <= c.gate_distance
            return (int(ok.sum()), -float(d[ok].sum())), np.flatnonzero(ok), j[ok]

        identity = np.eye(4)
        best = (identity,) + paired(identity)
        identity_n = best[1][0]
        turns = {}                      # (track, detection) -> the turn that pair proposes
        for r, T in enumerate(poses):
            for k, det in enumerate(dets):
                D = self._closest_symmetric(proper_pose(det.T), T)[0] @ invert_transform(T)
                turns[r, k] = D[:3, :3]
                if rotation_angle_deg(D[:3, :3]) > MAX_CAMERA_TURN_DEG:
                    continue
                score, rows, cols = paired(D)
                if score > best[1]:
                    best = (D, score, rows, cols)
        D, (n, _), rows, cols = best
        if n < 2 or n == identity_n:
            return None
        # Refitted to every pair it makes: the mean of the turns the pairs' orientations give
        # (their positions alone would leave the turn about a row of objects free), then the
        # mean of the shifts that turn leaves.
        R = Rotation.from_matrix(np.array([turns[r, k] for r, k in zip(rows, cols)])).mean().as_matrix()
        D = np.eye(4)
        D[:3, :3], D[:3, 3] = R, np.mean(pos_d[cols] - pos_t[rows] @ R.T, axis=0)
        return D

    def _correct(self, tr: Track, T_then: np.ndarray, det, stamp_ns: int) -> None:
        """Fuse one detection (found on frame stamp_ns, where the track was at T_then)."""
        c = self.config
        T_det, angle = self._closest_symmetric(proper_pose(det.T), T_then)
        if angle > c.gate_rotation_deg:
            # The object as seen in another symmetric pose, or the track's own orientation
            # was wrong: keep ours unless the detections keep agreeing on theirs.
            votes = [R for R in tr.flip_votes if rotation_angle_deg(R.T @ T_det[:3, :3]) <= c.gate_rotation_deg]
            tr.flip_votes = votes + [T_det[:3, :3]]
            flipped = len(tr.flip_votes) >= c.flip_after
            if not flipped:
                T_det = T_det.copy()
                T_det[:3, :3] = T_then[:3, :3]
            else:
                tr.flip_votes = []
        else:
            tr.flip_votes = []
            flipped = False
        # Carry the correction forward by the motion the track made since that frame.
        # (proper_pose: invert_transform assumes an orthonormal rotation, and the error of one
        # that is not doubles on every frame the depth does not re-fit.)
        motion = tr.T @ invert_transform(T_then)
        T_new = proper_pose(motion @ T_det)
        step = local_residual(tr.T, T_new)
        # With smoothing, "far" in orientation is in units of the detection's own spread (the
        # standard deviation of the pull's variance model, inliers^-1/2), as a Kalman filter
        # gates its innovations: a weak detection a few degrees off is its noise, pulled by its
        # small gain, not a jump for the depth to decide. (Static + arm sequences: one
        # 5-9-inlier detection 6-7 deg off had turned a settled track for 1-15 frames.)
        spread = np.sqrt(max(1.0, self._detection_variance(det.inliers))) if c.smoothing > 0 else 1.0
        far = (np.linalg.norm(step[3:]) > c.icp_max_step
               or (not flipped and np.degrees(np.linalg.norm(step[:3])) > c.icp_max_step_deg * spread))
        if tr.state != TENTATIVE and far and not self._detections_win:
            # A detection far from a confirmed track, in position or orientation, may be a bad
            # one (few inliers on an object half hidden by an arm): the depth decides between
            # the two (_align).
            tr.T_before_jump = tr.T.copy()
            tr.far_detections += 1
        elif tr.state != TENTATIVE and c.smoothing > 0 and not flipped and not far:
            # An agreeing detection: pull part of the way. The ICP (_align) re-fits what the
            # depth constrains, so this filters the rest, which the depth leaves at the track.
            # A Kalman gain: the first detections of a track are averaged, weak ones pull
            # less, and a resting track settles at detection_gain (see _pull_gain).
            gain = self._pull_gain(tr, det.inliers)
            T_new = proper_pose(local_step(tr.T, gain * step))
            tr.pulled = gain
        if not far or self._detections_win:
            tr.far_detections = 0
            if not tr.pulled:
                self._reset_pull(tr, det.inliers)     # the track is reset to this detection
        tr.T = T_new
        if tr.stamp_ns == stamp_ns and tr.history:
            tr.history[-1] = (stamp_ns, tr.T.copy())
        tr.detections += 1
        tr.last_detected_ns = max(tr.last_detected_ns, stamp_ns)
        tr.last_seen_ns = max(tr.last_seen_ns, stamp_ns)
        tr.inliers, tr.score = int(det.inliers), float(det.score)
        tr.detected_since_output = True
        if tr.state == TENTATIVE and tr.detections >= c.confirm_detections:
            tr.state = CONFIRMED

    def _detection_variance(self, inliers: int) -> float:
        """A detection's pose variance, in units of one with detection_gain_inliers inliers:
        inversely proportional to its inliers."""
        return self.config.detection_gain_inliers / max(int(inliers), 1)

    def _reset_pull(self, tr: Track, inliers: int) -> None:
        """The track's pose is now this detection's: its variance is the detection's."""
        tr.pull_variance, tr.frames_since_pull = self._detection_variance(inliers), 0

    def _pull_gain(self, tr: Track, inliers: int) -> float:
        """How far an agreeing detection moves the track (a scalar Kalman filter on what the
        depth leaves free): the track's variance grows by q a frame, q chosen so that a resting
        track's gain settles at detection_gain for a detection of detection_gain_inliers
        inliers (steady state of a random walk: q = g^2 / (1 - g))."""
        g = self.config.detection_gain
        if g >= 1.0:
            return 1.0
        variance = tr.pull_variance + g * g / (1.0 - g) * tr.frames_since_pull
        gain = variance / (variance + self._detection_variance(inliers))
        tr.pull_variance, tr.frames_since_pull = (1.0 - gain) * variance, 0
        return gain

    def _birth(self, det, stamp_ns: int, candidates) -> None:
        T = proper_pose(det.T)
        now = self.stamp_ns if self.stamp_ns is not None else stamp_ns
        if now != stamp_ns and candidates:
            # Found on an older frame: move it by the motion of the nearest track since then
            # (objects rest; what moves them in the image is mostly the camera).
            near = min(candidates, key=lambda c: np.linalg.norm(c[1][:3, 3] - T[:3, 3]))
            T = near[0].T @ invert_transform(near[1]) @ T
        tr = Track(self.next_id, T, T.copy(), born_ns=now, stamp_ns=now, last_seen_ns=now,
                   last_detected_ns=now, inliers=int(det.inliers), score=float(det.score))
        tr.history.append((now, T.copy()))
        self._reset_pull(tr, det.inliers)
        if self.config.confirm_detections <= 1:
            tr.state = CONFIRMED
        self.next_id += 1
        self.tracks.append(tr)

    def _align(self, stamp_ns: int, depth_m, intrinsics) -> None:
        c = self.config
        stamp_ns = int(stamp_ns)
        seen: dict[int, bool] = {}
        jumped: set[int] = set()         # moved by a detection's correction, not by motion
        depth_ok: set[int] = set()      # confirmed by the depth on this frame
        hidden: set[int] = set()        # mostly behind something well in front of it, nothing seen through it
        # A hidden track's pose is the prediction: evidence only where the camera's motion was
        # measured on this frame (odometry, or the tracks' joint alignment).
        carried = self._motion_measured or self.camera_correction is not None
        for tr in self.tracks:
            # Detected on this frame, or (a live stream) by a detection fused since the frame
            # before: found on an earlier frame and carried here by the camera's motion.
            seen[tr.track_id] = tr.last_seen_ns == stamp_ns or tr.detected_since_output
            tr.fitness = 0.0
            jumped_from, tr.T_before_jump = tr.T_before_jump, None
            if jumped_from is not None:
                jumped.add(tr.track_id)
            if self._icp is not None and depth_m is not None and intrinsics is not None:
                res = self._icp.align(tr.T, depth_m, intrinsics)
                if jumped_from is not None:
                    own = self._icp.align(jumped_from, depth_m, intrinsics)
                    # The depth decides: the detection wins where the depth confirms it
                    # (icp_min_fitness) better than the track, or confirms neither. Where it
                    # confirms both alike (a box's yaw seen from its top) one detection is not
                    # enough to move the track: flip_after such detections in a row are.
                    if tr.state == COASTING:
                        # Not confirmed by the depth on the frame before, mostly because
                        # something covers it: the points hidden behind that are evidence
                        # for neither pose. (For a confirmed track this cost the pan with the
                        # arm two identity switches.)
                        own_f, res_f = own.unoccluded_fitness, res.unoccluded_fitness
                    else:
                        own_f, res_f = own.fitness, res.fitness
                    if max(own_f, res_f) < c.icp_min_fitness:
                        # The depth vouches for neither: the detection is the evidence there is.
                        take_detection = True
                    elif own_f == res_f:
                        take_detection = tr.far_detections >= c.flip_after
                    else:
                        take_detection = res_f > own_f
                    if take_detection:
                        tr.far_detections = 0
                        self._reset_pull(tr, tr.inliers)
                    else:
                        # The track keeps its pose, which the detection does not vouch for:
                        # only the depth can (below).
                        tr.T, res = jumped_from, own
                        seen[tr.track_id] = False
                # An instance all but out of view is no evidence: a handful of points on the
                # image border would confirm it while it lags behind.
                tr.fitness = res.fitness if res.in_view >= c.icp_min_in_view else 0.0
                # Nor is a sliver: most of the points the depth usually measures on this track
                # gone without anything measured in front of them (an arm too close for the
                # depth camera) leaves a few that the ICP would tilt the pose to.
                if tr.measured_ref > 0 and res.visible < c.icp_min_measured * tr.measured_ref:
                    tr.fitness = 0.0
                step_m = float(np.linalg.norm(res.T[:3, 3] - tr.T[:3, 3]))
                step_deg = rotation_angle_deg(res.T[:3, :3] @ tr.T[:3, :3].T)
                # A large step is the model sliding along a plane it shares with a neighbour
                # (touching boxes, a box on the table), not the object moving: keep the start.
                if res.free_share > c.max_free_share:
                    # The camera saw through where the model would stand: whatever detected
                    # it, the object is not there (a wrong detection, or a track that slid
                    # off its object into space).
                    seen[tr.track_id] = False
                elif tr.fitness >= c.icp_min_fitness and step_m <= c.icp_max_step and step_deg <= c.icp_max_step_deg:
                    tr.T = proper_pose(res.T)
                    seen[tr.track_id] = True
                    depth_ok.add(tr.track_id)
                    tr.measured_ref = res.visible if tr.measured_ref <= 0 else 0.9 * tr.measured_ref + 0.1 * res.visible
                    # Confirmed at birth where the depth vouches for the whole of the object it
                    # can see: points hidden behind a neighbour are no evidence against it.
                    if (tr.state == TENTATIVE and c.confirm_fitness > 0 and tr.fitness > 0
                            and res.unoccluded_fitness >= c.confirm_fitness):
                        tr.state = CONFIRMED
                elif (not seen[tr.track_id] and carried and tr.state != TENTATIVE and res.visible
                      and c.min_hidden_share < 1.0 and res.occluded >= c.min_hidden_share * res.visible):
                    # Hidden: where the model stands the camera sees something more than
                    # icp_max_distance in front of it (an arm, a box in front), not the
                    # surface it sits in, and nowhere through it: the depth agrees with the
                    # pose without confirming it.
                    hidden.add(tr.track_id)
        movers = [tr for tr in self.tracks if seen[tr.track_id] and len(tr.history) >= 2 and tr.track_id not in jumped
                  and stamp_ns > tr.history[-2][0]]
        shared = self._shared_motion(movers, stamp_ns) if c.camera_motion else None
        # Unknown without the shared motion: then taken as moving (no rest_frames averaging).
        # Not judged at all where nothing uses it.
        self._camera_moving = (shared is None or c.smoothing <= 0 or c.rest_frames <= 1
                               or self._camera_moves(shared * self._frame_dt))
        alive = []
        for tr in self.tracks:
            T_prev, prev_stamp = (tr.history[-2][1], tr.history[-2][0]) if len(tr.history) >= 2 else (None, None)
            # Evidence on this frame: the depth confirms it, or a detection does and the depth
            # does not contradict it (a new track that only its detection vouches for is
            # published with publish_tentative).
            tr.evidence = ((seen[tr.track_id] and (tr.state != TENTATIVE or tr.track_id in depth_ok or c.publish_tentative))
                           or tr.track_id in hidden)
            if seen[tr.track_id]:
                tr.last_seen_ns = stamp_ns
                if tr.state == COASTING:
                    tr.state = CONFIRMED
                # The track's velocity is measured only from a confirmed pose: the step from a
                # coasting one (a prediction) or a tentative one (one detection) is the
                # correction of that pose, not the object's motion.
                measured_before = tr.state_before == CONFIRMED
                if (T_prev is not None and stamp_ns > prev_stamp and tr.track_id not in jumped
                        and measured_before):
                    dt = (stamp_ns - prev_stamp) * 1e-9
                    # The track's own motion: what the shared (camera) motion does not explain.
                    start = apply_twist(T_prev, shared, dt) if shared is not None else T_prev
                    v = relative_twist(start, tr.T) / dt
                    w = 0.5
                    if tr.pulled:
                        # v holds the pull (g) of the detection's residual: weigh it so
                        # that the velocity gets Kalata's beta for alpha g, not half of it, or
                        # the prediction feeds detection noise back. (The shared motion keeps
                        # 0.5: it must follow a sweeping camera; at Kalata's weight the tracks
                        # lagged, development sweep seed 21 IDF1 0.998 -> 0.984.)
                        g = tr.pulled
                        w = min(0.5, kalata_beta(g) / g)
                    tr.velocity = (1.0 - w) * tr.velocity + w * v
                    if tr.pulled or tr.last_detected_ns != stamp_ns:
                        # Depth only, or a detection's pull: the ICP leaves what the depth does
                        # not constrain at the prediction (plus the pull's share of a detection),
                        # so the measured motion mostly repeats the predicted one there and a
                        # velocity made of detection noise would persist and drift the track.
                        tr.velocity = c.velocity_decay * tr.velocity
                self._filter_output(tr, (stamp_ns - prev_stamp) * 1e-9 if T_prev is not None else 0.0)
            else:
                if tr.state == TENTATIVE:
                    self.ended += 1
                    continue
                tr.state = COASTING
                if (stamp_ns - tr.last_seen_ns) * 1e-9 > c.coast_s:
                    self.ended += 1
                    continue
                # Unseen (occluded, out of the depth): objects rest, so what moves it in the
                # camera is the camera: follow the nearest track that was seen, rather than
                # extrapolating its own velocity through the whole occlusion.
                if T_prev is not None and shared is not None:
                    tr.T = proper_pose(apply_twist(T_prev, shared, (stamp_ns - prev_stamp) * 1e-9))
                    tr.velocity = np.zeros(6)
                elif T_prev is not None and movers:
                    near = min(movers, key=lambda m: np.linalg.norm(m.history[-2][1][:3, 3] - T_prev[:3, 3]))
                    tr.T = proper_pose(near.T @ invert_transform(near.history[-2][1]) @ T_prev)
                    tr.velocity = near.velocity.copy()
                elif T_prev is not None:
                    tr.T, tr.velocity = T_prev.copy(), np.zeros(6)
                if c.smoothing > 0 and c.rest_frames > 1 and T_prev is not None and tr.T_out_before is not None:
                    # Keep what the published pose has averaged rather than take the track's
                    # pose, as noisy as its last measurement (and maybe what the depth lost it
                    # over): held where the camera is still (the shared motion is then noise,
                    # which would add up over the occlusion), else moved as the track was.
                    tr.T_out = (proper_pose(tr.T @ invert_transform(T_prev) @ tr.T_out_before) if self._camera_moving
                                else tr.T_out_before.copy())
                else:
                    tr.T_out = tr.T.copy()
                tr.out_velocity = np.zeros(6)
            if (c.max_undetected_s > 0 and (stamp_ns - tr.last_detected_ns) * 1e-9 > c.max_undetected_s
                    and tr.missed_rounds >= MISSED_ROUNDS):
                self.ended += 1
                continue
            tr.history[-1] = (stamp_ns, tr.T.copy())
            tr.pulled = 0.0
            alive.append(tr)
        self.tracks = self._without_duplicates(alive)

    def _camera_moves(self, step: np.ndarray) -> bool:
        """Whether the camera moves, judged from this frame's shared motion ``step`` (a
        twist) and the recent ones: a still camera's steps are noise, each as unlike the one
        before as it is large (their mean squares equal, that of the changes counted half);
        a moving camera's are alike from frame to frame, their RMS more than twice their
        changes'. A pose held still in the camera (rest_frames) would fall behind it. Scale
        free, so no noise level to set; the hand-held development sweeps and pans reverse
        direction within a few frames, where a test of the steps' mean against their spread
        took them for still."""
        if self._camera_step is None:
            self._camera_step, self._camera_square, self._camera_change = step, step * step, None
            return True
        change = (step - self._camera_step) ** 2 / 2.0
        self._camera_step = step
        self._camera_square = (1.0 - RECENT) * self._camera_square + RECENT * step * step
        self._camera_change = change if self._camera_change is None else (
            (1.0 - RECENT) * self._camera_change + RECENT * change)
        moves = bool(self._camera_square[:3].sum() > 4.0 * self._camera_change[:3].sum()
                     or self._camera_square[3:].sum() > 4.0 * self._camera_change[3:].sum())
        # Still only once it has been still for the frames those means span (and moving
        # until they span any).
        self._camera_still = 0 if moves else self._camera_still + 1
        return self._camera_still < 1.0 / RECENT

    def _shared_motion(self, movers: list[Track], stamp_ns: int) -> np.ndarray:
        """The motion (per second) shared by the tracks seen on this frame and the one before:
        the camera's, as the objects rest. Robust to a few that moved or were measured badly:
        the median rotation, then the median of the translations that rotation leaves (each
        track's position is better known than its orientation, which a lever arm of half a
        metre would turn into millimetres). Updates camera_velocity for the next prediction;
        with no such track the last one stays."""
        if (self.camera_correction is not None or self._motion_measured) and self._frame_dt > 0:
            # Measured by the odometry and / or the joint alignment: the predicted motion,
            # corrected.
            dt = self._frame_dt
            M = self._predicted_motion
            if self.camera_correction is not None:
                M = self.camera_correction @ M
            measured = relative_twist(np.eye(4), M) / dt
            self.camera_velocity = 0.5 * self.camera_velocity + 0.5 * measured
            return measured
        if not movers:
            return self.camera_velocity.copy()
        dts = np.array([(stamp_ns - tr.history[-2][0]) * 1e-9 for tr in movers])
        twists = np.array([relative_twist(tr.history[-2][1], tr.T) for tr in movers]) / dts[:, None]
        omega = np.median(twists[:, :3], axis=0)
        taus = [(tr.T[:3, 3] - apply_twist(tr.history[-2][1], np.concatenate([omega, np.zeros(3)]), dt)[:3, 3]) / dt
                for tr, dt in zip(movers, dts)]
        measured = np.concatenate([omega, np.median(np.array(taus), axis=0)])
        self.camera_velocity = 0.5 * self.camera_velocity + 0.5 * measured
        return measured

    def _filter_output(self, tr: Track, dt: float) -> None:
        """Alpha-beta filter (the steady state of a constant-velocity Kalman filter) of the
        published pose towards this frame's measured one, T_out already predicted to this
        frame. alpha = 1 - smoothing; beta from alpha by Kalata's relation for a
        constant-velocity target (Kalata 1984), so a resting pose settles and a steady motion
        is followed without lag."""
        c = self.config
        residual = local_residual(tr.T_out, tr.T)
        alpha = 1.0 - c.smoothing
        if (alpha >= 1.0 or dt <= 0 or tr.state_before == TENTATIVE or np.linalg.norm(residual[3:]) > c.icp_max_step
                or np.degrees(np.linalg.norm(residual[:3])) > c.icp_max_step_deg):
            # Off, just confirmed (nothing published yet), or the pose jumped (a reset by a
            # disagreeing detection): publish the measurement, and start from the track's own
            # velocity (about the camera's origin there: the object's origin t moves by
            # omega x t + tau).
            tr.T_out = tr.T.copy()
            v = tr.velocity + (self.camera_velocity if c.camera_motion else 0.0)   # own + shared (first order)
            omega, tau = v[:3], v[3:]
            tr.out_velocity = np.concatenate([omega, np.cross(omega, tr.T[:3, 3]) + tau])
            tr.out_count, tr.out_spread, tr.out_mean = 1.0, None, None
            return
        if c.rest_frames > 1 and self._rest_count(tr, residual) > 1.0 / alpha:
            # At rest: the published pose is the running mean of the measurements, held
            # still in the camera (a velocity estimated from their noise would drift it).
            tr.T_out = proper_pose(local_step(tr.T_out, residual / tr.out_count))
            tr.out_velocity = np.zeros(6)
            return
        beta = kalata_beta(alpha)
        tr.T_out = proper_pose(local_step(tr.T_out, alpha * residual))
        tr.out_velocity = tr.out_velocity + (beta / dt) * residual

    def _rest_count(self, tr: Track, residual: np.ndarray) -> float:
        """How many measurements the published pose averages on this frame (rest_frames):
        one more, up to rest_frames, while the camera is still and the measurements stay
        near the published pose (a resting object: the published pose becomes their running
        mean), else 1 / (1 - smoothing) (motion: followed as by the plain alpha-beta
        filter). Motion of the object: one measurement further than rest_sigmas times its
        usual distance, or the recent ones (a short running mean) off to one side by
        rest_sigmas times that mean's usual size (a slow motion that a pose at rest would
        fall behind). Usual: running mean squares of this track's own, so no noise level
        to set, and the correlation of the measured poses (the pull's) is in them."""
        c = self.config
        n_fast = 1.0 / (1.0 - c.smoothing)
        if self._camera_moving:
            # What the measurements usually do while the camera moves is no measure of their
            # noise at rest: start afresh once it stops.
            tr.out_count, tr.out_spread, tr.out_mean = n_fast, None, None
            return n_fast
        d2 = np.array([residual[:3] @ residual[:3], residual[3:] @ residual[3:]])
        tr.out_mean = residual.copy() if tr.out_mean is None else (1.0 - RECENT) * tr.out_mean + RECENT * residual
        m2 = np.array([tr.out_mean[:3] @ tr.out_mean[:3], tr.out_mean[3:] @ tr.out_mean[3:]])
        moving = (tr.out_spread is not None and (
            np.any(d2 > c.rest_sigmas ** 2 * tr.out_spread[:2]) or np.any(m2 > c.rest_sigmas ** 2 * tr.out_spread[2:])))
        if moving or tr.out_count < n_fast:
            tr.out_count = n_fast
        else:
            tr.out_count = min(tr.out_count + 1.0, float(c.rest_frames))
        # The usual distance, over about the frames the pose averages; slowly while moving,
        # where the distances are the motion's.
        w = 1.0 / (c.rest_frames if moving else max(tr.out_count, n_fast))
        both = np.concatenate([d2, m2])
        tr.out_spread = both if tr.out_spread is None else (1.0 - w) * tr.out_spread + w * both
        return tr.out_count

    def _without_duplicates(self, tracks: list[Track]) -> list[Track]:
        """Two tracks on one object (their model volumes overlap: e.g. a detection born next
        to a coasting track that then came back): the one with the better evidence on this
        frame stays (published before not, confirmed before tentative), then the older."""
        d = max(self.config.duplicate_distance, self._merge_distance)
        if d <= 0 or len(tracks) < 2:
            return tracks
        keep: list[Track] = []
        for tr in sorted(tracks, key=lambda t: (not t.evidence, t.state == TENTATIVE, t.track_id)):
            if all(np.linalg.norm(tr.T[:3, 3] - k.T[:3, 3]) >= d for k in keep):
                keep.append(tr)
            else:
                self.ended += 1
        return sorted(keep, key=lambda t: t.track_id)

    # ---- output ----------------------------------------------------------------------
    def output(self) -> list[TrackedInstance]:
        """The tracks to publish on the latest frame, by track_id: those with evidence on it
        (a detection or the depth vouched for them; see ``_align``). A coasting track is kept
        for its object's next detection, not published."""
        out = []
        for tr in self.tracks:
            detected, tr.detected_since_output = tr.detected_since_output, False
            if not tr.evidence:
                continue
            out.append(TrackedInstance(
                tr.track_id, -1, tr.T_out.copy(), tr.inliers, tr.score, tr.state,
                DETECTION if detected else TRACKING, (self.stamp_ns - tr.born_ns) * 1e-9, tr.fitness))
        for rank, k in enumerate(sorted(range(len(out)), key=lambda k: (-out[k].inliers, out[k].track_id))):
            out[k].id = rank
        return out


__all__ = ["TrackerConfig", "InstanceTracker", "TrackedInstance", "Track", "TENTATIVE", "CONFIRMED", "COASTING",
           "DETECTION", "TRACKING"]
