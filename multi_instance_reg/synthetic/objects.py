"""Catalogue of named tabletop objects (boxes and cylinders) with their textures.

Object frame (the frame the ground truth poses refer to): origin at the geometric centre;
for a box the axes run along its edges, x along ``dx``, y along ``dy``, z along ``dz``; for a
cylinder z is the axis and the dimensions are ``[diameter, diameter, height]``.

Textures are crops of pictures that ship inside scikit-image (no download at run time). They
depend on the object's name only, never on a seed: every instance of an object, in every
scene and capture bag, looks the same, while different faces of one object show different
crops so that the object's pose is not ambiguous to SIFT.
"""
from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..errors import InputError

OBJECT_FRAME_TEXT = ("origin at the geometric centre; box axes along the edges (dx, dy, dz); "
                     "cylinder axis = z, dimensions [diameter, diameter, height]")

# Texels per metre of object surface. 2000/m keeps a face sharp down to 0.4 m at 1280x720
# (fx ~ 758 px, i.e. ~1900 px/m at 0.4 m); the renderer mip-maps for farther views.
TEXELS_PER_METRE = 2000.0
_MAX_TEXTURE_SIDE = 1024

# Box faces: (name, outward normal, "up" direction of the picture on that face).
BOX_FACES = (
    ("+x", (1, 0, 0), (0, 0, 1)), ("-x", (-1, 0, 0), (0, 0, 1)),
    ("+y", (0, 1, 0), (0, 0, 1)), ("-y", (0, -1, 0), (0, 0, 1)),
    ("+z", (0, 0, 1), (0, 1, 0)), ("-z", (0, 0, -1), (0, 1, 0)),
)


@dataclass(frozen=True)
class ObjectSpec:
    """A named object. ``faces`` maps each face (box: "+x".."-z"; cylinder: "side", "+z",
    "-z") to the scikit-image picture its texture is cropped from; ``tint`` colours grey
    pictures; ``resting`` lists (object axis that points up, weight) for placing it on a table."""
    name: str
    shape: str                                  # "box" | "cylinder" | "bracket" | "profile" (see UNTEXTURED_OBJECTS)
    dimensions_m: tuple[float, float, float]    # box (dx, dy, dz); cylinder (d, d, h); bracket: its box
    faces: tuple[tuple[str, str], ...]
    resting: tuple[tuple[str, float], ...]
    tint: tuple[int, int, int] = (255, 255, 255)
    label: str = ""                             # printed on the larger faces like a brand name
    label_colour: tuple[int, int, int] = (200, 30, 30)
    # Boxes the object is made of, (centre, dimensions) in the object frame; a "bracket" is
    # drawn as these (the object frame stays at the centre of the whole object's box).
    parts: tuple = ()
    # A "profile": its outline in the object's (x, z) plane, counter-clockwise, extruded over
    # y in [-dy/2, dy/2]; ``parts`` are that outline cut into boxes (``profile_parts``).
    profile: tuple = ()
    # A "flat" face darkened over this much along its edges (a cardboard carton's crushed,
    # shadowed edges): cartons packed flush show a dark seam between them from above, as
    # real ones do (their outlines are in the colour image, not in the depth).
    worn_edge_m: float = 0.0
    # A band of packing tape this wide along the middle of the top and bottom ("+z", "-z"),
    # over the flaps' seam: a real carton's top is seldom one plain face.
    tape_m: float = 0.0

    @property
    def radius(self) -> float:
        return 0.5 * self.dimensions_m[0]

    @property
    def half_extents(self) -> np.ndarray:
        return 0.5 * np.asarray(self.dimensions_m, dtype=np.float64)

    def description(self) -> dict:
        """The JSON-able description that travels with a bag on /ground_truth/object."""
        return {"name": self.name, "shape": self.shape,
                "dimensions_m": [float(v) for v in self.dimensions_m],
                "object_frame": OBJECT_FRAME_TEXT}


