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

import math

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from ...messages import CameraIntrinsics
from ...rgbd.verify import _facing, _points_and_normals_kernel, outline_continuation
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
                    depth: np.ndarray, splat: float, tolerance: float, step: int) -> tuple:
    """The model's samples at pose T that face the camera, fall in the image, are not behind
    the model's own nearer surface (z-buffer of the samples, each drawn over ``splat``
    metres) and have depth on their pixel, each compared with that depth: (points (n, 3)
    camera frame, rows, cols, their indices in ``surface``, the measured depth minus theirs,
    agree: within ``tolerance`` and the measured normal, ``step`` pixels wide
    (``normal_step``), not turned from the model's by more than NORMAL_DEG)."""
    p = surface @ T[:3, :3].T + T[:3, 3]
    n = normals @ T[:3, :3].T
    K = intrinsics.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    index, u, v, r = _drawable(p, n, fx, fy, cx, cy, depth.shape[0], depth.shape[1], float(splat))
    keep, agree, diff = _compare(p, n, index, u, v, np.asarray(depth), fx, fy, cx, cy, _disc(r), float(2.0 * splat),
                                 float(tolerance), int(step))
    index = index[keep]
    return p[index], v[keep], u[keep], index, diff[keep], agree[keep]


_DISCS: dict = {}


def _disc(r: int) -> np.ndarray:
    """OpenCV's elliptic structuring element of radius r (uint8, 2r + 1 square)."""
    out = _DISCS.get(r)
    if out is None:
        out = _DISCS[r] = np.ascontiguousarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return out


@numba.njit(cache=True, nogil=True)
def _drawable(p, n, fx, fy, cx, cy, h, w, splat):
    # The samples facing the camera (``facing_camera``) that fall in the image: their
    # indices, pixels (``image_pixels``) and the z-buffer's splat radius in pixels at their
    # median distance (0 with fewer than two).
    facing = _facing(p, n)
    index = np.flatnonzero(facing)
    u = np.empty(len(index), np.int64)
    v = np.empty(len(index), np.int64)
    m = 0
    for k in range(len(index)):
        i = index[k]
        uu = np.int64(np.round(fx * p[i, 0] / p[i, 2] + cx))
        vv = np.int64(np.round(fy * p[i, 1] / p[i, 2] + cy))
        if uu >= 0 and uu < w and vv >= 0 and vv < h:
            index[m], u[m], v[m] = i, uu, vv
            m += 1
    index, u, v = index[:m], u[:m], v[:m]
    r = 0
    if m >= 2:
        z = np.empty(m)
        for k in range(m):
            z[k] = p[index[k], 2]
        r = max(1, int(np.round(splat * fx / np.median(z))))
    return index, u, v, r


@numba.njit(cache=True, nogil=True)
def _compare(p, n, index, u, v, depth, fx, fy, cx, cy, disc, front_slack, tolerance, step):
    # One pass where the array form made some 40 temporaries a pose (IC-BIN: a quarter of the
    # verification's time), the same arithmetic: the z-buffer's nearest sample per pixel,
    # eroded over the disc (cv2.erode), a sample in front within front_slack (float32, as
    # the buffer); then the depth on its pixel, and for those within the tolerance the
    # measured normal (``_points_and_normals``) where the four neighbours step pixels away
    # lie within the tolerance too; the samples ``index`` (pixels u, v). Returns (kept: in
    # front with depth, agree, the measured depth minus the sample's).
    m = index.shape[0]
    keep = np.zeros(m, np.bool_)
    agree = np.zeros(m, np.bool_)
    diff = np.zeros(m)
    if m == 0:
        return keep, agree, diff
    h, w = depth.shape
    if m < 2:
        for i in range(m):
            keep[i] = depth[v[i], u[i]] > 0
    else:
        u0, v0, u1, v1 = u.min(), v.min(), u.max(), v.max()
        zbuf = np.full((v1 - v0 + 1, u1 - u0 + 1), np.inf, np.float32)
        for i in range(m):
            z = np.float32(p[index[i], 2])
            if z < zbuf[v[i] - v0, u[i] - u0]:
                zbuf[v[i] - v0, u[i] - u0] = z
        r = disc.shape[0] // 2
        bh, bw = zbuf.shape
        slack = np.float32(front_slack)
        for i in range(m):
            y, x = v[i] - v0, u[i] - u0
            low = np.float32(np.inf)
            for dy in range(-r, r + 1):
                yy = y + dy
                if yy < 0 or yy >= bh:
                    continue
                for dx in range(-r, r + 1):
                    xx = x + dx
                    if xx < 0 or xx >= bw or disc[dy + r, dx + r] == 0:
                        continue
                    if zbuf[yy, xx] < low:
                        low = zbuf[yy, xx]
            keep[i] = p[index[i], 2] <= np.float32(low + slack) and depth[v[i], u[i]] > 0
    cos_turn = math.cos(math.radians(NORMAL_DEG))
    rows1 = np.zeros(1, np.int64)
    cols1 = np.zeros(1, np.int64)
    P1 = np.empty((1, 3))
    N1 = np.empty((1, 3))
    ok1 = np.zeros(1, np.bool_)
    for i in range(m):
        if not keep[i]:
            continue
        r0, c0 = v[i], u[i]
        d = float(depth[r0, c0])
        diff[i] = d - p[index[i], 2]
        if not abs(diff[i]) < tolerance:
            continue
        agree[i] = True
        smooth = True
        for k in range(4):
            rr = r0 + (step if k == 2 else (-step if k == 3 else 0))
            cc = c0 + (step if k == 0 else (-step if k == 1 else 0))
            rr = min(max(rr, 0), h - 1)
            cc = min(max(cc, 0), w - 1)
            if not abs(float(depth[rr, cc]) - d) < tolerance:
                smooth = False
        if not smooth:
            continue
        rows1[0], cols1[0], ok1[0] = r0, c0, False
        if _points_and_normals_kernel(depth, fx, fy, cx, cy, rows1, cols1, step, P1, N1, ok1) == 0:
            continue
        j = index[i]
        if N1[0, 0] * n[j, 0] + N1[0, 1] * n[j, 1] + N1[0, 2] * n[j, 2] < cos_turn:
            agree[i] = False
    return keep, agree, diff


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
    f, z = float(view.intrinsics.K[0, 0]), float(T[2, 3])
    step = normal_step(sigma, z, f, span * f / max(z, 1e-3))
    p, rows, cols, index, diff, agree = visible_samples(T, surface, normals, view.intrinsics, depth, 0.5 * voxel,
                                                        tolerance, step)
    free = diff >= tolerance
    behind = diff <= -tolerance
    mine = np.ones(len(diff), bool) if claimed is None else claimed[rows, cols] == 0
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
    depth = np.asarray(depth)
    return _own_surface(depth, np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(agree, np.bool_),
                        depth.dtype.type(step))


