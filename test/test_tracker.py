"""InstanceTracker with known answers: detections made up frame by frame (no depth, no ICP),
so every birth, confirmation, coast, death and assignment is decided by the tracker alone."""
from dataclasses import dataclass

import numpy as np
import pytest

from multi_instance_reg.tracking import InstanceTracker, TrackerConfig
from multi_instance_reg.tracking.icp import ProjectiveICP
from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.transforms import make_transform, rotation_angle_deg

FRAME_NS = 33_333_333


@dataclass
class Det:
    T: np.ndarray
    inliers: int = 20
    score: float = 0.9


@dataclass
class Model:
    points_xyz: np.ndarray


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def det_at(x, y=0.0, z=0.8, yaw=0.0):
    return Det(make_transform(rot_z(yaw), [x, y, z]))


def tracker(**kw):
    # A 1 cm object: the made-up scenes put objects 1-5 cm apart, and two poses closer than
    # half the object's thickness are one object (duplicate_distance).
    model = Model(np.random.default_rng(0).uniform(-0.005, 0.005, (200, 3)))
    return InstanceTracker(model, TrackerConfig(icp=False, **kw))


def run(tr, frames):
    """frames: list of detection lists (None = detector did not run). Returns outputs."""
    return [tr.step(k * FRAME_NS, None, None, dets) for k, dets in enumerate(frames)]


def test_birth_confirmation_and_ids():
    tr = tracker(confirm_detections=2, publish_tentative=False)
    out = run(tr, [[det_at(0.0), det_at(0.2)], [det_at(0.0), det_at(0.2)], [det_at(0.0), det_at(0.2)]])
    assert out[0] == []                                   # tentative ones are not published when asked
    assert [i.track_id for i in out[1]] == [0, 1]
    assert all(i.state == "confirmed" and i.source == "detection" for i in out[2])


def test_a_new_track_is_published_on_its_first_detection_unless_asked_not_to():
    out = run(tracker(), [[det_at(0.0)]])
    assert [(i.track_id, i.state) for i in out[0]] == [(0, "tentative")]
    assert run(tracker(publish_tentative=False), [[det_at(0.0)]]) == [[]]


def test_tentative_track_ends_at_first_miss_and_ids_are_not_reused():
    tr = tracker(confirm_detections=3)
    out = run(tr, [[det_at(0.0)], [], [det_at(0.0)], [det_at(0.0)], [det_at(0.0)]])
    assert out[-1][0].track_id == 1                       # id 0 ended with its miss, never reused


def test_coasting_then_recovery_keeps_the_id():
    tr = tracker(coast_s=0.5)
    frames = [[det_at(0.1)]] * 3 + [[]] * 5 + [[det_at(0.1)]]
    out = run(tr, frames)
    # Undetected: kept (coasting) for the object's next detection, but not published.
    assert out[4] == []
    assert out[-1][0].track_id == 0 and out[-1][0].state == "confirmed"


def test_track_ends_after_coast_s():
    tr = tracker(coast_s=0.1)                             # 3 frames at 30 Hz
    out = run(tr, [[det_at(0.1)]] * 3 + [[]] * 6)
    assert out[-1] == [] and tr.tracks == []


def test_two_identical_objects_crossing_do_not_swap():
    # Two objects moving towards each other along x, passing 1 cm apart in y.
    tr = tracker(gate_distance=0.03)
    frames = []
    for k in range(40):
        x = -0.1 + 0.005 * k
        frames.append([det_at(x, 0.0), det_at(-x, 0.01)])
    out = run(tr, frames)
    ids_left_mover = [next(i.track_id for i in o if abs(i.T[1, 3]) < 0.005) for o in out[1:]]
    assert set(ids_left_mover) == {0}


def test_symmetric_flip_is_rejected():
    tr = tracker(flip_after=3)
    frames = [[det_at(0.0, yaw=10)]] * 3 + [[det_at(0.0, yaw=190)], [det_at(0.0, yaw=10)], [det_at(0.0, yaw=190)]]
    out = run(tr, frames)
    for o in out[1:]:
        assert rotation_angle_deg(o[0].T[:3, :3].T @ rot_z(10)) < 1.0


def test_consistent_other_orientation_is_adopted():
    tr = tracker(flip_after=3)
    out = run(tr, [[det_at(0.0, yaw=10)]] * 3 + [[det_at(0.0, yaw=190)]] * 3)
    assert rotation_angle_deg(out[-1][0].T[:3, :3].T @ rot_z(190)) < 1.0


def test_late_detections_are_moved_by_the_track_motion():
    tr = tracker()
    for k in range(3):
        tr.step(k * FRAME_NS, None, None, [det_at(0.01 * k)])
    # The detector ran on frame 2 and reports while the tracker is at frame 4.
    tr.step(3 * FRAME_NS, None, None, None)
    tr.step(4 * FRAME_NS, None, None, None)
    tr.add_detections(2 * FRAME_NS, [det_at(0.02, 0.004)])
    assert len(tr.tracks) == 1
    assert tr.tracks[0].T[1, 3] == pytest.approx(0.004, abs=1e-9)


def test_smoothing_off_publishes_the_measured_pose():
    out = run(tracker(smoothing=0.0), [[det_at(0.0)], [det_at(0.003)]])
    assert out[1][0].T[0, 3] == pytest.approx(0.003)


