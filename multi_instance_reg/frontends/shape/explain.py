"""The shape front end's one verification: how well a pose explains the frame, and the
joint choice of the instances.

    view = FrameView.of(depth_m, intrinsics, rgb)           # once a frame: depth and grey levels
    e = explain(T, model, view, tolerance, claimed)          # one pose: Explanation
    chosen = select(candidates, model, view, ...)            # the set that explains most

The model's camera-facing surface samples at the pose, drawn with a z-buffer (a non-convex
object hides parts of itself), each compared with the depth measured on its pixel:

- *agree*: within the tolerance (3 sigma of the depth noise at its distance, sigma = k z^2,
  with a floor) and the measured normal within ``NORMAL_DEG`` of the model's (where the
  depth around the pixel gives one: a dropout or a flying pixel leaves it out, not against);
  weighted 1 within the noise itself, down to nothing at the tolerance;
- *free*: the measurement lies farther: the camera saw through where the model would stand;
- *hidden*: a nearer measured surface. Behind pixels another chosen instance claims, it is
  explained and left out; behind an occluder (a surface that steps in front) it is not
  judged, but a pose is judged over no fewer than ``MIN_SEEN`` of its samples seen and
  hidden (an object behind an unknown occluder stays possible while most of it shows; a
  pose mostly hidden does not pass on the little that shows); behind the very surface the
  pose agrees with, running on with no depth step, it may be inside that object and counts
  half against;
- no depth (dropouts, IR shadows): left out, neither for nor against;
- and any sample of the model, seen or not, more than a voxel (or the tolerance) below a support plane the
  depth shows there (floor, pallet, table): inside it, counted as free (two cartons sunk 3
  cm into a pallet fit a crate's top).

And the outline: the share of a band just outside the drawn model where the nearest model
face continues in the depth (``verify.outline_continuation``): a piece of a larger surface
(a carton fitted onto a crate's top, a pose sunk into the table) continues past its
outline; a true instance does not. Pixels another chosen instance claims, and with colour
a seam along the outline (a dark line: light does not reach into the gap between two
boxes; ``outline_seams``), break that continuation: flush-packed cartons form one plane
in depth, and their outlines are seen only as such lines. A print's, a tape's or a brick
wall's lines elsewhere say nothing of where the object ends.

And where the model has colour (a mesh with vertex colours or a texture) and the frame has
colour: the *appearance*, the correlation of the model's grey levels with the image's over
the agreeing samples (a gain and an offset of the light do not change it), at the best of
the model's symmetric poses (the shape leaves a can's turn open, its label does not). On
IC-BIN's real frames the cups' poses correlate 0.65-0.87, a cup fitted among juice cartons
-0.15-0.6, the same cup fitted upside down about 0.

The evidence of a pose is support - 2 x free - 2 x outline (shares of the judged samples),
plus appearance - 0.5 where there is one; the
gain a pose would add is its evidence times the samples it explains that no chosen
instance explains already. ``select`` takes the pose with the largest gain while it passes
``shape_min_support`` and ``shape_min_evidence``, claims its pixels, and scores the poses
that meet it again: hypotheses on the same pixels compete, and a neighbour's outline onto
a chosen instance no longer counts against it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ...messages import CameraIntrinsics
from ...rgbd.verify import _points_and_normals, facing_camera, image_pixels, outline_continuation
from ...symmetry import turn_about
from ...transforms import apply_transform, invert_transform

# A sample agrees only when the measured normal is within this of the model's (where the
# depth gives one): a cylinder's side laid over a block's edge agrees in depth, not in normals.
NORMAL_DEG = 45.0
NORMAL_STEP = 2         # pixels: the central differences' half width, at least
# ... and wide enough that the depth noise turns the measured normal by about this much (1
# sigma per axis) at most: 2 px at 1.7 m with the realistic sensor (k 0.004) gave normals
# 43 deg off per axis, over half the samples of a true carton "turned" (support 0.71-0.75).
NORMAL_NOISE_DEG = 15.0
# A pose is judged over the samples seen, but over no fewer than this share of those seen
# and those hidden by a nearer surface no chosen instance explains (a chosen instance's
# pixels explain what they hide): what shows of a mostly hidden pose does not confirm it.
# IC-BIN's cups in a pile are each behind others or the bin's side; counting each hidden
# sample half against the pose, a cup 60 % in view needed every seen sample to agree.
MIN_SEEN = 0.6
# ... except behind the surface the pose's own agreeing samples lie on, running on to the
# sample's pixel with no depth step: an occluder steps in front of what it hides, and a
# pose under a surface that goes on from its own may be inside that object (a cylinder
# lying half sunk into a wider one's top). Such a sample counts this much against the pose.
INSIDE_WEIGHT = 0.5
# A sample in space the camera saw through counts this many times against the pose: seen
# empty is stronger than not seen (a cylinder fitted over a distractor's edge overhangs by
# 6 % and agrees elsewhere: evidence 0.80 with the weight 1, true cylinders 0.79-0.99).
FREE_WEIGHT = 2.0
# The outline's weight in the evidence (as the earlier checks ranked: support - free - 2 x outline).
OUTLINE_WEIGHT = 2.0
# At least this many samples must be judged (on valid depth, not explained by another
# instance): fewer tell nothing.
MIN_JUDGED = 20
# A pose whose agreeing samples lie more than this share on pixels a chosen instance
# claims is that instance seen again (the same pixels): it is dropped.
MAX_CLAIMED = 0.5
# A seam between two boxes packed flush (``FrameView.seams``): a line at most about SEAM_PX
# pixels wide (a 1-2 mm gap and the boxes' rounded edges: 6-8 pixels at 1.5-2 m in the
# generator's frames), SEAM_DARKER grey levels darker than the image beside it.
SEAM_PX = 5
SEAM_DARKER = 8.0
# Pixels: the seams are widened by this (the line fades where a seam meets an outline or crosses tape).
SEAM_WIDEN = 2
# Pixels: a seam this near a drawing's outline runs along it (``outline_seams``).
OUTLINE_SEAM_PX = 2
# Seams mark outlines only where at most this share of a pose's samples inside its drawing
# lie on one: more is a print (a carton fitted onto a juice carton's print passed on them).
MAX_TEXTURE = 0.5
# Normals this far apart meet at a crease (``crease_distances``).
CREASE_DEG = 30.0
# The appearance's weight in the evidence (it counts as much as the support), and the
# correlation at which it neither adds nor takes: a pose that looks like the object (IC-BIN
# cups 0.65-0.87, generated cans 0.6-0.7) gains, one that looks like something else (a
# cylinder with another print 0.22-0.29, a plain one 0, cups fitted among juice cartons
# -0.15-0.6) loses up to 0.5.
APPEARANCE_WEIGHT = 1.0
APPEARANCE_BASE = 0.5
# The model's samples need this much spread of grey (levels, standard deviation) for an
# appearance: a plain object tells nothing by it. Where the image is plain under a printed
# model's samples, the appearance is 0: that is something else.
MIN_GREY_SPREAD = 8.0
# A sample more than this many voxels (or the depth tolerance, if larger) below a support
# plane the depth shows is inside it.
SUNK_VOXELS = 1.0


@dataclass
class FrameView:
    """What the verification reads of a frame: the depth, the camera, and the colour image's
    grey levels (None without colour)."""
    depth: np.ndarray
    intrinsics: CameraIntrinsics
    grey: np.ndarray | None = None                  # (H, W) float32, blurred over 5 x 5 pixels
    cache: dict = field(default_factory=dict)       # what is made once a frame (``seams``)

    def seams(self) -> np.ndarray:
        """(H, W) uint8: the dark thin lines of the colour image (made once a frame): pixels
        SEAM_DARKER grey levels darker than the image closed over SEAM_PX (a black-hat),
        widened by SEAM_WIDEN. Light does not reach into the gap between two boxes packed
        flush, however narrow; a print's or a tape's edge is a step between two shades,
        not such a line."""
        out = self.cache.get("seams")
        if out is None:
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SEAM_PX + 1, 2 * SEAM_PX + 1))
            dark = cv2.morphologyEx(self.grey, cv2.MORPH_BLACKHAT, disc) > SEAM_DARKER
            out = cv2.dilate(dark.astype(np.uint8), np.ones((2 * SEAM_WIDEN + 1, 2 * SEAM_WIDEN + 1), np.uint8))
            self.cache["seams"] = out
        return out

    def across_seams(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(N,) bool: whether the image line between points a[k] and b[k] (camera frame, a
        voxel or two apart) crosses a seam (``seams``), looked at a quarter, half and three
        quarters of the way. All False without colour."""
        if self.grey is None:
            return np.zeros(len(a), bool)
        seams = self.seams()
        h, w = seams.shape
        K = self.intrinsics.K
        uv = [(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]) for p in (a, b)]
        out = np.zeros(len(a), bool)
        for f in (0.25, 0.5, 0.75):
            u = np.clip(np.round((1 - f) * uv[0][0] + f * uv[1][0]).astype(np.int64), 0, w - 1)
            v = np.clip(np.round((1 - f) * uv[0][1] + f * uv[1][1]).astype(np.int64), 0, h - 1)
            out |= seams[v, u] > 0
        return out

    @staticmethod
    def of(depth_m: np.ndarray, intrinsics: CameraIntrinsics, rgb: np.ndarray | None = None) -> "FrameView":
        grey = None
        if rgb is not None and rgb.ndim == 3:
            grey = cv2.GaussianBlur(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), (5, 5), 0)
            grey = grey.astype(np.float32)
        return FrameView(depth_m, intrinsics, grey)


