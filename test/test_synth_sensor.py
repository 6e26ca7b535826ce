"""Sensor profiles (issue 35): the "realistic" depth does what real depth cameras do (NOTES
section 15), each effect measured on plain depth maps; "d455" stays what it was."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from multi_instance_reg.errors import InputError
from multi_instance_reg.synthetic.scene import make_tabletop_scene
from multi_instance_reg.synthetic.sensor import (
    DEPTH_IMAGER_FX_PX, EDGE_SPREAD_REL, PROFILE_RANGES, SENSOR_PROFILES, STEREO_BASELINE_M, sensor_profile,
    simulate_depth)

FX = 379.05
REALISTIC = SENSOR_PROFILES["realistic"]
PLAIN = replace(REALISTIC, edge_dropout=0.0, flying=0.0, speckle=0.0, disparity_step_px=0.0)


def wall(z: float, shape=(240, 320)) -> np.ndarray:
    return np.full(shape, z, np.float32)


def test_default_profile_is_the_old_model_byte_for_byte():
    depth = wall(1.2)
    depth[60:140, 100:200] = 0.8
    for seed in (1, 2):
        assert np.array_equal(simulate_depth(depth, FX, seed), simulate_depth(depth, FX, seed, 0.0, SENSOR_PROFILES["d455"]))


def test_isolated_dropouts_are_1_5_percent_of_a_flat_wall():
    depth = wall(1.5, (480, 640))
    base = simulate_depth(depth, FX, 7, profile=PLAIN) == 0          # the dropout blobs alone
    speckled = simulate_depth(depth, FX, 7, profile=replace(PLAIN, speckle=REALISTIC.speckle)) == 0
    extra = speckled & ~base
    assert 0.012 < extra.sum() / (~base).sum() < 0.018
    # Single pixels: most have no other new dropout among their 8 neighbours.
    n, _, stats, _ = cv2.connectedComponentsWithStats(extra.astype(np.uint8), connectivity=8)
    sizes = stats[1:, cv2.CC_STAT_AREA]
    assert (sizes == 1).mean() > 0.85


def test_noise_grows_as_0_004_z_squared_plus_half_a_millimetre():
    for z in (1.0, 2.0):
        mm = simulate_depth(wall(z), FX, 3, profile=PLAIN).astype(np.float64)
        valid = mm[mm > 0] / 1000.0
        expected = 0.004 * z * z + 0.0005
        assert abs(valid.std() - expected) < 0.1 * expected and abs(valid.mean() - z) < 0.002


def test_depth_comes_in_disparity_steps_of_a_few_millimetres():
    ramp = np.tile(np.linspace(1.0, 2.0, 640, dtype=np.float32), (40, 1))
    quiet = replace(REALISTIC, noise_per_m=0.0, noise_floor_m=0.0, edge_dropout=1.0, speckle=0.0)
    values = np.unique(simulate_depth(ramp, FX, 5, profile=quiet))
    values = values[values > 0].astype(np.float64)
    fb = DEPTH_IMAGER_FX_PX * STEREO_BASELINE_M
    for z in (1.0, 1.5, 2.0):
        near = values[np.abs(values / 1000.0 - z) < 0.05]
        step = np.diff(near).mean()                                    # (rounded to mm each)
        assert abs(step - 1000 * z * z / fb * REALISTIC.disparity_step_px) < 0.3
    assert 1.2 < np.diff(values[values < 1100]).mean() < 1.7              # 1.4 mm at 1 m
    assert 4.5 < np.diff(values[values > 1900]).mean() < 6.5              # 5.5 mm at 2 m


def test_depth_edges_lose_70_percent_and_the_rest_fly_between_the_surfaces():
    depth = wall(2.0, (480, 640))
    depth[120:360, 160:480] = 1.0
    z_near, z_far = cv2.erode(depth, np.ones((3, 3))), cv2.dilate(depth, np.ones((3, 3)))
    edge = z_far - z_near > EDGE_SPREAD_REL * depth + 0.004
    other = simulate_depth(depth, FX, 11, profile=replace(PLAIN, noise_per_m=0.0, noise_floor_m=0.0)) == 0
    judged = edge & ~other                                   # not in the shadow or a blob
    assert judged.sum() > 800
    mm = simulate_depth(depth, FX, 11, profile=replace(REALISTIC, speckle=0.0, disparity_step_px=0.0))
    assert abs((mm[judged] == 0).mean() - 0.7) < 0.05
    assert np.all(mm[edge & other] == 0)
    kept = mm[judged & (mm > 0)] / 1000.0
    between = (kept > 1.05) & (kept < 1.95)
    assert 0.3 < between.mean() < 0.6                        # flying pixels: half of the kept ones
    off_edge = mm[~edge & (mm > 0)] / 1000.0
    assert np.all((off_edge < 1.1) | (off_edge > 1.8))       # and none away from the edges
    # The d455 profile drops every edge pixel.
    assert np.all(simulate_depth(depth, FX, 11)[edge] == 0)


def test_randomise_draws_each_figure_per_seed_within_its_range():
    a, b, a2 = (sensor_profile("realistic", s, randomise=True) for s in (1, 2, 1))
    assert a == a2 and a != b and a.name == "realistic-random"
    for profile in (a, b):
        for key, (lo, hi) in PROFILE_RANGES.items():
            assert lo <= getattr(profile, key) <= hi
    with pytest.raises(InputError, match="unknown sensor profile 'kinect'"):
        sensor_profile("kinect")


def test_a_scene_with_the_realistic_sensor_changes_only_its_depth():
    kw = dict(object_name="snack_bar", instances=3, distractors=1, frames=2, seed=4)
    plain, real = make_tabletop_scene(**kw), make_tabletop_scene(**kw, sensor="realistic")
    f, g = plain.render_frame(1), real.render_frame(1)
    assert np.array_equal(f.rgb, g.rgb) and np.array_equal(f.poses, g.poses)
    assert not np.array_equal(f.depth_mm, g.depth_mm)
    assert (g.depth_mm > 0).sum() > 0.8 * (f.depth_mm > 0).sum()
    assert real.description()["sensor"]["name"] == "realistic" and "sensor" not in plain.description()


def test_the_cli_records_a_drawn_profile_in_the_bag(tmp_path, capsys):
    from multi_instance_reg.datasets.rgbd_bag import read_object_description
    from multi_instance_reg.tools import cli

    out = tmp_path / "pallet"
    assert cli.main(["synth", "untextured", "--preset", "pallet", "-o", str(out), "--instances", "3", "--frames", "1",
                     "--seed", "8", "--sensor", "realistic", "--randomise", "--no-imu"]) == 0
    assert "wrote 1 frames" in capsys.readouterr().out
    recorded = read_object_description(out)["sensor"]
    assert recorded == sensor_profile("realistic", 8, randomise=True).description()
    assert recorded["name"] == "realistic-random"
