"""ICP's nearest-point search (frontends/shape/geometry.py): the per-cell candidate lists give the same
nearest point as the grid's column search and as brute force, and ICP through them the same
pose as a plain reference ICP."""
import math

import numpy as np

from multi_instance_reg.frontends.shape.geometry import PointGrid, _grid_nearest, _listed_nearest, apply_twist, icp_point_to_plane


def _surfaces(rng, n=3000):
    """Points on a noisy plane and a sphere in front of it (camera frame), with normals."""
    plane = np.column_stack([rng.uniform(-0.3, 0.3, n // 2), rng.uniform(-0.2, 0.2, n // 2),
                             1.2 + rng.normal(0, 0.002, n // 2)])
    d = rng.normal(size=(n - n // 2, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sphere = d * 0.08 + [0.05, -0.02, 1.0] + rng.normal(0, 0.001, (len(d), 3))
    normals = np.vstack([np.tile([0.0, 0.0, -1.0], (len(plane), 1)), d])
    return np.vstack([plane, sphere]), normals


def _brute_nearest(pts, q, max_dist):
    e = pts - q
    d2 = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + e[:, 2] * e[:, 2]
    j = int(np.argmin(d2))
    return j if d2[j] < max_dist * max_dist else -1


def test_listed_nearest_is_the_grid_search_and_brute_force():
    rng = np.random.default_rng(3)
    pts, normals = _surfaces(rng)
    grid = PointGrid(pts, normals, 0.012)
    first, index, xyz = grid.neighbour_lists()
    assert grid.neighbour_lists()[0] is first            # built once
    # Queries near the surfaces, in empty space and outside the grid's box (each side).
    queries = np.vstack([grid.points[rng.integers(0, len(pts), 1500)] + rng.normal(0, 0.006, (1500, 3)),
                         rng.uniform(grid.lo - 0.03, grid.lo + grid.dims * grid.cell + 0.03, (1500, 3))])
    found = outside = 0
    for max_dist in (grid.cell, 0.75 * grid.cell, 0.3 * grid.cell):
        for q in queries:
            args = (grid.points, grid.start, grid.lo, grid.dims, grid.cell, max_dist)
            want = _brute_nearest(grid.points, q, max_dist)
            assert _grid_nearest(q[0], q[1], q[2], *args) == want
            assert _listed_nearest(q[0], q[1], q[2], first, index, xyz, *args) == want
            found += want >= 0
            outside += bool(np.any(np.floor((q - grid.lo) / grid.cell) < 0)
                            or np.any(np.floor((q - grid.lo) / grid.cell) >= grid.dims))
    assert found > 1500 and outside > 100                # both kinds of query were asked


def _reference_icp(T, mp, mn, sp, sn, max_dist, iterations):
    """``_icp_grid`` written plainly: brute-force nearest points, the same arithmetic."""
    T = T.copy()
    share = 0.0
    floor = 0.5 * max_dist
    for it in range(iterations):
        src, dst, nrm = [], [], []
        seen = 0
        for i in range(len(mp)):
            p = [T[r, 0] * mp[i, 0] + T[r, 1] * mp[i, 1] + T[r, 2] * mp[i, 2] + T[r, 3] for r in range(3)]
            n = [T[r, 0] * mn[i, 0] + T[r, 1] * mn[i, 1] + T[r, 2] * mn[i, 2] for r in range(3)]
            if not (n[0] * p[0] + n[1] * p[1] + n[2] * p[2] < -0.2 * math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])):
                continue
            seen += 1
            j = _brute_nearest(sp, np.array(p), max_dist)
            if j >= 0:
                src.append(p)
                dst.append(sp[j])
                nrm.append(sn[j])
        m = len(src)
        share = m / seen if seen else 0.0
        if m < 6:
            break
        c = [sum(s[k] for s in src) / m for k in range(3)]
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for s, d, n in zip(src, dst, nrm):
            sx, sy, sz = s[0] - c[0], s[1] - c[1], s[2] - c[2]
            a = [sy * n[2] - sz * n[1], sz * n[0] - sx * n[2], sx * n[1] - sy * n[0], n[0], n[1], n[2]]
            b = (d[0] - s[0]) * n[0] + (d[1] - s[1]) * n[1] + (d[2] - s[2]) * n[2]
            for r in range(6):
                g[r] += a[r] * b
                for q in range(r, 6):
                    H[r, q] += a[r] * a[q]
        H = np.triu(H) + np.triu(H, 1).T
        H[np.diag_indices(6)] += 1e-3 * np.trace(H) / 6.0 + 1e-12
        x = np.linalg.solve(H, g)
        T = apply_twist(T, x, np.array(c))
        if np.linalg.norm(x[:3]) < 1e-4 and np.linalg.norm(x[3:]) < 1e-5:
            break
        if it >= 2:
            max_dist = max(0.6 * max_dist, floor)
    return T, share


def test_icp_through_the_lists_is_the_plain_icp():
    rng = np.random.default_rng(5)
    pts, normals = _surfaces(rng)
    grid = PointGrid(pts, normals, 0.012)
    # The model: a sphere 1.1 times the scene's (its points 8 mm off the scene's, about the
    # pairing distance once ICP tightens it), started off its place.
    mn = normals[len(pts) // 2::3]
    mp = 0.088 * mn
    for shift in ([0.004, -0.003, 0.002], [0.0, 0.008, -0.004], [0.01, 0.0, 0.0]):
        T0 = np.eye(4)
        T0[:3, 3] = np.array([0.05, -0.02, 1.0]) + shift
        got, share = icp_point_to_plane(T0, mp, grid, 0.012, 8, model_normals=mn)
        want, want_share = _reference_icp(T0, mp, mn, grid.points, grid.normals, 0.012, 8)
        assert share == want_share and share > 0.5
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
