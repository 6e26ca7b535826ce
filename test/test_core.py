"""ECC core: each stage on small cases with known answers, properties, and bad inputs."""
import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from multi_instance_reg.core import ECC, ECCConfig
from multi_instance_reg.core.clustering import cluster_compatibility_vectors
from multi_instance_reg.core.compatibility import compatibility_matrix
from multi_instance_reg.core.refinement import fit_transforms, merge_duplicates, residuals
from multi_instance_reg.errors import InputError
from multi_instance_reg.metrics import evaluate_scene
from multi_instance_reg.synthetic.correspondences import make_band, make_sized_scene
from multi_instance_reg.transforms import make_transform, rigid_fit


def random_T(rng, scale=5.0):
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-scale, scale, 3))


def two_instance_scene(rng, n_per=60, n_out=40):
    """Two rigid copies of one random cloud plus random outliers (known ground truth)."""
    model = rng.uniform(-1, 1, (n_per, 3))
    Ts = [random_T(rng), random_T(rng)]
    src = [model, model]
    tgt = [model @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.005, (n_per, 3)) for T in Ts]
    src.append(rng.uniform(-1, 1, (n_out, 3)))
    tgt.append(rng.uniform(-6, 6, (n_out, 3)))
    truth = np.concatenate([np.zeros(n_per, int), np.ones(n_per, int), -np.ones(n_out, int)])
    return np.concatenate(src), np.concatenate(tgt), np.stack(Ts), truth


def test_compatibility_matrix_known_values():
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 3, 0.0]])
    tgt = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0.0]])
    G = compatibility_matrix(src, tgt)
    assert np.allclose(np.diag(G), 1)
    assert G[0, 1] == pytest.approx(0.25)          # d = 1, d' = 2: s = 0.5
    assert G[0, 2] == pytest.approx(1.0)           # distance kept
    assert np.allclose(G, G.T)
    # The spatial weight zeroes pairs whose mean distance is beyond sigma.
    Gw = compatibility_matrix(src, tgt, spatial_sigma=2.0)
    assert Gw[0, 2] == 0.0 and Gw[0, 1] == pytest.approx(0.25 * (1 - 1.5 ** 2 / 4))


def test_compatibility_of_duplicates_and_shared_source():
    src = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0.0]])
    tgt = np.array([[1, 1, 1], [1, 1, 1], [5, 1, 1.0]])
    G = compatibility_matrix(src, tgt)
    assert G[0, 1] == 1.0  # the same correspondence twice is fully compatible
    assert G[0, 2] == 0.0  # one source point matched to two distant targets: incompatible
    assert np.isfinite(G).all()


def _reference_clustering(G, thresh):
    """The paper's clustering written the slow, obvious way."""
    groups = [[i] for i in range(len(G))]
    reps = [G[i].astype(np.float64) for i in range(len(G))]
    while len(groups) > 1:
        best = (2.0, -1, -1)
        for i in range(len(groups)):
            for j in range(i + 1, len(groups)):
                p, q = reps[i], reps[j]
                dot = p @ q
                denom = p @ p + q @ q - dot
                d = 1.0 - dot / denom if denom > 0 else 1.0
                best = min(best, (d, i, j))
        d, i, j = best
        if d > thresh:
            break
        reps[i] = np.minimum(reps[i], reps[j])
        groups[i] += groups.pop(j)
        reps.pop(j)
    labels = np.empty(len(G), int)
    for k, g in enumerate(groups):
        labels[g] = k
    return labels


def _same_partition(a, b):
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_clustering_matches_the_plain_algorithm(seed, sigma):
    rng = np.random.default_rng(seed)
    src, tgt, _, _ = two_instance_scene(rng, n_per=25, n_out=20)
    G = compatibility_matrix(src, tgt, sigma)
    fast = cluster_compatibility_vectors(G, 0.2)
    slow = _reference_clustering(G, 0.2)
    assert _same_partition(fast, slow)