def test_smoothing_settles_a_resting_pose():
    # A resting object, detections with 2 mm / 1 deg of white noise: the filter's spread must
    # fall well under the measurements' (an alpha-beta filter with alpha 0.2 passes about 0.4
    # of the noise's standard deviation).
    rng = np.random.default_rng(5)
    dets = [[det_at(*(np.array([0.0, 0.0, 0.8]) + rng.normal(0, 0.002, 3)), yaw=rng.normal(0, 1.0))]
            for _ in range(200)]
    raw = np.array([o[0].T[:3, 3] for o in run(tracker(smoothing=0.0), dets)[50:]])
    out = run(tracker(smoothing=0.8, detection_gain=1.0), dets)[50:]     # the output filter alone
    pos = np.array([o[0].T[:3, 3] for o in out])
    yaw = np.degrees([np.arctan2(o[0].T[1, 0], o[0].T[0, 0]) for o in out])
    assert pos.std(axis=0).max() < 0.5 * raw.std(axis=0).min()
    assert np.linalg.norm(pos.mean(axis=0) - [0.0, 0.0, 0.8]) < 0.0005
    assert yaw.std() < 0.5


def test_smoothing_follows_a_steady_motion_without_lag():
    # 6 mm per frame (18 cm/s): once the filter has the velocity, no lag behind the truth.
    out = run(tracker(smoothing=0.8), [[det_at(0.006 * k)] for k in range(60)])
    assert out[-1][0].T[0, 3] == pytest.approx(0.006 * 59, abs=2e-4)


