"""Triangle meshes: reading and writing PLY, STL and OBJ, and sampling their surface.

Own small readers rather than a library: the three formats' geometry parts are short to read
(vertices, triangles or polygons fanned into triangles), and a mesh library would add a
large dependency for a few dozen lines. What is read: vertex positions and faces; colours,
texture coordinates and normals in the files are ignored (normals come from the faces).

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
    """Read a PLY, STL or OBJ file; ``units`` are those of the file's coordinates (m or mm)."""
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
        reader = {".ply": _read_ply, ".stl": _read_stl, ".obj": _read_obj}[suffix]
        vertices, triangles = reader(data)
    except InputError as exc:
        raise InputError(f"mesh file {path} is broken: {exc}") from None
    except (ValueError, IndexError, struct.error, UnicodeDecodeError) as exc:
        raise InputError(f"mesh file {path} is broken: cannot parse it as {suffix[1:].upper()} "
                         f"({type(exc).__name__}: {exc})") from None
    mesh = TriangleMesh(np.asarray(vertices, np.float64) * UNIT_SCALE[units], np.asarray(triangles, np.int64))
    _check_mesh(mesh, path, units)
    return mesh


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


def _fan(polygons: list[list[int]]) -> np.ndarray:
    """Triangles from polygons (fan from each polygon's first vertex)."""
    tris = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    if any(len(p) < 3 for p in polygons):
        raise InputError("a face has fewer than 3 vertices")
    return np.array(tris, np.int64).reshape(-1, 3)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply(data: bytes):
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list]] = []      # (name, count, [(prop, type, list count type)])
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise InputError("a property before any element in the header")
            if parts[1] == "list":
                elements[-1][2].append((parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]))
            else:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]], None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format '{fmt}'")
    vertices, polygons = None, []
    if fmt == "ascii":
        tokens = data[body_start:].split()
        pos = 0
        for name, count, props in elements:
            rows = []
            for _ in range(count):
                row = {}
                for pname, _, list_type in props:
                    if list_type is None:
                        row[pname] = float(tokens[pos])
                        pos += 1
                    else:
                        n = int(tokens[pos])
                        row[pname] = [int(float(t)) for t in tokens[pos + 1:pos + 1 + n]]
                        if len(row[pname]) != n:
                            raise InputError("the file ends inside a face list")
                        pos += 1 + n
                rows.append(row)
            if name == "vertex":
                vertices = np.array([[r["x"], r["y"], r["z"]] for r in rows], np.float64).reshape(-1, 3)
            elif name == "face":
                key = next((p[0] for p in props if p[2] is not None), None)
                polygons = [r[key] for r in rows] if key else []
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        pos = body_start
        for name, count, props in elements:
            if all(p[2] is None for p in props):
                dtype = np.dtype([(p[0], order + p[1]) for p in props])
                arr = np.frombuffer(data, dtype, count, pos)
                pos += dtype.itemsize * count
                if name == "vertex":
                    vertices = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
                continue
            rows = []
            for _ in range(count):
                row = {}
                for pname, ptype, list_type in props:
                    if list_type is None:
                        dt = np.dtype(order + ptype)
                        row[pname] = np.frombuffer(data, dt, 1, pos)[0]
                        pos += dt.itemsize
                    else:
                        lt = np.dtype(order + list_type)
                        n = int(np.frombuffer(data, lt, 1, pos)[0])
                        pos += lt.itemsize
                        it = np.dtype(order + ptype)
                        row[pname] = np.frombuffer(data, it, n, pos).astype(np.int64).tolist()
                        pos += it.itemsize * n
                rows.append(row)
            if name == "face":
                key = next((p[0] for p in props if p[2] is not None), None)
                polygons = [r[key] for r in rows] if key else []
    if vertices is None:
        raise InputError("no 'vertex' element")
    return vertices, _fan(polygons)


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
    return np.array(verts, np.float64).reshape(-1, 3), _fan(polygons)


# --------------------------------------------------------------------------- writing

def save_mesh(mesh: TriangleMesh, path, units: str = "m") -> Path:
    """Write a mesh as binary PLY, binary STL or ASCII OBJ (by suffix), coordinates in ``units``."""
    path = Path(path)
    v = mesh.vertices / UNIT_SCALE[units]
    f = mesh.triangles
    suffix = path.suffix.lower()
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".ply":
        head = (f"ply\nformat binary_little_endian 1.0\ncomment multi_instance_reg, units {units}\n"
                f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
                f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
        faces = np.zeros(len(f), np.dtype([("n", "u1"), ("i", "<i4", 3)]))
        faces["n"], faces["i"] = 3, f
        path.write_bytes(head + v.astype("<f4").tobytes() + faces.tobytes())
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

def sample_surface(mesh: TriangleMesh, spacing: float, seed: int = 0, max_points: int = 200_000
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Points spread over the surface about ``spacing`` apart, with their face normals:
    (P, 3), (P, 3) float64. Random points in proportion to area, then one per voxel of
    ``spacing`` so that the density is even."""
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
