"""Which correspondences to cluster when there are too many (ECC paper, Sec. 3.6).

The paper samples uniformly. At high outlier ratios that keeps too few inliers per instance
to form a cluster (at 95 % outliers and N = 6000, a sample of 1024 holds ~50 inliers spread
over up to 20 instances). ``consistency`` sampling keeps the correspondences that agree with
many spatial neighbours instead: for each correspondence, it counts the neighbours within
``radius`` (in the target cloud) whose pairwise distances are preserved to within
``tolerance``, | |x_i - x_j| - |y_i - y_j| | < tolerance, then draws the sample without
replacement with weights (score + 1)^exponent (Efraimidis-Spirakis keys). Inliers of one
instance preserve distances among themselves, outliers only by chance, so they are drawn
far more often; drawing rather than taking the top counts keeps every instance covered
when most correspondences are inliers (taking the top starved the sparser instances).

The score (``sampling_score``):
- ``chance`` (default): the agreeing neighbours in excess of those expected by chance,
  max(0, count - p0 * neighbours). A raw count
  favours crowded places: where many outlier matches land in a small region (a distractor
  object that several source points match, a dense patch of clutter), a tenth of its many
  neighbours agree by chance, which outnumbers an inlier's agreeing neighbours. On the
  reference sets (../shared/reference/core) 90-99 % of the raw-count weight went to such
  outliers. p0, the chance of agreement, is measured on the data itself: the same test with
  each query's source point taken from a random other correspondence (pairing broken).
- ``count``: the raw count (the earlier rule, kept for comparison).
"""
from __future__ import annotations

import numpy as np

from . import native
from .native import compiled, prange, row_parts, split_rows

# Neighbour search: the references are binned on a grid of cells 0.75 x radius wide, each
# query visits the columns of cells its sphere reaches, and in each column only the cells
# within the sphere's extent there: one contiguous run of references. Smaller cells mean
# more, shorter runs per query, larger ones more points outside the sphere; the cell size
# changes which points are looked at, never the counts (the distance test decides).
_CELL_PER_RADIUS = 0.75
# At most this many cells (the bin starts cost 8 bytes each); a wider cloud gets larger cells.
_MAX_CELLS = 1 << 18


@compiled()
def _column_run(start, dims, rc, ux, uy, uz, ix, iy):
    """The run start[first:end] of references in column (ix, iy) within the query's sphere
    (centre ux, uy, uz and radius rc in cell units; end <= first: none)."""
    gx = max(ix - ux, 0.0, ux - ix - 1.0)
    gy = max(iy - uy, 0.0, uy - iy - 1.0)
    g2 = gx * gx + gy * gy
    if g2 >= rc * rc:
        return 0, 0
    half = np.sqrt(rc * rc - g2)   # the sphere's half-height over this column
    z0 = int(max(np.floor(uz - half), 0.0))
    z1 = int(min(np.floor(uz + half), dims[2] - 1.0))
    if z0 > z1:
        return 0, 0
    column = (ix * dims[1] + iy) * dims[2]
    return start[column + z0], start[column + z1 + 1]


@compiled()
def _span(u, rc, n):
    """The cells along one axis that a sphere at u (radius rc, cell units) reaches."""
    return int(max(np.floor(u - rc), 0.0)), int(min(np.floor(u + rc), n - 1.0))


@compiled()
def _preserved(f2, e2, t2, t4):
    """| |f| - |e| | < t from the squared lengths f2, e2 (t2 = t^2, t4 = 4 t^4), without a
    square root (two per pair made the sampling's loop sqrt-bound): with d = f2 - e2, the
    test is d^2 < t^2 (f2 + e2 + 2 |f||e|); true when d^2 < t^2 (f2 + e2), else square again."""
    d = f2 - e2
    u = d * d - t2 * (f2 + e2)
    return (u < 0.0) | (u * u < t4 * f2 * e2)


