"""Symmetries of rigid objects: found from a mesh, stored with the model, used by the metrics.

An object's symmetries are the rotations S (model frame, about a centre c, as 4 x 4
transforms) that leave its surface where it was: a pose T and T @ S look the same. Stored as
- ``discrete`` (S, 4, 4), the identity first (a box: 180 deg about each axis; a square face
  adds the quarter turns);
- optionally a continuous axis (a plain cylinder): every turn about ``axis`` through
  ``point`` is a symmetry too, combined with each discrete one.

Found from the mesh (NOTES.md section 12): candidate rotations about the surface's centroid
- 180 deg about each principal axis, n-fold turns about an axis whose two other principal
moments are (nearly) equal, and turns by odd angles about that axis for the continuous case -
are kept when they move the sampled surface onto itself (95 % of points within
``tolerance``); the set is closed under composition.

Errors "over the symmetries" (BOP): the ground-truth pose is replaced by the symmetric pose
nearest to the estimate (``closest_symmetric_pose``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .errors import InputError
from .transforms import apply_transform


def _rotation(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _about(R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


@dataclass
class Symmetries:
    discrete: np.ndarray = field(default_factory=lambda: np.eye(4)[None])   # (S, 4, 4), identity first
    axis: np.ndarray | None = None          # (3,) unit: continuous symmetry about this axis ...
    point: np.ndarray | None = None         # (3,) ... through this point (model frame)

    @property
    def is_trivial(self) -> bool:
        return len(self.discrete) <= 1 and self.axis is None

    def describe(self) -> str:
        if self.is_trivial:
            return "none"
        parts = []
        if len(self.discrete) > 1:
            parts.append(f"{len(self.discrete)} discrete poses")
        if self.axis is not None:
            parts.append(f"continuous about axis {np.round(self.axis, 3).tolist()}")
        return ", ".join(parts)

    def conjugated(self, T: np.ndarray) -> "Symmetries":
        """The same symmetries expressed in another frame: T maps model -> that frame."""
        T = np.asarray(T, np.float64)
        Ti = np.linalg.inv(T)
        disc = np.einsum("ij,sjk,kl->sil", T, self.discrete, Ti)
        axis = None if self.axis is None else T[:3, :3] @ self.axis
        point = None if self.point is None else T[:3, :3] @ self.point + T[:3, 3]
        return Symmetries(disc, axis, point)


def turn_about(axis, point, angle: float) -> np.ndarray:
    """4 x 4: the turn by ``angle`` (radians) about ``axis`` through ``point``."""
    return _about(_rotation(axis, angle), np.asarray(point, np.float64))


def best_symmetry(x: np.ndarray, y: np.ndarray, sym: "Symmetries | None", within: float
                  ) -> tuple[np.ndarray, int, int]:
    """Which symmetry M (model frame) takes points ``x`` (N, 3) onto their matches ``y`` (N, 3)
    best: (M, pairs within ``within`` metres with it, with the best other discrete symmetry).
    With a continuous axis, each pair whose height along it and radius about it agree
    proposes a turn; the turn most pairs agree with wins, refined by least squares on those
    (a cup's shape is the same at any turn, its print is not)."""
    x, y = np.asarray(x, np.float64).reshape(-1, 3), np.asarray(y, np.float64).reshape(-1, 3)
    candidates = [np.eye(4)] if sym is None else list(sym.discrete)
    scored = []
    for S in candidates:
        xs = apply_transform(S, x)
        M = S
        if sym is not None and sym.axis is not None and len(x):
            a, c = sym.axis / np.linalg.norm(sym.axis), sym.point
            px, py = xs - c, y - c
            hx, hy = px @ a, py @ a
            rx, ry = px - np.outer(hx, a), py - np.outer(hy, a)
            ok = (np.abs(hx - hy) < within) & (np.abs(np.linalg.norm(rx, axis=1) - np.linalg.norm(ry, axis=1)) < within)
            if ok.sum() == 0:
                scored.append((0, S))
                continue
            rx, ry = rx[ok], ry[ok]
            ang = np.arctan2(np.cross(rx, ry) @ a, np.einsum("ij,ij->i", rx, ry))
            cos, sin = np.cos(ang)[:, None], np.sin(ang)[:, None]
            # (proposals, pairs): distance of every pair under every proposed turn.
            turned = (cos[:, :, None] * rx[None] + sin[:, :, None] * np.cross(a, rx)[None])
            support = np.linalg.norm(turned - ry[None], axis=2) < within
            members = support[int(np.argmax(support.sum(axis=1)))]
            angle = float(np.arctan2(np.sum(np.cross(rx[members], ry[members]) @ a),
                                     np.sum(np.einsum("ij,ij->i", rx[members], ry[members]))))
            M = turn_about(a, c, angle) @ S
            xs = apply_transform(M, x)
        scored.append((int(np.sum(np.linalg.norm(xs - y, axis=1) < within)), M))
    scored.sort(key=lambda s: -s[0])
    second = scored[1][0] if len(scored) > 1 else 0
    return scored[0][1], scored[0][0], second


def closest_symmetric_pose(T_gt: np.ndarray, T_est: np.ndarray, sym: Symmetries | None) -> np.ndarray:
    """Among the poses T_gt @ S that look like T_gt, the one nearest to T_est (rotation first:
    the continuous turn is the one that minimises the rotation error, in closed form)."""
    T_gt = np.asarray(T_gt, np.float64)
    if sym is None or sym.is_trivial:
        return T_gt
    best, best_cost = T_gt, np.inf
    for S in sym.discrete:
        cand = T_gt @ S
        if sym.axis is not None:
            # Maximise trace(M Rot_a(theta)), M = R_est^T R_cand: A cos + B sin + const.
            a = sym.axis
            M = T_est[:3, :3].T @ cand[:3, :3]
            ax = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            A = np.trace(M) - a @ M @ a
            B = np.trace(M @ ax)
            theta = np.arctan2(B, A)
            cand = cand @ _about(_rotation(a, theta), sym.point)
        cost = np.linalg.norm(cand - T_est)
        if cost < best_cost:
            best, best_cost = cand, cost
    return best


# --------------------------------------------------------------------------- detection

def detect_symmetries(points: np.ndarray, tolerance: float, max_order: int = 12) -> Symmetries:
    """Symmetries of a surface sampled densely and evenly by ``points`` (N, 3); a candidate
    passes when 95 % of the moved points lie within ``tolerance`` of the surface samples."""
    pts = np.asarray(points, np.float64)
    centre = pts.mean(axis=0)
    q = pts - centre
    evals, evecs = np.linalg.eigh(q.T @ q / len(q))
    tree = cKDTree(pts)
    # Test on a subset (the tree keeps all points): 3,000 points decide as well as 20,000.
    probe = q[np.random.default_rng(0).permutation(len(q))[:3000]]

    def fits(R: np.ndarray) -> bool:
        d, _ = tree.query(probe @ R.T + centre, k=1, workers=-1)
        return float(np.percentile(d, 95)) < tolerance

    axes = [evecs[:, k] for k in range(3)]
    scale = max(evals.max(), 1e-12)
    degenerate = [a for k, a in enumerate(axes)
                  if abs(np.diff([evals[j] for j in range(3) if j != k])[0]) <= 0.05 * scale]

    def in_plane(a):
        """Axes perpendicular to a, every 5 deg (a near-degenerate plane's principal axes
        are arbitrary)."""
        u = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        w = np.cross(a, u)
        return [np.cos(t) * u + np.sin(t) * w for t in np.radians(np.arange(0, 180, 5))]

    # Continuous: odd turns about a near-degenerate axis (or one of the mesh's axes) all fit.
    for a in degenerate + [np.eye(3)[k] for k in range(3)]:
        if all(fits(_rotation(a, np.radians(ang))) for ang in (7.0, 23.0, 71.0, 137.0)):
            a = a / np.linalg.norm(a)
            flip = next((_rotation(b, np.pi) for b in in_plane(a) if fits(_rotation(b, np.pi))), None)
            group = [np.eye(3)] + ([flip] if flip is not None else [])
            return Symmetries(np.stack([_about(R, centre) for R in group]), a, centre)

    found = [np.eye(3)]
    # The mesh's own axes too: when principal moments are equal (a cube) the principal axes
    # are arbitrary, and CAD models are usually drawn along their symmetry axes.
    candidates = [np.eye(3)[k] for k in range(3)] + axes
    for a in degenerate:
        candidates += in_plane(a)
    for a in candidates:
        R = _rotation(a, np.pi)
        if not any(np.linalg.norm(R - Q) < 0.1 for Q in found) and fits(R):
            found.append(R)
            if len(found) > 8:          # enough generators; the closure adds the rest
                break
    for a in [np.eye(3)[k] for k in range(3)] + degenerate:
        for n in range(max_order, 2, -1):
            if fits(_rotation(a, 2 * np.pi / n)):
                found.append(_rotation(a, 2 * np.pi / n))
                break
    group = _close(found)
    return Symmetries(np.stack([_about(R, centre) for R in group]))


def _close(rotations: list[np.ndarray], limit: int = 48) -> list[np.ndarray]:
    """The set closed under composition (a finite group), identity first."""
    group = [np.eye(3)]

    def add(R):
        # Near-equal rotations (axes estimated from samples) count as one.
        if len(group) < limit and not any(np.linalg.norm(R - Q) < 0.1 for Q in group):
            group.append(R)
            return True
        return False

    for R in rotations:
        add(R)
    changed = True
    while changed and len(group) < limit:
        changed = False
        for A in list(group):
            for B in list(group):
                if add(A @ B):
                    changed = True
    return group


def parse_symmetry_text(text: str, centre: np.ndarray) -> Symmetries:
    """Symmetries given on the command line: comma-separated items ``x:2`` (2-fold, i.e.
    180 deg, about the model's x axis), ``z:4``, ``z:inf`` (continuous about z), or ``none``;
    about ``centre``; closed under composition."""
    text = text.strip().lower()
    if text in ("", "none"):
        return Symmetries()
    unit = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
    rots, axis = [], None
    for item in text.split(","):
        try:
            name, order = item.strip().split(":")
            a = unit[name]
            if order == "inf":
                axis = a
                continue
            n = int(order)
            if n < 2:
                raise ValueError
        except (ValueError, KeyError):
            raise InputError(f"--symmetry item '{item}' must be AXIS:N (AXIS x, y or z; N an integer >= 2) "
                             f"or AXIS:inf, e.g. 'x:2,y:2' for a box or 'z:inf,x:2' for a cylinder") from None
        rots.append(_rotation(a, 2 * np.pi / n))
    group = _close(rots)
    if axis is not None:
        group = [R for R in group if abs(abs((R @ axis) @ axis) - 1) < 1e-6]
        reps = [np.eye(3)] + [R for R in group if (R @ axis) @ axis < 0][:1]
        group = reps
    return Symmetries(np.stack([_about(R, centre) for R in group]), axis,
                      np.asarray(centre, np.float64) if axis is not None else None)


__all__ = ["Symmetries", "detect_symmetries", "closest_symmetric_pose", "parse_symmetry_text"]