def resting_then_moving(speed, rest=60, move=60, seed=1):
    """Detections of one object (1 mm, 0.5 deg of white noise): at rest for ``rest`` frames,
    then moving along x at ``speed`` m per frame for ``move`` frames, then at rest again."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([np.zeros(rest), speed * np.arange(1, move + 1), np.full(rest, speed * move)])
    dets = [[det_at(xk + rng.normal(0, 0.001), rng.normal(0, 0.001), 0.8 + rng.normal(0, 0.001), yaw=rng.normal(0, 0.5))]
            for xk in x]
    return x, dets


def published_x(out):
    return np.array([o[0].T[0, 3] if o else np.nan for o in out])


def test_the_published_pose_of_resting_objects_converges():
    # Camera and five objects still, detections with 1 mm / 0.5 deg of white noise: with
    # rest_frames the published pose averages the measured ones while the camera is judged
    # still and they stay near it, so its spread falls below that of the plain alpha-beta
    # filter (measured: 0.23 against 0.39 mm; the camera's steps here are the median of
    # the tracks' own, noisier than a depth alignment's, and taken for motion at times),
    # about the same centre.
    rng = np.random.default_rng(1)
    homes = np.array([[x, y, 0.8] for x, y in ((0.0, 0.0), (0.08, 0.0), (-0.2, 0.1), (0.2, -0.1), (0.1, 0.15))])
    dets = [[det_at(*(h + rng.normal(0, 0.001, 3)), yaw=rng.normal(0, 0.5)) for h in homes] for _ in range(150)]
    spread, centre = {}, {}
    for rest in (0, 30):
        out = run(tracker(smoothing=0.5, rest_frames=rest), dets)[40:]
        assert all([o.track_id for o in f] == [0, 1, 2, 3, 4] for f in out)
        P = np.array([[o.T[:3, 3] for o in f] for f in out])
        spread[rest] = P.std(axis=0).mean()
        centre[rest] = np.abs(P.mean(axis=0) - homes).max()
    assert spread[30] < 0.7 * spread[0]
    assert centre[30] < 0.0005 and centre[0] < 0.0005


def test_a_resting_object_that_starts_to_move_is_followed_without_lag():
    # At rest for 60 frames, then moving at 3 mm per frame (9 cm/s): the first measurements
    # far from the averaged pose bring back the plain filter, which then has no lag; over
    # the 50 frames of motion after its first 10 the mean error is the plain filter's
    # within 0.5 mm (measured: both -0.4 mm, the filter slightly ahead).
    x, dets = resting_then_moving(0.003)
    err = {}
    for rest in (0, 30):
        xs = published_x(run(tracker(smoothing=0.5, rest_frames=rest), dets))
        err[rest] = (xs - x)[70:120].mean()
    assert abs(err[30] - err[0]) < 0.0005 and abs(err[30]) < 0.001


def test_the_camera_motion_test_tells_a_still_camera_from_a_moving_one():
    # Steps of a still camera are noise about zero; a moving camera's are alike from frame
    # to frame, also where it turns round (a hand-held sweep reverses within a few frames).
    rng = np.random.default_rng(3)
    still = tracker()
    judged = [still._camera_moves(rng.normal(0.0, 1e-4, 6)) for _ in range(200)]
    assert not any(judged[10:]) and all(judged[:4])            # moving until judged still for 4 frames
    sweep = tracker()
    steps = [np.concatenate([np.zeros(3), [0.003 * np.cos(k / 4.0), 0.001, 0.0]]) + rng.normal(0.0, 1e-4, 6)
             for k in range(100)]
    assert all(sweep._camera_moves(s) for s in steps)


def test_a_still_pose_is_not_held_while_the_camera_moves():
    # Three resting objects, the camera panning 2 mm per frame along x after 40 still
    # frames: every pose moves in the camera; held still they would fall behind. The
    # published poses follow as closely as the plain filter's.
    homes = [np.array([x, 0.0, 0.8]) for x in (-0.1, 0.0, 0.1)]
    rng = np.random.default_rng(4)
    shift = np.concatenate([np.zeros(40), -0.002 * np.arange(1, 61)])
    seq = [[det_at(*(h + [s, 0.0, 0.0] + rng.normal(0, 0.001, 3)), yaw=rng.normal(0, 0.5)) for h in homes]
           for s in shift]
    err = {}
    for rest in (0, 30):
        out = run(tracker(smoothing=0.5, rest_frames=rest), seq)
        err[rest] = np.mean([[abs(o.T[0, 3] - (homes[o.track_id][0] + shift[k])) for o in out[k]] for k in range(45, 100)])
    assert err[30] < err[0] + 0.0003


def test_smoothing_restarts_on_a_jump():
    # A measurement further than icp_max_step from the filter is published as it is.
    out = run(tracker(smoothing=0.8, gate_distance=0.1), [[det_at(0.0)]] * 10 + [[det_at(0.05)]])
    assert out[-1][0].T[0, 3] == pytest.approx(0.05)


def test_icp_recovers_a_displaced_pose():
    # Depth image of three planes meeting in a corner; the model is that very surface, so the
    # right answer is the identity.
    K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
    intr = CameraIntrinsics(K=K, width=320, height=240)
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    rays = np.stack([(u - 160) / 500.0, (v - 120) / 500.0, np.ones(u.shape)], -1)
    planes = [(np.array([0.3, 0.1, 1.0]), 0.8), (np.array([1.0, 0.2, 0.5]), 0.45), (np.array([0.1, 1.0, 0.6]), 0.5)]
    depth = np.zeros((240, 320))
    for n, d in planes:
        z = d / (rays @ n)
        ok = (z > 0.3) & ((depth == 0) | (z < depth))
        depth[ok] = z[ok]
    pick = np.random.default_rng(1).choice(240 * 320, 4000, replace=False)
    surface = (rays * depth[..., None]).reshape(-1, 3)[pick]
    icp = ProjectiveICP(surface, 400)
    icp.normals[np.einsum("ni,ni->n", icp.normals, icp.points) > 0] *= -1     # face the camera
    T0 = make_transform(rot_z(1.5), [0.004, -0.003, 0.005])
    res = icp.align(T0, depth.astype(np.float32), intr)
    assert res.fitness > 0.8
    assert np.linalg.norm(res.T[:3, 3]) < 1e-3 and rotation_angle_deg(res.T[:3, :3]) < 0.2
    # Nothing where the model is: a miss, not a pose.
    assert icp.align(T0, np.zeros((240, 320), np.float32), intr).fitness == 0.0



def test_live_tracker_fuses_detections_only_for_frames_it_stepped():
    from multi_instance_reg.tracking import LiveConfig, LiveTracker

    model = Model(np.random.default_rng(0).uniform(-0.05, 0.05, (200, 3)))
    live = LiveTracker(model, TrackerConfig(icp=False), LiveConfig())
    assert not live.add_detections(0, [det_at(0.0)])              # frame never stepped: refused
    for k in range(3):
        assert live.step(k * FRAME_NS, None, None) == []
    # Found on frame 1, arriving after frame 2 (the detector runs behind): fused.
    assert live.add_detections(1 * FRAME_NS, [det_at(0.0)])
    assert live.add_detections(2 * FRAME_NS, [det_at(0.0)])
    # Two detections confirmed it, fused after frame 2: evidence on frame 3, the first it is
    # published on; on frame 4 neither detected nor seen in a depth: coasting, kept but not
    # published (a prediction is not evidence).
    (out,) = live.step(3 * FRAME_NS, None, None)
    assert out.track_id == 0 and out.state == "confirmed" and out.source == "detection"
    assert live.step(4 * FRAME_NS, None, None) == []
    assert [(t.track_id, t.state) for t in live._tracker.tracks] == [(0, "coasting")]
    counts = live.counts()
    assert counts["detections_fused"] == 2 and counts["detections_refused"] == 1 and counts["tracks_live"] == 1
    # Time goes back (a camera restarted): frames from before are no longer this stream's past.
    live.step(1 * FRAME_NS, None, None)
    assert not live.add_detections(2 * FRAME_NS, [det_at(0.0)])
    assert live.add_detections(1 * FRAME_NS, [det_at(0.0)])


# ---- with depth: a box (6 x 6 x 4 cm) resting on a table, seen from straight above -----------
# The depth of its top face constrains height and tilt only: point-to-plane ICP leaves the
# slide along the table at its start pose, which is where a tracker can go wrong.
BOX_K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
BOX_INTR = CameraIntrinsics(K=BOX_K, width=320, height=240)


def box_model():
    g = np.linspace(-1.0, 1.0, 25)
    a, b = np.meshgrid(g, g)
    a, b = a.ravel(), b.ravel()
    half = np.array([0.03, 0.03, 0.02])
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((a.size, 3))
            p[:, axis] = sign
            p[:, (axis + 1) % 3], p[:, (axis + 2) % 3] = a, b
            faces.append(p * half)
    return Model(np.unique(np.concatenate(faces).round(6), axis=0))


def box_depth(x):
    """Table at 0.80 m, the box's top face at 0.76 m, centred at (x, 0)."""
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    depth = np.full((240, 320), 0.80, np.float32)
    X, Y = (u - 160) / 500.0 * 0.76, (v - 120) / 500.0 * 0.76
    depth[(np.abs(X - x) <= 0.03) & (np.abs(Y) <= 0.03)] = 0.76
    return depth


def without_edge_depth(depth):
    """No depth where a 3x3 window spans two surfaces, as a stereo camera (and the synthetic
    sensor) gives none there."""
    from scipy.ndimage import maximum_filter, minimum_filter
    spread = maximum_filter(depth, 3) - minimum_filter(depth, 3)
    return np.where(spread > 0.025 * depth + 0.004, 0.0, depth).astype(np.float32)


def box_det(x, inliers=40):
    return Det(make_transform(np.eye(3), [x, 0.0, 0.78]), inliers)


def box_tracker(**kw):
    return InstanceTracker(box_model(), TrackerConfig(**kw))


