"""Triangle meshes: reading and writing PLY, STL and OBJ, and sampling their surface.

Own small readers rather than a library: the three formats' geometry parts are short to read
(vertices, triangles or polygons fanned into triangles), and a mesh library would add a
large dependency for a few dozen lines. What is read: vertex positions and faces, and of a
PLY its vertex colours or its texture (per-vertex ``texture_u/v`` or a face ``texcoord``
list, the picture named by ``comment TextureFile``); normals in the files are ignored
(normals come from the faces).

Every problem with a file raises InputError naming the file and what is wrong with it.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

MESH_SUFFIXES = (".ply", ".stl", ".obj")
UNIT_SCALE = {"m": 1.0, "mm": 0.001}
# An object the camera can see whole lies between these sizes (largest box side, metres):
# outside them the units are almost certainly wrong.
MIN_SIZE_M, MAX_SIZE_M = 0.005, 5.0


@dataclass
class TriangleMesh:
    vertices: np.ndarray     # (V, 3) float64, metres
    triangles: np.ndarray    # (F, 3) int64
    # Colour, when the file has it (PLY): per vertex, or a texture picture with texture
    # coordinates per triangle corner (u to the right, v up from the picture's bottom, 0..1).
    vertex_colours: np.ndarray | None = None    # (V, 3) uint8 RGB
    corner_uv: np.ndarray | None = None         # (F, 3, 2) float32
    texture: np.ndarray | None = None           # (H, W, 3) uint8 RGB

    @property
    def has_colour(self) -> bool:
        return self.vertex_colours is not None or (self.texture is not None and self.corner_uv is not None)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        used = self.vertices[np.unique(self.triangles)]
        return used.min(axis=0), used.max(axis=0)

    def face_normals_areas(self) -> tuple[np.ndarray, np.ndarray]:
        a, b, c = (self.vertices[self.triangles[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        norm = np.linalg.norm(cross, axis=1)
        normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
        return normals, 0.5 * norm


# --------------------------------------------------------------------------- reading

def load_mesh(path, units: str = "m") -> TriangleMesh:
    """Read a PLY, STL or OBJ file; ``units`` are those of the file's coordinates (m or mm).
    A PLY's vertex colours and texture (``texture_u/v`` or a face ``texcoord`` list, and a
    ``comment TextureFile`` picture beside it) come with the mesh."""
    path = Path(path)
    if units not in UNIT_SCALE:
        raise InputError(f"--units must be one of {', '.join(UNIT_SCALE)}, got '{units}'")
    if not path.is_file():
        raise InputError(f"mesh file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(f"mesh file {path}: unknown format '{path.suffix}'; give a .ply, .stl or .obj file")
    data = path.read_bytes()
    try:
        if suffix == ".ply":
            mesh = _read_ply(data, path)
        else:
            vertices, triangles = (_read_stl if suffix == ".stl" else _read_obj)(data)
            mesh = TriangleMesh(np.asarray(vertices, np.float64), np.asarray(triangles, np.int64))
    except InputError as exc:
        raise InputError(f"mesh file {path} is broken: {exc}") from None
    except (ValueError, IndexError, struct.error, UnicodeDecodeError) as exc:
        raise InputError(f"mesh file {path} is broken: cannot parse it as {suffix[1:].upper()} "
                         f"({type(exc).__name__}: {exc})") from None
    mesh.vertices = np.asarray(mesh.vertices, np.float64) * UNIT_SCALE[units]
    mesh.triangles = np.asarray(mesh.triangles, np.int64).reshape(-1, 3)
    _check_mesh(mesh, path, units)
    return mesh


# What a model needs of a mesh, said whenever one is refused.
USABLE_MESH = ("a usable mesh is the object's outer surface: at least 4 triangles that enclose a solid, "
               "not all in one plane")
# Thinner than this share of its largest side (and than 1 mm) a mesh is a sheet, not a solid.
FLAT_SHARE = 0.01


def _check_mesh(mesh: TriangleMesh, path, units: str) -> None:
    v, f = mesh.vertices, mesh.triangles
    if len(v) == 0 or len(f) == 0:
        raise InputError(f"mesh file {path} is broken: {len(v)} vertices and {len(f)} faces "
                         f"(a surface needs both)")
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise InputError(f"mesh file {path} is broken: vertex coordinates are not finite x, y, z numbers")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"mesh file {path} is broken: a face refers to vertex {int(f.max() if f.max() >= len(v) else f.min())} "
                         f"but there are {len(v)} vertices")
    _, areas = mesh.face_normals_areas()
    if not np.any(areas > 0):
        raise InputError(f"mesh file {path} is broken: every face has zero area")
    lo, hi = mesh.bounds
    size = float(np.max(hi - lo))
    if not MIN_SIZE_M <= size <= MAX_SIZE_M:
        other = "mm" if units == "m" else "m"
        raise InputError(f"mesh file {path} read in {units} is {size:.4g} m across, outside "
                         f"{MIN_SIZE_M}-{MAX_SIZE_M} m; are its units {other}? (--units {other})")
    solid = int(np.count_nonzero(areas > 0))
    if solid < 4:
        raise InputError(f"mesh file {path} has {solid} triangle(s) with an area: it cannot bound an object; {USABLE_MESH}")
    # Thickness along the used vertices' principal axes (a sheet may lie at any slant).
    used = v[np.unique(f)]
    thickness = float(np.ptp((used - used.mean(axis=0)) @ np.linalg.svd(used - used.mean(axis=0),
                                                                          full_matrices=False)[2][2]))
    if thickness < min(FLAT_SHARE * size, 0.001):
        raise InputError(f"mesh file {path} is flat ({thickness * 1000:.3g} mm thick, {size * 1000:.4g} mm across): "
                         f"it cannot bound an object; {USABLE_MESH}")
    for name, arr, n in (("vertex colours", mesh.vertex_colours, len(v)), ("texture coordinates", mesh.corner_uv, len(f))):
        if arr is not None and len(arr) != n:
            raise InputError(f"mesh file {path} is broken: {len(arr)} {name} for {n} {'vertices' if n == len(v) else 'faces'}")


def _fan(polygons: list[list[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Triangles from polygons (fan from each polygon's first vertex), and for each triangle
    (polygon index, corner k in the polygon) x 3, to carry per-corner data along."""
    if any(len(p) < 3 for p in polygons):
        raise InputError("a face has fewer than 3 vertices")
    tris = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    corners = [(j, 0, i, i + 1) for j, p in enumerate(polygons) for i in range(1, len(p) - 1)]
    return np.array(tris, np.int64).reshape(-1, 3), np.array(corners, np.int64).reshape(-1, 4)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_TYPE_NAMES = "char, uchar, short, ushort, int, uint, float, double (or int8 ... float64)"