def _box_faces(top, bottom, sides) -> tuple[tuple[str, str], ...]:
    side = dict(zip(("+x", "-x", "+y", "-y"), sides))
    return tuple((f, {"+z": top, "-z": bottom}.get(f, side.get(f))) for f, _, _ in BOX_FACES)


OBJECTS: dict[str, ObjectSpec] = {spec.name: spec for spec in (
    # A flat box of crackers or tea: big textured top, lies flat most of the time.
    ObjectSpec("snack_box", "box", (0.18, 0.12, 0.05),
               _box_faces("astronaut", "astronaut", ("coffee", "coffee", "coffee", "coffee")),
               resting=(("+z", 0.45), ("-z", 0.35), ("+y", 0.1), ("-y", 0.1)),
               label="CRUNCH", label_colour=(30, 60, 170)),
    ObjectSpec("cereal_box", "box", (0.19, 0.07, 0.27),
               # Front and back: photos; the narrow sides: small print (like nutrition facts).
               _box_faces("rocket", "rocket", ("page", "page", "chelsea", "camera")),
               resting=(("+z", 0.6), ("-y", 0.15), ("+y", 0.15), ("-z", 0.1)),
               label="OATY", label_colour=(200, 120, 20)),
    ObjectSpec("snack_bar", "box", (0.12, 0.04, 0.02),
               _box_faces("hubble_deep_field", "hubble_deep_field",
                          ("hubble_deep_field",) * 4),
               resting=(("+z", 0.5), ("-z", 0.4), ("+y", 0.05), ("-y", 0.05)),
               label="BAR", label_colour=(150, 20, 120)),
    ObjectSpec("can", "cylinder", (0.066, 0.066, 0.122),
               (("side", "immunohistochemistry"), ("+z", "coins"), ("-z", "coins")),
               resting=(("+z", 0.8), ("+x", 0.2)), label="FIZZ", label_colour=(20, 140, 60)),
    # Distractors: other pictures, other sizes.
    ObjectSpec("book", "box", (0.21, 0.15, 0.03),
               _box_faces("retina", "retina", ("text", "text", "text", "text")),
               resting=(("+z", 0.6), ("-z", 0.4)), tint=(235, 225, 200),
               label="ATLAS", label_colour=(40, 40, 40)),
    ObjectSpec("toy_block", "box", (0.07, 0.07, 0.07),
               _box_faces("logo", "clock", ("logo", "clock", "logo", "clock")),
               resting=(("+z", 0.3), ("-z", 0.2), ("+x", 0.25), ("-y", 0.25)),
               tint=(250, 200, 120)),
    ObjectSpec("tea_tin", "cylinder", (0.085, 0.085, 0.11),
               (("side", "moon"), ("+z", "moon"), ("-z", "moon")),
               resting=(("+z", 0.9), ("+x", 0.1)), tint=(230, 190, 90),
               label="TEA", label_colour=(90, 20, 20)),
    ObjectSpec("jar", "cylinder", (0.075, 0.075, 0.14),
               (("side", "cell"), ("+z", "grass"), ("-z", "grass")),
               resting=(("+z", 1.0),), tint=(170, 220, 250)),
)}

DEFAULT_OBJECT = "snack_box"