@numba.njit(cache=True, nogil=True)
def _own_surface(depth, rows, cols, agree, step):
    # The pixels reached from an agreeing sample's through smooth 4-neighbours (as
    # cv2.connectedComponents labels them: the components holding one), in the samples'
    # crop; the steps in the depth's type (``step`` is of it).
    r0, c0, r1, c1 = rows.min(), cols.min(), rows.max(), cols.max()
    h, w = r1 - r0 + 1, c1 - c0 + 1
    s = step
    smooth = np.zeros((h, w), np.bool_)
    for y in range(h):
        for x in range(w):
            d = depth[r0 + y, c0 + x]
            ok = d > 0
            if ok and y > 0 and not abs(d - depth[r0 + y - 1, c0 + x]) < s:
                ok = False
            if ok and y < h - 1 and not abs(depth[r0 + y + 1, c0 + x] - d) < s:
                ok = False
            if ok and x > 0 and not abs(d - depth[r0 + y, c0 + x - 1]) < s:
                ok = False
            if ok and x < w - 1 and not abs(depth[r0 + y, c0 + x + 1] - d) < s:
                ok = False
            smooth[y, x] = ok
    reached = np.zeros((h, w), np.bool_)
    stack = np.empty(h * w, np.int64)
    top = 0
    for i in range(len(rows)):
        y, x = rows[i] - r0, cols[i] - c0
        if agree[i] and smooth[y, x] and not reached[y, x]:
            reached[y, x] = True
            stack[top] = y * w + x
            top += 1
    while top > 0:
        top -= 1
        y, x = stack[top] // w, stack[top] % w
        for k in range(4):
            yy = y + (1 if k == 0 else (-1 if k == 1 else 0))
            xx = x + (1 if k == 2 else (-1 if k == 3 else 0))
            if yy >= 0 and yy < h and xx >= 0 and xx < w and smooth[yy, xx] and not reached[yy, xx]:
                reached[yy, xx] = True
                stack[top] = yy * w + xx
                top += 1
    out = np.zeros(len(rows), np.bool_)
    for i in range(len(rows)):
        out[i] = reached[rows[i] - r0, cols[i] - c0]
    return out


def appearance(model_grey: np.ndarray, image_grey: np.ndarray) -> tuple[float, int]:
    """The correlation of the model's grey levels with the image's at the same samples
    (-1..1), the best over the columns of ``model_grey`` (n, M): the grey each sample shows
    under each of the poses the shape cannot tell apart (``Greys``); and that column. NaN
    (and 0) with fewer than ``MIN_JUDGED`` samples or less than ``MIN_GREY_SPREAD`` of spread
    on the model's side; 0 with less on the image's."""
    if len(image_grey) < MIN_JUDGED:
        return float("nan"), 0
    a = np.asarray(model_grey, np.float64).reshape(len(model_grey), -1)
    b = np.asarray(image_grey, np.float64)
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