def test_depth_keeps_a_track_against_a_bad_detection_and_follows_a_good_one():
    tr = box_tracker()
    for k in range(5):
        tr.step(k * FRAME_NS, box_depth(0.0), BOX_INTR, [box_det(0.0)])
    # A detection 2 cm off (inside the gate), few inliers, the box where it was: the depth
    # confirms the track, not the detection.
    out = tr.step(5 * FRAME_NS, box_depth(0.0), BOX_INTR, [box_det(0.02, inliers=7)])
    assert len(out) == 1 and abs(out[0].T[0, 3]) < 0.003
    out = tr.step(6 * FRAME_NS, box_depth(0.0), BOX_INTR, [box_det(0.0)])
    assert [o.track_id for o in out] == [0] and abs(out[0].T[0, 3]) < 0.003
    # The box really moved by 2 cm (put down elsewhere): the depth agrees with the detection.
    for k in range(7, 10):
        out = tr.step(k * FRAME_NS, box_depth(0.02), BOX_INTR, [box_det(0.02)])
        assert [o.track_id for o in out] == [0] and abs(out[0].T[0, 3] - 0.02) < 0.003


def test_a_velocity_the_depth_does_not_confirm_dies_out():
    # A plate whose top face lies in one plane with its neighbours: the depth cannot tell a
    # slide along that plane from rest. Detections with 2 mm of noise make a velocity; with
    # tracking.velocity_decay below 1 the track must not keep sliding on it through 1 s of
    # depth-only frames (at constant velocity, the default, it slides 12 cm).
    g = np.linspace(-0.03, 0.03, 25)
    a, b = np.meshgrid(g, g)
    plate = np.concatenate([np.stack([a.ravel(), b.ravel(), np.full(a.size, z)], 1) for z in (-0.005, 0.005)])
    plane = np.full((240, 320), 0.775, np.float32)
    xs = np.random.default_rng(3).normal(0.0, 0.002, 10)
    # (camera_motion off: with one track its motion is the shared one, which does not decay)
    tr = InstanceTracker(Model(plate), TrackerConfig(velocity_decay=0.7, camera_motion=False))
    for k, x in enumerate(xs):
        tr.step(k * FRAME_NS, plane, BOX_INTR, [box_det(x)])
    for k in range(10, 40):
        out = tr.step(k * FRAME_NS, plane, BOX_INTR, None)
    assert [o.track_id for o in out] == [0] and abs(out[0].T[0, 3] - xs[-1]) < 0.015


def test_icp_moves_only_what_the_depth_constrains():
    # The box's top face alone, with 1 mm of depth noise and no depth at its edges and sides
    # (a stereo camera gives none at a discontinuity or a steep face), and a model cloud with
    # 0.5 mm of noise (a captured one: its normals tilt by degrees): the depth fixes the
    # height and the tilt, not where the box lies in the table's plane nor its yaw. Started
    # 2 mm beside and 3 mm above the truth, the ICP must bring the height back and leave the
    # slide and the yaw where they were started; and only points with a depth measurement
    # count as visible, so the top face is all confirmed.
    from scipy.spatial.transform import Rotation

    from multi_instance_reg.tracking.icp import align_projective
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    X, Y = (u - 160) / 500.0 * 0.76, (v - 120) / 500.0 * 0.76
    top = (np.abs(X) <= 0.027) & (np.abs(Y) <= 0.027)
    depth = np.zeros((240, 320), np.float32)
    depth[top] = 0.76 + np.random.default_rng(5).normal(0.0, 0.001, top.sum()).astype(np.float32)
    points = box_model().points_xyz
    points = points + np.random.default_rng(6).normal(0.0, 0.0005, points.shape)
    T0 = make_transform(np.eye(3), [0.002, 0.0, 0.777])
    slide, yaw = {}, {}
    for share in (0.0, 0.03):
        icp = ProjectiveICP(points, 400, min_information=share)
        # (align_projective: the solve alone, without align's keeping a start it makes worse)
        res = align_projective(T0, icp.points, icp.normals, depth, BOX_INTR, icp.iterations, icp.max_distance,
                               icp.inlier_distance, icp.damping, share, icp.centroid, icp.radius, icp.noise_ref)
        slide[share] = np.linalg.norm(res.T[:2, 3] - T0[:2, 3])
        yaw[share] = abs(np.degrees(Rotation.from_matrix(res.T[:3, :3]).as_rotvec()[2]))
        if share:
            assert abs(res.T[2, 3] - 0.78) < 0.0005 and res.fitness > 0.9
    assert slide[0.03] < 0.0002 and yaw[0.03] < 0.05
    assert slide[0.0] > 0.001 and yaw[0.0] > 1.0       # a plain solve slides and turns on noise alone


def test_the_depth_confirms_a_new_track_at_once_but_not_a_false_detection():
    # The box is in the depth: its first detection is published on its own frame.
    depth = without_edge_depth(box_depth(0.0))
    out = box_tracker().step(0, depth, BOX_INTR, [box_det(0.0)])
    assert [(o.track_id, o.state) for o in out] == [(0, "confirmed")]
    # A detection where the depth shows only the table (a one-frame false detection) is not
    # published, and ends when the next detection round does not find it again.
    tr = box_tracker()
    table = np.full((240, 320), 0.80, np.float32)
    assert tr.step(0, table, BOX_INTR, [box_det(0.0)]) == []
    assert tr.step(FRAME_NS, table, BOX_INTR, []) == [] and tr.tracks == []
    # Off: two detections confirm it, but the depth vouching for it publishes it at once.
    out = box_tracker(confirm_fitness=0.0).step(0, depth, BOX_INTR, [box_det(0.0)])
    assert [(o.track_id, o.state) for o in out] == [(0, "tentative")]
    # The depth contradicting it (the camera sees the table through it): not published.
    assert box_tracker(confirm_fitness=0.0).step(0, table, BOX_INTR, [box_det(0.0)]) == []


def rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1.0, 0], [-np.sin(a), 0, np.cos(a)]])