# Things that are in a scene without being catalogue objects: never a target, never drawn as
# a distractor (so adding one here changes no existing scene).
PROPS: dict[str, ObjectSpec] = {spec.name: spec for spec in (
    # A forearm in a blue sleeve that passes between the camera and the table (the occluder of
    # the tracking scenes); its axis is the cylinder's z.
    ObjectSpec("forearm", "cylinder", (0.09, 0.09, 0.45),
               (("side", "grass"), ("+z", "moon"), ("-z", "grass")),
               resting=(("+x", 1.0),), tint=(95, 120, 175)),
    # The walls and floor of a plastic bin (layout "bin"): flat grey-blue, each panel a box
    # of its own size (the flat texture stretches to any size).
    ObjectSpec("bin_panel", "box", (0.4, 0.3, 0.012), _box_faces("flat", "flat", ("flat",) * 4),
               resting=(("+z", 1.0),), tint=(88, 112, 140)),
    # Furniture 2-3 m behind the table (background "clutter"): a cupboard, a bookshelf seen
    # from the front (print on its front: book spines and papers), a desk, a stack of boxes.
    ObjectSpec("cupboard", "box", (0.9, 0.45, 1.1), _box_faces("gravel", "gravel", ("gravel", "gravel", "gravel", "coins")),
               resting=(("+z", 1.0),), tint=(160, 120, 80)),
    ObjectSpec("bookshelf", "box", (0.9, 0.32, 1.8), _box_faces("gravel", "gravel", ("gravel", "gravel", "gravel", "text")),
               resting=(("+z", 1.0),), tint=(205, 180, 140)),
    ObjectSpec("desk", "box", (1.2, 0.7, 0.75), _box_faces("page", "gravel", ("gravel", "gravel", "gravel", "gravel")),
               resting=(("+z", 1.0),), tint=(190, 170, 140)),
    ObjectSpec("box_stack", "box", (0.6, 0.4, 0.8), _box_faces("astronaut", "gravel", ("chelsea", "coffee", "rocket", "camera")),
               resting=(("+z", 1.0),), tint=(225, 205, 175)),
)}
FURNITURE = ("cupboard", "bookshelf", "desk", "box_stack")


# Objects without texture, flat-coloured all over ("flat" faces), for the shape front end.
# Kept out of OBJECTS so that the textured scenes' distractor pool (and so every textured
# scene of a seed) stays as it was.
def _flat(shape: str) -> tuple[tuple[str, str], ...]:
    faces = ("side", "+z", "-z") if shape == "cylinder" else tuple(f for f, _, _ in BOX_FACES)
    return tuple((f, "flat") for f in faces)


def _bracket_parts(dims, thickness):
    """An L profile in the xz plane, extruded along y: a base plate on the bottom and an
    upright plate at the -x end, both ``thickness`` thick."""
    X, Y, Z = dims
    t = thickness
    return (((0.0, 0.0, -Z / 2 + t / 2), (X, Y, t)),
            ((-X / 2 + t / 2, 0.0, t / 2), (t, Y, Z - t)))