@pytest.mark.parametrize("seed", range(3))
def test_sparse_and_dense_products_give_the_same_clusters(seed, monkeypatch):
    from multi_instance_reg.core import clustering
    s = make_sized_scene(np.random.default_rng(seed), 600, 0.6, 5)
    order = np.argsort(s.tgt[:, 0])  # spatial order, as ECC.sample gives it
    G = compatibility_matrix(s.src[order], s.tgt[order], 2.0)
    counts, row_end = clustering._row_counts(G)
    indptr, indices, values = clustering._to_rows(G, counts)
    S = clustering._sparse_gram(G, indptr, indices, values, row_end)
    assert np.allclose(S, G.astype(np.float64) @ G, rtol=1e-4, atol=1e-4)
    labels = {}
    for name, cost in (("sparse", 0.0), ("dense", 1e12)):
        monkeypatch.setattr(clustering, "_SPARSE_PRODUCT_COST", cost)
        labels[name] = cluster_compatibility_vectors(G, 0.2)
    assert _same_partition(labels["sparse"], labels["dense"])


@pytest.mark.parametrize("n", [40, 130, 700])
def test_the_gram_product_is_the_whole_matrix_product(n):
    # Half the work by a rank-k update of the upper triangle, mirrored: the clustering reads
    # S's rows in full (the lower triangle as bounds), so every entry must be there.
    from multi_instance_reg.core import clustering
    s = make_sized_scene(np.random.default_rng(n), n, 0.5, 3)
    G = compatibility_matrix(s.src, s.tgt, 2.0)
    S = clustering._gram(G)
    assert S.flags.c_contiguous and S.dtype == np.float32
    assert np.allclose(S, G.astype(np.float64) @ G, rtol=1e-5, atol=1e-5)
    assert np.array_equal(S, S.T)


def test_clustering_leaves_g_alone_unless_allowed_to_overwrite_it():
    s = make_sized_scene(np.random.default_rng(4), 300, 0.5, 3)
    G = compatibility_matrix(s.src, s.tgt, 0.0)     # no spatial weight: dense rows
    before = G.copy()
    labels = cluster_compatibility_vectors(G, 0.2)
    assert np.array_equal(G, before)
    assert np.array_equal(cluster_compatibility_vectors(G, 0.2, overwrite=True), labels)
    assert not np.array_equal(G, before)             # used as scratch: no copy made


def test_residuals_are_alignment_errors():
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    Ts = np.stack([random_T(rng) for _ in range(4)])
    expected = np.linalg.norm(np.einsum("mij,nj->nmi", Ts[:, :3, :3], x) + Ts[:, :3, 3] - y[:, None], axis=2)
    assert np.allclose(residuals(x, y, Ts), expected)
    assert residuals(x, y, np.zeros((0, 4, 4))).shape == (50, 0)


def test_clustering_separates_two_instances():
    rng = np.random.default_rng(1)
    src, tgt, _, truth = two_instance_scene(rng)
    labels = cluster_compatibility_vectors(compatibility_matrix(src, tgt), 0.2)
    for k in (0, 1):
        members = labels[truth == k]
        assert np.bincount(members).max() >= 0.9 * len(members)
    assert labels[truth == 0][0] != labels[truth == 1][0]


def test_rigid_fit_recovers_transform_and_is_proper():
    rng = np.random.default_rng(2)
    T = random_T(rng)
    x = rng.normal(size=(30, 3))
    assert np.allclose(rigid_fit(x, x @ T[:3, :3].T + T[:3, 3]), T, atol=1e-9)
    # A mirrored target would want a reflection: the fit must stay a rotation.
    R = rigid_fit(x, x * [1, 1, -1])[:3, :3]
    assert np.linalg.det(R) == pytest.approx(1.0)
    # Degenerate: collinear and coincident points give a finite proper rotation.
    line = np.outer(np.linspace(0, 1, 5), [1, 2, 3])
    for a, b in ((line, line + 1), (np.zeros((4, 3)), np.ones((4, 3))), (x[:1], x[:1])):
        Tf = rigid_fit(a, b)
        assert np.isfinite(Tf).all() and np.linalg.det(Tf[:3, :3]) == pytest.approx(1.0)


def test_batched_fit_equals_single_fits():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(90, 3))
    labels = np.repeat([0, 1, -1], 30)
    Ts = [random_T(rng), random_T(rng)]
    y = x.copy()
    for k, T in enumerate(Ts):
        y[labels == k] = x[labels == k] @ T[:3, :3].T + T[:3, 3]
    batched = fit_transforms(x, y, labels, 2)
    for k in range(2):
        assert np.allclose(batched[k], rigid_fit(x[labels == k], y[labels == k]), atol=1e-9)
        assert np.allclose(batched[k], Ts[k], atol=1e-9)
    assert np.allclose(residuals(x[:30], y[:30], batched[:1]), 0, atol=1e-9)