def test_an_occluded_track_follows_the_shared_camera_motion():
    # Five resting objects, the camera turning 0.4 deg per frame (every pose in the camera
    # frame turns about the camera's origin). Object 0 is hidden for frames 10-24; its nearest
    # neighbour (object 1) is measured with 5 mm of noise. The hidden track must follow the
    # camera, estimated from all the seen tracks (median), not its noisy neighbour, and be
    # re-detected under its own id.
    rng = np.random.default_rng(7)
    homes = [np.array([x, y, 0.8]) for x, y in ((0.0, 0.0), (0.05, 0.0), (-0.2, 0.1), (0.2, -0.1), (0.1, 0.15))]

    def truth(k, i):
        return make_transform(rot_y(0.4 * k), rot_y(0.4 * k) @ homes[i])

    def frames(n):
        out = []
        for k in range(n):
            dets = []
            for i in range(5):
                if i == 0 and 10 <= k < 25:
                    continue
                T = truth(k, i)
                if i == 1:
                    T[:3, 3] += rng.normal(0.0, 0.005, 3)
                dets.append(Det(T))
            out.append(dets)
        return out

    seq = frames(30)
    tol = 0.003
    for on in (True, False):
        tr = tracker(camera_motion=on)
        out = run(tr, seq[:25])
        assert 0 not in [o.track_id for o in out[24]]              # hidden: not published ...
        hidden = [t for t in tr.tracks if t.track_id == 0]          # ... but kept, coasting
        assert hidden and hidden[0].state == "coasting"
        err = np.linalg.norm(hidden[0].T[:3, 3] - truth(24, 0)[:3, 3])
        out += [tr.step(k * FRAME_NS, None, None, dets) for k, dets in enumerate(seq[25:], start=25)]
        if on:
            assert err < tol
            assert [o.track_id for o in out[29]] == [0, 1, 2, 3, 4]
            on_err = err
        else:
            off_err = err
    assert off_err > tol and off_err > 3 * on_err      # following the nearest (noisy) neighbour does worse


def test_agreeing_detections_pull_the_unconstrained_directions_part_of_the_way():
    # Five resting boxes seen from their tops: the depth fixes their height and tilt, not
    # their yaw nor where they lie on the table, and those follow the detections. Detections
    # with 1.5 mm and 1 deg of white noise in exactly those directions. Reset by every
    # detection (detection_gain 1) the published pose (smoothing 0.5) keeps 0.6 of it;
    # pulled by the Kalman gain (detection_gain 0.3 for 100 inliers, these have 40) it must
    # keep less (measured: 0.53 of that in position, 0.58 in yaw), centred where the reset
    # one was.
    from scipy.spatial.transform import Rotation
    xs = (-0.16, -0.08, 0.0, 0.08, 0.16)
    depth = top_faces_depth(xs)
    rng = np.random.default_rng(7)
    dets = [[Det(make_transform(rot_z(rng.normal(0, 1.0)), [x + rng.normal(0, 0.0015), rng.normal(0, 0.0015), 0.78]), 40)
             for x in xs] for _ in range(150)]
    spread, centre = {}, {}
    for gain in (1.0, 0.3):
        tr = box_tracker(smoothing=0.5, detection_gain=gain, rest_frames=0)   # the pull alone, not the output's averaging
        outs = [tr.step(k * FRAME_NS, depth, BOX_INTR, d) for k, d in enumerate(dets)][30:]
        assert all([o.track_id for o in out] == [0, 1, 2, 3, 4] for out in outs)
        pos = np.array([[o.T[:3, 3] for o in out] for out in outs])            # frame, box, xyz
        yaw = np.degrees([[Rotation.from_matrix(o.T[:3, :3]).as_rotvec()[2] for o in out] for out in outs])
        spread[gain] = (np.median(pos[:, :, :2].std(axis=0)), np.median(yaw.std(axis=0)))
        centre[gain] = (pos.mean(axis=0), yaw.mean(axis=0))
    assert np.abs(centre[0.3][0] - centre[1.0][0]).max() < 0.0005 and np.abs(centre[0.3][1] - centre[1.0][1]).max() < 0.3
    assert spread[0.3][0] < 0.7 * spread[1.0][0] and spread[0.3][1] < 0.7 * spread[1.0][1]
    assert spread[1.0][1] > 0.3                       # the noise did reach the published pose before


def top_faces_depth(xs, noise=0.001, seed=5):
    """The top faces (0.76 m) of boxes centred at (x, 0), nothing else measured: the depth
    fixes their height and tilt, not their yaw nor where they lie on the table."""
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    X, Y = (u - 160) / 500.0 * 0.76, (v - 120) / 500.0 * 0.76
    top = np.any([(np.abs(X - x) <= 0.027) & (np.abs(Y) <= 0.027) for x in xs], axis=0)
    depth = np.zeros((240, 320), np.float32)
    depth[top] = 0.76 + np.random.default_rng(seed).normal(0.0, noise, top.sum()).astype(np.float32)
    return depth


def yaw_deg(T):
    from scipy.spatial.transform import Rotation
    return float(np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec()[2]))


def test_a_turned_detection_the_depth_cannot_judge_moves_the_track_only_when_repeated():
    # A settled track of a box seen from its top; a detection turned by 8 deg (beyond
    # icp_max_step_deg, inside gate_rotation_deg) that the depth fits as well as the track:
    # one such detection (a weak one on a half-hidden box) leaves the track; flip_after of
    # them in a row move it (the track was the wrong one).
    depth = top_faces_depth([0.0])
    tr = box_tracker()
    for k in range(5):
        tr.step(k * FRAME_NS, depth, BOX_INTR, [box_det(0.0)])
    turned = Det(make_transform(rot_z(8.0), [0.0, 0.0, 0.78]), 8)
    out = tr.step(5 * FRAME_NS, depth, BOX_INTR, [turned])
    assert abs(yaw_deg(out[0].T)) < 0.5
    for k in range(6, 6 + tr.config.flip_after):
        out = tr.step(k * FRAME_NS, depth, BOX_INTR, [turned])
    assert abs(yaw_deg(out[0].T) - 8.0) < 0.5 and out[0].track_id == 0


