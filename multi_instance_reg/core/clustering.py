"""Agglomerative clustering of compatibility vectors (ECC paper, Sec. 3.2).

Every correspondence starts as its own group, represented by its compatibility vector (a row
of G). The two groups with the smallest Tanimoto distance
    d(p, q) = 1 - <p, q> / (|p|^2 + |q|^2 - <p, q>)
are merged, the merged representation being the element-wise minimum, until the smallest
distance exceeds ``min_dist_thresh``.

The authors' code recomputes a full N x N distance matrix and takes a global argmin per
merge, O(N^3) in all. This implementation makes the same merges with far less work:
- dot products of groups a merge does not touch never change, so they are computed once;
- for a merged group m = min(p, q) and any group r, <m, r> <= min(<p, r>, <q, r>) because all
  entries are non-negative; that bound rules out almost every pair, and the exact dot
  product is computed only for pairs that could still merge; with dense rows, only once the
  merge loop reaches them: a pair waits keyed by the lower bound of its distance the bound
  gives, and most wait in lists that a later merge makes stale, never read;
- candidate pairs wait in per-group lists sorted by distance, and a heap holds each group's
  best one: a pop per merge rather than per pair. Entries whose partner changed since the
  list was built are skipped, so nothing is ever rescanned. Ties break by index, so results
  are deterministic;
- vectors are stored sparsely (the spatial weight zeroes most of G), and a merged vector's
  support is the intersection of its parts', so it only ever shrinks.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from .native import compiled, prange, row_parts, split_rows

# The initial dot products S = G G: a dense GEMM (BLAS) costs N^3 multiply-adds at the FMA
# peak; the sparse product below costs one multiply-add per (non-zero of G) x (column of its
# partner row up to that row's last non-zero), at about a tenth of the speed per operation
# (measured: 51 vs 23 ms at a fifth of the work). The cheaper is chosen per call.
_SPARSE_PRODUCT_COST = 10.0
# Above this fraction of non-zeros, rows are stored in full (zeros included): contiguous dot
# products vectorise and beat gathering over the non-zeros.
_DENSE_ROWS_ABOVE = 0.25

@compiled(fastmath=True)
def _tanimoto_distance(dot, sq_a, sq_b):
    denom = sq_a + sq_b - dot
    if denom <= 0.0:
        return 1.0
    return 1.0 - dot / denom


# Room for rounding between a bound min(<p, r>, <q, r>) and the exact <min(p, q), r>, each
# summed in float32 (relative errors of n * 6e-8 at most: 1e-3 covers n up to 16,000).
_BOUND_SLACK = 1e-3


@compiled(fastmath=True)
def _distance_at_least(bound, sq_a, sq_b):
    """A lower bound of the distance of a pair whose dot product is at most ``bound``."""
    dot = bound * (1.0 + _BOUND_SLACK)
    denom = sq_a + sq_b - dot
    if denom <= 0.0:
        return 0.0
    return max(0.0, 1.0 - dot / denom)


# The merge queue: a 4-ary min-heap of int64 items packing (distance, index): the distance,
# in [0, 1], as a fixed-point number in the high bits (steps of 1e-9), a group or partner
# index in the low bits, which also breaks ties deterministically. A partner entry holds the
# partner index shifted by one, its lowest bit set while the distance is only a lower bound. One array and 4 children
# per level cut the time per pop to a third of a binary heap of (key, value) pairs.
@compiled()
def _pack(distance, entry):
    return (np.int64(distance * 1073741824.0) << 32) | entry


@compiled()
def _heap_push(heap, size, item):
    i = size
    while i > 0:
        p = (i - 1) >> 2
        if heap[p] <= item:
            break
        heap[i] = heap[p]
        i = p
    heap[i] = item
    return size + 1


@compiled()
def _sift_down(heap, size, i):
    item = heap[i]
    while True:
        c = 4 * i + 1
        if c >= size:
            break
        m = c
        mv = heap[c]
        for j in range(c + 1, min(c + 4, size)):
            if heap[j] < mv:
                mv = heap[j]
                m = j
        if item <= mv:
            break
        heap[i] = mv
        i = m
    heap[i] = item


@compiled()
def _heap_pop(heap, size):
    item = heap[0]
    size -= 1
    if size > 0:
        heap[0] = heap[size]
        _sift_down(heap, size, 0)
    return item, size


@compiled()
def _grow(arr, cap):
    out = np.empty(cap, dtype=arr.dtype)
    out[: len(arr)] = arr
    return out


@compiled("UniTuple(i8[::1], 2)(f4[:, ::1])", parallel=True)
def _row_counts(G):
    """Per row: the number of non-zeros and the end (one past the last non-zero column)."""
    n = G.shape[0]
    counts = np.zeros(n, dtype=np.int64)
    row_end = np.zeros(n, dtype=np.int64)
    for i in prange(n):
        row = G[i]
        c = 0
        end = 0
        for j in range(n):
            if row[j] > 0.0:
                c += 1
                end = j + 1
        counts[i] = c
        row_end[i] = end
    return counts, row_end


@compiled("Tuple((i8[::1], i4[::1], f4[::1]))(f4[:, ::1], i8[::1])", parallel=True)
def _to_rows(G, counts):
    """Row-wise sparse form (CSR) of a dense matrix: indptr, column indices, values."""
    n = G.shape[0]
    indptr = np.zeros(n + 1, dtype=np.int64)
    indptr[1:] = np.cumsum(counts)
    indices = np.empty(indptr[n], dtype=np.int32)
    values = np.empty(indptr[n], dtype=np.float32)
    for i in prange(n):
        row = G[i]
        p = indptr[i]
        for j in range(n):
            if row[j] > 0.0:
                indices[p] = j
                values[p] = row[j]
                p += 1
    return indptr, indices, values


@compiled("i8(i8[::1], i4[::1], i8[::1])")
def _sparse_product_work(indptr, indices, row_end):
    """Multiply-adds _sparse_gram will do: per non-zero G[i, c], the columns i..row_end[c]."""
    w = 0
    for i in range(len(row_end)):
        for p in range(indptr[i], indptr[i + 1]):
            w += max(0, row_end[indices[p]] - i)
    return w


@compiled("i8(f4[:, ::1], i8, i8)", parallel=True)
def _mirror_upper(S, lo, hi):
    """Copy the upper triangle onto the lower one, in 64 x 64 tiles (cache-friendly): the
    tile rows lo..hi-1."""
    n = S.shape[0]
    for bi in prange(lo, hi):
        for bj in range(bi + 1):
            for i in range(bi * 64, min(n, bi * 64 + 64)):
                for j in range(bj * 64, min(i, bj * 64 + 64)):
                    S[i, j] = S[j, i]
    return hi - lo


@compiled(fastmath=True)
def _gram_row(G, indptr, indices, values, row_end, S, i):
    """Row i of S = G G from column i on: G[i, c] * G[c, i:row_end[c]] summed over the
    non-zeros c of row i."""
    n = G.shape[0]
    acc = S[i, i:]   # summed in place: no scratch row to allocate and copy
    acc[:] = 0.0
    for p in range(indptr[i], indptr[i + 1]):
        c = indices[p]
        length = row_end[c] - i
        if length <= 0:
            continue
        g = values[p]
        # Slices starting at 0: the loop index is provably non-negative, so numba needs
        # no wrap-around check and the loop vectorises.
        dst = acc[:length]
        src = G[c, i:i + length]
        for k in range(length):
            dst[k] += g * src[k]


@compiled("i8(f4[:, ::1], i8[::1], i4[::1], f4[::1], i8[::1], f4[:, ::1], i8, i8)", parallel=True)
def _sparse_gram_rows(G, indptr, indices, values, row_end, S, lo, hi):
    """Rows t and n - 1 - t of S's upper triangle for t in lo..hi-1: row i's work shrinks
    with i, so each task takes a row from both ends to stay balanced."""
    n = G.shape[0]
    for t in prange(lo, hi):
        _gram_row(G, indptr, indices, values, row_end, S, t)
        if n - 1 - t != t:
            _gram_row(G, indptr, indices, values, row_end, S, n - 1 - t)
    return hi - lo


def _sparse_gram(G, indptr, indices, values, row_end):
    """S = G G for a sparse symmetric G: the upper triangle row by row, then mirrored.
    Correspondences sorted along space keep row_end close to the diagonal."""
    n = G.shape[0]
    S = np.empty((n, n), dtype=np.float32)
    split_rows(_sparse_gram_rows, row_parts((n + 1) // 2, 64), G, indptr, indices, values, row_end, S)
    split_rows(_mirror_upper, row_parts((n + 63) // 64, 2, "growing"), S)
    return S


def _gram(G):
    """S = G G for a symmetric G (float32, C-contiguous), all row dot products at once: its
    upper triangle by one BLAS rank-k update, half a matrix product's work (1024 rows: 16
    against 22.5 ms), then mirrored. G G = G^T G; given G^T (Fortran order: no copy), the
    update fills the lower triangle of a Fortran-order result, which read as C order is S's
    upper one."""
    n = G.shape[0]
    S = blas.ssyrk(1.0, G.T, lower=1).T
    split_rows(_mirror_upper, row_parts((n + 63) // 64, 2, "growing"), S)
    return S


@compiled(fastmath=True)
def _dot_with_row(dense, indices, values, start, length, n):
    """<dense, row>, the row given by its entries; a full row (every column, in order, as
    rows of a dense G are) is read as a plain contiguous vector, which vectorises."""
    s = np.float32(0.0)
    if length == n:
        # A slice from 0: the index is provably non-negative, so the loop vectorises.
        row = values[start:start + n]
        for c in range(n):
            s += dense[c] * row[c]
    else:
        cols = indices[start:start + length]
        vals = values[start:start + length]
        for q in range(length):
            s += dense[cols[q]] * vals[q]
    return np.float64(s)


@compiled(fastmath=True)
def _dot_with_g_row(G, k, cols, vals, length):
    """<G[k], row>, the row given by its first ``length`` entries (cols, vals): as
    _dot_with_row on G[k], without making a view of G per call (numba refcounts views)."""
    s = np.float32(0.0)
    for q in range(length):
        s += G[k, cols[q]] * vals[q]
    return np.float64(s)


@compiled()
def _row_heap_push(heap, size, item, queued, row):
    queued[row] = item
    return _heap_push(heap, size, item)


@compiled("i8[::1](f4[:, ::1], i8[::1], i4[::1], f4[::1], f4[:, ::1], f8, b1, i8[::1])")
def _agglomerate(G, indptr, indices, values, S, max_dist, dense, stats):
    n = S.shape[0]
    # Row i's current entries are indices/values[indptr[i] : indptr[i] + rowlen[i]].
    rowlen = np.empty(n, dtype=np.int64)
    sq = np.empty(n, dtype=np.float64)
    for i in range(n):
        rowlen[i] = indptr[i + 1] - indptr[i]
        sq[i] = S[i, i]
    active = np.ones(n, dtype=np.bool_)
    parent = np.arange(n)
    candidate = np.zeros(n, dtype=np.bool_)
    dense_a = np.zeros(n, dtype=np.float32)   # scratch (sparse rows): the merged vector, scattered
    dense_b = np.zeros(n, dtype=np.float32)
    # d(p, q) <= max_dist  <=>  <p, q> >= t / (1 + t) * (|p|^2 + |q|^2) with t = 1 - max_dist;
    # the multiplicative form is cheap, and the slack keeps rounding from losing a pair.
    t = 1.0 - max_dist
    merge_ratio = t / (1.0 + t) * (1.0 - 1e-6)

    # Candidate pairs live in per-group lists sorted by distance: keys _pack(d, partner) in
    # pool[start[g]:stop[g]], the next unread at head[g]. A group's list is rebuilt whenever
    # it changes; an entry is stale once its partner changed after the list was built
    # (changed_at[k] >= built_at[g]) or left. A heap holds one item per group, keyed by the
    # distance of its head: pops are per merge, not per candidate pair. An entry keyed by a
    # lower bound is made exact when it reaches its list's head, and moved to its place:
    # every entry's exact key is at least its key, so the pops come in the eager order.
    # Loops run over slices indexed from 0 throughout: numba then knows the index is not
    # negative, drops its wrap-around check and vectorises (3x faster here).
    start = np.zeros(n, dtype=np.int64)
    stop = np.zeros(n, dtype=np.int64)
    head = np.zeros(n, dtype=np.int64)
    built_at = np.zeros(n, dtype=np.int64)
    changed_at = -np.ones(n, dtype=np.int64)     # merge count when last changed; -1 = still a row of G
    n_initial = 0
    for i in range(n - 1):
        row = S[i, i + 1:]
        sq_rest = sq[i + 1:]
        for k in range(n - 1 - i):
            n_initial += row[k] >= merge_ratio * (sq[i] + sq_rest[k])
    cap = n_initial + 4 * n + 16
    pool = np.empty(cap, dtype=np.int64)
    used = 0
    for i in range(n - 1):
        row = S[i, i + 1:]
        sq_rest = sq[i + 1:]
        start[i] = used
        for k in range(n - 1 - i):
            if row[k] < merge_ratio * (sq[i] + sq_rest[k]):
                continue
            d = _tanimoto_distance(row[k], sq[i], sq_rest[k])
            if d <= max_dist:
                pool[used] = _pack(d, (i + 1 + k) << 1)
                used += 1
        stop[i] = used
        head[i] = start[i]
        pool[start[i]:used] = np.sort(pool[start[i]:used])
    start[n - 1] = stop[n - 1] = head[n - 1] = used
    stats[0] = used
    heap = np.empty(2 * n + 16, dtype=np.int64)  # at most one live item per group, plus outdated ones
    queued = -np.ones(n, dtype=np.int64)      # the one live heap item of each group
    size = 0
    for i in range(n):
        if head[i] < stop[i]:
            size = _row_heap_push(heap, size, ((pool[head[i]] >> 32) << 32) | i, queued, i)
    merges = 0

    while size > 0:
        item, size = _heap_pop(heap, size)
        r = item & 0xFFFFFFFF
        if not active[r] or queued[r] != item:
            continue
        queued[r] = -1
        # Skip the stale entries at the head of r's list, making bounds exact on the way.
        h = head[r]
        while h < stop[r]:
            k = (pool[h] & 0xFFFFFFFF) >> 1
            if not active[k] or changed_at[k] >= built_at[r]:
                h += 1
                continue
            if (pool[h] & 1) == 0:
                break
            # (Dense rows.) r's and k's vectors are those the bound was taken from: the dot
            # product is the one an eager pass would have computed then, the same sums in
            # the same order.
            s = _dot_with_row(values[indptr[r]:indptr[r] + n], indices, values, indptr[k], rowlen[k], n)
            stats[2] += 1
            S[r, k] = s
            S[k, r] = s
            dk = _tanimoto_distance(s, sq[r], sq[k])
            if dk > max_dist:
                h += 1
                continue
            key = _pack(dk, k << 1)
            j = h
            while j + 1 < stop[r] and pool[j + 1] < key:
                pool[j] = pool[j + 1]
                j += 1
            pool[j] = key
        head[r] = h
        if h == stop[r]:
            continue
        if (pool[h] >> 32) != (item >> 32):
            # Its best pair is now a worse one: requeue, something else may come first.
            size = _row_heap_push(heap, size, ((pool[h] >> 32) << 32) | r, queued, r)
            continue
        k = (pool[h] & 0xFFFFFFFF) >> 1
        a = min(r, k)
        b = max(r, k)
        merges += 1
        # Room for every entry this merge can add, reserved here and not inside the loops
        # below: reassigning arrays there makes numba refcount them on every iteration.
        if used + n > cap:
            cap = 2 * (used + n)
            pool = _grow(pool, cap)
        # Merge b into a: element-wise minimum, on the intersection of the supports.
        pa, pb = indptr[a], indptr[b]
        va = values[pa:pa + rowlen[a]]
        vb = values[pb:pb + rowlen[b]]
        ca = indices[pa:pa + rowlen[a]]   # empty for full rows
        s_aa = 0.0
        if dense:
            # Full rows: the merged row, in place, is the scattered vector itself.
            merged = va
            for c in range(n):
                v = min(va[c], vb[c])
                va[c] = v
                s_aa += v * v
        else:
            merged = dense_a
            cb = indices[pb:pb + rowlen[b]]
            for q in range(len(cb)):
                dense_b[cb[q]] = vb[q]
            kept = 0
            for q in range(len(ca)):
                c = ca[q]
                v = min(va[q], dense_b[c])
                if v > 0.0:
                    ca[kept] = c
                    va[kept] = v
                    dense_a[c] = v
                    kept += 1
                    s_aa += v * v
            rowlen[a] = kept
            for q in range(len(cb)):
                dense_b[cb[q]] = 0.0
        sq[a] = s_aa
        S[a, a] = s_aa
        active[b] = False
        parent[b] = a
        changed_at[a] = merges
        # New dot products of a: the bound min(<p_a, r>, <p_b, r>) everywhere; only where
        # it still allows a merge is the exact one needed. With dense rows the pair waits
        # with the distance the bound gives, made exact at its list's head (most never
        # are); sparse rows gain less (more dot products stay needed) and would pay for
        # scattering the row again each time, so they are computed now. Only row a is
        # rewritten (contiguous): a column entry S[k, a] left stale is still an upper
        # bound, since a's vector only ever shrinks. First a branch-free pass (it
        # vectorises), then the few candidates.
        row_a = S[a]
        row_b = S[b]
        for k in range(n):
            bound = min(row_a[k], row_b[k])
            row_a[k] = bound
            candidate[k] = bound >= merge_ratio * (s_aa + sq[k])
        first = used
        for k in range(n):
            if not candidate[k] or k == a or not active[k]:
                continue
            if dense:
                dk = _distance_at_least(row_a[k], s_aa, sq[k])
                if dk <= max_dist:
                    pool[used] = _pack(dk, (k << 1) | 1)
                    used += 1
                continue
            if changed_at[k] < 0 and rowlen[a] < rowlen[k]:
                # The merged vector's support (an intersection) is often the shorter:
                # walk it and read the partner, never merged, from its row of G.
                s = _dot_with_g_row(G, k, ca, va, rowlen[a])
            else:
                s = _dot_with_row(merged, indices, values, indptr[k], rowlen[k], n)
            stats[2] += 1
            row_a[k] = s
            S[k, a] = s
            dk = _tanimoto_distance(s, s_aa, sq[k])
            if dk <= max_dist:
                pool[used] = _pack(dk, k << 1)
                used += 1
        if not dense:
            ca = indices[pa:pa + rowlen[a]]
            for q in range(len(ca)):
                dense_a[ca[q]] = 0.0
        # a's new list replaces the old one (whose entries all predate a's new vector).
        pool[first:used] = np.sort(pool[first:used])
        start[a] = head[a] = first
        stop[a] = used
        built_at[a] = merges + 1
        if first < used:
            if size + 1 > len(heap):
                heap = _grow(heap, 2 * len(heap))
            size = _row_heap_push(heap, size, ((pool[first] >> 32) << 32) | a, queued, a)
    stats[1] = merges
    # Resolve merge chains into cluster labels 0..C-1 (first appearance order).
    labels = np.empty(n, dtype=np.int64)
    root_label = -np.ones(n, dtype=np.int64)
    n_clusters = 0
    for i in range(n):
        r = i
        while parent[r] != r:
            r = parent[r]
        if root_label[r] < 0:
            root_label[r] = n_clusters
            n_clusters += 1
        labels[i] = root_label[r]
    return labels


def cluster_compatibility_vectors(G: np.ndarray, min_dist_thresh: float = 0.2,
                                  stats: np.ndarray | None = None, overwrite: bool = False) -> np.ndarray:
    """Cluster labels (N,) int64, 0..C-1, from the agglomerative clustering of G's rows.

    ``stats``, if given (4 int64), receives: initial candidate pairs, merges, exact dot
    products computed, 0. ``overwrite``: G (float32, C-contiguous) may be overwritten (dense
    rows become the merged vectors in place), which saves a copy of it.
    """
    n = len(G)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    G = np.ascontiguousarray(G, dtype=np.float32)
    counts, row_end = _row_counts(G)
    if counts.sum() > _DENSE_ROWS_ABOVE * n * n:
        # Dense: one GEMM (the sparse product cannot win here), and full rows need no
        # column indices: the rows of G (or of a copy) are used as they are.
        S = _gram(G)
        indptr = np.arange(0, n * n + 1, n, dtype=np.int64)
        indices = np.zeros(0, dtype=np.int32)
        values = G.reshape(-1) if overwrite else G.reshape(-1).copy()
        dense = True
    else:
        indptr, indices, values = _to_rows(G, counts)
        if _SPARSE_PRODUCT_COST * _sparse_product_work(indptr, indices, row_end) < float(n) ** 3:
            S = _sparse_gram(G, indptr, indices, values, row_end)
        else:
            S = _gram(G)
        dense = False
    stats = np.zeros(4, dtype=np.int64) if stats is None else stats
    return _agglomerate(G, indptr, indices, values, S, float(min_dist_thresh), dense, stats)