def profile_parts(outline, length):
    """Boxes, (centre, dimensions), that make up the rectilinear ``outline`` in (x, z)
    extruded over ``length`` along y: the outline cut into strips between its vertices' x
    values, each strip into the z intervals inside the outline, neighbouring strips with the
    same intervals joined (fewer seams for the renderer)."""
    pts = np.asarray(outline, np.float64)
    xs = np.unique(pts[:, 0])
    edges = [(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
    horizontal = [(min(a[0], b[0]), max(a[0], b[0]), a[1]) for a, b in edges if a[1] == b[1]]
    strips = []
    for x0, x1 in zip(xs[:-1], xs[1:]):
        xm = 0.5 * (x0 + x1)
        zs = sorted(z for lo, hi, z in horizontal if lo < xm < hi)     # crossings: in, out, in, ...
        spans = tuple(zip(zs[0::2], zs[1::2]))
        if strips and strips[-1][2] == spans and strips[-1][1] == x0:
            strips[-1] = (strips[-1][0], x1, spans)
        else:
            strips.append((x0, x1, spans))
    return tuple(((0.5 * (x0 + x1), 0.0, 0.5 * (z0 + z1)), (x1 - x0, float(length), z1 - z0))
                 for x0, x1, spans in strips for z0, z1 in spans)


def _profile(name, dims, outline, resting, tint) -> ObjectSpec:
    outline = tuple(tuple(float(v) for v in p) for p in outline)
    return ObjectSpec(name, "profile", dims, _flat("box"), resting=resting, tint=tint,
                      parts=profile_parts(outline, dims[1]), profile=outline)


def _channel_outline(X, Z, t):
    """A U open towards +z: a floor and two walls, all ``t`` thick."""
    return ((-X / 2, -Z / 2), (X / 2, -Z / 2), (X / 2, Z / 2), (X / 2 - t, Z / 2), (X / 2 - t, -Z / 2 + t),
            (-X / 2 + t, -Z / 2 + t), (-X / 2 + t, Z / 2), (-X / 2, Z / 2))


def _stairs_outline(X, Z):
    """Three steps, each a third of X long and a third of Z high, the highest at -x."""
    return ((-X / 2, -Z / 2), (X / 2, -Z / 2), (X / 2, -Z / 6), (X / 6, -Z / 6), (X / 6, Z / 6), (-X / 6, Z / 6),
            (-X / 6, Z / 2), (-X / 2, Z / 2))


def _tee_outline(X, Z, t):
    """A T: a flange ``t`` thick across the top, a web ``t`` thick down the middle."""
    return ((-t / 2, -Z / 2), (t / 2, -Z / 2), (t / 2, Z / 2 - t), (X / 2, Z / 2 - t), (X / 2, Z / 2),
            (-X / 2, Z / 2), (-X / 2, Z / 2 - t), (-t / 2, Z / 2 - t))


BRACKET_THICKNESS_M = 0.012
WORN_EDGE_M = 0.006
TAPE_M = 0.048
# Packing tape's shade against the carton's (lighter, glossy).
TAPE_SHADE = 1.12
# The worn edge's darkest shade (at the very edge), rising linearly to the tint.
WORN_EDGE_SHADE = 0.55
UNTEXTURED_OBJECTS: dict[str, ObjectSpec] = {spec.name: spec for spec in (
    # A plain brown shipping carton (stacked on pallets).
    ObjectSpec("carton", "box", (0.30, 0.20, 0.15), _flat("box"),
               resting=(("+z", 0.8), ("-z", 0.2)), tint=(168, 128, 84), worn_edge_m=WORN_EDGE_M,
               tape_m=TAPE_M),
    # A turned grey part, standing or lying.
    ObjectSpec("grey_cylinder", "cylinder", (0.06, 0.06, 0.10), _flat("cylinder"),
               resting=(("+z", 0.6), ("+x", 0.4)), tint=(150, 152, 158)),
    # An L-shaped angle bracket (no proper rotational symmetry).
    ObjectSpec("bracket", "bracket", (0.12, 0.06, 0.08), _flat("box"),
               resting=(("+z", 0.7), ("+x", 0.3)), tint=(118, 124, 132),
               parts=_bracket_parts((0.12, 0.06, 0.08), BRACKET_THICKNESS_M)),
    # Distractors: other plain shapes and sizes.
    ObjectSpec("crate", "box", (0.40, 0.30, 0.12), _flat("box"), resting=(("+z", 1.0),), tint=(96, 120, 150)),
    ObjectSpec("grey_block", "box", (0.08, 0.07, 0.05), _flat("box"),
               resting=(("+z", 0.6), ("+x", 0.4)), tint=(140, 140, 146)),
    ObjectSpec("wide_cylinder", "cylinder", (0.10, 0.10, 0.06), _flat("cylinder"),
               resting=(("+z", 1.0),), tint=(160, 160, 150)),
    ObjectSpec("pallet", "box", (1.20, 0.80, 0.144), _flat("box"), resting=(("+z", 1.0),), tint=(186, 160, 118)),
    # Shapes the shape front end was not developed on (session 12), never distractors (so
    # the scenes above stay as they were): a U channel (a half turn about z maps it onto
    # itself), open side up or down.
    _profile("channel", (0.10, 0.16, 0.05), _channel_outline(0.10, 0.05, 0.008),
             resting=(("+z", 0.6), ("-z", 0.4)), tint=(112, 138, 104)),
    # A block of three steps (no symmetry), on its base or on its end.
    _profile("stairs", (0.12, 0.08, 0.06), _stairs_outline(0.12, 0.06),
             resting=(("+z", 0.7), ("+y", 0.3)), tint=(172, 150, 118)),
    # A T profile (a half turn about z), on its flange or on its end.
    _profile("tee", (0.10, 0.12, 0.07), _tee_outline(0.10, 0.07, 0.010),
             resting=(("-z", 0.7), ("+y", 0.3)), tint=(108, 114, 142)),
)}


def get_object(name: str) -> ObjectSpec:
    spec = OBJECTS.get(name) or UNTEXTURED_OBJECTS.get(name)
    if spec is None:
        raise InputError(f"unknown object '{name}'; choose one of: {', '.join(list(OBJECTS) + list(UNTEXTURED_OBJECTS))}")
    return spec


def scaled(spec: ObjectSpec, scale) -> ObjectSpec:
    """The object made ``scale`` (3,) times as large along its x, y and z axes (its parts and
    profile too, in the same object frame): a real carton is seldom the size of the mesh
    its user measured for it. A cylinder keeps a round section (x and y take their mean)."""
    s = np.asarray(scale, np.float64)
    if spec.shape == "cylinder":
        s = np.array([0.5 * (s[0] + s[1])] * 2 + [s[2]])
    dims = tuple(float(v) for v in np.asarray(spec.dimensions_m) * s)
    parts = tuple((tuple(float(v) for v in np.asarray(c) * s), tuple(float(v) for v in np.asarray(d) * s))
                  for c, d in spec.parts)
    profile = tuple((float(x * s[0]), float(z * s[2])) for x, z in spec.profile)
    return replace(spec, dimensions_m=dims, parts=parts, profile=profile)


def object_mesh(spec: ObjectSpec):
    """The object's surface as a triangle mesh in its object frame (metres)."""
    from ..meshes import box_mesh, cylinder_mesh, extruded_polygon_mesh

    if spec.shape == "cylinder":
        return cylinder_mesh(spec.dimensions_m[0], spec.dimensions_m[2])
    if spec.shape == "box":
        return box_mesh(*spec.dimensions_m)
    if spec.shape == "profile":
        from ..meshes import polygon_triangles

        outline = np.asarray(spec.profile, np.float64)
        mesh = extruded_polygon_mesh(outline, spec.dimensions_m[1], polygon_triangles(outline))
        v = mesh.vertices               # extruded along z; a quarter turn about x, as below
        mesh.vertices = np.column_stack([v[:, 0], -v[:, 2], v[:, 1]])
        return mesh
    # bracket: the L outline in (x, z), counter-clockwise, extruded along y.
    X, Y, Z = spec.dimensions_m
    t = BRACKET_THICKNESS_M
    outline = np.array([[-X / 2, -Z / 2], [X / 2, -Z / 2], [X / 2, -Z / 2 + t], [-X / 2 + t, -Z / 2 + t],
                        [-X / 2 + t, Z / 2], [-X / 2, Z / 2]])
    mesh = extruded_polygon_mesh(outline, Y, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]])
    # (a, b, c) -> (a, -c, b): a quarter turn about x takes the extrusion axis to y.
    v = mesh.vertices
    mesh.vertices = np.column_stack([v[:, 0], -v[:, 2], v[:, 1]])
    return mesh