@dataclass
class Explanation:
    """One pose's account of the frame."""
    T: np.ndarray
    agree: float            # samples the depth confirms (and their normals), weighted by how closely
    free: int               # samples in space the camera saw through
    hidden: int             # samples behind a nearer surface (an occluder) no chosen instance explains
    seen: int               # agree + free + those off in depth or normal (the sunk among free)
    inside: int             # samples behind the surface its agreeing samples lie on, running on
    outline: float          # share of the outline band where the surface goes on
    pixels: np.ndarray      # flat pixel indices of the agreeing samples (what it claims)
    rect: tuple             # image rows and columns its judged samples span (top, bottom, left, right)
    claimed: float = 0.0    # of its agreeing samples (weighted), those on pixels already claimed
    appearance: float = float("nan")   # correlation of the model's grey with the image's (NaN: none)
    weights: np.ndarray | None = None  # the agreeing samples' weights, as ``pixels``
    turn: np.ndarray | None = None     # (4, 4) the symmetry the appearance chose (None: none)

    @property
    def pose(self) -> np.ndarray:
        """T turned to the one of the poses the shape cannot tell apart that looks most like
        the image: the pose to report. T is the pose judged (and judged again when claims
        change): a model's symmetry is seldom exact (IC-BIN's cup: its lid's spout; a turn
        of 30-90 deg moved 8 -> 47 of its samples into free space), so the turned pose's
        numbers are not T's."""
        return self.T if self.turn is None else self.T @ self.turn

    def claimed_in(self, mask: np.ndarray) -> float:
        """``claimed`` as it is with the pixels of ``mask`` (H, W) claimed, without explaining
        the pose again: its agreeing samples do not depend on what is claimed."""
        if self.weights is None or len(self.pixels) == 0:
            return 0.0
        return float(np.sum(self.weights[mask.flat[self.pixels] > 0]))

    @property
    def judged(self) -> float:
        """The samples it is judged over: those seen and half those inside, no fewer than
        ``MIN_SEEN`` of those seen, hidden and inside."""
        return max(self.seen + INSIDE_WEIGHT * self.inside, MIN_SEEN * (self.seen + self.hidden + self.inside))

    @property
    def support(self) -> float:
        return self.agree / self.judged if self.judged else 0.0

    @property
    def evidence(self) -> float:
        if self.seen < MIN_JUDGED:
            return -1.0
        return (self.agree - FREE_WEIGHT * self.free) / self.judged - OUTLINE_WEIGHT * self.outline + self.looks

    @property
    def looks(self) -> float:
        """The appearance's part of the evidence (0 where there is none)."""
        return APPEARANCE_WEIGHT * (self.appearance - APPEARANCE_BASE) if np.isfinite(self.appearance) else 0.0

    @property
    def possible(self) -> float:
        """The most evidence the pose can reach, as it would be with everything that hides
        it explained by chosen instances and its outline clear: what it is judged on first
        (``select``), and so what ``explain`` asks before it looks at the outline."""
        net = self.agree - FREE_WEIGHT * self.free
        # Claims leave between the seen and judged samples judged: the most either way.
        return net / max(self.seen if net >= 0 else self.judged, 1.0) + self.looks

    @property
    def gain(self) -> float:
        """Evidence times the samples it explains that no chosen instance explains."""
        return self.evidence * (self.agree - self.claimed)