def _ply_type(name: str, prop: str, element: str) -> str:
    if name not in _PLY_TYPES:
        raise InputError(f"property '{prop}' of element '{element}' has the unknown type '{name}' "
                         f"(PLY's types: {_PLY_TYPE_NAMES}); convert the file, e.g. re-save it with MeshLab")
    return _PLY_TYPES[name]


def _ply_header(data: bytes):
    """(format, [(element, count, [(property, type, list count type or None)])], comments, body start)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, comments = None, [], []
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] == "obj_info":
            continue
        if parts[0] == "comment":
            comments.append(line.strip()[len("comment"):].strip())
        elif parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else None
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise InputError(f"header line '{line.strip()}' is not 'element NAME COUNT'")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise InputError("a property before any element in the header")
            el = elements[-1][0]
            if len(parts) == 5 and parts[1] == "list":
                elements[-1][2].append((parts[4], _ply_type(parts[3], parts[4], el), _ply_type(parts[2], parts[4], el)))
            elif len(parts) == 3:
                elements[-1][2].append((parts[2], _ply_type(parts[1], parts[2], el), None))
            else:
                raise InputError(f"header line '{line.strip()}' is not 'property TYPE NAME' or "
                                 f"'property list COUNT_TYPE TYPE NAME'")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format '{fmt}'")
    return fmt, elements, comments, body_start


def _ascii_element(tokens: np.ndarray, pos: int, count: int, props) -> tuple[dict, int]:
    """One element's rows from the file's numbers: {property: (count,) array, or for a list
    (count, n) array when every row has n entries, else a list of arrays}, and the new position."""
    # Most files have one list length throughout (triangles): read all rows at once.
    width, at = 0, pos
    lengths = []
    for _, _, list_type in props:
        if list_type is None:
            width, at = width + 1, at + 1
        else:
            n = int(tokens[at]) if at < len(tokens) else 0
            lengths.append((width, n))
            width, at = width + 1 + n, at + 1 + n
    if pos + count * width <= len(tokens):
        block = tokens[pos:pos + count * width].reshape(count, width)
        if all(np.all(block[:, col] == n) for col, n in lengths):
            out, col = {}, 0
            for name, _, list_type in props:
                if list_type is None:
                    out[name], col = block[:, col], col + 1
                else:
                    n = int(block[0, col]) if count else 0
                    out[name], col = block[:, col + 1:col + 1 + n], col + 1 + n
            return out, pos + count * width
    out = {name: [] for name, _, _ in props}
    for _ in range(count):
        for name, _, list_type in props:
            if list_type is None:
                out[name].append(tokens[pos])
                pos += 1
            else:
                n = int(tokens[pos])
                if pos + 1 + n > len(tokens):
                    raise InputError(f"the file ends inside element rows ('{name}' lists)")
                out[name].append(tokens[pos + 1:pos + 1 + n])
                pos += 1 + n
    if pos > len(tokens):
        raise InputError("the file ends before its last element row")
    return {name: (np.array(out[name]) if list_type is None else out[name]) for name, _, list_type in props}, pos


def _binary_element(data: bytes, pos: int, count: int, props, order: str) -> tuple[dict, int]:
    """As ``_ascii_element`` for a binary body."""
    # Fixed layout from the first row's list lengths, checked on every row.
    fields, at = [], pos
    for name, ptype, list_type in props:
        if list_type is None:
            fields.append((name, order + ptype))
            at += np.dtype(ptype).itemsize
        else:
            n = int(np.frombuffer(data, order + list_type, 1, at)[0]) if count else 0
            fields.append((name + "\0n", order + list_type))
            fields.append((name, order + ptype, (n,)))
            at += np.dtype(list_type).itemsize + n * np.dtype(ptype).itemsize
    dtype = np.dtype(fields)
    if pos + count * dtype.itemsize <= len(data):
        arr = np.frombuffer(data, dtype, count, pos)
        if all(np.all(arr[f[0]] == arr[f[0]][0]) for f in fields if f[0].endswith("\0n")):
            return {name: arr[name] for name, _, _ in props}, pos + count * dtype.itemsize
    out = {name: [] for name, _, _ in props}
    for _ in range(count):
        for name, ptype, list_type in props:
            if list_type is None:
                out[name].append(np.frombuffer(data, order + ptype, 1, pos)[0])
                pos += np.dtype(ptype).itemsize
            else:
                n = int(np.frombuffer(data, order + list_type, 1, pos)[0])
                pos += np.dtype(list_type).itemsize
                out[name].append(np.frombuffer(data, order + ptype, n, pos))
                pos += n * np.dtype(ptype).itemsize
    return {name: (np.array(out[name]) if list_type is None else out[name]) for name, _, list_type in props}, pos


# Property names for colours and texture coordinates, as writers spell them.
_COLOUR_NAMES = (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"), ("r", "g", "b"))
_UV_NAMES = (("texture_u", "texture_v"), ("s", "t"), ("u", "v"), ("texture_s", "texture_t"))


def _read_ply(data: bytes, path: Path) -> TriangleMesh:
    fmt, elements, comments, body_start = _ply_header(data)
    tokens = np.array(data[body_start:].split(), np.float64) if fmt == "ascii" else None
    order = "<" if fmt == "binary_little_endian" else ">"
    columns, types, pos = {}, {}, 0 if fmt == "ascii" else body_start
    for name, count, props in elements:
        if fmt == "ascii":
            cols, pos = _ascii_element(tokens, pos, count, props)
        else:
            cols, pos = _binary_element(data, pos, count, props, order)
        columns.setdefault(name, cols)
        types.setdefault(name, {p[0]: p[1] for p in props})
    vert = columns.get("vertex")
    if vert is None:
        raise InputError("no 'vertex' element")
    if not all(k in vert for k in "xyz"):
        raise InputError("the vertex element has no x, y, z properties")
    vertices = np.stack([np.asarray(vert[k], np.float64) for k in "xyz"], axis=1)
    face = columns.get("face", {})
    key = next((k for k in ("vertex_indices", "vertex_index") if k in face), None)
    if key is None:
        key = next((k for k, v in face.items() if isinstance(v, list) or np.ndim(v) == 2), None)
    polys = face.get(key, []) if key else []
    if not isinstance(polys, list) and polys.ndim == 2 and polys.shape[1] == 3:
        triangles = polys.astype(np.int64)
        corners = np.column_stack([np.arange(len(triangles)), np.zeros(len(triangles), np.int64),
                                   np.ones(len(triangles), np.int64), np.full(len(triangles), 2)])
    else:
        triangles, corners = _fan([np.asarray(p).astype(np.int64).tolist() for p in polys])
    mesh = TriangleMesh(vertices, triangles)
    names = next((n for n in _COLOUR_NAMES if all(k in vert for k in n)), None)
    if names is not None:
        rgb = np.stack([np.asarray(vert[k], np.float64) for k in names], axis=1)
        if all(types["vertex"][k].startswith("f") for k in names) and rgb.max(initial=0) <= 1.0:
            rgb = rgb * 255.0       # float colours are 0..1
        mesh.vertex_colours = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    texture_file = next((words[1] for words in (c.split(None, 1) for c in comments)
                         if len(words) == 2 and words[0].lower() == "texturefile"), None)
    uv_names = next((n for n in _UV_NAMES if all(k in vert for k in n)), None)
    in_range = len(triangles) == 0 or (triangles.min() >= 0 and triangles.max() < len(vertices))
    if uv_names is not None and in_range:       # out of range: _check_mesh says so
        uv = np.stack([np.asarray(vert[k], np.float64) for k in uv_names], axis=1)
        mesh.corner_uv = uv[triangles].astype(np.float32)
    elif "texcoord" in face:
        tc = face["texcoord"]
        per_poly = [np.asarray(t, np.float64).reshape(-1, 2) for t in tc] if isinstance(tc, list) else \
            np.asarray(tc, np.float64).reshape(len(tc), -1, 2)
        if any(len(t) != len(p) for t, p in zip(per_poly, polys)):
            raise InputError("a face's texcoord list does not give 2 numbers per corner")
        mesh.corner_uv = _corner_data(per_poly, corners)
    # A texture needs both its coordinates and its picture; either alone says nothing of the
    # colour (writers leave stray TextureFile comments), so the mesh is read without it.
    if mesh.corner_uv is not None and texture_file is not None:
        mesh.texture = _read_texture(path.parent / texture_file)
    else:
        mesh.corner_uv = None
    return mesh


def _corner_data(per_polygon, corners: np.ndarray) -> np.ndarray:
    """(T, 3, 2) float32: per-corner data of the polygons gathered for their fanned triangles."""
    if not isinstance(per_polygon, list):
        return np.asarray(per_polygon)[corners[:, :1], corners[:, 1:]].astype(np.float32)
    return np.array([[per_polygon[j][k] for k in c] for j, *c in corners.tolist()], np.float32).reshape(-1, 3, 2)


def _read_texture(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError(f"its texture picture {path} does not exist (put it beside the mesh, as "
                         f"'comment TextureFile' names it)")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"its texture picture {path} cannot be read as an image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def _read_stl(data: bytes):
    if len(data) >= 84:
        n = struct.unpack_from("<I", data, 80)[0]
        if len(data) == 84 + 50 * n:
            rec = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), n, 84)
            verts = rec["v"].reshape(-1, 3).astype(np.float64)
            return verts, np.arange(3 * n, dtype=np.int64).reshape(-1, 3)
    text = data.decode("ascii")
    if not text.lstrip().startswith("solid"):
        raise InputError("neither a binary STL (size does not match its triangle count) nor an ASCII one")
    verts = [[float(x) for x in line.split()[1:4]] for line in text.splitlines() if line.strip().startswith("vertex")]
    if len(verts) % 3:
        raise InputError(f"{len(verts)} vertices, not a multiple of 3")
    return np.array(verts, np.float64).reshape(-1, 3), np.arange(len(verts), dtype=np.int64).reshape(-1, 3)


def _read_obj(data: bytes):
    verts, polygons = [], []
    for line in data.decode("utf-8").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
            if len(verts[-1]) != 3:
                raise InputError(f"vertex line '{line.strip()}' has fewer than 3 coordinates")
        elif parts[0] == "f":
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            # OBJ counts from 1; negative indices count back from the latest vertex.
            polygons.append([i - 1 if i > 0 else len(verts) + i for i in idx])
    return np.array(verts, np.float64).reshape(-1, 3), _fan(polygons)[0]


# --------------------------------------------------------------------------- writing

def save_mesh(mesh: TriangleMesh, path, units: str = "m") -> Path:
    """Write a mesh as binary PLY, binary STL or ASCII OBJ (by suffix), coordinates in ``units``;
    a PLY keeps the mesh's colour (vertex colours, or a texture: NAME_texture.png beside it)."""
    path = Path(path)
    v = mesh.vertices / UNIT_SCALE[units]
    f = mesh.triangles
    suffix = path.suffix.lower()
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".ply":
        # Colour goes along as readers expect it: vertex colours, or texture coordinates per
        # face corner (MeshLab's texcoord list) and the picture beside the file.
        textured = mesh.texture is not None and mesh.corner_uv is not None
        picture = path.with_name(path.stem + "_texture.png")
        vert_fields = [("xyz", "<f4", 3)] + ([("rgb", "u1", 3)] if mesh.vertex_colours is not None else [])
        face_fields = [("n", "u1"), ("i", "<i4", 3)] + ([("m", "u1"), ("uv", "<f4", 6)] if textured else [])
        head = (f"ply\nformat binary_little_endian 1.0\ncomment multi_instance_reg, units {units}\n"
                + (f"comment TextureFile {picture.name}\n" if textured else "")
                + f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
                + ("property uchar red\nproperty uchar green\nproperty uchar blue\n" if len(vert_fields) > 1 else "")
                + f"element face {len(f)}\nproperty list uchar int vertex_indices\n"
                + ("property list uchar float texcoord\n" if textured else "") + "end_header\n").encode()
        verts = np.zeros(len(v), np.dtype(vert_fields))
        verts["xyz"] = v
        if mesh.vertex_colours is not None:
            verts["rgb"] = mesh.vertex_colours
        faces = np.zeros(len(f), np.dtype(face_fields))
        faces["n"], faces["i"] = 3, f
        if textured:
            import cv2

            faces["m"], faces["uv"] = 6, np.asarray(mesh.corner_uv, np.float32).reshape(-1, 6)
            cv2.imwrite(str(picture), np.ascontiguousarray(mesh.texture[:, :, ::-1]))
        path.write_bytes(head + verts.tobytes() + faces.tobytes())
    elif suffix == ".stl":
        normals, _ = mesh.face_normals_areas()
        rec = np.zeros(len(f), np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]))
        rec["n"], rec["v"] = normals, v[f]
        path.write_bytes(b"multi_instance_reg".ljust(80, b" ") + struct.pack("<I", len(f)) + rec.tobytes())
    elif suffix == ".obj":
        lines = [f"# multi_instance_reg, units {units}"] + [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
        path.write_text("\n".join(lines) + "\n")
    else:
        raise InputError(f"mesh file {path}: unknown format '{path.suffix}'; use .ply, .stl or .obj")
    return path


# --------------------------------------------------------------------------- sampling

def sample_surface(mesh: TriangleMesh, spacing: float, seed: int = 0, max_points: int = 200_000,
                   where: bool = False) -> tuple:
    """Points spread over the surface about ``spacing`` apart, with their face normals:
    (P, 3), (P, 3) float64. Random points in proportion to area, then one per voxel of
    ``spacing`` so that the density is even. With ``where``, also each point's triangle (P,)
    and barycentric weights (P, 3) (to read the mesh's colour there)."""
    normals, areas = mesh.face_normals_areas()
    total = float(areas.sum())
    n = int(min(max_points, max(1000, 4.0 * total / spacing ** 2)))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(areas), size=n, p=areas / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = (mesh.vertices[mesh.triangles[face, k]] for k in range(3))
    pts = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    keys = np.floor(pts / spacing).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    if where:
        bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        return pts[first], normals[face[first]], face[first], bary[first]
    return pts[first], normals[face[first]]


# --------------------------------------------------------------------------- simple solids

def box_mesh(dx: float, dy: float, dz: float) -> TriangleMesh:
    """A box centred at the origin, edges along the axes, faces facing out."""
    return extruded_polygon_mesh(np.array([[-dx / 2, -dy / 2], [dx / 2, -dy / 2], [dx / 2, dy / 2], [-dx / 2, dy / 2]]),
                                 dz, [[0, 1, 2], [0, 2, 3]])


def cylinder_mesh(diameter: float, height: float, segments: int = 64) -> TriangleMesh:
    """A closed cylinder about z, centred at the origin."""
    a = 2 * np.pi * np.arange(segments) / segments
    ring = 0.5 * diameter * np.stack([np.cos(a), np.sin(a)], axis=1)
    cap = [[0, i, i + 1] for i in range(1, segments - 1)]
    return extruded_polygon_mesh(ring, height, cap)


def polygon_triangles(outline: np.ndarray) -> np.ndarray:
    """(n - 2, 3) counter-clockwise triangles covering a simple counter-clockwise polygon
    (ear clipping: a fan from one vertex covers only polygons star-shaped about it, not a U
    or a T profile)."""
    pts = np.asarray(outline, np.float64)
    left = list(range(len(pts)))
    tris = []

    def cross(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    while len(left) > 3:
        for k in range(len(left)):
            i, j, m = left[k - 1], left[k], left[(k + 1) % len(left)]
            a, b, c = pts[i], pts[j], pts[m]
            if cross(a, b, c) <= 1e-15:                     # reflex or straight: no ear
                continue
            # An ear holds no other vertex (on its edges counts: a collinear vertex would
            # leave a sliver crossing the outline).
            if any(cross(a, b, pts[q]) >= 0 and cross(b, c, pts[q]) >= 0 and cross(c, a, pts[q]) >= 0
                   for q in left if q not in (i, j, m)):
                continue
            tris.append((i, j, m))
            del left[k]
            break
        else:
            raise InputError("the outline is not a simple counter-clockwise polygon")
    tris.append(tuple(left))
    return np.array(tris, np.int64)


def extruded_polygon_mesh(outline: np.ndarray, height: float, cap_triangles) -> TriangleMesh:
    """A prism: the counter-clockwise 2D ``outline`` (n, 2) in the xy plane extruded over
    z in [-height/2, height/2]; ``cap_triangles`` index the outline (counter-clockwise)."""
    n = len(outline)
    lo = np.column_stack([outline, np.full(n, -height / 2)])
    hi = np.column_stack([outline, np.full(n, height / 2)])
    verts = np.concatenate([lo, hi])
    caps = np.asarray(cap_triangles, np.int64)
    tris = [caps[:, ::-1], caps + n]                            # bottom faces down, top faces up
    for i in range(n):
        j = (i + 1) % n
        tris.append(np.array([[i, j, n + j], [i, n + j, n + i]]))
    return TriangleMesh(verts, np.concatenate(tris).astype(np.int64))


__all__ = ["TriangleMesh", "load_mesh", "save_mesh", "sample_surface", "box_mesh", "cylinder_mesh",
           "extruded_polygon_mesh", "polygon_triangles", "MESH_SUFFIXES", "UNIT_SCALE"]