def settled_box_tracker(depth, frames):
    """A tracker with smoothing 0.5 whose one track has had ``frames`` 100-inlier detections
    of a box at rest (yaw 0)."""
    tr = box_tracker(smoothing=0.5)
    for k in range(frames):
        tr.step(k * FRAME_NS, depth, BOX_INTR, [box_det(0.0, inliers=100)])
    return tr


def test_a_weak_detection_pulls_a_settled_track_less_than_a_strong_one():
    # With smoothing on, the pull is a Kalman gain: a detection's variance is inversely
    # proportional to its inliers.
    depth = top_faces_depth([0.0])
    moved = {}
    for inliers in (10, 300):
        tr = settled_box_tracker(depth, 20)
        tr.step(20 * FRAME_NS, depth, BOX_INTR, [Det(make_transform(rot_z(3.0), [0.0, 0.0, 0.78]), inliers)])
        moved[inliers] = yaw_deg(tr.tracks[0].T)
    assert 0.0 < moved[10] < 0.5 * moved[300] and moved[300] < 3.0


def test_with_smoothing_a_weak_turned_detection_is_pulled_by_its_gain_a_strong_one_left_to_the_depth():
    # "Far" in orientation is in units of the detection's spread: 8 deg off a settled track is
    # within the noise of an 8-inlier detection (gate 5 deg x sqrt(100 / 8) = 17.7 deg), so it
    # pulls the track by its small gain and repeating it moves the track only gradually; for a
    # 300-inlier one it is a jump the depth cannot judge, taken after flip_after in a row.
    depth = top_faces_depth([0.0])
    yaws = {}
    for inliers in (8, 300):
        tr = settled_box_tracker(depth, 20)
        turned = Det(make_transform(rot_z(8.0), [0.0, 0.0, 0.78]), inliers)
        yaws[inliers] = []
        for k in range(20, 20 + tr.config.flip_after):
            tr.step(k * FRAME_NS, depth, BOX_INTR, [turned])
            yaws[inliers].append(yaw_deg(tr.tracks[0].T))
    assert 0.0 < yaws[8][0] < 1.0 and yaws[8][0] < yaws[8][-1] < 3.0, yaws[8]
    assert abs(yaws[300][0]) < 0.5 and abs(yaws[300][-1] - 8.0) < 0.5, yaws[300]


def test_a_sliver_of_depth_does_not_move_a_track():
    # An arm too close for the depth camera hides all but a strip of the box's top: the few
    # points left are no measurement of the pose (icp_min_measured), the track coasts where
    # it was; with the check off the strip counts as seen.
    depth = without_edge_depth(box_depth(0.0))
    sliver = depth.copy()
    sliver[:, :172] = 0.0
    for share, state in ((0.5, "coasting"), (0.0, "confirmed")):
        tr = box_tracker(icp_min_measured=share)
        for k in range(5):
            tr.step(k * FRAME_NS, depth, BOX_INTR, [box_det(0.0)])
        out = tr.step(5 * FRAME_NS, sliver, BOX_INTR, None)
        assert [t.state for t in tr.tracks] == [state]
        assert len(out) == (state == "confirmed")          # a coasting track is not published
        assert np.linalg.norm(tr.tracks[0].T[:3, 3] - [0.0, 0.0, 0.78]) < 0.002


def test_the_joint_alignment_measures_the_camera_motion():
    # Five boxes with their sides in view (table and box depth, no depth at the edges); the
    # camera moved by 3 mm and 0.5 deg since the poses were known. One alignment of all five
    # recovers the turn (which the top of one box does not show) and brings every box closer
    # to its true pose than that box's own alignment does (measured: 1.0-1.1 mm left in the
    # table's plane, which the steep sides barely measure, against 1.5-2.2 mm and 0.1-0.7
    # deg for each box alone).
    centres = ((-0.15, -0.08), (0.15, -0.08), (0.0, 0.0), (-0.15, 0.08), (0.15, 0.08))
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    depth = np.full((240, 320), 0.80, np.float32)
    X, Y = (u - 160) / 500.0 * 0.76, (v - 120) / 500.0 * 0.76
    for x, y in centres:
        depth[(np.abs(X - x) <= 0.03) & (np.abs(Y - y) <= 0.03)] = 0.76
    depth = without_edge_depth(depth)
    motion = make_transform(rot_z(0.5), [0.003, -0.002, 0.0])
    truth = [make_transform(np.eye(3), [x, y, 0.78]) for x, y in centres]
    known = [np.linalg.inv(motion) @ T for T in truth]       # where the tracks think they are
    icp = ProjectiveICP(box_model().points_xyz, 400, 10, 0.03, 0.006)
    D = icp.align_all(known, depth, BOX_INTR).T
    assert rotation_angle_deg(D[:3, :3].T @ motion[:3, :3]) < 0.1
    for T_known, T_true in zip(known, truth):
        alone = icp.align(T_known, depth, BOX_INTR).T
        joint = D @ T_known
        assert np.linalg.norm(joint[:3, 3] - T_true[:3, 3]) < np.linalg.norm(alone[:3, 3] - T_true[:3, 3])
        assert rotation_angle_deg(joint[:3, :3].T @ T_true[:3, :3]) < 0.1


