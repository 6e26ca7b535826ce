"""Synthetic multi-instance correspondence sets following the ECC paper's Table 1 protocol.

ModelNet40 is not available here, so shapes are generated: unions of boxes, cylinders, cones,
spheres and tori (tables, chairs, lamps, planes, mugs, ...), normalised to the unit sphere.
One scene (NOTES.md section 2):
- source: 256 points sampled on one shape, jitter N(0, 0.01) clipped at 0.05;
- K instances (1..20): the same shape resampled independently (no exact point
  correspondences), jittered, a uniformly random rotation and a translation of length 2.5 to
  12.5 in a random direction;
- distractors: other shapes placed the same way; 1000 uniform noise points in [0, 10)^3;
- every target point is matched to one source point (one-to-many, as feature matching does):
  an inlier to its nearest source point on the true instance, an outlier to a random one;
- the outlier ratio r is drawn uniformly inside a band; when the target points cannot give
  that ratio, noise/distractor points are subsampled or instance points mismatched.

The hard variant (``HARD``, `mireg bench table1 --hard`) is closer to real feature matching:
each instance shows only a partial view (the 30-100 % of its points nearest a random viewing
direction), a quarter of the matches on an instance go to a near-neighbour of the right
source point (2nd to 5th nearest: the confusion of similar descriptors; counted as
outliers), and up to 30 instances instead of 20.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

POINTS_PER_MODEL = 256
NOISE_POINTS = 1000
BANDS = {"10-50": (0.10, 0.50), "50-70": (0.50, 0.70), "70-90": (0.70, 0.90), "90-99": (0.90, 0.99)}


# -- shapes: lists of primitives (kind, params, centre) -------------------------------------
def _box_surface(rng, n, size):
    size = np.asarray(size, float)
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]) * 2
    face = rng.choice(3, n, p=areas / areas.sum())
    p = (rng.random((n, 3)) - 0.5) * size
    sign = np.where(rng.random(n) < 0.5, -0.5, 0.5)
    p[np.arange(n), face] = sign * size[face]
    return p


def _cylinder_surface(rng, n, radius, height, top_radius=None):
    top_radius = radius if top_radius is None else top_radius
    side = np.pi * (radius + top_radius) * np.hypot(height, radius - top_radius)
    caps = np.pi * (radius ** 2 + top_radius ** 2)
    on_side = rng.random(n) < side / (side + caps)
    z = (rng.random(n) - 0.5) * height
    r = np.where(on_side, radius + (top_radius - radius) * (z / height + 0.5), 0.0)
    top = rng.random(n) < top_radius ** 2 / max(radius ** 2 + top_radius ** 2, 1e-12)
    cap_r = np.where(top, top_radius, radius) * np.sqrt(rng.random(n))
    r = np.where(on_side, r, cap_r)
    z = np.where(on_side, z, np.where(top, 0.5, -0.5) * height)
    phi = rng.random(n) * 2 * np.pi
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _sphere_surface(rng, n, radius):
    v = rng.normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def _torus_surface(rng, n, major, minor):
    # Rejection sampling for uniform area density.
    out = []
    while sum(len(o) for o in out) < n:
        u, v, w = rng.random((3, 2 * n)) * [[2 * np.pi], [2 * np.pi], [1.0]]
        keep = w < (major + minor * np.cos(v)) / (major + minor)
        u, v = u[keep], v[keep]
        out.append(np.stack([(major + minor * np.cos(v)) * np.cos(u),
                             (major + minor * np.cos(v)) * np.sin(u), minor * np.sin(v)], 1))
    return np.concatenate(out)[:n]


_PRIMITIVES = {
    "box": lambda rng, n, p: _box_surface(rng, n, p),
    "cyl": lambda rng, n, p: _cylinder_surface(rng, n, *p),
    "sphere": lambda rng, n, p: _sphere_surface(rng, n, *p),
    "torus": lambda rng, n, p: _torus_surface(rng, n, *p),
}

SHAPES = {
    "table": [("box", (1.6, 1.0, 0.08), (0, 0, 0.5))] + [
        ("box", (0.08, 0.08, 0.9), (sx * 0.7, sy * 0.42, 0.0)) for sx in (-1, 1) for sy in (-1, 1)],
    "chair": [("box", (0.8, 0.8, 0.08), (0, 0, 0)), ("box", (0.8, 0.08, 0.9), (0, 0.36, 0.45))] + [
        ("box", (0.07, 0.07, 0.7), (sx * 0.35, sy * 0.35, -0.35)) for sx in (-1, 1) for sy in (-1, 1)],
    "lamp": [("cyl", (0.35, 0.06), (0, 0, -0.8)), ("cyl", (0.04, 1.3), (0, 0, -0.1)),
             ("cyl", (0.15, 0.4, 0.45), (0, 0.0, 0.65))],
    "airplane": [("cyl", (0.12, 1.8, 0.05), (0, 0, 0)), ("box", (1.6, 0.35, 0.04), (0, 0.1, 0)),
                 ("box", (0.6, 0.15, 0.03), (0, -0.75, 0.05)), ("box", (0.03, 0.2, 0.35), (0, -0.8, 0.2))],
    "mug": [("cyl", (0.4, 0.9), (0, 0, 0)), ("torus", (0.25, 0.06), (0.55, 0, 0))],
    "bottle": [("cyl", (0.3, 1.1), (0, 0, -0.3)), ("cyl", (0.3, 0.3, 0.1), (0, 0, 0.4)),
               ("cyl", (0.1, 0.35), (0, 0, 0.72))],
    "guitar": [("cyl", (0.45, 0.2), (0, -0.45, 0)), ("cyl", (0.33, 0.2), (0, 0.15, 0)),
               ("box", (0.12, 1.0, 0.06), (0, 0.85, 0.05))],
    "sofa": [("box", (1.6, 0.7, 0.35), (0, 0, 0)), ("box", (1.6, 0.2, 0.6), (0, 0.35, 0.3)),
             ("box", (0.2, 0.7, 0.5), (0.8, 0, 0.2)), ("box", (0.2, 0.7, 0.5), (-0.8, 0, 0.2))],
    "bowl": [("sphere", (0.7,), (0, 0, 0)), ("torus", (0.7, 0.05), (0, 0, 0.1))],
    "stool": [("cyl", (0.4, 0.08), (0, 0, 0.5))] + [
        ("cyl", (0.04, 1.0), (0.28 * np.cos(a), 0.28 * np.sin(a), 0.0)) for a in (0.3, 2.4, 4.5)],
}


def sample_shape(name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points on the surface of a named shape, centred and scaled into the unit sphere."""
    parts = SHAPES[name]
    # Area-proportional allocation, estimated from a generous sample of each part.
    probe = [_PRIMITIVES[k](np.random.default_rng(0), 4096, p) for k, p, _ in parts]
    extents = np.array([np.prod(np.ptp(q, 0) + 1e-3) ** (2 / 3) for q in probe])
    counts = rng.multinomial(n, extents / extents.sum())
    pts = np.concatenate([_PRIMITIVES[k](rng, c, p) + np.asarray(centre)
                          for (k, p, centre), c in zip(parts, counts) if c > 0])
    # Normalise with fixed statistics (from the probe) so every resample shares one frame.
    ref = np.concatenate([q + np.asarray(c) for q, (_, _, c) in zip(probe, parts)])
    centre = (ref.max(0) + ref.min(0)) / 2
    scale = np.linalg.norm(ref - centre, axis=1).max()
    return (pts - centre) / scale