def test_merge_duplicates_keeps_the_transform_with_fewer_outliers():
    sets = np.zeros((100, 3), bool)
    sets[:50, 0] = True           # 50 inliers
    sets[:45, 1] = True           # IoU 0.9 with 0: duplicate, fewer inliers -> dropped
    sets[60:90, 2] = True         # disjoint: kept
    assert sorted(merge_duplicates(sets, 0.8).tolist()) == [0, 2]
    assert sorted(merge_duplicates(sets, 0.95).tolist()) == [0, 1, 2]


def _merge_duplicates_plain(inlier_sets, iou_thresh):
    # The numpy form the compiled merge_duplicates replaced: all IoUs at once, then the pass.
    counts = inlier_sets.sum(0)
    order = np.argsort(-counts, kind="stable")
    sets = inlier_sets[:, order].astype(np.float32)
    inter = sets.T @ sets
    union = counts[order][:, None] + counts[order][None, :] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    keep = np.ones(len(order), dtype=bool)
    for i in range(len(order)):
        if keep[i]:
            keep[i + 1:] &= iou[i, i + 1:] < iou_thresh
    return order[keep]


@pytest.mark.parametrize("seed", range(6))
def test_compiled_merge_duplicates_equals_the_plain_one(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 400), rng.integers(1, 40)
    base = rng.random((n, m)) < rng.uniform(0.05, 0.6)
    # Near-copies of some columns (the duplicates to merge), exact copies (count ties) and
    # empty sets (union 0).
    for j in rng.choice(m, m // 2):
        k = rng.integers(m)
        base[:, j] = base[:, k] ^ (rng.random(n) < rng.choice([0.0, 0.02, 0.2]))
    base[:, rng.choice(m, m // 8)] = False
    for thresh in (0.0, 0.5, 0.8, 1.0):
        assert np.array_equal(merge_duplicates(base, thresh), _merge_duplicates_plain(base, thresh))


def test_registration_finds_every_instance():
    rng = np.random.default_rng(4)
    src, tgt, Ts, truth = two_instance_scene(rng, n_per=80, n_out=60)
    cfg = ECCConfig(inlier_thresh=0.05)
    result = ECC(cfg).register(src, tgt)
    assert len(result) == 2
    score = evaluate_scene(Ts, result.transforms, 2.0, 0.05)
    assert score.hits == 2
    assert list(result.inlier_counts) == sorted(result.inlier_counts, reverse=True)
    for m in range(2):
        assert len(result.inliers(m)) == result.inlier_counts[m]
    assert ((result.labels >= 0) == (truth >= 0)).mean() > 0.95
    assert 0 < result.scores.min() and result.scores.max() <= 1


def test_scores_belong_to_their_instances():
    s = make_band("10-50", 1, seed=2)[0]
    cfg = ECCConfig.modelnet()
    r = ECC(cfg).register(s.src, s.tgt)
    assert len(r) > 3
    for m in range(len(r)):
        inl = r.inliers(m)
        res = np.linalg.norm(s.src[inl] @ r.transforms[m][:3, :3].T + r.transforms[m][:3, 3] - s.tgt[inl], axis=1)
        assert r.scores[m] == pytest.approx(np.mean(1 - res / cfg.inlier_thresh))
        assert 0 <= r.scores[m] <= 1


def test_permuting_rows_permutes_labels_only():
    s = make_band("50-70", 1, seed=5)[0]
    cfg = ECCConfig.modelnet()
    idx = np.random.default_rng(0).choice(len(s.src), 800, replace=False)
    src, tgt = s.src[idx], s.tgt[idx]
    a = ECC(cfg).register(src, tgt)
    perm = np.random.default_rng(1).permutation(len(src))
    b = ECC(cfg).register(src[perm], tgt[perm])
    assert len(a) == len(b) > 0
    assert _same_partition(a.labels[perm], b.labels)
    assert np.array_equal(np.sort(a.inlier_counts), np.sort(b.inlier_counts))
    for T in a.transforms:
        assert min(np.abs(T - Tb).max() for Tb in b.transforms) < 1e-6


def test_moving_all_targets_composes_into_every_result():
    rng = np.random.default_rng(6)
    src, tgt, _, _ = two_instance_scene(rng, n_per=60, n_out=30)
    cfg = ECCConfig(inlier_thresh=0.05)
    a = ECC(cfg).register(src, tgt)
    M = random_T(rng)
    b = ECC(cfg).register(src, tgt @ M[:3, :3].T + M[:3, 3])
    assert np.array_equal(a.labels, b.labels)
    assert np.allclose(b.transforms, M @ a.transforms, atol=1e-6)


def test_large_inputs_are_sampled_deterministically():
    s = make_sized_scene(np.random.default_rng(7), 3000, 0.5, 5)
    cfg = ECCConfig.modelnet()
    a = ECC(cfg).register(s.src, s.tgt)
    b = ECC(cfg).register(s.src, s.tgt)
    assert a.n_clustered == 1024 and len(a.labels) == 3000
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.transforms, b.transforms)
    assert evaluate_scene(s.T_gt, a.transforms).hits == 5
    c = ECC(dataclasses.replace(cfg, seed=1)).register(s.src, s.tgt)
    assert evaluate_scene(s.T_gt, c.transforms).hits == 5


@pytest.mark.parametrize("n", [0, 1, 2])
def test_fewer_than_three_correspondences(n):
    r = ECC().register(np.zeros((n, 3)), np.ones((n, 3)))
    assert len(r) == 0 and r.labels.shape == (n,) and (r.labels == -1).all()


def test_pure_outliers_give_no_instance_and_no_nan():
    rng = np.random.default_rng(8)
    r = ECC(ECCConfig.modelnet()).register(rng.uniform(-1, 1, (300, 3)), rng.uniform(0, 10, (300, 3)))
    assert len(r) == 0 and (r.labels == -1).all()


def test_degenerate_inputs_do_not_crash_or_nan():
    rng = np.random.default_rng(9)
    cases = {
        "coincident": (np.zeros((50, 3)), np.ones((50, 3))),
        "duplicated rows": (np.repeat(rng.normal(size=(5, 3)), 10, 0),) * 2,
        "collinear": (np.outer(np.linspace(0, 1, 40), [1, 0, 0]), np.outer(np.linspace(0, 1, 40), [0, 1, 0])),
    }
    for name, (x, y) in cases.items():
        r = ECC(ECCConfig(min_cluster_size=3)).register(x, y)
        assert np.isfinite(r.transforms).all(), name
        for T in r.transforms:
            assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0), name


def test_rows_with_nan_or_inf_are_dropped_and_counted():
    rng = np.random.default_rng(10)
    src, tgt, Ts, _ = two_instance_scene(rng, n_per=60, n_out=20)
    src[3] = np.nan
    tgt[70, 1] = np.inf
    r = ECC(ECCConfig(inlier_thresh=0.05)).register(src, tgt)
    assert r.n_invalid == 2 and r.labels[3] == -1 and r.labels[70] == -1
    assert evaluate_scene(Ts, r.transforms, 2.0, 0.05).hits == 2


@pytest.mark.parametrize("src,tgt", [(np.zeros((5, 2)), np.zeros((5, 2))), (np.zeros((5, 3)), np.zeros((4, 3)))])
def test_bad_shapes_raise_input_error(src, tgt):
    with pytest.raises(InputError):
        ECC().register(src, tgt)


@pytest.mark.parametrize("rule,expected", [("at_or_below", 1), ("below", 2)])
def test_gamma_rule_decides_an_instance_at_exactly_the_threshold(rule, expected):
    # Two instances, 60 and 30 inliers: gamma_2 = 0.5 exactly. The paper drops it
    # (gamma_k <= 0.5), the authors' code keeps it (gamma_k < 0.5).
    rng = np.random.default_rng(4)
    model = rng.uniform(-1, 1, (60, 3))
    Ts = [random_T(rng), random_T(rng)]
    src = np.concatenate([model, model[:30]])
    tgt = np.concatenate([model @ Ts[0][:3, :3].T + Ts[0][:3, 3], model[:30] @ Ts[1][:3, :3].T + Ts[1][:3, 3]])
    r = ECC(dataclasses.replace(ECCConfig.paper(), gamma_rule=rule)).register(src, tgt)
    assert list(r.inlier_counts) == [60, 30][:expected]
    assert evaluate_scene(np.stack(Ts)[:expected], r.transforms).hits == expected


@pytest.mark.parametrize("n, reference_size", [(1500, None), (1500, 600)])
def test_consistency_counts_pair_once_equal_the_per_query_counts(n, reference_size):
    # The references among themselves are counted once per pair (the test is symmetric);
    # every count must equal the plain per-query kernel's, shared target points included.
    from multi_instance_reg.core import sampling

    rng = np.random.default_rng(7)
    tgt = rng.random((n, 3))
    src = tgt @ Rotation.from_euler("z", 90, degrees=True).as_matrix().T + rng.normal(0, 0.02, (n, 3))
    src[: n // 3] = rng.random((n // 3, 3))
    tgt[10:20] = tgt[0]
    scores = sampling.consistency_scores(src, tgt, 0.3, 0.05, np.random.default_rng(0),
                                         reference_size=reference_size, score="count")
    # The same reference subset, counted query by query.
    r = np.random.default_rng(0)
    ref = np.arange(n) if reference_size is None else r.choice(n, reference_size, replace=False)
    table, start, grid, dims, _ = sampling._binned_references(src, tgt, ref, 0.3)
    counts, _ = sampling._counts(src, tgt, table, start, grid, dims, 0.3, 0.05)
    assert counts.sum() > n
    assert np.array_equal(scores, counts.astype(np.float64))


@pytest.mark.parametrize("cell_per_radius", [0.3, 0.75, 1.5, 4.0])
def test_consistency_counts_do_not_depend_on_the_grid_cell_size(cell_per_radius, monkeypatch):
    # The grid only decides which references a query looks at; every neighbour within the
    # radius must be visited whatever the cell size, so the counts are the brute-force ones.
    from multi_instance_reg.core import sampling

    rng = np.random.default_rng(11)
    n, radius, tol = 800, 0.2, 0.03
    tgt = rng.random((n, 3))
    src = tgt @ Rotation.from_euler("z", 30, degrees=True).as_matrix().T + rng.normal(0, 0.01, (n, 3))
    src[: n // 2] = rng.random((n // 2, 3))
    monkeypatch.setattr(sampling, "_CELL_PER_RADIUS", cell_per_radius)
    counts = sampling.consistency_scores(src, tgt, radius, tol, np.random.default_rng(0), score="count")
    e = np.linalg.norm(tgt[:, None] - tgt[None], axis=2)
    f = np.linalg.norm(src[:, None] - src[None], axis=2)
    near = (e < radius) & (e != 0.0)
    assert (np.abs(np.abs(f - e)[near] - tol) > 1e-9).all()   # no pair on the boundary of the test
    brute = (near & (np.abs(f - e) < tol)).sum(1)
    assert brute.sum() > n
    assert np.array_equal(counts, brute.astype(np.float64))


def test_distance_preservation_without_square_roots_is_the_plain_test():
    # The sampling kernels test | |f| - |e| | < t from squared lengths without a square root;
    # it must agree with the plain test everywhere but within rounding of the boundary.
    from multi_instance_reg.core.sampling import _preserved

    rng = np.random.default_rng(3)
    e = rng.uniform(0.0, 1.0, 200_000)
    f = np.concatenate([e[:100_000] + rng.normal(0, 0.05, 100_000), rng.uniform(0.0, 1.0, 100_000)])
    f = np.abs(f)
    f[:10] = 0.0                                  # coincident source points
    t = 0.03
    plain = np.abs(f - e) < t
    fast = np.array([_preserved(a * a, b * b, t * t, 4.0 * t ** 4) for a, b in zip(f[:20_000], e[:20_000])])
    away = np.abs(np.abs(f[:20_000] - e[:20_000]) - t) > 1e-9
    assert plain[:20_000].sum() > 1000 and (~plain[:20_000]).sum() > 1000
    assert np.array_equal(fast[away], plain[:20_000][away])


def test_an_instance_turned_over_in_place_is_dropped_a_real_neighbour_kept():
    # A model symmetric under a half turn about its x axis (an ellipsoid's surface). Instance A
    # is matched sparsely (60 right, 600 of its points matched to random source points);
    # B, the model turned over in A's place, collects chance matches on A's surface; C is a
    # second real object that interpenetrates A (30 right matches).
    from multi_instance_reg.core.placement import covered_by_stronger
    from multi_instance_reg.core.refinement import assign_nearest

    rng = np.random.default_rng(12)
    v = rng.normal(size=(256, 3))
    model = v / np.linalg.norm(v, axis=1, keepdims=True) * [1.0, 0.5, 0.4]
    TA = random_T(rng)
    TB = TA @ make_transform(Rotation.from_euler("x", 180, degrees=True).as_matrix(), np.zeros(3))
    TC = TA @ make_transform(Rotation.from_euler("z", 70, degrees=True).as_matrix(), [0.4, 0.3, 0.0])
    on_a = model[rng.integers(0, 256, 660)]
    src = [on_a[:60], model[rng.integers(0, 256, 600)], model[rng.integers(0, 256, 30)], model[rng.integers(0, 256, 2000)]]
    tgt = [on_a[:60] @ TA[:3, :3].T + TA[:3, 3], on_a[60:] @ TA[:3, :3].T + TA[:3, 3],
           src[2] @ TC[:3, :3].T + TC[:3, 3], rng.uniform(-10, 10, (2000, 3))]
    src, tgt = np.concatenate(src), np.concatenate(tgt)
    T = np.stack([TA, TB, TC])
    labels, _ = assign_nearest(src, tgt, T, 0.3)
    counts = np.bincount(labels[labels >= 0], minlength=3)
    assert counts[1] > 10 and counts[2] > 10 and counts[0] > max(counts[1:])
    assert list(covered_by_stronger(src, tgt, T, labels, 0.3)) == [True, False, True]
    # The turned-over copy is judged against the kept instance, never the other way.
    assert list(covered_by_stronger(src, tgt, T[[0, 2]], assign_nearest(src, tgt, T[[0, 2]], 0.3)[0], 0.3)) == [True, True]


def test_turned_over_copies_at_90_to_99_percent_outliers_are_dropped_and_no_hit_lost():
    # Own Table-1 set, 90-99 % band, seed 0, samples 10 and 17: with covered_instances keep,
    # 8 and 12 instances are selected, of them 3 and 6 wrong, several the model turned over
    # on an instance already found.
    scenes = make_band("90-99", 18, seed=0)
    for i in (10, 17):
        s = scenes[i]
        kept = ECC(dataclasses.replace(ECCConfig.modelnet(), covered_instances="keep")).register(s.src, s.tgt)
        dropped = ECC(ECCConfig.modelnet()).register(s.src, s.tgt)
        before, after = evaluate_scene(s.T_gt, kept.transforms), evaluate_scene(s.T_gt, dropped.transforms)
        assert len(dropped) < len(kept)
        assert after.hits == before.hits and after.f1 > before.f1


def test_a_contrario_test_tells_real_support_from_chance_in_clutter():
    # 3,000 correspondences: a real instance with 25 right matches, and a crowd of 1,000
    # targets shaped like the model (a distractor copy) matched to random source points,
    # where the transform laying the model over it collects dozens of inliers by chance.
    from multi_instance_reg.core.refinement import assign_nearest
    from multi_instance_reg.core.significance import meaningful

    rng = np.random.default_rng(13)
    model = rng.uniform(-0.5, 0.5, (256, 3))
    real, crowd = random_T(rng), make_transform(Rotation.random(random_state=rng).as_matrix(), [20.0, 0.0, 0.0])
    right = model[rng.integers(0, 256, 25)]
    copy = model[rng.integers(0, 256, 1000)] @ crowd[:3, :3].T + crowd[:3, 3] + rng.normal(0, 0.02, (1000, 3))
    src = np.concatenate([right, model[rng.integers(0, 256, 2975)]])
    tgt = np.concatenate([right @ real[:3, :3].T + real[:3, 3], copy, rng.uniform(-30, 30, (1975, 3))])
    T = np.stack([real, crowd])
    labels, errors = assign_nearest(src, tgt, T, 0.3)
    counts = np.bincount(labels[labels >= 0], minlength=2)
    assert counts[1] > counts[0] >= 25          # the crowd's transform has more inliers
    assert list(meaningful(src, tgt, T, labels, errors, np.arange(2), np.random.default_rng(0))) == [True, False]


def test_an_under_drawn_instance_lost_in_the_sample_is_found_on_all_correspondences():
    # Own Table-1 set, 70-90 % band, seed 0, sample 3 (19 instances, N = 6,376): one
    # instance, interpenetrating another, had 6 of its 55 inliers drawn, in clusters of
    # 3, 2 and 1, and the refinement dropped them; judged on all N, the cluster of 3 fits it.
    s = make_band("70-90", 4, seed=0)[3]
    dropped = ECC(dataclasses.replace(ECCConfig.modelnet(), lost_clusters="drop")).register(s.src, s.tgt)
    tested = ECC(ECCConfig.modelnet()).register(s.src, s.tgt)
    assert evaluate_scene(s.T_gt, dropped.transforms).hits == 18
    score = evaluate_scene(s.T_gt, tested.transforms)
    assert score.hits == 19 and len(tested) == 19
