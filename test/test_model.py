"""The stored object model: building from views, the file format, and broken files."""
import subprocess
import sys

import cv2
import numpy as np
import pytest
from planar_scene import INTRINSICS, card_pose, render_planes, table
from skimage import data

from multi_instance_reg.errors import InputError
from multi_instance_reg.models.model import (MODEL_SCHEMA_VERSION, BuildSettings, CaptureView, ObjectModel, build_model,
                                           load_model, object_mask, save_model)
from multi_instance_reg.transforms import apply_transform, invert_transform

CARD = (0.14, 0.14)   # metres


def card_on_table(T_card, seed=0):
    """A textured card 10 cm in front of a weakly textured table plane."""
    rgb, depth = table(np.random.default_rng(seed), z=T_card[2, 3] + 0.1)
    return render_planes(data.astronaut(), CARD, [T_card], rgb, depth)


@pytest.fixture(scope="module")
def card_model():
    views = []
    for k, (ry, rz) in enumerate([(0, 0), (-15, 10), (15, -10)]):
        T = card_pose(ry=ry, rz=rz, t=(0.02, -0.01, 0.55))
        rgb, depth = card_on_table(T, seed=k)
        views.append(CaptureView(rgb, depth, INTRINSICS, T))
    return build_model(views, BuildSettings(), name="card"), views


def test_model_isolates_the_object_and_lands_in_its_frame(card_model):
    model, views = card_model
    assert model.num_keypoints > 100
    assert model.T_object_model is not None
    # Keypoints in the object frame lie on the card: z ~ 0, inside its rectangle.
    kp_obj = apply_transform(model.T_object_model, model.keypoints_xyz.astype(np.float64))
    assert np.percentile(np.abs(kp_obj[:, 2]), 95) < 0.002
    assert np.all(np.abs(kp_obj[:, :2]) < np.array(CARD) / 2 + 0.01)
    # T_capture_model places the model in the first view's optical frame.
    kp_cap = apply_transform(model.T_capture_model, model.keypoints_xyz.astype(np.float64))
    kp_obj0 = apply_transform(invert_transform(views[0].T_camera_object), kp_cap)
    np.testing.assert_allclose(kp_obj0, kp_obj, atol=1e-6)
    # The model frame is centred on the object; the table is gone from the dense cloud.
    assert np.linalg.norm(model.points_xyz.mean(axis=0)) < 0.02
    assert np.all(model.extent < 0.2) and model.extent[:2].min() > 0.1


def test_object_mask_removes_the_table():
    T = card_pose(t=(0.0, 0.0, 0.6))
    rgb, depth = card_on_table(T)
    mask, plane = object_mask(CaptureView(rgb, depth, INTRINSICS), BuildSettings())
    card_pixels = np.abs(depth - 0.6) < 0.01
    assert plane is not None
    assert (mask & card_pixels).sum() > 0.95 * card_pixels.sum()
    assert (mask & ~card_pixels).sum() < 0.02 * mask.sum()


def test_model_round_trip(tmp_path, card_model):
    model, _ = card_model
    path = save_model(model, tmp_path / "card.npz")
    back = load_model(path)
    for key in ("keypoints_xyz", "descriptors", "points_xyz", "extent", "T_capture_model", "T_object_model"):
        np.testing.assert_array_equal(getattr(back, key), getattr(model, key))
    assert back.name == "card"
    with np.load(path, allow_pickle=False) as npz:
        assert int(npz["schema_version"]) == MODEL_SCHEMA_VERSION
        assert npz["descriptors"].dtype == np.float32 and npz["descriptors"].shape[1] == 128


def _arrays(model):
    return {"schema_version": np.array(MODEL_SCHEMA_VERSION), "keypoints_xyz": model.keypoints_xyz,
            "descriptors": model.descriptors, "points_xyz": model.points_xyz, "extent": model.extent,
            "T_capture_model": model.T_capture_model}


@pytest.mark.parametrize("breakage, message", [
    (lambda a: a.pop("descriptors"), "lacks descriptors"),
    (lambda a: a.update(schema_version=np.array(99)), "schema_version"),
    (lambda a: a.update(extent=np.zeros(4)), "extent has shape"),
    (lambda a: a.update(descriptors=a["descriptors"][:-1]), "descriptors"),
    (lambda a: a.update(keypoints_xyz=np.zeros((0, 3), np.float32), descriptors=np.zeros((0, 128), np.float32)),
     "0 keypoints"),
    (lambda a: a.update(T_capture_model=np.full((4, 4), np.nan)), "finite"),
])
def test_broken_model_files_are_refused(tmp_path, card_model, breakage, message):
    arrays = _arrays(card_model[0])
    breakage(arrays)
    path = tmp_path / "broken.npz"
    np.savez(path, **arrays)
    with pytest.raises(InputError, match=message):
        load_model(path)


def test_not_a_model_file_is_refused(tmp_path, card_model):
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(InputError, match="not a readable .npz"):
        load_model(junk)
    with pytest.raises(InputError, match="does not exist"):
        load_model(tmp_path / "missing.npz")
    pickled = tmp_path / "pickled.npz"
    arrays = _arrays(card_model[0])
    arrays["keypoints_xyz"] = np.array([object()], dtype=object)
    np.savez(pickled, **arrays)
    with pytest.raises(InputError, match="not a valid model"):
        load_model(pickled)


def test_all_zero_depth_gives_a_clear_error():
    rgb, depth = card_on_table(card_pose())
    with pytest.raises(InputError, match="no valid depth"):
        build_model([CaptureView(rgb, np.zeros_like(depth), INTRINSICS)])


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", *args],
                          capture_output=True, text=True, timeout=120)


def test_build_model_cli_from_pngs(tmp_path):
    rgb, depth = card_on_table(card_pose(t=(0.0, 0.0, 0.6)))
    cv2.imwrite(str(tmp_path / "c.png"), rgb[:, :, ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), np.round(depth * 1000).astype(np.uint16))
    K = INTRINSICS.K
    intr = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    out = tmp_path / "m.npz"
    res = _cli("build-model", "--rgb", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d.png"),
               "--intrinsics", intr, "--roi", "150,70,340,340", "-o", str(out))
    assert res.returncode == 0, res.stderr
    model = load_model(out)
    assert model.num_keypoints > 50 and model.T_object_model is None
    # Colour and depth of different sizes: one line, exit 2.
    cv2.imwrite(str(tmp_path / "d_small.png"), np.round(depth[:240, :320] * 1000).astype(np.uint16))
    res = _cli("build-model", "--rgb", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d_small.png"),
               "--intrinsics", intr, "-o", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "320x240 but colour is 640x480" in res.stderr
    res = _cli("build-model", "--rgb", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d.png"),
               "--intrinsics", "1,2,3", "-o", str(tmp_path / "x.npz"))
    assert res.returncode == 2 and "--intrinsics must be fx,fy,cx,cy" in res.stderr
