"""Flat faces: the model's, and the flat patches of a frame's segments, matched by their
outline's second moments. No ROS; colour only as the seams that cut a plane.

A carton seen from above shows its top alone. Point pairs on one plane differ only in their
distance, so its references vote for poses blurred in the plane (3-7 right references of 70
on a carton's own segment), and point-to-plane ICP holds nothing in the plane either: a pose
10-15 deg off in yaw stays off. What places such a face is its outline. A patch of the
frame's points on one plane, cut off by depth steps all round, whose second moments are those
of a model face (the same two side lengths of its equivalent rectangle, within a voxel and a
half or a tenth), is that face seen whole: its centroid and long axis give the pose, up to the
turn of half a turn about the face's normal (both are tried; a box's symmetry makes them one).

Faces whose two moments are nearly equal (a square, a disc) give no axis and are not used; a
curved surface has no face both of whose sides are two voxels long at one normal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...symmetry import turn_about
from .segments import connected_segments

# Normals within this of a plane's are on it (the frame's PCA normals of noisy depth; the
# model's voxel means at a face's edge).
FACE_ANGLE_DEG = 15.0
# The model's planes are found by the normals within this of each other: exact on a flat
# face, while at its edges (normals between two faces) a looser test found faces of edges.
MODEL_SEED_ANGLE_DEG = 3.0
# The equivalent rectangle's sides must agree within this many voxels, or this share.
SIDE_VOXELS = 1.5
SIDE_SHARE = 0.1
SIDE_SHORT = 2.0
# A face without a long axis (its sides within this ratio) gives no turn.
MIN_SIDE_RATIO = 1.15


@dataclass
class Faces:
    centre: np.ndarray    # (F, 3)
    normal: np.ndarray    # (F, 3) outward (model) / towards the camera (frame)
    axis: np.ndarray      # (F, 3) unit, in the plane: the long axis
    sides: np.ndarray     # (F, 2) the equivalent rectangle's sides (long, short): sqrt(12 x moment)
    joined: np.ndarray | None = None   # (F,) bool, frame patches: one of several pieces of one plane

    def __len__(self) -> int:
        return len(self.centre)

    def take(self, keep) -> "Faces":
        joined = None if self.joined is None else self.joined[keep]
        return Faces(self.centre[keep], self.normal[keep], self.axis[keep], self.sides[keep], joined)


def _moments(p: np.ndarray, n: np.ndarray):
    """Centroid, long axis and the equivalent rectangle's sides of points on a plane of normal n."""
    c = p.mean(axis=0)
    q = p - c
    q -= np.outer(q @ n, n)
    w, V = np.linalg.eigh(q.T @ q / len(q))
    # The two largest (the third, along n, is ~0).
    order = np.argsort(w)[::-1]
    long_axis = V[:, order[0]]
    sides = np.sqrt(12.0 * np.maximum(w[order[:2]], 0.0))
    return c, long_axis, sides


def _collect(items, joined=None) -> Faces:
    """Faces of (centre, normal, axis, sides) items, ``joined`` (one bool each) or not known."""
    faces = Faces(*(np.array([it[k] for it in items], np.float64).reshape(-1, n) for k, n in enumerate((3, 3, 3, 2))))
    if joined is not None:
        faces.joined = np.array(joined, bool).reshape(-1)
    return faces


