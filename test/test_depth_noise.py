"""The depth noise measured from a frame: known answers on generated depth images and on the
synthetic sensor's profiles."""
import numpy as np
import pytest

from multi_instance_reg.rgbd.depth_noise import measure_depth_noise


def tilted_scene(k, rng, h=480, w=640, steps=True):
    """A tilted plane 0.8-1.6 m away, with boxes standing out of it (depth steps of 5-20 cm),
    plus noise sigma = k z^2."""
    v, u = np.mgrid[0:h, 0:w]
    z = 0.8 + 0.8 * v / h + 0.1 * u / w
    if steps:
        for _ in range(12):
            r, c = rng.integers(0, h - 60), rng.integers(0, w - 80)
            z[r:r + 60, c:c + 80] -= rng.uniform(0.05, 0.2)
    return z + rng.standard_normal(z.shape) * k * z * z


@pytest.mark.parametrize("k", [0.001, 0.002, 0.004, 0.008])
def test_measures_the_noise_of_a_scene_with_edges(k):
    rng = np.random.default_rng(int(k * 1e4))
    measured = measure_depth_noise(tilted_scene(k, rng))
    assert measured == pytest.approx(k, rel=0.1)


def test_holes_and_dropouts_do_not_bias_it():
    rng = np.random.default_rng(1)
    depth = tilted_scene(0.003, rng)
    depth[rng.random(depth.shape) < 0.015] = 0.0          # isolated dropouts
    depth[100:300, 200:400] = np.nan                       # a hole
    assert measure_depth_noise(depth) == pytest.approx(0.003, rel=0.1)


def test_no_answer_without_enough_depth():
    depth = np.zeros((480, 640))
    assert measure_depth_noise(depth) is None
    depth[:20, :20] = 1.0
    assert measure_depth_noise(depth) is None


def test_tracks_the_synthetic_sensor_profiles():
    # The generator's depth noise (rendered scene, disparity quantisation, dropouts, flying
    # pixels): the measure follows the profile's k where the noise floor is small against k z^2.
    from multi_instance_reg.synthetic.untextured import make_untextured_scene

    for sensor, k in (("d455", 0.0018), ("realistic", 0.004)):
        scene = make_untextured_scene("pallet", frames=1, seed=2)
        scene.set_sensor(sensor, False)
        measured = measure_depth_noise(scene.render_frame(0).depth_mm / 1000.0)
        assert measured == pytest.approx(k, rel=0.15), sensor
