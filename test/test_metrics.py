import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from multi_instance_reg.metrics import evaluate_scene, summarize
from multi_instance_reg.transforms import make_transform


def T_at(x, angle_deg=0.0):
    return make_transform(Rotation.from_euler("z", angle_deg, degrees=True).as_matrix(), [x, 0, 0])


def test_hungarian_matching_rre_rte_and_hits():
    gt = np.stack([T_at(0), T_at(5), T_at(10)])
    est = np.stack([T_at(10.1), T_at(0, 30), T_at(5.0, 5)])  # order shuffled; one bad rotation
    s = evaluate_scene(gt, est, max_rre_deg=20, max_rte=0.5)
    assert sorted(s.pairs) == [(0, 1), (1, 2), (2, 0)]
    by_gt = dict(zip([g for g, _ in s.pairs], zip(s.rre_deg, s.rte)))
    assert by_gt[0][0] == pytest.approx(30) and by_gt[2][1] == pytest.approx(0.1)
    assert s.hits == 2 and s.recall == pytest.approx(2 / 3) and s.precision == pytest.approx(2 / 3)


def test_empty_cases():
    assert evaluate_scene(np.zeros((0, 4, 4)), np.zeros((0, 4, 4))).f1 == 1.0
    s = evaluate_scene(np.stack([T_at(0)]), np.zeros((0, 4, 4)))
    assert (s.recall, s.precision, s.f1) == (0.0, 0.0, 0.0)
    s = evaluate_scene(np.zeros((0, 4, 4)), np.stack([T_at(0)]))
    assert s.precision == 0.0 and s.f1 == 0.0


def test_mhf1_is_mean_of_scene_f1_and_mf_is_f1_of_means():
    perfect = evaluate_scene(np.stack([T_at(0)]), np.stack([T_at(0)]))
    half = evaluate_scene(np.stack([T_at(0), T_at(5)]), np.stack([T_at(0), T_at(50), T_at(80), T_at(90)]))
    m = summarize([perfect, half])
    assert m["MHR"] == pytest.approx((1 + 0.5) / 2)
    assert m["MHP"] == pytest.approx((1 + 0.25) / 2)
    f1_half = 2 * 0.5 * 0.25 / 0.75
    assert m["MHF1"] == pytest.approx((1 + f1_half) / 2)
    assert m["MF"] == pytest.approx(2 * m["MHR"] * m["MHP"] / (m["MHR"] + m["MHP"]))
    assert m["median_rte"] == pytest.approx(0.0)
