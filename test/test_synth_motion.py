"""Camera paths and frame timing for the tracker benchmark (issue 35): the hand-held shaky pan,
the arm's jumps, other frame rates, dropped frames and a loop. Each changes what it should;
the defaults stay what they were (test_synth_tracking pins a default frame's digests)."""
import numpy as np
import pytest

from multi_instance_reg.datasets.rgbd_bag import read_rgbd_frames
from multi_instance_reg.errors import InputError
from multi_instance_reg.synthetic.scene import (
    ARM_STEP_DEG, PAN_SECONDS, SHAKE_STEP_DEG, SHAKE_STEP_M, SHAKY_ARC_DEG, START_STAMP_NS, ShakyPanPlan,
    generate_scene_bag, make_tabletop_scene)
from multi_instance_reg.tools import cli
from multi_instance_reg.transforms import invert_transform, rotation_angle_deg

SCENE = dict(object_name="snack_bar", instances=4, distractors=2)


def steps(poses):
    """Per consecutive pair of camera -> world poses: (rotation deg, translation m)."""
    rel = [invert_transform(a) @ b for a, b in zip(poses, poses[1:])]
    return (np.array([rotation_angle_deg(r[:3, :3]) for r in rel]),
            np.array([np.linalg.norm(r[:3, 3]) for r in rel]))


def test_shaky_pan_arcs_30_degrees_in_5_s_and_shakes_anew_every_frame():
    scene = make_tabletop_scene(**SCENE, frames=151, seed=4, motion="shaky_pan")
    plan = ShakyPanPlan.draw(np.random.default_rng([4, 6]))          # the motion stream of seed 4
    smooth = plan.trajectory(scene.placements, 151, shake=False)
    # The smooth arc: the viewing direction turns SHAKY_ARC_DEG about the vertical in PAN_SECONDS.
    d0, d1 = smooth[0][:3, 2], smooth[int(30 * PAN_SECONDS)][:3, 2]
    turn = np.degrees(abs(np.arctan2(d1[1], d1[0]) - np.arctan2(d0[1], d0[0])))
    assert abs(turn - SHAKY_ARC_DEG) < 0.5
    # The shake is the difference to the smooth arc, in the camera frame.
    shake = [invert_transform(s) @ p for s, p in zip(smooth, scene.camera_poses)]
    rot, trans = steps(shake)
    assert SHAKE_STEP_M[0] * 0.8 < trans.mean() < SHAKE_STEP_M[1] * 1.2
    assert SHAKE_STEP_DEG[0] * 0.8 < rot.mean() < SHAKE_STEP_DEG[1] * 1.2
    assert abs(trans.mean() - plan.step_m) < 0.2 * plan.step_m and abs(rot.mean() - plan.step_deg) < 0.2 * plan.step_deg
    # Not smooth: consecutive shake steps are anti-correlated (white noise: -0.5), where a
    # smooth wobble's would be close to +1.
    offsets = np.array([p[:3, 3] for p in shake])
    d = np.diff(offsets, axis=0)
    corr = np.mean([np.corrcoef(d[:-1, k], d[1:, k])[0, 1] for k in range(3)])
    assert corr < -0.3
    # Every frame differs from the last by a few mm (arc and shake together), never by a jump.
    rot_all, trans_all = steps(scene.camera_poses)
    assert np.all(trans_all < 0.015) and np.all(rot_all < 2.5) and np.median(trans_all) > 0.002


def test_arm_jumps_3_to_8_degrees_per_frame_in_bursts_and_holds_still_between():
    scene = make_tabletop_scene(**SCENE, frames=120, seed=2, motion="jumps")
    rot, trans = steps(scene.camera_poses)
    moving = rot > 1e-3                                  # (arccos of a trace of 3 - 1e-16: ~1e-5 deg)
    assert 0.05 < moving.mean() < 0.6                      # bursts, and holds in between
    assert np.all((rot[moving] > ARM_STEP_DEG[0] - 0.05) & (rot[moving] < ARM_STEP_DEG[1] + 0.05))
    assert np.all(trans[~moving] < 1e-9) and np.all(trans[moving] > 0.02)
    starts = np.flatnonzero(np.diff(moving.astype(int)) == 1)
    assert len(starts) >= 2                                # more than one burst in 4 s