def textured_object_mesh(spec: ObjectSpec, segments: int = 64):
    """An object's mesh with its pictures as the renderer draws them, the pictures side by side
    in one texture (an atlas), texture coordinates per triangle corner. A box: 4 vertices a
    face. A cylinder: its side in ``segments`` strips, the picture wrapped once round from the
    +x axis (column = angle / 2 pi, row = down from the top), each cap's picture over the
    square the cap is inscribed in. Objects made of parts (a bracket): ``object_mesh`` (no
    colour)."""
    from ..meshes import TriangleMesh

    if spec.parts or spec.shape not in ("box", "cylinder"):
        return object_mesh(spec)
    textures = object_textures(spec.name)
    half = spec.half_extents
    if spec.shape == "box":
        # (face, corners as picture (column, row) fractions -> object points)
        quads = []
        for face, normal, up in BOX_FACES:
            n, upv = np.asarray(normal, np.float64), np.asarray(up, np.float64)
            right = np.cross(upv, n)            # the picture's rows run along it, seen from outside
            width, height = 2 * np.abs(right) @ half, 2 * np.abs(upv) @ half
            centre = n * (np.abs(n) @ half)
            quads.append((face, [((s_, t_), centre + (s_ - 0.5) * width * right - (t_ - 0.5) * height * upv)
                                 for s_, t_ in ((0, 0), (1, 0), (1, 1), (0, 1))]))
    else:
        r, hh = spec.radius, half[2]
        quads = []
        for k in range(segments):           # counter-clockwise seen from outside: angle, then up
            a0, a1 = 2 * np.pi * k / segments, 2 * np.pi * (k + 1) / segments
            s0, s1 = k / segments, (k + 1) / segments
            quads.append(("side", [((s0, 1), (r * np.cos(a0), r * np.sin(a0), -hh)),
                                   ((s1, 1), (r * np.cos(a1), r * np.sin(a1), -hh)),
                                   ((s1, 0), (r * np.cos(a1), r * np.sin(a1), hh)),
                                   ((s0, 0), (r * np.cos(a0), r * np.sin(a0), hh))]))
        # The caps as the scene draws them (a disc in the square quad of its picture).
        ring = [(r * np.cos(a), r * np.sin(a)) for a in 2 * np.pi * np.arange(segments) / segments]
        caps = []
        for face, sign in (("+z", 1.0), ("-z", -1.0)):
            corners = [(((sign * x + r) / (2 * r), (r - y) / (2 * r)), (x, y, sign * hh)) for x, y in ring]
            caps.append((face, corners if sign > 0 else corners[::-1]))
    atlas_faces = sorted({face for face, _ in quads} | ({face for face, _ in caps} if spec.shape == "cylinder" else set()))
    atlas_h = max(textures[f].shape[0] for f in atlas_faces)
    atlas_w = sum(textures[f].shape[1] for f in atlas_faces)
    atlas = np.zeros((atlas_h, atlas_w, 3), np.uint8)
    column = {}
    col = 0
    for f in atlas_faces:
        th, tw = textures[f].shape[:2]
        atlas[:th, col:col + tw] = textures[f]
        column[f] = col
        col += tw

    def uv(face, s_, t_):
        th, tw = textures[face].shape[:2]
        return ((column[face] + s_ * tw) / atlas_w, 1.0 - t_ * th / atlas_h)

    verts, tris, corner_uv = [], [], []
    polygons = quads + (caps if spec.shape == "cylinder" else [])
    for face, corners in polygons:
        base = len(verts)
        verts.extend(p for _, p in corners)
        for j in range(1, len(corners) - 1):        # a fan: quads and the convex caps
            tri = (0, j + 1, j) if spec.shape == "box" else (0, j, j + 1)
            tris.append([base + i for i in tri])
            corner_uv.append([uv(face, *corners[i][0]) for i in tri])
    return TriangleMesh(np.array(verts, np.float64), np.array(tris, np.int64),
                        corner_uv=np.array(corner_uv, np.float32), texture=atlas)