def visible_samples(T: np.ndarray, surface: np.ndarray, normals: np.ndarray, intrinsics: CameraIntrinsics,
                    shape, splat: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The model's samples at pose T that face the camera, fall in the image and are not
    behind the model's own nearer surface (z-buffer of the samples, each drawn over
    ``splat`` metres): (points (n, 3), normals, rows, cols, their indices in ``surface``)."""
    p = surface @ T[:3, :3].T + T[:3, 3]
    n = normals @ T[:3, :3].T
    index = np.flatnonzero(facing_camera(p, n))
    p, n = p[index], n[index]
    K = intrinsics.K
    u, v, inside = image_pixels(p, intrinsics, shape)
    p, n, u, v, index = p[inside], n[inside], u[inside], v[inside], index[inside]
    if len(p) < 2:
        return p, n, v, u, index
    # z-buffer in a crop around the drawing: the nearest sample per pixel, spread over its splat.
    r = max(1, int(round(splat * K[0, 0] / float(np.median(p[:, 2])))))
    u0, v0 = u.min(), v.min()
    zbuf = np.full((v.max() - v0 + 1, u.max() - u0 + 1), np.inf, np.float32)
    np.minimum.at(zbuf, (v - v0, u - u0), p[:, 2].astype(np.float32))
    zbuf = cv2.erode(zbuf, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    front = p[:, 2] <= zbuf[v - v0, u - u0] + 2.0 * splat
    return p[front], n[front], v[front], u[front], index[front]


def outline_seams(view: FrameView, rows: np.ndarray, cols: np.ndarray, index: np.ndarray, gap: int, r: int,
                  creases: np.ndarray | None, metres_per_px: float) -> np.ndarray | None:
    """(H, W) uint8: the seams (``FrameView.seams``) that run along a drawing's outline
    (within OUTLINE_SEAM_PX of it; the drawing: the samples' pixels rows, cols, gaps of up
    to ``gap`` closed), widened by ``r``; None where the drawing is not plain: where more than
    MAX_TEXTURE of its samples farther than ``r`` inside it and off the model's creases
    (``creases``: the samples' ``crease_distances``, metres; ``index`` into them) lie on
    one. A dark line tells where an object ends only where the object has none of its own
    (a print's lines lie along any outline by chance; a plain carton's faces meet at a dark
    line too, its worn edge, hence the creases)."""
    disc = lambda k: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    seams = view.seams()
    h, w = seams.shape
    pad = gap + r + OUTLINE_SEAM_PX + 1
    r0, c0 = max(int(rows.min()) - pad, 0), max(int(cols.min()) - pad, 0)
    r1, c1 = min(int(rows.max()) + pad + 1, h), min(int(cols.max()) + pad + 1, w)
    drawing = np.zeros((r1 - r0, c1 - c0), np.uint8)
    drawing[rows - r0, cols - c0] = 1
    body = cv2.erode(cv2.dilate(drawing, disc(gap)), disc(gap), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    inner = cv2.erode(body, disc(r), borderType=cv2.BORDER_CONSTANT, borderValue=0)[rows - r0, cols - c0] > 0
    if creases is not None:
        inner &= creases[index] > r * metres_per_px
    judge = inner if np.count_nonzero(inner) >= MIN_JUDGED else slice(None)
    if np.mean(seams[rows[judge], cols[judge]] > 0) > MAX_TEXTURE:
        return None
    ring = cv2.dilate(body, disc(OUTLINE_SEAM_PX)) & (1 - cv2.erode(body, disc(OUTLINE_SEAM_PX)))
    out = np.zeros((h, w), np.uint8)
    out[r0:r1, c0:c1] = cv2.dilate(seams[r0:r1, c0:c1] & ring, disc(r))
    return out


def crease_distances(surface: np.ndarray, normals: np.ndarray, reach: float) -> np.ndarray:
    """(N,) metres from each sample to the nearest one whose normal turns from its own by more
    than CREASE_DEG (``reach`` where none is nearer)."""
    out = np.full(len(surface), float(reach))
    pairs = cKDTree(surface).query_pairs(reach, output_type="ndarray")
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        turned = np.sum(normals[a] * normals[b], axis=1) < np.cos(np.radians(CREASE_DEG))
        d = np.linalg.norm(surface[a[turned]] - surface[b[turned]], axis=1)
        np.minimum.at(out, a[turned], d)
        np.minimum.at(out, b[turned], d)
    return out

def normal_step(sigma: float, z: float, focal_px: float, span_px: float) -> int:
    """Pixels: the central differences' half width for normals at distance ``z`` with depth
    noise ``sigma`` (metres): the slope over 2 s pixels (2 s z / f metres) carries sqrt(2)
    sigma of noise; s such that its angle is at most ``NORMAL_NOISE_DEG``, at least
    ``NORMAL_STEP``, at most a quarter of ``span_px`` (the object's size in the image)."""
    need = np.sqrt(2.0) * sigma * focal_px / (2.0 * max(z, 1e-3) * np.tan(np.radians(NORMAL_NOISE_DEG)))
    return int(max(NORMAL_STEP, min(np.ceil(need), 0.25 * span_px)))


def explain(T: np.ndarray, surface: np.ndarray, normals: np.ndarray, view: FrameView, tolerance: float,
            voxel: float, same_surface: float, claimed: np.ndarray | None = None,
            up: np.ndarray | None = None, planes=(), sigma: float = 0.0, span: float = 0.0,
            grey: "Greys | None" = None, creases: np.ndarray | None = None,
            needed: float | None = None) -> Explanation:
    """How well pose T explains the frame (module docstring). ``surface``, ``normals``: the
    model's samples (model frame, outward); ``tolerance``: metres, agreement in depth at
    the pose's distance; ``same_surface``: metres, "the same surface" for the outline (the
    depth noise); ``claimed``: (H, W) uint8, pixels chosen instances explain (or None);
    ``up``: the support's normal (what lies below the object does not continue it);
    ``planes``: the frame's support planes ((normal towards the camera, offset) each);
    ``sigma``: metres, the depth noise at the pose's distance, and ``span``: metres, the
    object's size, for the normals' spacing (``normal_step``); ``grey``: the model's colour
    (``Greys``; None: it has none), for the appearance; ``creases``: the samples'
    ``crease_distances`` (``outline_seams``); ``needed``: the evidence a pose must be able to
    reach (``Explanation.possible``); one that cannot is not looked at further, its outline
    reported as 1 (the surface going on all around; most hypotheses of a real frame: 165 of
    201 on IC-BIN's, where the outline took half of the explanation's time). With an
    appearance, the symmetric turn that looks most like the image is kept (``Explanation.pose``)."""
    depth = view.depth
    p, n, rows, cols, index = visible_samples(T, surface, normals, view.intrinsics, depth.shape, 0.5 * voxel)
    d = depth[rows, cols].astype(np.float64)
    valid = d > 0
    p, n, rows, cols, d, index = p[valid], n[valid], rows[valid], cols[valid], d[valid], index[valid]
    diff = d - p[:, 2]
    near = np.abs(diff) < tolerance
    free = diff >= tolerance
    behind = diff <= -tolerance
    mine = np.ones(len(d), bool) if claimed is None else claimed[rows, cols] == 0
    # Normals where the depth gives one: four neighbours a couple of pixels away, all on the
    # same surface (not across a depth step, where a difference is no normal).
    r, c = rows[near], cols[near]
    f, z = float(view.intrinsics.K[0, 0]), float(T[2, 3])
    step = normal_step(sigma, z, f, span * f / max(z, 1e-3))
    _, measured, has = _points_and_normals(depth, view.intrinsics.K, r, c, step)
    h, w = depth.shape
    smooth = np.ones(len(r), bool)
    for dr, dc in ((0, step), (0, -step), (step, 0), (-step, 0)):
        q = depth[np.clip(r + dr, 0, h - 1), np.clip(c + dc, 0, w - 1)]
        smooth &= np.abs(q - d[near]) < tolerance
    turned = np.zeros(len(r), bool)
    turned[has] = np.sum(measured * n[near][has], axis=1) < np.cos(np.radians(NORMAL_DEG))
    turned &= smooth
    agree = near.copy()
    agree[np.flatnonzero(near)[turned]] = False
    hidden_other = behind & mine
    inside = hidden_other & _on_own_surface(depth, rows, cols, agree, same_surface) if hidden_other.any() \
        else hidden_other
    hidden = int(np.sum(hidden_other & ~inside))
    sunk = sunk_samples(T, surface, view, tolerance, voxel, planes)
    seen = int(np.sum(~behind)) + sunk
    pix = rows[agree] * depth.shape[1] + cols[agree]
    # Each agreeing sample counts 1 within the depth noise (same_surface), less towards the
    # tolerance (nothing at it): the tolerance's floor is many sigma near the camera, and a shape
    # that only passes near the surface (a cylinder lying in a wider one's place: 87 % within
    # 8 mm) is not the surface.
    weight = np.clip((tolerance - np.abs(diff)) / max(tolerance - same_surface, 1e-9), 0.0, 1.0)
    rect = (int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())) if len(rows) else (0, -1, 0, -1)
    looks, turn = float("nan"), 0
    if grey is not None and view.grey is not None:
        looks, turn = appearance(grey.grey[index[agree]], view.grey[rows[agree], cols[agree]])
    out = Explanation(T, float(np.sum(weight[agree])), int(free.sum()) + sunk, hidden, seen, int(inside.sum()), 1.0,
                      pix, rect, 0.0, looks, weight[agree], None if turn == 0 else grey.symmetries[turn])
    if claimed is not None:
        out.claimed = out.claimed_in(claimed)
    if needed is not None and out.possible < needed:
        return out
    explained = claimed
    if view.grey is not None and len(p):
        # Seams along the outline, widened over the outline band's inner edge (the samples'
        # splat and half a voxel past them, as outline_continuation draws it, and two
        # pixels): there the surface past the outline is another object's going on.
        px = voxel * view.intrinsics.K[0, 0] / float(np.median(p[:, 2]))
        r = int(round(0.75 * px)) + int(round(0.5 * px)) + 2
        seams = outline_seams(view, rows, cols, index, int(round(0.75 * px)), r, creases, voxel / px)
        if seams is not None:
            explained = seams if claimed is None else np.maximum(seams, claimed)
    out.outline = float(outline_continuation(T, surface, normals, depth, view.intrinsics, voxel, same_surface,
                                             up=up, explained=explained, normal_step=step)[0])
    return out


def _on_own_surface(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, agree: np.ndarray,
                    step: float) -> np.ndarray:
    """(n,) bool: whether each sample's pixel (``rows``, ``cols``) lies on a piece of the
    measured surface that holds an agreeing sample's pixel (``agree``): the pixels, in a crop
    around the samples, joined to their four neighbours where the depth differs by less than
    ``step`` metres; a pixel with a larger step to any neighbour (an edge) joins none."""
    out = np.zeros(len(rows), bool)
    if not agree.any() or agree.all():
        return out
    r0, c0 = int(rows.min()), int(cols.min())
    d = depth[r0:int(rows.max()) + 1, c0:int(cols.max()) + 1]
    smooth = d > 0
    down = np.abs(d[1:, :] - d[:-1, :]) >= step
    smooth[1:, :] &= ~down
    smooth[:-1, :] &= ~down
    right = np.abs(d[:, 1:] - d[:, :-1]) >= step
    smooth[:, 1:] &= ~right
    smooth[:, :-1] &= ~right
    _, labels = cv2.connectedComponents(smooth.astype(np.uint8), connectivity=4)
    lab = labels[rows - r0, cols - c0]
    own = np.unique(lab[agree])
    return np.isin(lab, own[own > 0])


def appearance(model_grey: np.ndarray, image_grey: np.ndarray) -> tuple[float, int]:
    """The correlation of the model's grey levels with the image's at the same samples
    (-1..1), the best over the columns of ``model_grey`` (n, M): the grey each sample shows
    under each of the poses the shape cannot tell apart (``Greys``); and that column. NaN
    (and 0) with fewer than ``MIN_JUDGED`` samples or less than ``MIN_GREY_SPREAD`` of spread
    on the model's side; 0 with less on the image's."""
    a = np.asarray(model_grey, np.float64).reshape(len(model_grey), -1)
    b = np.asarray(image_grey, np.float64)
    if len(b) < MIN_JUDGED:
        return float("nan"), 0
    sa = a.std(axis=0)
    ok = sa >= MIN_GREY_SPREAD
    if not ok.any():
        return float("nan"), 0
    if b.std() < MIN_GREY_SPREAD:
        return 0.0, 0
    corr = np.full(a.shape[1], -np.inf)
    corr[ok] = ((a[:, ok] - a[:, ok].mean(axis=0)) * (b - b.mean())[:, None]).mean(axis=0) / (sa[ok] * b.std())
    best = int(np.argmax(corr))
    return float(corr[best]), best


@dataclass
class Greys:
    """A model's colour for the appearance: ``grey`` (N, M), the grey level each surface
    sample shows under each of M poses T S the shape cannot tell apart (``symmetries`` (M,
    4, 4), identity first)."""
    grey: np.ndarray
    symmetries: np.ndarray


def symmetric_greys(surface: np.ndarray, grey: np.ndarray, symmetries, turns: int = 36) -> Greys:
    """``Greys`` of the N ``surface`` samples (model frame) with grey levels ``grey`` under
    the ``symmetries`` (their discrete ones, each with ``turns`` turns about a continuous
    axis): under pose T S the sample at x is the model's point S^-1 x, the nearest sample's
    grey. One column (identity) without symmetries."""
    mats = [np.eye(4)] if symmetries is None else [np.asarray(S, np.float64) for S in symmetries.discrete]
    if symmetries is not None and symmetries.axis is not None:
        mats = [S @ turn_about(symmetries.axis, symmetries.point, 2.0 * np.pi * k / turns)
                for S in mats for k in range(turns)]
    tree = cKDTree(surface)
    cols = []
    for S in mats:
        _, j = tree.query(apply_transform(invert_transform(S), surface), k=1)
        cols.append(np.asarray(grey, np.float64)[j])
    return Greys(np.stack(cols, axis=1), np.stack(mats))


def sunk_samples(T: np.ndarray, surface: np.ndarray, view: FrameView, tolerance: float, voxel: float,
                 planes) -> int:
    """How many of the model's samples at pose T, seen or not, lie more than ``SUNK_VOXELS``
    (or ``tolerance``) below one of the support ``planes`` where the depth shows that plane (or something on it)
    on their pixel: inside the support. The camera sees little of what is sunk (a carton's
    sides at a grazing angle), so the volume is asked, as two instances' volumes are."""
    if not planes:
        return 0
    p = surface @ T[:3, :3].T + T[:3, 3]
    deep = max(SUNK_VOXELS * voxel, tolerance)
    out = np.zeros(len(p), bool)
    for n_up, offset in planes:
        out |= p @ n_up + offset < -deep
    if not out.any():
        return 0
    q = p[out]
    K = view.intrinsics.K
    h, w = view.depth.shape
    z = np.maximum(q[:, 2], 1e-6)
    u = np.round(K[0, 0] * q[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * q[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (q[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    q, d = q[inside], view.depth[v[inside], u[inside]].astype(np.float64)
    count = np.zeros(len(q), bool)
    for n_up, offset in planes:
        below = q @ n_up + offset < -deep
        seen = (d > 0) & ((q @ n_up) * (d / q[:, 2]) + offset >= -tolerance)    # measured on or above it
        count |= below & seen
    return int(count.sum())


def claim(mask: np.ndarray, e: Explanation, radius: int) -> None:
    """Mark the pixels of explanation e's agreeing samples (spread over ``radius`` pixels:
    the samples lie a few pixels apart) as claimed in ``mask`` (H, W) uint8."""
    if len(e.pixels) == 0:
        return
    one = np.zeros(mask.shape, np.uint8)
    one.flat[e.pixels] = 1
    r = max(1, radius)
    one = cv2.dilate(one, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    np.maximum(mask, one, out=mask)


def select(candidates: list, rescore, conflicts, min_support: float, min_evidence: float, radius: int,
           margin: int, shape, late=lambda: False) -> list:
    """The instances chosen jointly from ``candidates`` (Explanations with nothing claimed;
    those that could pass were what hides them and their outlines explained): of those that
    pass, the best gain first; after each choice the rest are scored again with its pixels claimed
    (``rescore(e, claimed)`` -> Explanation), those that ``conflicts(e, chosen)`` (their
    volumes overlap a chosen one's: two objects cannot fill one space, which the depth
    alone cannot tell where neither is seen) or repeat its pixels (``MAX_CLAIMED``) drop
    out; only those whose drawings come within ``margin`` pixels of the chosen one's are
    scored again. Stops when no pose passes ``min_support`` and ``min_evidence``; once
    ``late()`` (the frame's deadline), without scoring again.

    Lazily: a pose near a choice made since it was scored stands in with the most it can
    gain now (``possible`` times what it explains that is not claimed; claiming only
    explains more of what hides it and of its outline) and is scored again only when that
    could win. The same choices as scoring every such pose after each choice, for a few of
    those scorings (flush cartons: each is near up to eight chosen neighbours)."""
    def passes(e):
        return e.support >= min_support and e.evidence >= min_evidence and e.agree - e.claimed >= MIN_JUDGED // 2

    def rank(e, stale):
        if stale:
            return e.possible * (e.agree - e.claimed)
        return e.gain if passes(e) else -np.inf

    pending = [[e, False] for e in candidates if e.possible >= min_evidence]      # (explanation, stale)
    claimed = np.zeros(shape, np.uint8)
    chosen: list = []
    while pending:
        scoring = not late()
        ranks = [rank(e, stale and scoring) for e, stale in pending]
        k = int(np.argmax(ranks))
        if ranks[k] == -np.inf:
            break
        e, stale = pending[k]
        if stale and scoring:
            pending[k] = [rescore(e, claimed), False]
            continue
        pending.pop(k)
        chosen.append(e)
        claim(claimed, e, radius)
        kept = []
        for c, stale in pending:
            if conflicts(c, e):
                continue
            if _near(c.rect, e.rect, margin):
                # Only the poses whose drawing comes near the chosen one's can score otherwise.
                c, stale = replace(c, claimed=c.claimed_in(claimed)), True
            if c.claimed <= MAX_CLAIMED * max(c.agree, 1):
                kept.append([c, stale])
        pending = kept
    return chosen


def _near(a: tuple, b: tuple, margin: int) -> bool:
    """Whether two image rectangles (top, bottom, left, right) come within ``margin`` pixels."""
    return not (a[0] > b[1] + margin or b[0] > a[1] + margin or a[2] > b[3] + margin or b[2] > a[3] + margin)