def _planes(points: np.ndarray, normals: np.ndarray, idx: np.ndarray, tolerance: float, min_points: int,
            most: int, seed_angle_deg: float = FACE_ANGLE_DEG):
    """Up to ``most`` planes among points ``idx``, largest first: the normal most of the
    remaining points share (within ``seed_angle_deg``; tried at a spread subset of their own
    normals), averaged over them, and the points whose normals are within FACE_ANGLE_DEG of
    it and that lie within ``tolerance`` of the plane through their median. Yields (normal,
    indices, the indices of those within ``seed_angle_deg``)."""
    cos_seed, cos_max = np.cos(np.radians(seed_angle_deg)), np.cos(np.radians(FACE_ANGLE_DEG))
    for _ in range(most):
        if len(idx) < min_points:
            return
        nn = normals[idx]
        seeds = nn[:: max(1, len(idx) // 32)]
        n0 = seeds[int(np.argmax((seeds @ nn.T > cos_seed).sum(axis=1)))]
        core = nn @ n0 > cos_seed
        n0 = nn[core].mean(axis=0)
        n0 /= np.linalg.norm(n0)
        d = points[idx] @ n0
        on = (nn @ n0 > cos_max) & (np.abs(d - np.median(d[core])) < tolerance)
        if on.sum() < min_points:
            return
        yield n0, idx[on], idx[on & core]
        idx = idx[~on]


def model_faces(points: np.ndarray, normals: np.ndarray, voxel: float, most: int = 12) -> Faces:
    """The model's flat faces with a long axis (``_planes`` of its surface, within half a
    voxel), both sides at least two voxels where the normals agree within
    MODEL_SEED_ANGLE_DEG (a strip of a cylinder's side, its normals turning, is no face)."""
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    out = []
    for normal, on, core in _planes(p, n, np.arange(len(p)), 0.5 * voxel, 10, most, MODEL_SEED_ANGLE_DEG):
        c, axis, sides = _moments(p[on], normal)
        flat = len(core) >= 3 and _moments(p[core], normal)[2][1] >= 2.0 * voxel
        if flat and sides[1] >= 2.0 * voxel and sides[0] >= MIN_SIDE_RATIO * sides[1]:
            out.append((c, normal, axis, sides))
    return _collect(out)


def frame_patches(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, reach: float, link: float,
                  tolerance, min_points: int = 15, per_segment: int = 2, across_seams=None) -> Faces:
    """The flat patches of each segment: its ``per_segment`` largest planes (``_planes``;
    ``tolerance(z)``: metres off the plane at the segment's median distance z),
    a plane wider than ``reach`` (the object's diameter: it holds several objects' faces)
    cut into connected pieces (points within ``link``: coplanar tops of touching cartons
    are apart where a gap shows between them). ``across_seams(a, b)`` ((N,) bool: the
    image between points a[k] and b[k] crosses a seam; ``FrameView.across_seams``): no
    link across one either, for cartons packed flush show no gap in depth, only a dark
    line in colour. The pieces of a plane cut in several are ``joined``: their neighbours
    lie in their plane, which holds them in it only at a gap, if there is one."""
    out, wide = [], []
    for s in np.unique(labels[labels >= 0]):
        idx = np.flatnonzero(labels == s)
        for normal, plane, _ in _planes(points, normals, idx, tolerance(float(np.median(points[idx, 2]))),
                                     min_points, per_segment):
            q = points[plane]
            if np.linalg.norm(q.max(axis=0) - q.min(axis=0)) <= reach:
                c, axis, sides = _moments(q, normal)
                out.append((c, normal, axis, sides))
            else:
                wide.append((normal, q))
    joined = [False] * len(out)
    if wide:
        # All wide planes cut in one call, each moved far from the others (no link across).
        q = np.concatenate([q for _, q in wide])
        plane_of = np.repeat(np.arange(len(wide)), [len(p) for _, p in wide])
        apart = None if across_seams is None else (lambda i, j: across_seams(q[i], q[j]))
        lab = connected_segments(q + np.outer(plane_of, [0.0, 0.0, 10.0 * (reach + link)]), link, min_points,
                                 apart=apart)
        pieces, first = np.unique(lab, return_index=True)
        pieces, plane_of_piece = pieces[pieces >= 0], plane_of[first[pieces >= 0]]
        for k, plane in zip(pieces, plane_of_piece):
            c, axis, sides = _moments(q[lab == k], wide[plane][0])
            out.append((c, wide[plane][0], axis, sides))
            joined.append(bool(np.count_nonzero(plane_of_piece == plane) > 1))
    return _collect(out, joined)


def matches(model: Faces, frame: Faces, voxel: float) -> np.ndarray:
    """(J, F) bool: frame patch j has the sides of model face f (long with long, short with
    short): no longer by more than SIDE_VOXELS voxels or SIDE_SHARE of the side, no shorter
    by more than SIDE_SHORT times that. A patch loses a rim to depth noise, flying pixels
    and dropouts at its edges and to the seams that cut it; it seldom gains one (the
    realistic sensor's carton tops measured 0.27-0.29 x 0.16-0.18 m for 0.30 x 0.20)."""
    tol = np.maximum(SIDE_VOXELS * voxel, SIDE_SHARE * model.sides)[None]
    longer = frame.sides[:, None] - model.sides[None]
    return np.all((longer <= tol) & (-longer <= SIDE_SHORT * tol), axis=2)


def face_pose(model: Faces, f: int, centre: np.ndarray, normal: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(4, 4) model -> camera: model face f's outward normal onto ``normal``, its long axis
    onto ``axis``, its centroid onto ``centre``."""
    def frame(n, a):
        a = a - (a @ n) * n
        a = a / np.sqrt(a @ a)
        b = np.array([n[1] * a[2] - n[2] * a[1], n[2] * a[0] - n[0] * a[2], n[0] * a[1] - n[1] * a[0]])
        return np.column_stack([a, b, n])       # (np.cross costs 30 us on 3-vectors)
    R = frame(normal, axis) @ frame(model.normal[f], model.axis[f]).T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ model.centre[f]
    return T


def nearest_face_pose(model: Faces, frame: Faces, fits: np.ndarray, T: np.ndarray, reach: float,
                      max_angle_deg: float = 20.0, keep_plane: bool = False) -> np.ndarray | None:
    """Pose T moved onto the frame patch that one of its model faces matches (``fits``,
    ``matches``) and nearly lies on: normals within ``max_angle_deg``, centroids within
    ``reach``; of those the nearest, the face's long axis onto the patch's with the sign
    nearest T's. None when there is none. ``keep_plane``: moved in the plane of its face
    only (shifted and turned about the face's normal), which keeps the plane T had (ICP's,
    from the depth; a noisy patch's normal is a few degrees off)."""
    if len(model) == 0 or len(frame) == 0:
        return None
    R, t = T[:3, :3], T[:3, 3]
    normal = model.normal @ R.T
    centre = model.centre @ R.T + t
    near = fits & (frame.normal @ normal.T > np.cos(np.radians(max_angle_deg)))
    if not near.any():
        return None
    d = np.where(near, np.linalg.norm(frame.centre[:, None] - centre[None], axis=2), np.inf)
    j, f = np.unravel_index(int(np.argmin(d)), d.shape)
    if d[j, f] >= reach:
        return None
    axis = frame.axis[j] if (R @ model.axis[f]) @ frame.axis[j] >= 0 else -frame.axis[j]
    if not keep_plane:
        return face_pose(model, f, frame.centre[j], frame.normal[j], axis)
    n, a = normal[f], R @ model.axis[f]
    axis = axis - (axis @ n) * n
    angle = np.arctan2(np.cross(a, axis) @ n, a @ axis)
    c = centre[f] + (frame.centre[j] - centre[f]) - ((frame.centre[j] - centre[f]) @ n) * n
    M = turn_about(n, centre[f], angle)
    M[:3, 3] += c - centre[f]
    return M @ T


def patch_poses(model: Faces, frame: Faces, fits: np.ndarray) -> np.ndarray:
    """(K, 4, 4): for each frame patch, each model face it matches (``fits``), on either
    sign of the long axis."""
    out = [face_pose(model, f, frame.centre[j], frame.normal[j], sign * frame.axis[j])
           for j, f in np.argwhere(fits) for sign in (1.0, -1.0)]
    return np.array(out) if out else np.zeros((0, 4, 4))


__all__ = ["Faces", "model_faces", "frame_patches", "matches", "face_pose", "nearest_face_pose", "patch_poses"]