def test_frame_rate_spaces_the_stamps_and_scales_the_motion_per_frame():
    fast = make_tabletop_scene(**SCENE, frames=31, seed=1, motion="shaky_pan")
    slow = make_tabletop_scene(**SCENE, frames=11, seed=1, motion="shaky_pan", frame_rate=10)
    stamps = np.array([slow.stamp_ns(i) for i in range(slow.num_frames)])
    assert stamps[0] == START_STAMP_NS and np.all(np.diff(stamps) == 100_000_000)
    assert slow.render_frame(1).stamp_ns == START_STAMP_NS + 100_000_000
    # Same seed, same placements; frame k at 10 Hz is where frame 3k at 30 Hz is (the smooth
    # arc: the shake is drawn per frame), so the path per frame is three times as long.
    plan = ShakyPanPlan.draw(np.random.default_rng([1, 6]))
    arc30 = plan.trajectory(fast.placements, 31, 30.0, shake=False)
    arc10 = plan.trajectory(slow.placements, 11, 10.0, shake=False)
    assert all(np.allclose(arc10[k], arc30[3 * k]) for k in range(11))
    assert slow.description()["frame_rate_hz"] == 10.0 and "frame_rate_hz" not in fast.description()
    # The accelerometer still samples at 200 Hz: 20 samples per 100 ms frame.
    offsets, accel = slow.accel_samples(5)
    assert len(offsets) == 20 and offsets[-1] == 0 and offsets[0] == -95_000_000


def test_dropped_frames_leave_gaps_in_the_stamps_and_the_truth_stays_per_frame():
    full = make_tabletop_scene(**SCENE, frames=60, seed=3, motion="shaky_pan")
    gappy = make_tabletop_scene(**SCENE, frames=60, seed=3, motion="shaky_pan", drop=0.2)
    assert gappy.num_frames == 60 - round(0.2 * 59)
    stamps = np.array([gappy.stamp_ns(i) for i in range(gappy.num_frames)])
    gaps = np.diff(stamps) / (1e9 / 30)
    assert stamps[0] == START_STAMP_NS and np.allclose(gaps, np.round(gaps), atol=0.02)
    assert np.round(gaps).max() in (2, 3, 4) and (np.round(gaps) > 1).sum() >= 3
    # A kept frame is the full path's frame at the same stamp: same camera, same truth.
    for i in (0, gappy.num_frames // 2, gappy.num_frames - 1):
        j = gappy.slot(i)
        assert full.stamp_ns(j) == gappy.stamp_ns(i)
        assert np.array_equal(full.camera_poses[j], gappy.camera_poses[i])
    a, b = full.render_frame(full.num_frames - 1), gappy.render_frame(gappy.num_frames - 1)
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.depth_mm, b.depth_mm)
    # The accelerometer keeps sampling through the gap.
    i = int(np.argmax(gaps)) + 1
    offsets, _ = gappy.accel_samples(i)
    gap_ns = stamps[i] - stamps[i - 1]
    assert -gap_ns < offsets[0] <= -gap_ns + 5_000_000 and np.all(np.diff(offsets) == 5_000_000)
    assert gappy.description()["dropped_frames"] == round(0.2 * 59)


def test_a_loop_plays_the_frames_twice_with_the_stamps_jumping_back_once(tmp_path):
    out = tmp_path / "loop"
    summary = generate_scene_bag(out, **SCENE, frames=4, seed=6, motion="jumps", loop=True)
    assert summary.frames == 8
    frames = list(read_rgbd_frames(out))
    stamps = [f.stamp_ns for f in frames]
    assert len(frames) == 8 and stamps[:4] == stamps[4:]
    assert sum(b < a for a, b in zip(stamps, stamps[1:])) == 1
    for a, b in zip(frames[:4], frames[4:]):            # the same recording, byte for byte
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m)
        assert np.array_equal(a.gt_poses, b.gt_poses)


def test_bad_timing_options_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(InputError, match="frame rate"):
        make_tabletop_scene(**SCENE, frames=2, frame_rate=0)
    with pytest.raises(InputError, match="drop"):
        make_tabletop_scene(**SCENE, frames=2, drop=0.9)
    assert cli.main(["synth", "scene", "-o", str(tmp_path / "x"), "--frames", "3", "--drop", "0.7"]) == 2
    assert "drop" in capsys.readouterr().err
    assert cli.main(["synth", "scene", "-o", str(tmp_path / "y"), "--instances", "2", "--distractors", "0",
                     "--frames", "3", "--motion", "shaky_pan", "--frame-rate", "5", "--no-imu"]) == 0
    assert "wrote 3 frames" in capsys.readouterr().out
    frames = list(read_rgbd_frames(tmp_path / "y"))
    assert [f.stamp_ns - START_STAMP_NS for f in frames] == [0, 200_000_000, 400_000_000]
