"""Synthetic scenes for tracking: a static camera, a slow pan along which instances enter and
leave the view, and an arm passing in front; the default scene unchanged by all of that."""
import hashlib
import json

import numpy as np
import pytest

from multi_instance_reg.datasets import bag_writer as bw
from multi_instance_reg.synthetic.scene import (
    LABEL_DISTRACTOR, MIN_CAMERA_CLEARANCE_M, PAN_SECONDS, _clearance, generate_scene_bag, make_tabletop_scene)
from multi_instance_reg.tools import cli

from test_synth_bag import read_bag

TRACKING = dict(object_name="snack_bar", instances=8, distractors=3)
ENTERED = 0.25           # visibility from which an instance counts as in view


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def test_default_scene_is_what_it_was_before_motion_and_occluder():
    # Digests recorded from the code before motion/occluder existed (commit 8264224): other
    # benchmarks compare against bags made with the defaults. The pixels are exact; poses and
    # camera matrices are rounded to 1e-6 because their last bits differ between CPUs (BLAS
    # kernels), which made the exact digests fail on an AMD EPYC host with unchanged code.
    kw = dict(object_name="snack_bar", instances=4, distractors=2, frames=6, seed=5)
    for scene in (make_tabletop_scene(**kw), make_tabletop_scene(**kw, motion="sweep", occluder=False)):
        f = scene.render_frame(5)
        assert digest(f.rgb, f.depth_mm) == "a1dc8a060d31910d"
        assert digest(np.round(f.poses, 6), np.round(f.visibility, 4), f.instance_mask) == "925332ddf550a7f0"
        assert digest(np.round(f.T_world_camera, 6)) == "251f2c25fe5dccca"
        assert "motion" not in scene.description() and "occluder" not in scene.description()


def test_static_camera_does_not_move_but_the_noise_changes():
    scene = make_tabletop_scene(**TRACKING, frames=20, seed=3, motion="static")
    assert all(np.array_equal(P, scene.camera_poses[0]) for P in scene.camera_poses)
    assert _clearance(scene.camera_poses[0][:3, 3], scene.placements) >= MIN_CAMERA_CLEARANCE_M
    a, b = scene.render_frame(0), scene.render_frame(19)
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.visibility, b.visibility)
    assert not np.array_equal(a.rgb, b.rgb) and not np.array_equal(a.depth_mm, b.depth_mm)
    # Most instances in view, 0.5-1.0 m away (what the static scene is for: pose jitter).
    in_view = a.visibility >= 0.5
    assert in_view.sum() >= 5
    assert np.all((np.linalg.norm(a.poses[in_view, :3, 3], axis=1) > 0.45)
                  & (np.linalg.norm(a.poses[in_view, :3, 3], axis=1) < 1.1))
    assert scene.description()["motion"] == "static"
    # Same objects where the sweep puts them (same seed): only the camera differs.
    sweep = make_tabletop_scene(**TRACKING, frames=20, seed=3)
    assert all(np.array_equal(p.pose, q.pose) for p, q in zip(scene.placements, sweep.placements))


def test_pan_brings_instances_into_view_and_takes_others_out():
    frames = int(PAN_SECONDS * 30)
    scene = make_tabletop_scene(**TRACKING, frames=frames, seed=1, motion="pan")
    eyes = np.array([P[:3, 3] for P in scene.camera_poses])
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    assert steps.max() < 0.01                                   # slow: under 0.3 m/s
    assert 0.4 < abs(eyes[-1, 0] - eyes[0, 0]) < 0.8            # along the table (world x)
    assert min(_clearance(e, scene.placements) for e in eyes) >= MIN_CAMERA_CLEARANCE_M
    idx = list(range(0, frames, 10)) + [frames - 1]
    vis = np.array([scene.render_frame(i).visibility for i in idx]) >= ENTERED
    entered = [k for k in range(vis.shape[1]) if not vis[0, k] and vis[-1, k]]
    left = [k for k in range(vis.shape[1]) if vis[0, k] and not vis[-1, k]]
    assert entered and left, (entered, left)


def test_occluder_hides_instances_while_it_passes_and_is_not_ground_truth():
    scene = make_tabletop_scene(**TRACKING, frames=30, seed=2, motion="static", occluder=True)
    first, last = scene.occluder.frames
    assert 8 <= first < 15 < last <= 21
    frames = [scene.render_frame(i) for i in range(30)]
    vis = np.array([f.visibility for f in frames])
    assert all(len(f.poses) == 8 for f in frames)
    # The camera stands still: outside the passage the visibility is constant.
    assert np.array_equal(vis[0], vis[first - 1]) and np.array_equal(vis[0], vis[-1])
    during = vis[first:last + 1]
    hidden = [k for k in range(8) if vis[0, k] >= 0.5 and during[:, k].min() < 0.2 * vis[0, k]]
    assert len(hidden) >= 2, vis.T
    for k in hidden:   # hidden for a while, not all the passage: it moves across
        assert 1 <= np.sum(during[:, k] < 0.5 * vis[0, k]) < len(during) - 1
    # What hides them is drawn in front (nearer) and labelled as a distractor.
    k = hidden[0]
    i = first + int(np.argmin(during[:, k]))
    was = frames[0].instance_mask == k
    covered = was & (frames[i].instance_mask == LABEL_DISTRACTOR)
    assert covered.sum() > 0.5 * was.sum()
    assert np.all(frames[i].depth_true_m[covered] < frames[0].depth_true_m[covered] - 0.05)
    desc = scene.description()
    assert desc["occluder"]["frames"] == [first, last] and desc["occluder"]["name"] not in desc["distractors"]


def test_tracking_bags_repeat_and_the_cli_takes_the_options(tmp_path, capsys):
    kw = dict(TRACKING, frames=4, seed=7, motion="pan", occluder=True)
    generate_scene_bag(tmp_path / "a", **kw)
    generate_scene_bag(tmp_path / "b", **kw)
    a, b = read_bag(tmp_path / "a"), read_bag(tmp_path / "b")
    for topic in a:
        assert [(t, raw) for t, raw, _ in a[topic]] == [(t, raw) for t, raw, _ in b[topic]], topic
    desc = json.loads(a[bw.TOPIC_GT_OBJECT][0][2].data)
    assert desc["motion"] == "pan" and desc["occluder"]["shape"] == "cylinder"

    out = tmp_path / "cli"
    assert cli.main(["synth", "scene", "-o", str(out), "--instances", "2", "--distractors", "0", "--frames", "3",
                     "--motion", "static", "--occluder"]) == 0
    assert "wrote 3 frames" in capsys.readouterr().out
    desc = json.loads(read_bag(out)[bw.TOPIC_GT_OBJECT][0][2].data)
    assert desc["motion"] == "static" and desc["occluder"]["frames"] == [1, 2]
    with pytest.raises(SystemExit) as exc:
        cli.main(["synth", "scene", "-o", str(tmp_path / "x"), "--motion", "orbit"])
    assert exc.value.code == 2 and "invalid choice: 'orbit'" in capsys.readouterr().err
    assert cli.main(["synth", "scene", "-o", str(tmp_path / "y"), "--frames", "2", "--occluder"]) == 2
    assert capsys.readouterr().err.strip() == "mireg synth: error: an occluder needs at least 3 frames, got 2"