@dataclass
class CorrespondenceScene:
    src: np.ndarray         # (N, 3)
    tgt: np.ndarray         # (N, 3)
    T_gt: np.ndarray        # (K, 4, 4) source -> target
    is_inlier: np.ndarray   # (N,) bool
    instance: np.ndarray    # (N,) int64, instance of an inlier, -1 otherwise
    outlier_ratio: float
    shape: str


def _random_pose(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(2.5, 12.5)
    return T


def _jitter(rng, n):
    return np.clip(rng.normal(0.0, 0.01, (n, 3)), -0.05, 0.05)


@dataclass(frozen=True)
class Difficulty:
    max_instances: int = 20
    visible: tuple[float, float] = (1.0, 1.0)   # fraction of each instance's points seen
    confusion: float = 0.0                      # share of instance matches sent to a near neighbour


PLAIN = Difficulty()
HARD = Difficulty(max_instances=30, visible=(0.3, 1.0), confusion=0.25)


def _partial_view(rng, pts: np.ndarray, fraction: float) -> np.ndarray:
    """Indices of the ``fraction`` of points that lie furthest along a random direction."""
    if fraction >= 1.0:
        return np.arange(len(pts))
    direction = rng.normal(size=3)
    order = np.argsort(-(pts @ direction), kind="stable")
    return np.sort(order[: max(3, int(round(fraction * len(pts))))])


def make_scene(rng: np.random.Generator, band=(0.1, 0.5), max_instances: int | None = None,
               n_distractors: int = 2, difficulty: Difficulty = PLAIN) -> CorrespondenceScene:
    names = list(SHAPES)
    shape = names[rng.integers(len(names))]
    src_clean = sample_shape(shape, POINTS_PER_MODEL, rng)
    src = src_clean + _jitter(rng, POINTS_PER_MODEL)
    tree = cKDTree(src_clean)
    max_instances = difficulty.max_instances if max_instances is None else max_instances
    k = int(rng.integers(1, max_instances + 1))
    T_gt = np.stack([_random_pose(rng) for _ in range(k)])

    inst_tgt, inst_src_idx, inst_id, confused = [], [], [], []
    for i, T in enumerate(T_gt):
        pts = sample_shape(shape, POINTS_PER_MODEL, rng)
        if difficulty.visible != (1.0, 1.0):
            pts = pts[_partial_view(rng, pts, rng.uniform(*difficulty.visible))]
        if difficulty.confusion > 0:
            # The 2nd to 5th nearest source point: a match to a similar-looking neighbour.
            near = tree.query(pts, k=5)[1]
            wrong_near = rng.random(len(pts)) < difficulty.confusion
            idx = np.where(wrong_near, near[np.arange(len(pts)), rng.integers(1, 5, len(pts))], near[:, 0])
        else:
            idx, wrong_near = tree.query(pts)[1], np.zeros(len(pts), bool)
        inst_src_idx.append(idx)
        confused.append(wrong_near)
        inst_tgt.append((pts + _jitter(rng, len(pts))) @ T[:3, :3].T + T[:3, 3])
        inst_id.append(np.full(len(pts), i))
    inst_tgt = np.concatenate(inst_tgt)
    inst_src_idx = np.concatenate(inst_src_idx)
    inst_id = np.concatenate(inst_id)
    confused = np.concatenate(confused)

    others = [rng.uniform(0, 10, (NOISE_POINTS, 3))]
    for name in rng.choice([s for s in names if s != shape], n_distractors, replace=False):
        T = _random_pose(rng)
        others.append(sample_shape(name, POINTS_PER_MODEL, rng) @ T[:3, :3].T + T[:3, 3])
    others = np.concatenate(others)

    ratio = float(rng.uniform(*band))
    n_inst, n_other = len(inst_tgt), len(others)
    n_out_needed = int(round(n_inst * ratio / (1 - ratio)))
    if n_out_needed <= n_other:
        # Enough clutter: every instance point is an inlier, clutter is subsampled.
        n_in = n_inst
        others = others[rng.choice(n_other, n_out_needed, replace=False)]
        wrong = confused.copy()
    else:
        # Not enough clutter: keep all of it and mismatch some instance points.
        n_in = int(round((1 - ratio) * (n_inst + n_other)))
        wrong = np.ones(n_inst, bool)
        right = np.flatnonzero(~confused)
        wrong[rng.choice(right, min(n_in, len(right)), replace=False)] = False

    src_idx = inst_src_idx.copy()
    # A mismatched point gets any other source point (never its true one); a confused one
    # keeps its near neighbour.
    mismatch = wrong & ~confused
    src_idx[mismatch] = (inst_src_idx[mismatch] + rng.integers(1, POINTS_PER_MODEL, mismatch.sum())) % POINTS_PER_MODEL
    tgt = np.concatenate([inst_tgt, others])
    all_src_idx = np.concatenate([src_idx, rng.integers(0, POINTS_PER_MODEL, len(others))])
    is_inlier = np.concatenate([~wrong, np.zeros(len(others), bool)])
    instance = np.concatenate([np.where(wrong, -1, inst_id), -np.ones(len(others), np.int64)])
    perm = rng.permutation(len(tgt))
    return CorrespondenceScene(src[all_src_idx][perm], tgt[perm], T_gt, is_inlier[perm],
                               instance[perm].astype(np.int64), 1 - is_inlier.mean(), shape)


def make_band(band: str, n_samples: int, seed: int = 0, difficulty: Difficulty = PLAIN) -> list[CorrespondenceScene]:
    """n_samples scenes of one outlier band, deterministic for a seed (and a difficulty:
    the hard set draws from its own stream, so the plain set stays as it was)."""
    stream = [seed, list(BANDS).index(band)] + ([1] if difficulty != PLAIN else [])
    rng = np.random.default_rng(stream)
    return [make_scene(rng, BANDS[band], difficulty=difficulty) for _ in range(n_samples)]


def make_sized_scene(rng: np.random.Generator, n: int, outlier_ratio: float = 0.6,
                     n_instances: int = 10) -> CorrespondenceScene:
    """Exactly n correspondences with a given outlier ratio, for timing the core at a size.

    Same construction as ``make_scene`` (one-to-many, resampled instances, noise and
    distractor clutter), but instances are sampled more or less densely to reach n.
    """
    names = list(SHAPES)
    shape = names[rng.integers(len(names))]
    src_clean = sample_shape(shape, POINTS_PER_MODEL, rng)
    src = src_clean + _jitter(rng, POINTS_PER_MODEL)
    tree = cKDTree(src_clean)
    n_in = int(round(n * (1 - outlier_ratio)))
    per_instance = np.full(n_instances, n_in // n_instances)
    per_instance[: n_in % n_instances] += 1
    T_gt = np.stack([_random_pose(rng) for _ in range(n_instances)])
    tgt, src_idx, inst = [], [], []
    for i, (T, m) in enumerate(zip(T_gt, per_instance)):
        pts = sample_shape(shape, int(m), rng)
        src_idx.append(tree.query(pts)[1])
        tgt.append((pts + _jitter(rng, len(pts))) @ T[:3, :3].T + T[:3, 3])
        inst.append(np.full(len(pts), i))
    n_out = n - n_in
    n_noise = n_out // 2
    clutter = [rng.uniform(0, 10, (n_noise, 3))]
    n_distract = n_out - n_noise
    for j in range(2):
        T = _random_pose(rng)
        m = n_distract // 2 + (j < n_distract % 2)
        other = names[(names.index(shape) + 1 + j) % len(names)]
        clutter.append(sample_shape(other, m, rng) @ T[:3, :3].T + T[:3, 3])
    clutter = np.concatenate(clutter)
    src_idx.append(rng.integers(0, POINTS_PER_MODEL, len(clutter)))
    inst.append(-np.ones(len(clutter), np.int64))
    tgt = np.concatenate(tgt + [clutter])
    src_idx = np.concatenate(src_idx)
    inst = np.concatenate(inst).astype(np.int64)
    perm = rng.permutation(n)
    return CorrespondenceScene(src[src_idx][perm], tgt[perm], T_gt, inst[perm] >= 0, inst[perm],
                               n_out / n, shape)