# --------------------------------------------------------------------------------------------
# Textures


@functools.lru_cache(maxsize=None)
def load_picture(name: str) -> np.ndarray:
    """A scikit-image sample picture as HxWx3 uint8 RGB (grey pictures are replicated)."""
    from skimage import data  # imported lazily: only renderers need it

    img = np.asarray(getattr(data, name)())
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def _stable_rng(*keys: str) -> np.random.Generator:
    """A generator that depends on the given strings only (not on PYTHONHASHSEED)."""
    return np.random.default_rng(zlib.crc32("/".join(keys).encode()))


def crop_texture(picture: str, width_m: float, height_m: float, key: str,
                 tint=(255, 255, 255), texels_per_metre: float = TEXELS_PER_METRE) -> np.ndarray:
    """A crop of ``picture`` with the aspect of a ``width_m`` x ``height_m`` face, resized to
    ``texels_per_metre``. ``key`` picks the crop (the same key gives the same crop)."""
    img = load_picture(picture)
    h, w = img.shape[:2]
    aspect = width_m / height_m
    rng = _stable_rng(picture, key)
    # Largest crop of that aspect, then a random fraction of it at a random place.
    cw, ch = (w, w / aspect) if w / aspect <= h else (h * aspect, h)
    frac = rng.uniform(0.45, 0.85)
    cw, ch = cw * frac, ch * frac
    x0 = rng.uniform(0, w - cw)
    y0 = rng.uniform(0, h - ch)
    crop = img[int(y0):int(y0 + ch), int(x0):int(x0 + cw)]
    tw = int(np.clip(round(width_m * texels_per_metre), 16, _MAX_TEXTURE_SIDE))
    th = int(np.clip(round(height_m * texels_per_metre), 16, _MAX_TEXTURE_SIDE))
    interp = cv2.INTER_AREA if crop.shape[1] > tw else cv2.INTER_CUBIC
    tex = cv2.resize(crop, (tw, th), interpolation=interp)
    if tuple(tint) != (255, 255, 255):
        tex = (tex.astype(np.float32) * (np.asarray(tint, np.float32) / 255.0)).astype(np.uint8)
    return tex


