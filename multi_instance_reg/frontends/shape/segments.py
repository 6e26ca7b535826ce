"""Where objects can be, from depth alone: support surfaces removed, the rest cut into
connected segments. No ROS, no colour.

A flat face of an object and the floor it stands on are both planes; what tells them apart is
size. So each dominant plane (RANSAC, repeatedly: floor, pallet top, table, wall) is cut into
its connected pieces in the image, and only the pieces larger than any face of the object
(``max_area``) are removed - carton tops that lie in one plane across a pallet stay, each a
piece of its own. Points are removed where they are on the plane (within the depth noise),
not behind it: a lower layer seen past a gap is still searched; nor where the points about
them lie a few mm above it on average (a tray's floor, a plate: within the noise of one point,
not of their mean).

The remaining points, voxel-downsampled, are split into connected segments (neighbours within
``link`` metres): each object, or a few touching ones, then forms one segment, and shape
matching pairs points only within a segment (bounded work, no pairs across the scene).
"""
from __future__ import annotations

import cv2
import numba
import numpy as np
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from ...messages import CameraIntrinsics
from ...threads import submit_each
from ...rgbd.lifting import depth_to_cloud, fit_dominant_plane


def support_mask(depth_m: np.ndarray, intrinsics: CameraIntrinsics, valid: np.ndarray, max_area: float,
                 thresh: float, noise_per_m2: float, max_planes: int = 4, min_share: float = 0.03,
                 stride: int = 2, ground: list | None = None, planes: list | None = None,
                 up: np.ndarray | None = None, up_tolerance_deg: float = 20.0, window: int = 5,
                 rest: list | None = None, face_heights=None, min_width: float = 0.0) -> np.ndarray:
    """(H, W) bool: valid pixels that lie on a large piece of a dominant plane (support
    surfaces). A plane point is within ``thresh`` + 3 sigma(z) of it, sigma(z) =
    ``noise_per_m2`` z^2 (stereo depth noise grows with the square of the distance); a piece
    is large when its area exceeds ``max_area`` (m^2). A point in that band is still not on
    the plane when the mean height of the band points in the ``window`` x ``window`` sampled
    pixels about it is off the plane by more than ``thresh`` + 3 sigma of such means (measured
    on the plane; ``_leave_raised``): a surface a few mm above the table (a tray's floor, a
    plate, a lid) stays, the table's noise averaged out; ``window`` 1: point by point.
    ``ground``, a list, receives the unit normal (towards the camera) of the plane with the
    largest removed area: "up", if the floor, pallet or table is in view; and its offset
    (up . p + offset = 0 on it). ``planes``, a list, receives (normal, offset) alike for every plane a large piece of
    which was removed (the floor and the pallet's top on it, a table and a wall) and holds a
    disc ``min_width`` across (metres): what carries nothing, a bin's rim or a strip of
    pallet seen between two rows of cartons, is removed but is no support (a bin's rim 2 cm
    wide, level with the floor: cans standing above it had 105-212 samples "sunk" into it).

    ``up`` (unit, camera frame: the direction of gravity's reaction, from an IMU or TF): then
    ``ground`` is the plane with the largest removed area among those whose normal lies within
    ``up_tolerance_deg`` of it (what objects stand on, not a wall that happens to be larger);
    when there is none, the largest as without it.

    ``rest``, a list, receives (points (P, 3) float32, pixels (P, 2)) of the valid pixels
    sampled ``stride`` apart that were not removed: ``depth_to_cloud`` of ``valid`` and not
    the mask returned, at ``stride``, without lifting the depth a second time.

    ``face_heights`` (metres; ``object_face_heights``): the heights above a support at which
    the object, resting on it, shows a flat face up. A large piece whose points stand at one
    of them above a larger removed plane, with nothing standing on it, is the tops of
    objects lying flush on that plane, not a support: it stays (``_is_object_tops``)."""
    h, w = depth_m.shape
    lifted, pix = depth_to_cloud(depth_m, intrinsics, valid, stride=stride)
    pts = lifted.astype(np.float64)
    out = np.zeros((h, w), bool)
    if len(pts) < 50:
        if rest is not None:
            rest[:] = [lifted, pix]
        return out
    rows, cols = pix[:, 0] // stride, pix[:, 1] // stride
    hs, ws = (h + stride - 1) // stride, (w + stride - 1) // stride
    z = pts[:, 2]
    tol = thresh + 3.0 * noise_per_m2 * z * z
    K = intrinsics.K
    rng = np.random.default_rng(0)
    alive = np.ones(len(pts), bool)
    total = len(pts)
    best_area = 0.0
    level_area, level = 0.0, None
    min_cos = np.cos(np.radians(up_tolerance_deg)) if up is not None else 0.0
    fxfy = K[0, 0] * K[1, 1]

    def cut(plane_band):
        """The plane's large pieces (and large raised surfaces in its band) marked in
        ``out``; their area. Bands of different planes share no point."""
        n, on, band, img, height = plane_band
        if window > 1:
            _leave_raised(pts, on, img, height, rows, cols, thresh, window)
        count, labels = cv2.connectedComponents(img, connectivity=8)
        removed_area, areas = _remove_large_pieces(pts, on, labels, rows, cols, stride, fxfy, n, max_area, count,
                                                   pix, out)
        widest = _widest_piece(labels, np.flatnonzero(areas > max_area), float(np.median(z[on])) * stride / K[0, 0]) \
            if removed_area > 0 and min_width > 0 else 0.0
        # For the object tops' check: each plane point's piece (0: off the plane), each piece's area.
        pieces = (np.where(on, labels[rows, cols], 0), areas) if face_heights is not None and removed_area > 0 \
            else None
        raised = band & ~on
        if raised.any():
            # A raised surface larger than any face of the object supports too (a board on
            # the table), as a piece of the plane would.
            img[:] = 0
            img[rows[raised], cols[raised]] = 1
            count, labels = cv2.connectedComponents(img, connectivity=8)
            _remove_large_pieces(pts, raised, labels, rows, cols, stride, fxfy, n, max_area, count, pix, out)
        return removed_area, pieces, widest

    # Each plane's band is cut into pieces in the shared thread pool while the next plane
    # is sought here (the search needs only the band, not the pieces).
    cuts = []
    for k in range(max_planes):
        cand = np.flatnonzero(alive)
        if len(cand) < min_share * total or len(cand) < 50:
            break
        sample = cand if len(cand) <= 3000 else rng.choice(cand, 3000, replace=False)
        plane = fit_dominant_plane(pts[sample], float(np.median(tol[sample])), iterations=150, seed=k, max_sample=3000)
        if plane is None:
            break
        n, d, _ = plane
        img = np.zeros((hs, ws), np.uint8)
        height = np.zeros((hs, ws), np.float32)
        on = _on_plane(pts, alive, tol, n, d, rows, cols, img, height)
        if on.sum() < min_share * total:
            break
        band = on.copy()
        cuts.append((n, d, submit_each(cut, [(n, on, band, img, height)])[0]))
        # The raised points too: the next plane is then sought among the same points as
        # without them (one found among them by chance was the tops of touching channels, a
        # piece larger than three faces, removed with every channel in it).
        alive &= ~band
    found = []
    for n, d, task in cuts:
        removed_area, pieces, widest = task.result()
        # The normal on the camera's side, and the offset: normal . p + offset = 0 on the plane.
        normal, offset = np.asarray(n, np.float64) * (1.0 if d > 0 else -1.0), abs(float(d))
        found.append([normal, offset, removed_area, pieces, widest])
    if face_heights is not None and len(found) > 1:
        # The large pieces of each plane's own points (a raised surface in its band stays removed).
        heights = np.asarray(face_heights, np.float64)
        for plane in found:
            if plane[3] is None:
                continue
            labels, areas = plane[3]
            large = np.flatnonzero(areas[1:] > max_area) + 1
            kept = []
            for k in large:
                lower = [other for other in found if other is not plane and other[2] > areas[k]]
                if not lower:
                    continue
                idx = np.flatnonzero(labels == k)
                if any(_is_object_tops(pts, idx, other[0], other[1], heights, tol) for other in lower):
                    out[pix[idx, 0], pix[idx, 1]] = False
                    kept.append(k)
            if kept:
                plane[2] = float(sum(areas[k] for k in large if k not in kept))
    for normal, offset, removed_area, _, widest in found:
        if planes is not None and removed_area > 0 and 2.0 * widest >= min_width:
            planes.append((normal, offset))
        if ground is not None and removed_area > best_area:
            best_area = removed_area
            ground[:] = [normal, offset]
        if ground is not None and up is not None and removed_area > level_area and float(normal @ up) >= min_cos:
            level_area, level = removed_area, [normal, offset]
    if level is not None:
        ground[:] = level
    if rest is not None:
        # Only the sampled pixels are marked yet: the filling below marks none of them anew.
        # (take: rows by a boolean mask were 3 ms for 73,000 points, take 0.3)
        kept = np.flatnonzero(~out[pix[:, 0], pix[:, 1]])
        rest[:] = [lifted.take(kept, axis=0), pix.take(kept, axis=0)]
    if stride > 1:
        # Fill the pixels between the sampled ones.
        out = cv2.dilate(out.astype(np.uint8), np.ones((stride, stride), np.uint8),
                         anchor=(stride - 1, stride - 1)).astype(bool) & valid
    return out


