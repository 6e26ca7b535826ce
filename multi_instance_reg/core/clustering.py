"""Agglomerative clustering of compatibility vectors (ECC paper, Sec. 3.2).

Every correspondence starts as its own group, represented by its compatibility vector (a row
of G). The two groups with the smallest Tanimoto distance
    d(p, q) = 1 - <p, q> / (|p|^2 + |q|^2 - <p, q>)
are merged, the merged representation being the element-wise minimum, until the smallest
distance exceeds ``min_dist_thresh``.

The authors' code recomputes a full N x N distance matrix and takes a global argmin per
merge, O(N^3) in all. This implementation gives the same merges with far less work:
- dot products of untouched groups never change, so they are computed once (one GEMM);
- for a merged group m = min(p, q) and any group r, <m, r> <= min(<p, r>, <q, r>) because all
  entries are non-negative; that bound (and the Tanimoto bound it implies) rules out almost
  every pair, and the exact dot product is computed only for pairs that could still merge;
- candidate pairs wait in a heap; entries of groups that changed since are skipped, so
  nothing is ever rescanned. Ties break by index, so results are deterministic.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=True)
def _tanimoto_distance(dot, sq_a, sq_b):
    denom = sq_a + sq_b - dot
    if denom <= 0.0:
        return 1.0
    return 1.0 - dot / denom


@numba.njit(cache=True, fastmath=True)
def _exact_dot(P, a, k, support, n_support):
    # Dense rows vectorise (SIMD) and beat a gather over the support unless it is small.
    s = np.float32(0.0)
    if 32 * n_support < P.shape[1]:
        for t in range(n_support):
            c = support[t]
            s += P[a, c] * P[k, c]
    else:
        for c in range(P.shape[1]):
            s += P[a, c] * P[k, c]
    return np.float64(s)


# A binary min-heap of (key, entry) held in two parallel arrays, keys inline so sifting
# touches contiguous memory (numba's heapq on tuples is several times slower).
@numba.njit(cache=True)
def _heap_push(hkey, hval, size, k, v):
    i = size
    while i > 0:
        p = (i - 1) >> 1
        if hkey[p] <= k:
            break
        hkey[i] = hkey[p]
        hval[i] = hval[p]
        i = p
    hkey[i] = k
    hval[i] = v
    return size + 1


@numba.njit(cache=True)
def _sift_down(hkey, hval, size, i):
    k = hkey[i]
    v = hval[i]
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and hkey[c + 1] < hkey[c]:
            c += 1
        if k <= hkey[c]:
            break
        hkey[i] = hkey[c]
        hval[i] = hval[c]
        i = c
    hkey[i] = k
    hval[i] = v


@numba.njit(cache=True)
def _heap_pop(hkey, hval, size):
    v = hval[0]
    size -= 1
    if size > 0:
        hkey[0] = hkey[size]
        hval[0] = hval[size]
        _sift_down(hkey, hval, size, 0)
    return v, size


@numba.njit(cache=True)
def _agglomerate(P, S, max_dist, stats):
    n = P.shape[0]
    sq = np.empty(n, dtype=np.float64)
    for i in range(n):
        sq[i] = S[i, i]
    active = np.ones(n, dtype=np.bool_)
    version = np.zeros(n, dtype=np.int64)
    parent = np.arange(n)
    support = np.empty(n, dtype=np.int64)

    # Entry storage: the initial candidate pairs (counted first, so the hot loop never
    # reallocates) plus room for merges; it grows by doubling if merges need more.
    n_initial = 0
    for i in range(n):
        for j in range(i + 1, n):
            if _tanimoto_distance(S[i, j], sq[i], sq[j]) <= max_dist:
                n_initial += 1
    cap = n_initial + 4 * n + 16
    hkey = np.empty(cap, dtype=np.float64)
    ea = np.empty(cap, dtype=np.int64)
    eb = np.empty(cap, dtype=np.int64)
    eva = np.zeros(cap, dtype=np.int64)
    evb = np.zeros(cap, dtype=np.int64)
    heap = np.empty(cap, dtype=np.int64)
    n_entries = 0
    for i in range(n):
        for j in range(i + 1, n):
            d = _tanimoto_distance(S[i, j], sq[i], sq[j])
            if d <= max_dist:
                hkey[n_entries] = d
                ea[n_entries] = i
                eb[n_entries] = j
                n_entries += 1
    # Heapify bottom-up: O(n_entries).
    for e in range(n_entries):
        heap[e] = e
    size = n_entries
    for i in range(size // 2 - 1, -1, -1):
        _sift_down(hkey, heap, size, i)
    stats[0] = n_entries

    while size > 0:
        e, size = _heap_pop(hkey, heap, size)
        a = ea[e]
        b = eb[e]
        if not (active[a] and active[b] and version[a] == eva[e] and version[b] == evb[e]):
            continue
        stats[1] += 1
        # Room for every push this merge can make, reserved here and not inside the loop
        # below: reassigning arrays there makes numba refcount them on every iteration.
        if n_entries + n > cap:
            cap = 2 * (n_entries + n)
            hkey = _grow(hkey, cap)
            ea = _grow(ea, cap)
            eb = _grow(eb, cap)
            eva = _grow(eva, cap)
            evb = _grow(evb, cap)
            heap = _grow(heap, cap)
        # Merge b into a: element-wise minimum.
        n_support = 0
        s_aa = 0.0
        for c in range(n):
            v = min(P[a, c], P[b, c])
            P[a, c] = v
            if v > 0.0:
                support[n_support] = c
                n_support += 1
                s_aa += v * v
        sq[a] = s_aa
        S[a, a] = s_aa
        active[b] = False
        parent[b] = a
        version[a] += 1
        # New dot products of a: the bound min(<p_a, r>, <p_b, r>) everywhere, made exact
        # only where the bound still allows a merge.
        # Only row a is rewritten (contiguous): a column entry S[k, a] left stale is still an
        # upper bound, since a's vector only ever shrinks. Exact values go both ways.
        for k in range(n):
            if k == a or not active[k]:
                continue
            bound = min(S[a, k], S[b, k])
            S[a, k] = bound
            if _tanimoto_distance(bound, sq[a], sq[k]) <= max_dist:
                s = _exact_dot(P, a, k, support, n_support)
                stats[2] += 1
                stats[3] += n_support
                S[a, k] = s
                S[k, a] = s
                dk = _tanimoto_distance(s, sq[a], sq[k])
                if dk <= max_dist:
                    lo = min(a, k)
                    hi = max(a, k)
                    ea[n_entries] = lo
                    eb[n_entries] = hi
                    eva[n_entries] = version[lo]
                    evb[n_entries] = version[hi]
                    size = _heap_push(hkey, heap, size, dk, n_entries)
                    n_entries += 1
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


@numba.njit(cache=True)
def _grow(arr, cap):
    out = np.empty(cap, dtype=arr.dtype)
    out[: len(arr)] = arr
    return out


def cluster_compatibility_vectors(G: np.ndarray, min_dist_thresh: float = 0.2) -> np.ndarray:
    """Cluster labels (N,) int64, 0..C-1, from the agglomerative clustering of G's rows."""
    n = len(G)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    P = np.array(G, dtype=np.float32, order="C", copy=True)
    S = P @ P  # G is symmetric: row dot products, one GEMM.
    stats = np.zeros(4, dtype=np.int64)
    return _agglomerate(P, S, float(min_dist_thresh), stats)