def _print_label(tex: np.ndarray, text: str, colour) -> None:
    """Print a brand band with ``text`` across the lower part of a face, in place."""
    h, w = tex.shape[:2]
    band = max(4, int(0.2 * h))
    y0 = h - band - max(2, h // 12)
    tex[y0:y0 + band] = colour
    scale = band / 30.0
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, max(1, int(scale * 2)))
    if tw > 0.9 * w:
        scale *= 0.9 * w / tw
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, max(1, int(scale * 2)))
    org = ((w - tw) // 2, y0 + (band + th) // 2)
    cv2.putText(tex, text, org, cv2.FONT_HERSHEY_DUPLEX, scale, (255, 255, 255),
                max(1, int(scale * 2)), cv2.LINE_AA)


def face_size_m(spec: ObjectSpec, face: str) -> tuple[float, float]:
    """(width, height) in metres of a face's picture (width along the picture's rows)."""
    dx, dy, dz = spec.dimensions_m
    if spec.shape == "cylinder":
        return (np.pi * dx, dz) if face == "side" else (dx, dx)
    return {"+x": (dy, dz), "-x": (dy, dz), "+y": (dx, dz), "-y": (dx, dz),
            "+z": (dx, dy), "-z": (dx, dy)}[face]


def _flat_texture(tint, width_m: float, height_m: float, worn_edge_m: float, tape_m: float = 0.0) -> np.ndarray:
    """The tint all over; with ``worn_edge_m``, darkened towards the face's edges over that
    width (WORN_EDGE_SHADE at the edge), at a texel a millimetre; with ``tape_m``, a band of
    tape that wide along the face's width through its middle (TAPE_SHADE)."""
    if worn_edge_m <= 0 and tape_m <= 0:
        tex = np.empty((16, 16, 3), np.uint8)
        tex[:] = tint
        return tex
    w, h = (int(np.clip(round(1000.0 * m), 16, _MAX_TEXTURE_SIDE)) for m in (width_m, height_m))
    xs = np.minimum(np.arange(w) + 0.5, w - np.arange(w) - 0.5) / w * width_m
    ys = np.minimum(np.arange(h) + 0.5, h - np.arange(h) - 0.5) / h * height_m
    to_edge = np.minimum(xs[None, :], ys[:, None])
    shade = WORN_EDGE_SHADE + (1.0 - WORN_EDGE_SHADE) * np.clip(to_edge / max(worn_edge_m, 1e-9), 0.0, 1.0)
    if tape_m > 0:
        across = np.abs((np.arange(h) + 0.5) / h - 0.5) * height_m
        shade = np.where((across < 0.5 * tape_m)[:, None] & (to_edge > 0), shade * TAPE_SHADE, shade)
    shade = np.minimum(shade, 255.0 / max(max(tint), 1))
    return (shade[:, :, None] * np.asarray(tint, np.float32)[None, None]).astype(np.uint8)


@functools.lru_cache(maxsize=None)
def object_textures(name: str) -> dict[str, np.ndarray]:
    """Face name -> HxWx3 uint8 texture for object or prop ``name`` (cached; treat as read-only)."""
    spec = PROPS[name] if name in PROPS else get_object(name)
    textures = {}
    for face, picture in spec.faces:
        width_m, height_m = face_size_m(spec, face)
        if picture == "flat":       # untextured: the tint all over (and its worn edges)
            tex = _flat_texture(spec.tint, width_m, height_m, spec.worn_edge_m,
                                spec.tape_m if face in ("+z", "-z") else 0.0)
            tex.setflags(write=False)
            textures[face] = tex
            continue
        tex = crop_texture(picture, width_m, height_m, key=f"{name}{face}", tint=spec.tint)
        # Brand band on the faces big enough to carry it (and the cylinder's wrap).
        if spec.label and min(width_m, height_m) >= 0.035 and face in ("side", "+x", "-x", "+y", "-y", "+z"):
            _print_label(tex, spec.label, spec.label_colour)
        tex.setflags(write=False)
        textures[face] = tex
    return textures


# Environment surfaces: (metres covered along rows, along columns, texels per metre).
ENVIRONMENT_SIZE = {"table": (3.2, 3.2, 800.0), "wall": (6.0, 2.8, 512.0), "floor": (6.0, 6.0, 200.0)}


@functools.lru_cache(maxsize=None)
def environment_texture(kind: str) -> np.ndarray:
    """Textures covering the whole table top and the wall behind it (``ENVIRONMENT_SIZE``),
    tiled with mirrored copies so there are no seams. Tiled once here rather than wrapped at
    render time: OpenCV's wrapping border is several times slower than an in-range lookup."""
    if kind == "table":   # a granite/terrazzo worktop
        tile = load_picture("gravel").astype(np.float32)
        tile = 0.55 * tile + 0.45 * 150.0
        tile = (tile * (np.array([200, 175, 150], np.float32) / 255.0)).astype(np.uint8)
    elif kind == "floor":  # a darker grey floor (the room behind the table, background "clutter")
        tile = load_picture("gravel").astype(np.float32)
        tile = (0.7 * tile + 0.3 * 90.0) * (np.array([150, 150, 160], np.float32) / 255.0)
        tile = tile.astype(np.uint8)
    elif kind == "wall":  # painted brick
        tile = load_picture("brick").astype(np.float32)
        tile = (0.6 * tile + 0.4 * 200.0) * (np.array([235, 225, 215], np.float32) / 255.0)
        tile = tile.astype(np.uint8)
    else:
        raise ValueError(kind)
    tile = np.concatenate([tile, tile[:, ::-1]], axis=1)
    tile = np.concatenate([tile, tile[::-1]], axis=0)
    width_m, height_m, per_m = ENVIRONMENT_SIZE[kind]
    w, h = int(round(width_m * per_m)), int(round(height_m * per_m))
    reps = (-(-h // tile.shape[0]), -(-w // tile.shape[1]), 1)
    tex = np.ascontiguousarray(np.tile(tile, reps)[:h, :w])
    tex.setflags(write=False)
    return tex