@compiled("i8(f8[:, ::1], f8[:, ::1], f8[:, ::1], i8[::1], f8[::1], i8[::1], f8, f8, i8[::1], i8[::1], i8, i8)", parallel=True)
def _consistency_counts(src, tgt, ref, start, grid, dims, radius, tolerance, counts, neighbours, lo, hi):
    """Per query lo..hi-1, into counts and neighbours: the reference neighbours within
    ``radius`` whose distance is preserved to within ``tolerance``, and all reference
    neighbours within ``radius``.

    ref is (6, R): target x, y, z and source x, y, z as rows, ordered by cell; the run of
    cell c (index (ix * ny + iy) * nz + iz) is start[c]:start[c + 1]. grid = origin x, y, z
    and the cell's width; dims = nx, ny, nz."""
    r2 = radius * radius
    t2 = tolerance * tolerance
    t4 = 4.0 * t2 * t2
    cell = grid[3]
    # The sphere in cell units, a hair larger so that rounding never drops a cell a
    # neighbour is in (visiting extra points is harmless: the distance test decides).
    rc = radius / cell * (1.0 + 1e-9) + 1e-9
    tx_all, ty_all, tz_all = ref[0], ref[1], ref[2]
    sx_all, sy_all, sz_all = ref[3], ref[4], ref[5]
    for i in prange(lo, hi):
        qx, qy, qz = tgt[i, 0], tgt[i, 1], tgt[i, 2]
        px, py, pz = src[i, 0], src[i, 1], src[i, 2]
        ux, uy, uz = (qx - grid[0]) / cell, (qy - grid[1]) / cell, (qz - grid[2]) / cell
        x0, x1 = _span(ux, rc, dims[0])
        y0, y1 = _span(uy, rc, dims[1])
        c = 0
        m = 0
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                first, end = _column_run(start, dims, rc, ux, uy, uz, ix, iy)
                if first >= end:
                    continue
                # 0-based slices and no branch: the loop vectorises (2-3x faster).
                tx, ty, tz = tx_all[first:end], ty_all[first:end], tz_all[first:end]
                sx, sy, sz = sx_all[first:end], sy_all[first:end], sz_all[first:end]
                for j in range(end - first):
                    ex, ey, ez = qx - tx[j], qy - ty[j], qz - tz[j]
                    e2 = ex * ex + ey * ey + ez * ez
                    fx, fy, fz = px - sx[j], py - sy[j], pz - sz[j]
                    f2 = fx * fx + fy * fy + fz * fz
                    near = (e2 < r2) & (e2 != 0.0)
                    m += near
                    c += near & _preserved(f2, e2, t2, t4)
        counts[i] = c
        neighbours[i] = m
    return hi - lo


@compiled("i8(f8[:, ::1], i8[::1], f8[::1], i8[::1], f8, f8, i8[::1], i8[::1])")
def _consistency_counts_pairs(ref, start, grid, dims, radius, tolerance, counts, neighbours):
    """_consistency_counts with every correspondence a reference (ref as there): the test is
    symmetric, so each pair is visited once, from its first position in cell order, and
    counted for both; counts and neighbours are per position in ``ref``."""
    r2 = radius * radius
    t2 = tolerance * tolerance
    t4 = 4.0 * t2 * t2
    cell = grid[3]
    rc = radius / cell * (1.0 + 1e-9) + 1e-9
    tx_all, ty_all, tz_all = ref[0], ref[1], ref[2]
    sx_all, sy_all, sz_all = ref[3], ref[4], ref[5]
    n = ref.shape[1]
    for a in range(n):
        qx, qy, qz = tx_all[a], ty_all[a], tz_all[a]
        px, py, pz = sx_all[a], sy_all[a], sz_all[a]
        ux, uy, uz = (qx - grid[0]) / cell, (qy - grid[1]) / cell, (qz - grid[2]) / cell
        x0, x1 = _span(ux, rc, dims[0])
        y0, y1 = _span(uy, rc, dims[1])
        c = 0
        m = 0
        for ix in range(x0, x1 + 1):
            for iy in range(y0, y1 + 1):
                first, end = _column_run(start, dims, rc, ux, uy, uz, ix, iy)
                # Only the positions after a: the pairs before were counted from there.
                first = max(first, a + 1)
                if first >= end:
                    continue
                tx, ty, tz = tx_all[first:end], ty_all[first:end], tz_all[first:end]
                sx, sy, sz = sx_all[first:end], sy_all[first:end], sz_all[first:end]
                cb, mb = counts[first:end], neighbours[first:end]
                for j in range(end - first):
                    ex, ey, ez = qx - tx[j], qy - ty[j], qz - tz[j]
                    e2 = ex * ex + ey * ey + ez * ez
                    fx, fy, fz = px - sx[j], py - sy[j], pz - sz[j]
                    f2 = fx * fx + fy * fy + fz * fz
                    near = (e2 < r2) & (e2 != 0.0)
                    agree = near & _preserved(f2, e2, t2, t4)
                    m += near
                    c += agree
                    mb[j] += near
                    cb[j] += agree
        counts[a] += c
        neighbours[a] += m
    return n


