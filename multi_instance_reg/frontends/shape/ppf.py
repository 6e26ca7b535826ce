"""Point-pair features (Drost et al., CVPR 2010) voted per segment, turned into
correspondences for ECC. No ROS, no colour.

Why PPF and not FPFH on boxes, bins and cylinders: FPFH describes a point's neighbourhood,
and on a flat face every neighbourhood is the same; a pair of points (distance, and the angles
of both normals to the line joining them and to each other) relates two places of the object
that may be a whole face apart. Voting over all pairs of a reference point finds which model
point it is and how the object is turned about its normal; on a face seen alone the votes
peak where the whole segment fits inside the model's face, i.e. the outline decides.

Model (once): every ordered pair of surface points within the object's diameter, hashed by
its quantised feature, each with its angle alpha_m about the first point's normal. Buckets
are capped (a random subset), since a box has thousands of coplanar pairs per distance.

Frame: for each reference point of a segment (a subset), pair it with points of the same
segment within the object's diameter (at most ``max_partners``, evenly spread), look each pair up, and vote for (model point, turn
about the normal). The peak gives the reference point's model point and a full pose. Each
reference yields the correspondence (model point -> reference point), once per discrete
symmetry of the object and, for a continuous one, on the turn nearest a canonical one (so
that the references of one instance agree): ECC then groups consistent correspondences into
instances.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from ...symmetry import Symmetries
from ...threads import map_in_chunks

ANGLE_BINS = 15         # over [0, pi]: 12 deg
TURN_BINS = 30          # over [0, 2 pi): 12 deg


@numba.njit(cache=True, fastmath=True)
def _align_to_x(n0, n1, n2):
    """Rotation (3x3) taking unit vector n to +x."""
    R = np.eye(3)
    c = n0
    # axis = n x e_x = (0, n2, -n1)
    a1, a2 = n2, -n1
    s = math.sqrt(a1 * a1 + a2 * a2)
    if s < 1e-9:
        if c < 0:
            R[0, 0] = -1.0
            R[1, 1] = -1.0
        return R
    a1 /= s
    a2 /= s
    # Rodrigues with axis (0, a1, a2), sin = s, cos = c.
    C = 1.0 - c
    R[0, 0] = c
    R[0, 1] = -a2 * s
    R[0, 2] = a1 * s
    R[1, 0] = a2 * s
    R[1, 1] = c + a1 * a1 * C
    R[1, 2] = a1 * a2 * C
    R[2, 0] = -a1 * s
    R[2, 1] = a1 * a2 * C
    R[2, 2] = c + a2 * a2 * C
    return R


@numba.njit(cache=True, fastmath=True)
def _feature(p, n, i, j, R, d_step, a_step, n_dist):
    """(key, alpha) of the pair (i, j); key -1 when too far or degenerate. R aligns n[i] to x."""
    dx = p[j, 0] - p[i, 0]
    dy = p[j, 1] - p[i, 1]
    dz = p[j, 2] - p[i, 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d < 1e-9:
        return -1, 0.0
    db = int(d / d_step)
    if db >= n_dist:
        return -1, 0.0
    ux, uy, uz = dx / d, dy / d, dz / d
    c2 = n[i, 0] * ux + n[i, 1] * uy + n[i, 2] * uz
    c3 = n[j, 0] * ux + n[j, 1] * uy + n[j, 2] * uz
    c4 = n[i, 0] * n[j, 0] + n[i, 1] * n[j, 1] + n[i, 2] * n[j, 2]
    b2 = min(int(math.acos(max(-1.0, min(1.0, c2))) / a_step), ANGLE_BINS - 1)
    b3 = min(int(math.acos(max(-1.0, min(1.0, c3))) / a_step), ANGLE_BINS - 1)
    b4 = min(int(math.acos(max(-1.0, min(1.0, c4))) / a_step), ANGLE_BINS - 1)
    key = ((db * ANGLE_BINS + b2) * ANGLE_BINS + b3) * ANGLE_BINS + b4
    vy = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
    vz = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz
    return key, math.atan2(vz, vy)


@numba.njit(cache=True)
def _model_pairs(p, n, d_step, a_step, n_dist):
    m = p.shape[0]
    keys = np.empty(m * (m - 1), np.int64)
    first = np.empty(m * (m - 1), np.int32)
    alpha = np.empty(m * (m - 1), np.float32)
    k = 0
    for i in range(m):
        R = _align_to_x(n[i, 0], n[i, 1], n[i, 2])
        for j in range(m):
            if j == i:
                continue
            key, a = _feature(p, n, i, j, R, d_step, a_step, n_dist)
            if key < 0:
                continue
            keys[k] = key
            first[k] = i
            alpha[k] = a
            k += 1
    return keys[:k], first[:k], alpha[:k]


@numba.njit(cache=True, nogil=True)
def _vote(p, n, refs, seg_start, seg_end, reach, max_partners, bucket_start, entry_first, entry_alpha,
          n_model, d_step, a_step, n_dist):
    """Per reference: (model point, turn bin, votes, partners) of the accumulator's peak;
    its partners within ``reach[r]`` of it."""
    nr = refs.shape[0]
    out_m = np.full(nr, -1, np.int64)
    out_turn = np.zeros(nr, np.int64)
    out_votes = np.zeros(nr, np.float32)
    out_partners = np.zeros(nr, np.int64)
    acc = np.zeros(n_model * TURN_BINS, np.float32)
    touched = np.empty(n_model * TURN_BINS, np.int64)
    two_pi = 2.0 * math.pi
    for r in range(nr):
        i = refs[r]
        lo, hi = seg_start[r], seg_end[r]
        # Partners spread evenly over the segment's points within the reach (the object's
        # diameter, or less; a segment may join several touching objects: spread over all of
        # it, most partners would lie on the others).
        reach2 = reach[r] ** 2
        in_reach = 0
        for j in range(lo, hi):
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            dz = p[j, 2] - p[i, 2]
            if dx * dx + dy * dy + dz * dz < reach2:
                in_reach += 1
        step = max(1, in_reach // max_partners)
        R = _align_to_x(n[i, 0], n[i, 1], n[i, 2])
        nt = 0
        partners = 0
        seen = -1
        for j in range(lo, hi):
            if j == i:
                continue
            dx = p[j, 0] - p[i, 0]
            dy = p[j, 1] - p[i, 1]
            dz = p[j, 2] - p[i, 2]
            if dx * dx + dy * dy + dz * dz >= reach2:
                continue
            seen += 1
            if seen % step != 0:
                continue
            key, a_s = _feature(p, n, i, j, R, d_step, a_step, n_dist)
            if key < 0:
                continue
            partners += 1
            b0, b1 = bucket_start[key], bucket_start[key + 1]
            if nt + b1 - b0 > touched.shape[0]:
                grown = np.empty(2 * (nt + b1 - b0), np.int64)
                grown[:nt] = touched[:nt]
                touched = grown
            # Every vote's cell listed, repeats too: the test "first vote in this cell?" was
            # a branch the CPU mispredicted on most votes (a third of the time). The cells
            # first (a loop that vectorises), then the votes.
            cells = touched[nt:nt + b1 - b0]
            alphas, firsts = entry_alpha[b0:b1], entry_first[b0:b1]
            for e in range(b1 - b0):
                turn = a_s - alphas[e]
                if turn < 0:
                    turn += two_pi
                tb = int(turn / two_pi * TURN_BINS)
                if tb >= TURN_BINS:
                    tb = 0
                cells[e] = firsts[e] * TURN_BINS + tb
            for e in range(b1 - b0):
                acc[cells[e]] += 1.0
            nt += b1 - b0
        # The peak, and the accumulator cleared for the next reference (touched cells only).
        # A cell's first listing sees its full count and clears it, its repeats see 0: the
        # same peak (the first-touched of the largest) as a list without repeats.
        best = 0.0
        bc = -1
        for q in range(nt):
            c = touched[q]
            if acc[c] > best:
                best = acc[c]
                bc = c
            acc[c] = 0.0
        if bc >= 0:
            out_m[r] = bc // TURN_BINS
            out_turn[r] = bc % TURN_BINS
        out_votes[r] = best
        out_partners[r] = partners
    return out_m, out_turn, out_votes, out_partners


def _rot_x(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1], R[:, 1, 2], R[:, 2, 1], R[:, 2, 2] = c, -s, s, c
    return R


class PPFModel:
    """The model's pair table and symmetries; ``correspondences`` votes a frame's segments."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, diameter: float, d_step: float,
                 symmetries: Symmetries | None = None, bucket_cap: int = 300, seed: int = 0):
        self.points = np.ascontiguousarray(points, np.float64)
        self.normals = np.ascontiguousarray(normals, np.float64)
        self.normals /= np.maximum(np.linalg.norm(self.normals, axis=1, keepdims=True), 1e-12)
        self.d_step = float(d_step)
        self.a_step = math.pi / ANGLE_BINS
        self.n_dist = int(diameter / d_step) + 1
        self.symmetries = symmetries
        keys, first, alpha = _model_pairs(self.points, self.normals, self.d_step, self.a_step, self.n_dist)
        # Random order, then grouped by key: a bucket's first ``bucket_cap`` entries are a
        # random subset of it.
        rng = np.random.default_rng(seed)
        perm = rng.permutation(len(keys))
        order = perm[np.argsort(keys[perm], kind="stable")]
        keys, first, alpha = keys[order], first[order], alpha[order]
        n_keys = self.n_dist * ANGLE_BINS ** 3
        start = np.searchsorted(keys, np.arange(n_keys + 1))
        rank = np.arange(len(keys)) - start[keys]
        keep = rank < bucket_cap
        keys, self._first, self._alpha = keys[keep], first[keep], alpha[keep]
        self._start = np.searchsorted(keys, np.arange(n_keys + 1)).astype(np.int64)
        self._first = np.ascontiguousarray(self._first)
        self._alpha = np.ascontiguousarray(self._alpha)
        self.pairs = int(len(keys))

    def vote(self, points: np.ndarray, normals: np.ndarray, labels: np.ndarray, ref_step: int, max_partners: int,
             reach: np.ndarray | None = None):
        """Peaks for reference points of the labelled segments (label >= 0), every
        ``ref_step``-th point of the segments laid end to end. Returns (scene index (R,),
        model index (R,), pose (R, 4, 4) model -> camera, votes / partners (R,))."""
        order = np.flatnonzero(labels >= 0)
        order = order[np.argsort(labels[order], kind="stable")]
        lab = labels[order]
        bounds = np.flatnonzero(np.diff(lab)) + 1
        seg_lo = np.concatenate([[0], bounds]).astype(np.int64)
        seg_hi = np.concatenate([bounds, [len(lab)]]).astype(np.int64)
        refs = np.arange(0, len(order), max(int(ref_step), 1))
        return self._peaks(points, normals, order, refs, seg_lo, seg_hi, max_partners, reach)[:4]

    def vote_groups(self, points: np.ndarray, normals: np.ndarray, groups: list, ref_step: int, max_partners: int,
                    leads=None):
        """``vote`` over groups of point indices (a point may be in several), each group's
        every ``ref_step``-th point a reference paired with points of that group only (the
        same peaks as one call per group); ``leads`` (one per group): only the group's first
        that many points are references, the rest partners only. Returns ``vote``'s and each
        reference's group (R,)."""
        sizes = np.asarray([len(g) for g in groups], np.int64)
        leads = sizes if leads is None else np.minimum(np.asarray(leads, np.int64), sizes)
        order = np.concatenate(groups).astype(np.int64) if len(groups) else np.zeros(0, np.int64)
        seg_hi = np.cumsum(sizes)
        seg_lo = seg_hi - sizes
        step = max(int(ref_step), 1)
        refs = np.concatenate([lo + np.arange(0, lead, step) for lo, lead in zip(seg_lo, leads)]) \
            if len(groups) else np.zeros(0, np.int64)
        return self._peaks(points, normals, order, refs.astype(np.int64), seg_lo, seg_hi, max_partners)

    def _peaks(self, points, normals, order, refs, seg_lo, seg_hi, max_partners, reach=None):
        """The references ``refs`` (positions in ``order``, the scene indices of segments laid
        end to end from ``seg_lo`` to ``seg_hi``) voted with partners of their own segment."""
        if len(order) < 2 or len(refs) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, np.int64)
        p = np.ascontiguousarray(points[order], np.float64)
        n = np.ascontiguousarray(normals[order], np.float64)
        seg = np.searchsorted(seg_hi, refs, side="right")
        lo, hi = seg_lo[seg], seg_hi[seg]
        # Each reference's partners within the object's diameter, or within ``reach`` (per
        # scene point) when that is less.
        full = self.n_dist * self.d_step
        radius = np.full(len(refs), full) if reach is None else np.minimum(np.asarray(reach, np.float64)[order[refs]], full)
        # Each reference votes on its own: the references in two halves on two cores (the
        # kernel releases the GIL; the same peaks as in one call).
        parts = map_in_chunks(lambda rows: _vote(p, n, refs[rows], lo[rows], hi[rows], radius[rows], int(max_partners), self._start,
                                                 self._first, self._alpha, len(self.points), self.d_step, self.a_step,
                                                 self.n_dist), np.arange(len(refs)), min_chunk=64)
        m, turn, votes, partners = (np.concatenate(column) for column in zip(*parts))
        ok = m >= 0
        refs, seg, m, turn, votes, partners = refs[ok], seg[ok], m[ok], turn[ok], votes[ok], partners[ok]
        poses = self._poses(p[refs], n[refs], m, (turn + 0.5) * (2 * math.pi / TURN_BINS))
        return order[refs], m, poses, votes / np.maximum(partners, 1), seg

    def _poses(self, s, ns, m, turn) -> np.ndarray:
        """T = R_s^T Rx(turn) R_m (rotations), mapping model point m onto scene point s."""
        Rm = _align_all(np.ascontiguousarray(self.normals[m], np.float64))
        Rs = _align_all(np.ascontiguousarray(ns, np.float64))
        R = np.transpose(Rs, (0, 2, 1)) @ _rot_x(turn) @ Rm
        T = np.tile(np.eye(4), (len(m), 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = s - np.einsum("rij,rj->ri", R, self.points[m])
        return T

    def canonical_poses(self, poses: np.ndarray) -> np.ndarray:
        """Each pose T replaced by the T @ S (S a symmetry) nearest a fixed orientation
        relative to the camera, so that the references of one symmetric instance agree (a
        continuous turn: a fixed model direction across the axis as nearly as it can along
        the viewing direction; then the discrete S whose rotation is nearest the camera's
        axes)."""
        sym = self.symmetries
        if sym is None or sym.is_trivial or len(poses) == 0:
            return poses
        out = np.array(poses, np.float64)
        if sym.axis is not None:
            out = out @ _canonical_turns(out, sym)
        if len(sym.discrete) > 1:
            cand = np.einsum("rij,sjk->rsik", out, np.asarray(sym.discrete, np.float64))
            best = np.argmax(np.trace(cand[:, :, :3, :3], axis1=2, axis2=3), axis=1)
            out = cand[np.arange(len(out)), best]
        return out

    def correspondences(self, scene_idx, poses, points: np.ndarray, neighbours: int = 4, canonical: bool = False,
                        tree=None) -> tuple[np.ndarray, np.ndarray]:
        """(model points (N, 3), scene indices (N,)): for each reference, itself and its
        ``neighbours`` nearest scene points spread over a few voxels, each with the model
        point its reference's (canonical) pose puts there. One reference thus gives a small
        rigid set; the references that agree on an instance's pose give one large consistent
        set, which ECC finds among the rest. ``tree``: a ``cKDTree(points)`` already built
        (the frame cloud's)."""
        if len(scene_idx) == 0:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        if not canonical:
            poses = self.canonical_poses(poses)
        from scipy.spatial import cKDTree

        k = 3 * neighbours + 1
        tree = cKDTree(points) if tree is None else tree
        # On every core: the pool's workers wait for ECC, which waits for these (the
        # queries are independent: the same neighbours on any number of threads).
        _, nb = tree.query(points[scene_idx], k=min(k, len(points)), workers=-1)
        nb = np.atleast_2d(nb)[:, ::3][:, :neighbours + 1]       # itself first, then every third nearest
        tgt = points[nb]                                          # (R, K, 3)
        Tinv = np.linalg.inv(poses)
        src = np.einsum("rij,rkj->rki", Tinv[:, :3, :3], tgt) + Tinv[:, None, :3, 3]
        return src.reshape(-1, 3), nb.reshape(-1)


def cluster_poses(poses: np.ndarray, weights: np.ndarray, max_angle_deg: float, max_shift: float,
                  max_clusters: int, min_members: int = 2, indices: bool = False, densest: bool = False) -> np.ndarray:
    """Pose hypotheses straight from the references' votes (Drost et al.'s pose clustering):
    greedily, strongest reference first, a pose joins the first cluster whose seed it is
    within ``max_angle_deg`` and ``max_shift`` of; clusters ranked by their summed weight.
    Returns the seeds of the best ``max_clusters`` clusters of at least ``min_members``
    (K, 4, 4), or with ``indices`` their indices in ``poses`` (K,). ``poses`` should be
    canonical over the symmetries (``canonical_poses``). ``densest``: the poses taken in the
    order of the summed weight of the poses within those bounds of each (its own included),
    not of their own weight: where the references spread about the right pose (a flat
    plate's votes, blurred in its plane), the strongest one may lie at the cluster's edge,
    25 deg off, and the seed is the hypothesis."""
    if len(poses) == 0:
        return np.zeros(0, np.int64) if indices else np.zeros((0, 4, 4))
    rank = np.asarray(weights, np.float64)
    if densest:
        rank = _pose_density(np.ascontiguousarray(poses[:, :3, :3], np.float64),
                             np.ascontiguousarray(poses[:, :3, 3], np.float64), rank, float(max_shift),
                             math.cos(math.radians(max_angle_deg)))
    order = np.argsort(-rank, kind="stable")
    R = poses[order, :3, :3]
    t = poses[order, :3, 3]
    w = np.asarray(weights, np.float64)[order]
    label, seeds = _greedy_pose_labels(np.ascontiguousarray(R, np.float64), np.ascontiguousarray(t, np.float64),
                                       float(max_shift), math.cos(math.radians(max_angle_deg)))
    counts = np.bincount(label, minlength=len(seeds))
    score = np.bincount(label, weights=w, minlength=len(seeds))
    best = [k for k in np.argsort(-score, kind="stable") if counts[k] >= min_members][:max_clusters]
    chosen = order[np.asarray([seeds[k] for k in best], np.int64)]
    if indices:
        return chosen
    return poses[chosen] if best else np.zeros((0, 4, 4))


@numba.njit(cache=True, nogil=True)
def _pose_density(R, t, w, max_shift, cos_max):
    """(N,): per pose, the summed weight ``w`` of the poses (itself included) within
    ``max_shift`` and an angle of arccos(``cos_max``) of it."""
    n = len(t)
    out = np.zeros(n)
    for i in range(n):
        for j in range(n):
            if _poses_near(R, t, i, j, max_shift, cos_max):
                out[i] += w[j]
    return out


@numba.njit(cache=True, nogil=True)
def _poses_near(R, t, i, j, max_shift, cos_max):
    """Poses i and j within ``max_shift`` and an angle of arccos(``cos_max``)."""
    dx, dy, dz = t[j, 0] - t[i, 0], t[j, 1] - t[i, 1], t[j, 2] - t[i, 2]
    if not math.sqrt(dx * dx + dy * dy + dz * dz) < max_shift:
        return False
    # trace(Ri^T Rj) = 1 + 2 cos(angle).
    tr = 0.0
    for a in range(3):
        for b in range(3):
            tr += R[i, a, b] * R[j, a, b]
    return (tr - 1.0) / 2.0 >= cos_max


@numba.njit(cache=True, nogil=True)
def _greedy_pose_labels(R, t, max_shift, cos_max):
    """cluster_poses' greedy pass, compiled (it ran 20 ms a frame as numpy calls per seed):
    each pose in turn, if still unassigned, seeds a cluster of the unassigned poses within
    ``max_shift`` and an angle of arccos(``cos_max``). Returns (label per pose, seeds)."""
    n = len(t)
    label = np.full(n, -1, np.int64)
    seeds = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if label[i] >= 0:
            continue
        for j in range(n):
            if label[j] < 0 and _poses_near(R, t, i, j, max_shift, cos_max):
                label[j] = k
        seeds[k] = i
        k += 1
    return label, seeds[:k]


def _canonical_turns(T: np.ndarray, sym: Symmetries) -> np.ndarray:
    """(R, 4, 4): per pose T (R, 4, 4), the turn S about the continuous axis that points a
    fixed model direction across the axis as nearly as it can along the camera's viewing
    direction (T @ S). All poses at once (one at a time it cost 40-70 ms a cylinder frame)."""
    a = sym.axis / np.linalg.norm(sym.axis)
    u = np.cross(a, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.3:
        u = np.cross(a, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    # R^T e_z and R^T e_x: rows 2 and 0 of R, less their part along the axis.
    w = T[:, 2, :3] - np.outer(T[:, 2, :3] @ a, a)
    side = np.linalg.norm(w, axis=1) < 0.3
    if side.any():
        w[side] = T[side, 0, :3] - np.outer(T[side, 0, :3] @ a, a)
    theta = np.arctan2(np.cross(u, w) @ a, w @ u)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    S = np.tile(np.eye(4), (len(T), 1, 1))
    S[:, :3, :3] = np.eye(3) + np.sin(theta)[:, None, None] * K + (1 - np.cos(theta))[:, None, None] * (K @ K)
    centre = np.asarray(sym.point, np.float64)
    S[:, :3, 3] = centre - S[:, :3, :3] @ centre
    return S


@numba.njit(cache=True, nogil=True)
def _align_all(n):
    """(N, 3, 3): _align_to_x of each row of n (one call, not one per row: 2-3 ms a frame)."""
    out = np.empty((n.shape[0], 3, 3))
    for i in range(n.shape[0]):
        out[i] = _align_to_x(n[i, 0], n[i, 1], n[i, 2])
    return out


__all__ = ["PPFModel", "cluster_poses"]