# Degrees: a removed plane is a support when it is this nearly parallel to the one below
# the objects (``level_supports``).
SUPPORT_LEVEL_DEG = 5.0


def level_supports(planes, up: np.ndarray | None) -> tuple:
    """The ``planes`` ((normal, offset) each, ``support_mask``'s) that are supports: parallel
    to ``up``, the plane below the objects, within ``SUPPORT_LEVEL_DEG``; () without it.
    Supports measured in one depth image are parallel within a degree or two (floor, pallet
    top, a bin's floor); one farther off was fitted across a narrow strip, which the noise's
    band lets it tilt about (a pallet's top seen between two rows of cartons, fitted 18 deg
    off level: every carton "sunk" into it). The rest are walls, a bin's sides."""
    if up is None:
        return ()
    level = np.cos(np.radians(SUPPORT_LEVEL_DEG))
    return tuple((n, d) for n, d in planes if abs(float(np.asarray(n) @ up)) >= level)


# ``_is_object_tops``: at least this share of the piece's points within the tolerance of one
# face height above the plane below ...
TOPS_SHARE = 0.9
# ... and at most this share of its points' number rising above it within its outline.
TOPS_STANDING_SHARE = 0.02


def _is_object_tops(pts, idx, up, offset, face_heights, tol) -> bool:
    """Whether the plane piece ``pts[idx]`` is made of the tops of objects lying flush on the
    plane (``up`` towards the camera, up . p + offset = 0) below it: its points stand at
    one height above that plane at which the object shows a flat face up (within the
    depth tolerance ``tol``), and nothing stands on it (no points rise above it within
    its outline, seen along ``up``). A support raised at such a height (a pallet's top, as
    high as a carton) carries objects (its tops would too, stacked on them: then it stays a
    support)."""
    # (Every few points of a large piece are plenty for where it stands.)
    few = idx[::max(1, len(idx) // 2000)]
    h = pts[few] @ up + offset
    face = face_heights[np.argmin(np.abs(face_heights - np.median(h)))]
    if np.mean(np.abs(h - face) <= tol[few]) < TOPS_SHARE:
        return False
    limit = TOPS_STANDING_SHARE * len(idx)
    above = np.flatnonzero(pts @ up + offset > face + tol)
    if len(above) <= limit:
        return True
    # Along up, in the plane's own axes: the points above within the piece's outline (its
    # convex hull), every few of them counted for as many (the outline of every few piece
    # points is all but the piece's).
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    axes = np.stack([a, np.cross(up, a)], axis=1)
    flat = pts[few] @ axes
    step = max(1, len(above) // 2000)
    try:
        inside = Delaunay(flat[ConvexHull(flat).vertices]).find_simplex(pts[above[::step]] @ axes) >= 0
    except QhullError:
        return False
    return int(inside.sum()) * step <= limit


@numba.njit(cache=True, nogil=True)
def _on_plane(pts, alive, tol, n, d, rows, cols, img, height):
    # The per-point steps of support_mask compiled (each a pass over ~77,000 points; as
    # numpy arrays they took half its time). The points on the plane, marked in img too,
    # their signed heights above it in ``height``.
    on = np.zeros(pts.shape[0], np.bool_)
    for i in range(pts.shape[0]):
        h = pts[i, 0] * n[0] + pts[i, 1] * n[1] + pts[i, 2] * n[2] + d
        on[i] = alive[i] and abs(h) < tol[i]
        if on[i]:
            img[rows[i], cols[i]] = 1
            height[rows[i], cols[i]] = h
    return on


def _leave_raised(pts, on, img, height, rows, cols, thresh, window):
    """Unmarks (in ``on`` and ``img``) the band points of a surface raised a few mm above
    the plane (a tray's floor, a plate, a lid): where the mean height of the band points in
    the ``window`` x ``window`` cells about them (``height``, sampled grid) is more than
    ``thresh`` + 3 sigma of such a mean off the plane. Sigma is measured on the plane, from
    the differences of means a window apart: 1 / sqrt(count) of a point's noise if it is
    independent, nearly all of it if neighbouring pixels share it (a stereo matcher's
    window); a smooth error of the plane's fit cancels in them."""
    box = (window, window)
    count = cv2.boxFilter(img.astype(np.float32), -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(height, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    diffs = _window_differences(pts, on, rows, cols, img, total, count, window)
    if len(diffs) < 100:
        return
    spread = 1.4826 * float(np.median(diffs)) / np.sqrt(2.0)
    _unmark_raised(pts, on, rows, cols, img, total, count, thresh, 3.0 * spread, window)


@numba.njit(cache=True, nogil=True)
def _window_differences(pts, on, rows, cols, img, total, count, window):
    # |mean - mean a window to the right| and below, over z^2, at every third band point
    # (plenty for a median) whose window and the other are at least half band.
    h, w = img.shape
    full = 0.5 * window * window
    out = np.empty(2 * (pts.shape[0] // 3 + 1))
    k = 0
    for i in range(0, pts.shape[0], 3):
        r, c = rows[i], cols[i]
        if not on[i] or count[r, c] < full:
            continue
        m = total[r, c] / count[r, c]
        z2 = pts[i, 2] * pts[i, 2]
        if c + window < w and img[r, c + window] > 0 and count[r, c + window] >= full:
            out[k] = abs(m - total[r, c + window] / count[r, c + window]) / z2
            k += 1
        if r + window < h and img[r + window, c] > 0 and count[r + window, c] >= full:
            out[k] = abs(m - total[r + window, c] / count[r + window, c]) / z2
            k += 1
    return out[:k]


@numba.njit(cache=True, nogil=True)
def _unmark_raised(pts, on, rows, cols, img, total, count, thresh, sigmas, window):
    # A window of fewer band points (at the plane's edge) averages less noise away.
    for i in range(pts.shape[0]):
        if on[i]:
            r, c = rows[i], cols[i]
            z = pts[i, 2]
            if abs(total[r, c]) / count[r, c] > thresh + sigmas * z * z * window / np.sqrt(count[r, c]):
                on[i] = False
                img[r, c] = 0


def _widest_piece(labels: np.ndarray, pieces: np.ndarray, metres_per_pixel: float) -> float:
    """Metres: the radius of the largest disc inside any of the ``pieces`` (labels in the
    sampled image ``labels``), single missing samples (dropouts) closed first."""
    mask = cv2.morphologyEx(np.isin(labels, pieces).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return float(cv2.distanceTransform(mask, cv2.DIST_L2, 5).max()) * metres_per_pixel


@numba.njit(cache=True, nogil=True)
def _remove_large_pieces(pts, on, labels, rows, cols, stride, fxfy, n, max_area, count, pix, out):
    """Marks in ``out`` (at their pixels ``pix``) the points ``on`` the plane (normal n)
    that lie in a piece (``labels`` at rows, cols) of more than ``max_area`` m^2; returns
    their summed area: each point stands for its pixel's footprint facing the camera
    (pixels ``stride`` apart, fxfy = fx fy), divided by the plane's slant there (at most 5x);
    and each piece's area (by label)."""
    area = np.zeros(pts.shape[0])
    piece = np.zeros(count)
    for i in range(pts.shape[0]):
        if on[i]:
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            r = np.sqrt(x * x + y * y + z * z)
            area[i] = (z * stride) ** 2 / fxfy / max(abs(x / r * n[0] + y / r * n[1] + z / r * n[2]), 0.2)
            piece[labels[rows[i], cols[i]]] += area[i]
    removed = 0.0
    for i in range(pts.shape[0]):
        label = labels[rows[i], cols[i]]
        if on[i] and label > 0 and piece[label] > max_area:
            out[pix[i, 0], pix[i, 1]] = True
            removed += area[i]
    return removed, piece


def connected_segments(points: np.ndarray, link: float, min_points: int, tree: cKDTree | None = None,
                       apart=None) -> np.ndarray:
    """(N,) segment label per point (-1: in a segment of fewer than ``min_points``), points
    joined when closer than ``link``. ``tree``: a k-d tree of ``points``, when there is one.
    ``apart(first, second)``: (P,) bool, the pairs of points (indices) not to join though near."""
    n = len(points)
    if n == 0:
        return np.zeros(0, np.int64)
    pairs = (cKDTree(points) if tree is None else tree).query_pairs(link, output_type="ndarray")
    if apart is not None and len(pairs):
        pairs = pairs[~apart(pairs[:, 0], pairs[:, 1])]
    labels = graph_components(n, pairs[:, 0], pairs[:, 1])
    sizes = np.bincount(labels)
    keep = sizes[labels] >= min_points
    # Renumber the kept segments 0..S-1.
    _, relabel = np.unique(labels[keep], return_inverse=True)
    out = np.full(n, -1, np.int64)
    out[keep] = relabel
    return out


@numba.njit(cache=True, nogil=True)
def graph_components(n, first, second):
    """(n,) component label of each vertex of the undirected graph with edges (first[k],
    second[k]), numbered as scipy's ``connected_components`` does (in order of each
    component's lowest vertex). Union-find, compiled: the sparse matrix and its checks
    cost 1.5 ms for a frame's 5,000 points and 24,000 links, this 0.2."""
    parent = np.arange(n)
    for k in range(first.shape[0]):
        a = first[k]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        b = second[k]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a != b:
            parent[max(a, b)] = min(a, b)
    labels = np.empty(n, np.int32)
    count = 0
    for v in range(n):
        root = v
        while parent[root] != root:
            root = parent[root]
        if root == v:
            labels[v] = count
            count += 1
        else:
            labels[v] = labels[root]
    return labels


def segment_members(labels: np.ndarray) -> tuple[np.ndarray, list]:
    """The segments' ids (labels >= 0, ascending) and each one's point indices in their
    order, found by one sort (not a pass over all labels per segment)."""
    order = np.flatnonzero(labels >= 0)
    order = order[np.argsort(labels[order], kind="stable")]
    ids, starts = np.unique(labels[order], return_index=True)
    return ids, np.split(order, starts[1:]) if len(order) else []


def segments_within_reach(points: np.ndarray, labels: np.ndarray, reach: float) -> np.ndarray:
    """The ids (ascending) of the segments (labels >= 0) ``within_reach``: small enough to be
    (part of) one object."""
    ids, members = segment_members(labels)
    return np.array([s for s, m in zip(ids.tolist(), members) if within_reach(points[m], reach)], np.int64)


def segment_pairs(points: np.ndarray, labels: np.ndarray, reach: float, members: list | None = None) -> list:
    """Point indices of the union of each pair of segments (labels >= 0) that is
    ``within_reach``: two pieces that may be one object. ``members``: ``segment_members``'
    lists, when the caller has them already."""
    if members is None:
        _, members = segment_members(labels)
    lo = np.array([points[m].min(axis=0) for m in members]) if members else np.zeros((0, 3))
    hi = np.array([points[m].max(axis=0) for m in members]) if members else np.zeros((0, 3))
    out = []
    for a in range(len(members)):
        for b in range(a + 1, len(members)):
            # Their joint box's longest side over the reach: no pair of points within it.
            if (np.maximum(hi[a], hi[b]) - np.minimum(lo[a], lo[b])).max() > reach:
                continue
            union = np.concatenate([members[a], members[b]])
            if within_reach(points[union], reach):
                out.append(union)
    return out


def within_reach(p: np.ndarray, reach: float) -> bool:
    """No two of the points farther apart than ``reach``. The box's diagonal bounds the
    farthest pair from above and its longest side from below; only between them are the
    pairs measured."""
    if len(p) < 2:
        return True
    side = p.max(axis=0) - p.min(axis=0)
    if np.linalg.norm(side) <= reach:
        return True
    if side.max() > reach:
        return False
    from scipy.spatial.distance import pdist

    try:
        # The farthest pair are corners of the points' convex hull (a few dozen of hundreds).
        p = p[ConvexHull(p).vertices]
    except QhullError:          # flat or too few points
        pass
    return bool(pdist(p).max() <= reach)


__all__ = ["support_mask", "level_supports", "connected_segments", "segment_members", "segments_within_reach",
           "segment_pairs", "within_reach"]
