"""Layouts and backgrounds (issue 35): boxes packed flush, a pile in a bin, a room behind the
table. Each is checked on its geometry and on what a frame shows; the defaults are pinned by
test_synth_tracking's digests."""
import cv2
import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.synthetic.scene import (
    BIN_PANEL_M, CLUTTER_DISTANCE_M, FLUSH_GAP_M, _obb_overlap, _top_z, make_tabletop_scene)
from multi_instance_reg.synthetic.preview import colour_and_depth, colourise_depth, write_preview
from multi_instance_reg.tools import cli


def test_flush_boxes_touch_face_to_face_with_their_tops_in_one_plane():
    scene = make_tabletop_scene("snack_box", instances=6, distractors=1, frames=2, seed=3, layout="flush",
                                motion="overhead")
    boxes = scene.instances
    assert all(np.allclose(b.pose[:3, :3], boxes[0].pose[:3, :3]) for b in boxes)      # all turned the same way
    assert boxes[0].pose[2, 2] > 0.999 or boxes[0].pose[2, 2] < -0.999                 # lying on their largest face
    tops = [_top_z(b.pose, b.spec.half_extents) for b in boxes]
    assert np.ptp(tops) < 1e-9
    half = boxes[0].spec.half_extents
    R = boxes[0].pose[:3, :3]
    for i, b in enumerate(boxes):
        gaps = []
        for j, c in enumerate(boxes):
            if i != j:
                assert not _obb_overlap(b.pose, half, c.pose, half, margin=0.0)
                d = np.abs(R.T @ (c.pose[:3, 3] - b.pose[:3, 3]))          # in the boxes' own axes
                axis = int(np.argmax(d / half))
                if np.all(np.delete(d, axis) < 1e-9):                      # side by side along that axis
                    gaps.append(d[axis] - 2 * half[axis])
        assert gaps and 0 < min(gaps) <= FLUSH_GAP_M                       # each touches a neighbour
    # From above, two boxes side by side meet without a step in depth: only the colour has the outline.
    frame = scene.render_frame(0)
    mask, z = frame.instance_mask, frame.depth_true_m
    left, right = mask[:, :-1], mask[:, 1:]
    seam = (left >= 0) & (right >= 0) & (left != right)
    assert seam.sum() > 20
    assert np.median(np.abs(z[:, :-1] - z[:, 1:])[seam]) < 0.002


def test_a_bin_holds_a_pile_at_random_orientations_each_resting_on_something():
    scene = make_tabletop_scene("can", instances=8, distractors=2, frames=2, seed=5, layout="bin", motion="overhead")
    panels = [p for p in scene.placements if p.arrangement == "fixture"]
    objects = [p for p in scene.placements if p.arrangement != "fixture"]
    assert len(panels) == 5 and all(p.label == -1 for p in panels) and len(objects) == 10
    inside = np.array([max(p.pose[0, 3] for p in panels), max(p.pose[1, 3] for p in panels)]) - BIN_PANEL_M / 2
    assert sum(p.arrangement == "pile" for p in objects) >= 9
    tilts = []
    for k, p in enumerate(objects):
        half = p.spec.half_extents
        reach = np.abs(p.pose[:3, :3]) @ half
        if p.arrangement == "pile":
            assert np.all(np.abs(p.pose[:2, 3]) + reach[:2] <= inside + 1e-6)       # inside the walls
        assert p.pose[2, 3] - reach[2] >= BIN_PANEL_M - 1e-3                      # above the floor panel
        others = [q for q in scene.placements if q is not p]
        assert not any(_obb_overlap(p.pose, half, q.pose, q.spec.half_extents, margin=0.0) for q in others)
        lowered = p.pose.copy()
        lowered[2, 3] -= 0.002
        assert any(_obb_overlap(lowered, half, q.pose, q.spec.half_extents, margin=0.0) for q in others), k
        tilts.append(np.degrees(np.arccos(min(1.0, abs(p.pose[2, 2])))))
    assert np.ptp(tilts) > 30                                                      # not all standing the same way
    frame = scene.render_frame(1)
    assert (frame.visibility > 0.5).sum() >= 4 and (frame.instance_mask == -1).any()
    assert scene.description()["layout"] == "bin" and "bin_panel" not in scene.description()["distractors"]


def test_clutter_puts_a_room_2_to_3_m_behind_the_table_in_view(tmp_path):
    kw = dict(object_name="snack_box", instances=4, distractors=2, frames=1, seed=2)
    plain, room = make_tabletop_scene(**kw), make_tabletop_scene(**kw, background="clutter")
    assert [p.pose.tolist() for p in plain.placements] == [p.pose.tolist() for p in room.placements]
    a, b = plain.render_frame(0), room.render_frame(0)
    assert a.depth_true_m.max() < 1.6                                              # the wall right behind
    far = b.depth_true_m > 1.0 + CLUTTER_DISTANCE_M[0] - 0.5
    assert far.mean() > 0.01 and b.depth_true_m.max() < 6.0                        # the room, in range
    assert (b.depth_mm[far] > 0).mean() > 0.8
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.visibility, b.visibility)
    assert room.description()["background"] == "clutter" and "background" not in plain.description()
    # Its preview colours the room's depth (up to 4 m) instead of clipping it at 2 m.
    depth_png = cv2.imread(str(write_preview(tmp_path, b, room)[1]))
    assert depth_png.shape == (480, 640, 3)
    assert np.array_equal(depth_png, colourise_depth(b.depth_mm, far_mm=4000.0))
    assert np.array_equal(colour_and_depth(b)[:, 640:], colourise_depth(b.depth_mm, far_mm=3500.0))


def test_bad_layouts_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(InputError, match="layout flush packs boxes"):
        make_tabletop_scene("can", instances=2, frames=1, layout="flush")
    with pytest.raises(InputError, match="layout must be one of"):
        make_tabletop_scene("can", instances=2, frames=1, layout="shelf")
    with pytest.raises(InputError, match="needs layout table"):
        make_tabletop_scene("can", instances=2, frames=1, layout="bin", motion="pan")
    assert cli.main(["synth", "scene", "-o", str(tmp_path / "x"), "--object", "can", "--layout", "flush"]) == 2
    assert "packs boxes" in capsys.readouterr().err