def test_alignment_warm_up_compiles_what_a_live_frame_uses():
    """The node compiles the depth alignment at start (tracking.icp.warm_up), not on the first
    detection it carries forward: a live frame's types must find it compiled."""
    from multi_instance_reg.tracking import icp

    icp.warm_up()
    kernels = [icp._icp]                 # the entry kernel; the ones it calls compile into it
    compiled = [len(k.signatures) for k in kernels]
    assert all(compiled)
    rng = np.random.default_rng(1)
    model_points = rng.uniform(-0.04, 0.04, (500, 3)).astype(np.float32)    # as a model file stores them
    aligner = ProjectiveICP(model_points, num_points=100)
    depth = np.full((480, 640), 0.7, np.float32)                            # as the node converts depth
    intrinsics = CameraIntrinsics(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)
    T = make_transform(np.eye(3), [0.0, 0.0, 0.65])
    aligner.align(T, depth, intrinsics)
    aligner.align_all([T, T @ make_transform(np.eye(3), [0.1, 0, 0])], depth, intrinsics)
    assert [len(k.signatures) for k in kernels] == compiled


# ---- evidence, camera motion, one track per object, streams that jump back ---------------------

def test_the_stamps_going_back_end_every_track_and_say_so(caplog):
    # A bag played in a loop: before the jump the coast test (stamp - last seen > coast_s)
    # would stay negative and the old tracks would never end.
    tr = tracker()
    run(tr, [[det_at(0.0), det_at(0.1)]] * 3)
    assert len(tr.tracks) == 2
    with caplog.at_level("WARNING"):
        out = tr.step(0, None, None, [det_at(0.05)])
    assert tr.resets == 1 and "stamps went back" in caplog.text
    assert [t.track_id for t in tr.tracks] == [2] and [o.track_id for o in out] == [2]   # ids go on counting
    assert [o.track_id for o in tr.step(FRAME_NS, None, None, [det_at(0.05)])] == [2]


def test_a_camera_that_jumps_several_degrees_between_frames_keeps_every_id():
    # Five resting objects, the camera turning 6 deg between frames about a point 0.8 m ahead
    # (every object moves 4-9 cm in the camera: beyond the gate). The detections show the
    # camera's motion: every detection continues its own track, none is born twice.
    homes = [np.array([x, y, 0.0]) for x, y in ((0.0, 0.0), (0.06, 0.0), (-0.2, 0.1), (0.2, -0.1), (0.1, 0.15))]
    centre = np.array([0.0, 0.0, 0.8])

    def truth(k, i):
        R = rot_y(6.0 * ((-1) ** k) * (k % 3))                  # back and forth, 0-12 deg
        return make_transform(R, R @ homes[i] + centre)

    tr = tracker()
    out = run(tr, [[Det(truth(k, i)) for i in range(5)] for k in range(12)])
    assert tr.next_id == 5
    for k in range(1, 12):
        assert sorted(o.track_id for o in out[k]) == [0, 1, 2, 3, 4]
        for o in out[k]:
            assert np.linalg.norm(o.T[:3, 3] - truth(k, o.track_id)[:3, 3]) < 1e-6


def test_a_detection_beside_a_drifted_track_corrects_it():
    # Beyond the gate (3 cm) but within the object's volume: the same object, not a second one.
    tr = InstanceTracker(Model(np.random.default_rng(0).uniform(-0.05, 0.05, (200, 3))), TrackerConfig(icp=False))
    run(tr, [[det_at(0.0)]] * 3)
    out = tr.step(3 * FRAME_NS, None, None, [det_at(0.04)])
    assert [o.track_id for o in out] == [0] and out[0].T[0, 3] == pytest.approx(0.04)
    assert tr.next_id == 1


def test_two_detections_of_one_object_publish_one_pose():
    # A detector that found one object twice, 1 cm apart (the object is 10 cm across): the
    # tracks' volumes overlap, one is kept.
    tr = InstanceTracker(Model(np.random.default_rng(0).uniform(-0.05, 0.05, (200, 3))),
                         TrackerConfig(icp=False, confirm_detections=1))
    out = run(tr, [[det_at(0.0), det_at(0.01)]] * 3)
    assert [len(o) for o in out] == [1, 1, 1] and len(tr.tracks) == 1


def test_the_depth_seeing_through_a_track_takes_its_evidence_away():
    # The box was taken away: the camera sees the table 4 cm behind where its top was. A
    # detection that still reports it is not published, nor is the track kept by the depth.
    depth = without_edge_depth(box_depth(0.0))
    table = np.full((240, 320), 0.80, np.float32)
    tr = box_tracker()
    for k in range(5):
        assert len(tr.step(k * FRAME_NS, depth, BOX_INTR, [box_det(0.0)])) == 1
    assert tr.step(5 * FRAME_NS, table, BOX_INTR, [box_det(0.0)]) == []
    assert tr.step(6 * FRAME_NS, table, BOX_INTR, None) == []
    # Hidden instead (something nearer covers it): no evidence either way, not published, kept.
    cover = np.full((240, 320), 0.5, np.float32)
    tr = box_tracker()
    for k in range(5):
        tr.step(k * FRAME_NS, depth, BOX_INTR, [box_det(0.0)])
    assert tr.step(5 * FRAME_NS, cover, BOX_INTR, None) == [] and [t.state for t in tr.tracks] == ["coasting"]
    assert [o.track_id for o in tr.step(6 * FRAME_NS, depth, BOX_INTR, None)] == [0]
    # ... but where the camera's motion was measured (odometry), its pose is carried exactly,
    # and being hidden by something well in front of it is evidence enough: published as coasting.
    out = tr.step(7 * FRAME_NS, cover, BOX_INTR, None, camera_motion=np.eye(4))
    assert [(o.track_id, o.state) for o in out] == [(0, "coasting")]
    # The box gone (the table where its top was): carried exactly or not, it stands in space
    # the camera sees through, which is no hiding.
    carried = tr.step(8 * FRAME_NS, table, BOX_INTR, None, camera_motion=np.eye(4))
    assert carried == [] and [t.state for t in tr.tracks] == ["coasting"]