def _counts(src, tgt, table, start, grid, dims, radius, tolerance):
    """_consistency_counts over all queries, on the process's threads."""
    n = len(src)
    counts, neighbours = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    split_rows(_consistency_counts, row_parts(n, 512), src, tgt, table, start, grid, dims,
               float(radius), float(tolerance), counts, neighbours)
    return counts, neighbours


def _binned_references(src, tgt, ref, radius):
    """The references as _consistency_counts reads them: (ref (6, R), start, grid, dims, and
    the order that sorted ``ref`` by cell)."""
    points = tgt[ref]
    origin = points.min(0)
    extent = points.max(0) - origin
    cell = _CELL_PER_RADIUS * radius
    while np.prod(extent // cell + 1) > _MAX_CELLS:
        cell *= 2.0
    dims = (extent // cell).astype(np.int64) + 1
    idx = np.minimum(((points - origin) // cell).astype(np.int64), dims - 1)
    lin = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    order = np.argsort(lin, kind="stable")
    start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.cumsum(np.bincount(lin, minlength=len(start) - 1), out=start[1:])
    table = np.ascontiguousarray(np.concatenate([tgt[ref[order]].T, src[ref[order]].T]))
    return table, start, np.append(origin, cell), dims, order


# Queries for the chance rate p0: enough for a rate within about +-0.005 on typical data.
_CHANCE_QUERIES = 2048


def consistency_scores(src, tgt, radius: float, tolerance: float, rng: np.random.Generator,
                       reference_size: int | None = None, score: str = "chance") -> np.ndarray:
    """Per correspondence: how strongly its neighbours (from a random reference subset)
    keep their distances to it within ``tolerance``; ``score`` as in the module docstring.

    The reference subset is 4096 up to N = 8192 and shrinks beyond, so that the work per
    correspondence stays the same and the total grows linearly with N (measured: 4096 rather
    than 2048 references lifts MHF1 at 90-99 % outliers from 0.65 to 0.73 for N ~ 5000)."""
    src = np.ascontiguousarray(src, dtype=np.float64)
    tgt = np.ascontiguousarray(tgt, dtype=np.float64)
    n = len(src)
    if reference_size is None:
        reference_size = 4096 if n <= 8192 else max(1024, 4096 * 8192 // n)
    ref = np.arange(n) if n <= reference_size else rng.choice(n, reference_size, replace=False)
    table, start, grid, dims, order = _binned_references(src, tgt, ref, radius)
    if native.THREADS == 1:
        # The references among themselves: each pair once (the test is symmetric; the same
        # counts, half the pairs), then the other correspondences against them.
        by_position = np.zeros(len(ref), dtype=np.int64), np.zeros(len(ref), dtype=np.int64)
        _consistency_counts_pairs(table, start, grid, dims, float(radius), float(tolerance), *by_position)
        counts, neighbours = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
        counts[ref[order]], neighbours[ref[order]] = by_position
        rest = np.setdiff1d(np.arange(n), ref)
        if len(rest):
            counts[rest], neighbours[rest] = _counts(src[rest], tgt[rest], table, start, grid, dims, radius, tolerance)
    else:
        counts, neighbours = _counts(src, tgt, table, start, grid, dims, radius, tolerance)
    if score == "count":
        return counts.astype(np.float64)
    # Chance agreement: queries whose source point comes from another, random correspondence.
    q = rng.choice(n, min(n, _CHANCE_QUERIES), replace=False)
    null_counts, null_neighbours = _counts(
        np.ascontiguousarray(src[rng.permutation(q)]), np.ascontiguousarray(tgt[q]),
        table, start, grid, dims, radius, tolerance)
    p0 = null_counts.sum() / max(null_neighbours.sum(), 1)
    return np.maximum(counts - p0 * neighbours, 0.0)


def choose_sample(n: int, size: int, method: str, rng: np.random.Generator, src=None, tgt=None,
                  radius: float = 0.0, tolerance: float = 0.0, exponent: float = 6.0,
                  score: str = "chance") -> np.ndarray:
    """Sorted indices of the ``size`` correspondences to cluster (all when n <= size).

    ``consistency`` needs radius > 0 and tolerance > 0; otherwise sampling is uniform."""
    if size <= 0 or n <= size:
        return np.arange(n)
    if method == "consistency" and radius > 0 and tolerance > 0:
        scores = consistency_scores(src, tgt, radius, tolerance, rng, score=score)
        # Weighted sampling without replacement: the largest log(u) / w win.
        keys = np.log(rng.random(n)) / (scores + 1.0) ** exponent
        return np.sort(np.argsort(-keys, kind="stable")[:size])
    return np.sort(rng.choice(n, size=size, replace=False))
