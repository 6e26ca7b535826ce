"""Guided matching (frontends/sift/guided.py): known answers on a box whose texture repeats."""
import numpy as np
from scipy.spatial.transform import Rotation

from multi_instance_reg.frontends.sift.guided import GuidedMatcher, guide_instances
from multi_instance_reg.frontends.sift.matching import DescriptorMatcher, prepare_descriptors
from multi_instance_reg.transforms import apply_transform, make_transform, rigid_fit, rotation_angle_deg

EXTENT = np.array([0.16, 0.10, 0.04])
INLIER_THRESH, RADIUS, MAX_DISTANCE = 0.015, 0.006, 0.6


def repeated_texture_box(rng, unique=6, repeated=30):
    """Model keypoints on the top face of a box: ``unique`` with a descriptor of their own and
    ``repeated`` pairs of points 4-8 cm apart sharing one descriptor (the same print twice)."""
    def top(n):
        return np.c_[rng.uniform(-0.075, 0.075, n), rng.uniform(-0.045, 0.045, n), np.full(n, 0.02)]
    xyz = [top(unique)]
    raw = [rng.random((unique, 128)) ** 4]
    first = top(repeated)
    first[:, 0] = rng.uniform(-0.075, 0.0, repeated)
    second = first + np.c_[rng.uniform(0.04, 0.075, repeated), np.zeros((repeated, 2))]
    desc = rng.random((repeated, 128)) ** 4
    xyz += [first, second]
    raw += [desc, desc]
    return np.concatenate(xyz), np.concatenate(raw).astype(np.float32)


def observed(rng, model_xyz, model_raw, T, noise=0.0015, desc_noise=0.01):
    """The model's keypoints at pose T, with position and descriptor noise."""
    xyz = apply_transform(T, model_xyz) + rng.normal(0.0, noise, model_xyz.shape)
    raw = np.maximum(model_raw + rng.normal(0.0, desc_noise, model_raw.shape), 0.0).astype(np.float32)
    return xyz, prepare_descriptors(raw)


def pose_error(T, T_true):
    return rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3]), float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]))


def test_an_instance_thinned_by_the_ratio_test_regains_its_inliers_and_a_better_pose():
    errors_before, errors_after, gained = [], [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        model_xyz, model_raw = repeated_texture_box(rng)
        model_desc = prepare_descriptors(model_raw)
        T_true = make_transform(Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix(), np.array([0.05, -0.02, 0.7]))
        scene_xyz, scene_desc = observed(rng, model_xyz, model_raw, T_true)
        # The global ratio test keeps only the unique keypoints: each repeated one has an equal
        # descriptor at another physical point.
        scene_idx, model_idx, _ = DescriptorMatcher(model_desc, model_xyz, 0.8, 0.01).match(scene_desc)
        assert set(model_idx) <= set(range(6)) and len(scene_idx) >= 5
        T0 = rigid_fit(model_xyz[model_idx], scene_xyz[scene_idx])
        matcher = GuidedMatcher(model_xyz, model_desc, np.zeros(3), EXTENT, RADIUS, MAX_DISTANCE)
        g = guide_instances(matcher, [T0], [scene_idx], [model_idx], scene_xyz, scene_desc, INLIER_THRESH, RADIUS)
        # Each repeated keypoint is paired with its own physical point, not its twin.
        pairs = dict(zip(g.scene[0], g.model[0]))
        assert all(pairs[s] == s for s in pairs)
        gained.append(len(g.scene[0]) / len(scene_idx))
        errors_before.append(pose_error(T0, T_true))
        errors_after.append(pose_error(g.transforms[0], T_true))
    before, after = np.median(errors_before, axis=0), np.median(errors_after, axis=0)
    assert np.median(gained) > 5                 # 6 matches -> most of the 66 keypoints
    assert after[0] < 0.5 * before[0] and after[1] < 0.5 * before[1]


def test_keypoints_with_other_texture_or_held_by_another_instance_are_not_taken():
    rng = np.random.default_rng(1)
    model_xyz, model_raw = repeated_texture_box(rng)
    model_desc = prepare_descriptors(model_raw)
    T = make_transform(np.eye(3), np.array([0.0, 0.0, 0.7]))
    scene_xyz, scene_desc = observed(rng, model_xyz, model_raw, T)
    # Something else lies on the box's keypoints' places: descriptors of other texture.
    other = prepare_descriptors((rng.random((len(model_xyz), 128)) ** 4).astype(np.float32))
    matcher = GuidedMatcher(model_xyz, model_desc, np.zeros(3), EXTENT, RADIUS, MAX_DISTANCE)
    own = np.arange(6)
    g = guide_instances(matcher, [T], [own], [own], scene_xyz, other, INLIER_THRESH, RADIUS)
    assert set(g.scene[0]) == set(own)
    # A stronger instance (kept as it is: more than max_inliers) holds keypoints 6-35 as its
    # inliers: the weaker one cannot take them, only the others.
    g = guide_instances(matcher, [T, T], [np.arange(6, 36), own], [np.arange(6, 36), own], scene_xyz, scene_desc,
                        INLIER_THRESH, RADIUS, max_inliers=29)
    assert np.array_equal(g.scene[0], np.arange(6, 36))
    assert set(g.scene[1]) == set(own) | set(range(36, 66))