def test_a_measured_camera_motion_carries_every_track_across_a_jump():
    # The camera turned 8 deg and moved 10 cm between two frames (an arm): the measured motion
    # (odometry) moves every track, kept or coasting, exactly; no velocity guessed from the
    # frames before. Without it the tracks stay where they were (still camera before).
    for motion in (make_transform(rot_y(8.0), [0.1, 0.0, 0.0]), None):
        tr = tracker()
        run(tr, [[det_at(0.0), det_at(0.1)]] * 3)
        before = [t.T.copy() for t in tr.tracks]
        tr.step(3 * FRAME_NS, None, None, None, camera_motion=motion)
        expected = before if motion is None else [motion @ T for T in before]
        for t, T in zip(tr.tracks, expected):
            assert np.allclose(t.T, T, atol=1e-9)


def test_a_loop_played_a_hundred_times_keeps_its_tracks_bounded():
    # 3,000 frames: a 30-frame recording of three objects played 100 times (the stamps go back
    # at every pass). Every pass ends the tracks of the one before: never more tracks than
    # objects, one reset per pass, and after the last pass the tracks are where the first
    # pass left them (nothing drifts or piles up from pass to pass).
    from multi_instance_reg.tracking import LiveConfig, LiveTracker

    model = Model(np.random.default_rng(0).uniform(-0.005, 0.005, (200, 3)))
    live = LiveTracker(model, TrackerConfig(icp=False), LiveConfig())
    most = 0
    for rep in range(100):
        for k in range(30):
            live.step(k * FRAME_NS, None, None)
            live.add_detections(k * FRAME_NS, [det_at(x + 0.001 * k) for x in (-0.1, 0.0, 0.1)])
            most = max(most, live.counts()["tracks_live"])
        if rep == 0:
            first = sorted(t.T[0, 3] for t in live._tracker.tracks)
    last = sorted(t.T[0, 3] for t in live._tracker.tracks)
    assert most == 3 and live.counts()["tracking_resets"] == 99          # at the start of every pass but the first
    assert len(last) == 3 and np.allclose(first, last)


def test_a_detection_older_than_the_kept_depth_is_moved_by_the_camera_motions_since():
    # A loaded host's first detection comes more frames late than the depth images kept to
    # carry it (catch_up_frames): a new object must still be born where it is now, moved by
    # the camera's motions measured since its frame, not where it was then.
    from multi_instance_reg.tracking import LiveConfig, LiveTracker

    step = make_transform(np.eye(3), [0.004, 0.0, 0.0])   # the box moves 4 mm a frame in the image
    for catch_up, expected in ((3, 0.036), (0, 0.0)):     # 0: never carried, fused where it was found
        live = LiveTracker(box_model(), TrackerConfig(), LiveConfig(catch_up_frames=catch_up))
        for k in range(10):
            live.step(k * FRAME_NS, box_depth(0.004 * k), BOX_INTR, camera_motion=step if k else None)
        assert live.add_detections(0, [box_det(0.0)])
        (track,) = live._tracker.tracks
        assert abs(track.T[0, 3] - expected) < 0.002, (catch_up, track.T[0, 3])
    # A step whose motion was not measured: nothing to move it by, fused where it was found.
    live = LiveTracker(box_model(), TrackerConfig(), LiveConfig(catch_up_frames=3))
    for k in range(10):
        live.step(k * FRAME_NS, box_depth(0.004 * k), BOX_INTR, camera_motion=step if k != 4 else None)
    live.add_detections(0, [box_det(0.0)])
    assert abs(live._tracker.tracks[0].T[0, 3]) < 0.002


def test_an_alignment_that_confirms_less_of_the_box_than_its_start_keeps_the_start():
    # A box touching a taller neighbour (1.5 cm higher): the first, wide pairing takes the
    # neighbour's top for the box's, and a plain ICP slides the box 9 mm towards it, confirming
    # less of it (the demo scene: a track slid 6-9 mm a frame, 5 cm in all). The tracker's ICP
    # keeps the start there, and still corrects a start that is off (alone, 8 mm too high).
    from multi_instance_reg.tracking.icp import align_projective

    icp = ProjectiveICP(box_model().points_xyz, 1000, 10, 0.03, 0.006, 1e-3, 0.03)
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    X, Y = (u - 160) / 500.0 * 0.76, (v - 120) / 500.0 * 0.76
    depth = box_depth(0.0)
    depth[(X > 0.03) & (X < 0.15) & (np.abs(Y) <= 0.05)] = 0.745
    depth = without_edge_depth(depth)
    T0 = make_transform(np.eye(3), [0.0, 0.0, 0.78])
    plain = align_projective(T0, icp.points, icp.normals, depth, BOX_INTR, icp.iterations, icp.max_distance,
                             icp.inlier_distance, icp.damping, icp.min_information, icp.centroid, icp.radius,
                             icp.noise_ref)
    kept = icp.align(T0, depth, BOX_INTR)
    assert plain.T[0, 3] > 0.005 and plain.fitness < kept.fitness - 0.1
    assert np.allclose(kept.T, T0) and kept.fitness > 0.85
    off = make_transform(np.eye(3), [0.0, 0.0, 0.772])
    fixed = icp.align(off, without_edge_depth(box_depth(0.0)), BOX_INTR)
    assert abs(fixed.T[2, 3] - 0.78) < 0.001 and fixed.fitness > 0.85
