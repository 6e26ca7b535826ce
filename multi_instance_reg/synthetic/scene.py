"""Synthetic D455 tabletop scenes with ground truth: placement, camera paths, bags.

Python API (what tests, the demo and the tools call):

- ``make_tabletop_scene(object_name="snack_box", instances=6, distractors=3, frames=60,
  seed=0, resolution="640x480", motion="sweep", occluder=False) -> SyntheticScene``: K
  identical instances of a catalogue object (:mod:`.objects`) and D distractors on a textured
  table in front of a wall, seen by a hand-held camera sweeping at 30 Hz, 0.4-1.5 m away.
  Objects rest on the table with random yaw; some touch, some are stacked or lean on another,
  some are occluded or leave the view. For tracking, ``motion="static"`` holds the camera
  still, ``motion="pan"`` pans it slowly along objects spread in a strip (instances enter and
  leave the view), and ``occluder=True`` passes an arm in front (``occluder_path``).
  As recorded bags are (tracker benchmark, issue 35): ``motion="shaky_pan"`` a hand-held
  30 deg arc in 5 s with shake new in every frame (``ShakyPanPlan``), ``motion="jumps"`` an
  arm moving in bursts of 3-8 deg per 1/30 s (``jumps_trajectory``); ``frame_rate`` (Hz,
  default 30: the paths are functions of time, so each frame moves further at a lower
  rate), ``drop`` (share of frames left out in runs of 1-3: gaps in the stamps) and ``loop``
  (the frames twice, the stamps jumping back once; ``frame_timeline``). As real cells look:
  ``layout="flush"`` boxes packed face to face (the ``flush`` arrangement), ``layout="bin"``
  everything dropped into a bin at random orientations (``bin_fixtures``, the ``pile``
  arrangement), ``motion="overhead"`` a camera above them, ``background="clutter"`` a room
  2-3 m behind the table (``clutter_primitives``), ``sensor="realistic"`` (and
  ``randomise=True``) the depth of :mod:`.sensor`'s realistic profile.
  ``object_name`` may also be a list of names (a mixed scene): K instances of each, labelled
  object after object (the first object's K, then the next's); ``SyntheticScene.instance_objects``
  names each instance's object, and /ground_truth/object carries it as ``instance_objects``.
- ``make_capture_scene(object_name, seed=0, views=10, resolution="640x480")``: the object
  alone on the table seen from ``views`` viewpoints around it (elevation 30-60 deg,
  0.4-0.6 m), the way a user scans it to build the stored model; half way the object is
  turned over, so every face is seen (the ground-truth pose follows it).
- ``SyntheticScene.render_frame(i) -> RenderedFrame`` / ``SyntheticScene.frames()``: per frame
  ``rgb`` (H, W, 3) uint8, ``depth_mm`` (H, W) uint16 (0 = invalid), ``depth_true_m`` (H, W)
  float32 noise-free (0 = nothing), ``K`` (3, 3), ``poses`` (K, 4, 4) object -> colour optical
  frame (metres), ``instance_mask`` (H, W) int16 (k = instance k, -1 table/wall, -2
  distractor), ``visibility`` (K,) visible fraction of each instance's silhouette, ``stamp_ns``.
- ``generate_scene_bag(out_path, object_name=..., instances=..., distractors=..., frames=...,
  seed=..., storage="sqlite3", resolution="640x480", preview_dir=None, motion="sweep",
  occluder=False, frame_rate=30.0, drop=0.0, loop=False, sensor="d455", randomise=False,
  layout="table", background="wall") -> BagSummary`` and
  ``generate_capture_bag(out_path, object_name, seed=0, views=10, ...)``: the same written as a
  rosbag2 with realsense-ros topics plus /ground_truth/{poses,object,visibility}
  (:mod:`multi_instance_reg.datasets.bag_writer`).

World frame: z up, table top at z = 0, objects around the origin, the wall at +y behind them.
Everything is a function of the seed: the same seed gives the same bag content.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..messages import CameraIntrinsics
from ..transforms import invert_transform, make_transform
from .objects import (BOX_FACES, DEFAULT_OBJECT, ENVIRONMENT_SIZE, FURNITURE, OBJECTS, PROPS, ObjectSpec,
                      environment_texture, get_object, object_textures)
from .preview import box_corners
from .render import AMBIENT, DIFFUSE, LIGHT_DIR_WORLD, CylinderSide, Quad, Renderer, Texture
from .sensor import (SENSOR_PROFILES, SensorProfile, UnalignedDepth, d455_intrinsics, sensor_profile, simulate_colour,
                     simulate_depth, unaligned_depth_sensor)

FRAME_RATE_HZ = 30.0
START_STAMP_NS = 1_700_000_000 * 1_000_000_000
MAX_INSTANCES = 20
MAX_DISTRACTORS = 20
LABEL_DISTRACTOR = -2
_DISTRACTOR_LABEL0 = 1000        # internal render labels of distractors (and of the occluder)
TABLE_HALF_X = 1.6
TABLE_FRONT_Y = -2.4
MIN_CAMERA_CLEARANCE_M = 0.32    # camera to any object surface (the depth minimum is 0.3 m)
MOTIONS = ("sweep", "static", "pan", "shaky_pan", "jumps", "overhead")
LAYOUTS = ("table", "flush", "bin")
BACKGROUNDS = ("wall", "clutter")
MIN_FRAME_RATE_HZ, MAX_FRAME_RATE_HZ = 1.0, 90.0
MAX_DROP = 0.5                   # share of the frames that ``drop`` may leave out
# The accelerometer (sensor_msgs/Imu on realsense-ros' accel/sample topic): a D455 samples it
# at 100 or 200 Hz (63 / 250 on units made before mid 2022). 200 Hz: 6-7 messages of ~330
# bytes per frame, nothing beside a frame's 1.5 MB of images.
ACCEL_RATE_HZ = 200.0
GRAVITY_M_S2 = 9.80665
# White noise per axis per sample (BMI085 datasheet: 160 ug/sqrt(Hz), 0.014 m/s^2 at 200 Hz;
# measured D4xx streams show a few hundredths) and a constant bias per axis per recording
# (zero-g offset +-20 mg typical after calibration; uncalibrated units read up to 0.5 m/s^2 off).
ACCEL_NOISE_M_S2 = 0.03
ACCEL_BIAS_M_S2 = 0.15


# ----------------------------------------------------------------------------------------------
# Geometry helpers


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# Rotation that turns the named object axis to world up (+z).
_UP_AXIS_ROTATION = {
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "+x": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "+y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "-y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


@dataclass
class Placement:
    """One object on the table: ``pose`` maps the object frame to the world frame."""
    spec: ObjectSpec
    pose: np.ndarray
    label: int                      # 0..K-1 for instances, >= 1000 for distractors, -1 fixtures (a bin)
    arrangement: str = "free"       # free | touching | stacked | leaning | flush | pile | fixture

    @property
    def is_instance(self) -> bool:
        return 0 <= self.label < _DISTRACTOR_LABEL0

    @property
    def is_distractor(self) -> bool:
        return self.label >= _DISTRACTOR_LABEL0


def _obb_overlap(pa: np.ndarray, ha: np.ndarray, pb: np.ndarray, hb: np.ndarray, margin: float = 5e-4) -> bool:
    """Do two oriented boxes (pose, half extents) overlap? Separating-axis test, 15 axes."""
    Ra, Rb = pa[:3, :3], pb[:3, :3]
    d = pb[:3, 3] - pa[:3, 3]
    ha = ha + margin
    hb = hb + margin
    axes = [Ra[:, i] for i in range(3)] + [Rb[:, i] for i in range(3)]
    for i in range(3):
        for j in range(3):
            c = np.cross(Ra[:, i], Rb[:, j])
            n = np.linalg.norm(c)
            if n > 1e-9:
                axes.append(c / n)
    for ax in axes:
        ra = np.sum(ha * np.abs(Ra.T @ ax))
        rb = np.sum(hb * np.abs(Rb.T @ ax))
        if abs(d @ ax) > ra + rb:
            return False
    return True


def _lowest_z(pose: np.ndarray, half: np.ndarray) -> float:
    return float(pose[2, 3] - np.sum(np.abs(pose[2, :3]) * half))


def _top_z(pose: np.ndarray, half: np.ndarray) -> float:
    return float(pose[2, 3] + np.sum(np.abs(pose[2, :3]) * half))


def _resting_rotation(spec: ObjectSpec, up: str, yaw: float, rng) -> np.ndarray:
    R = _rot_z(yaw) @ _UP_AXIS_ROTATION[up]
    if spec.shape == "cylinder":        # a can spins freely about its own axis
        R = R @ _rot_z(rng.uniform(0, 2 * np.pi))
    return R


def _choose_up(spec: ObjectSpec, rng) -> str:
    ups = [u for u, _ in spec.resting]
    w = np.array([wt for _, wt in spec.resting], dtype=np.float64)
    return ups[int(rng.choice(len(ups), p=w / w.sum()))]


# ----------------------------------------------------------------------------------------------
# Placement


class _Table:
    """Objects placed so far, with collision checks against all of them."""

    def __init__(self):
        self.placed: list[Placement] = []

    def collides(self, pose, half, margin: float = 5e-4) -> bool:
        return any(_obb_overlap(pose, half, p.pose, p.spec.half_extents, margin) for p in self.placed)

    def slide_to_contact(self, pose, half, target: np.ndarray, direction: np.ndarray, other: Placement):
        """Move ``pose`` along -``direction`` from far away towards ``target`` until it just
        touches ``other`` (bisection); None if it never gets free."""
        far = np.linalg.norm(half) + np.linalg.norm(other.spec.half_extents) + 0.05
        def at(dist):
            p = pose.copy()
            p[:2, 3] = target[:2] - direction[:2] * dist
            return p
        if _obb_overlap(at(far), half, other.pose, other.spec.half_extents):
            return None
        lo, hi = 0.0, far           # overlap at lo (probably), free at hi
        if not _obb_overlap(at(lo), half, other.pose, other.spec.half_extents):
            return at(lo)
        for _ in range(22):
            mid = 0.5 * (lo + hi)
            if _obb_overlap(at(mid), half, other.pose, other.spec.half_extents):
                lo = mid
            else:
                hi = mid
        return at(hi + 1e-3)


def footprint_area(specs) -> float:
    """Summed footprints (m^2) of objects, each as its x size times its larger other size."""
    return sum(s.dimensions_m[0] * max(s.dimensions_m[1], s.dimensions_m[2]) for s in specs)


ARRANGEMENTS = ("free", "touching", "stacked", "leaning", "flush", "pile")


def place_objects(target: ObjectSpec, instances: int, distractor_specs: list[ObjectSpec], rng,
                  arrangement_probs=(0.62, 0.2, 0.09, 0.09), region_half=None,
                  more_targets: tuple[ObjectSpec, ...] = (), fixtures: tuple[Placement, ...] = ()) -> list[Placement]:
    """Place ``instances`` copies of ``target`` (and of each of ``more_targets``, labelled
    after them) and the distractors on the table.

    Each object is placed free (anywhere in the region), touching a neighbour, stacked on a
    flat top, leaning against a taller object, flush against a copy of itself (same
    orientation, face to face with a hairline gap: boxes packed on a pallet) or dropped onto a
    pile at a random orientation (in a bin), with probabilities ``arrangement_probs`` in
    the order of ``ARRANGEMENTS`` (fewer probabilities: the later kinds not drawn); if its
    arrangement fails it is placed free. No two objects interpenetrate. The region is
    centred on the origin, 4:3 and about 2.4 times the summed footprints, unless
    ``region_half`` gives its (x, y) half sizes (e.g. a strip along a camera pan, a bin's
    inside). ``fixtures`` (e.g. a bin's walls and floor) are there before the first object
    and are returned with the objects.
    """
    items = [(spec, k) for k, spec in enumerate(s for s in (target,) + tuple(more_targets) for _ in range(instances))] + \
            [(spec, _DISTRACTOR_LABEL0 + j) for j, spec in enumerate(distractor_specs)]
    order = rng.permutation(len(items))
    # Region: about 2.4 times the summed footprints, 4:3.
    area = max(0.1, 2.4 * footprint_area([s for s, _ in items]))
    half = np.array([np.sqrt(area * 4 / 3) / 2, np.sqrt(area * 3 / 4) / 2])
    if region_half is not None:
        half = np.asarray(region_half, dtype=np.float64)
    table = _Table()
    table.placed.extend(fixtures)
    for idx in order:
        spec, label = items[idx]
        placement = None
        up = _choose_up(spec, rng)      # once: retrying must not favour small footprints
        arrangement = ARRANGEMENTS[int(rng.choice(len(arrangement_probs), p=arrangement_probs))]
        if arrangement != "free" and table.placed:
            placement = _try_arrangement(arrangement, spec, up, label, table, half, rng)
        grow = 1.0
        while placement is None:
            for _ in range(100):
                placement = _place_free(spec, up, label, table, half * grow, rng)
                if placement is not None:
                    break
            grow *= 1.15
        table.placed.append(placement)
    table.placed.sort(key=lambda p: p.label)
    return table.placed


def _place_free(spec, up, label, table, half, rng) -> Placement | None:
    R = _resting_rotation(spec, up, rng.uniform(0, 2 * np.pi), rng)
    pose = make_transform(R, [rng.uniform(-half[0], half[0]), rng.uniform(-half[1], half[1]), 0.0])
    pose[2, 3] -= _lowest_z(pose, spec.half_extents)
    if table.collides(pose, spec.half_extents):
        return None
    return Placement(spec, pose, label, "free")


FLUSH_GAP_M = 5e-4              # at most, between boxes packed flush (a hairline step in depth: none)
PILE_STEP_M = 0.01              # how far a dropped object falls between collision checks
PILE_SPOTS = 8                  # spots tried for each object dropped onto a pile


def _drop(pose: np.ndarray, half: np.ndarray, reach_z: float, placed: list[Placement]) -> np.ndarray:
    """``pose`` moved down from above everything near it until it touches something or its
    lowest point reaches the table (to within 0.1 mm); ``reach_z`` is its lowest point's depth
    below its centre. Only objects whose upright bounding boxes meet its own are tested."""
    reach = np.abs(pose[:3, :3]) @ half
    near = []
    for p in placed:
        other = np.abs(p.pose[:3, :3]) @ p.spec.half_extents
        if np.all(np.abs(p.pose[:2, 3] - pose[:2, 3]) <= reach[:2] + other[:2] + 1e-3):
            near.append((p, p.pose[2, 3] - other[2], p.pose[2, 3] + other[2]))
    pose = pose.copy()
    pose[2, 3] = max([top for _, _, top in near], default=0.0) + reach_z + 1e-3

    def hits(z):
        trial = pose.copy()
        trial[2, 3] = z
        # No margin: a margin would hold it up by margin / cos(slope) on a steep face.
        return any(_obb_overlap(trial, half, p.pose, p.spec.half_extents, 0.0) for p, bottom, top in near
                   if z - reach_z <= top + 1e-3 and z + reach_z >= bottom - 1e-3)
    free = pose[2, 3]
    while free - PILE_STEP_M > reach_z and not hits(free - PILE_STEP_M):
        free -= PILE_STEP_M
    low = max(free - PILE_STEP_M, reach_z)
    if not hits(low):
        free = low                      # reached the table
    else:
        for _ in range(7):              # between touching (low) and free
            mid = 0.5 * (low + free)
            if hits(mid):
                low = mid
            else:
                free = mid
    pose[2, 3] = free
    return pose


def _try_arrangement(kind, spec, up, label, table, half, rng) -> Placement | None:
    margin = 5e-4
    for _ in range(25):
        other = table.placed[int(rng.integers(len(table.placed)))]
        if kind == "flush":
            # Against a copy of itself, turned the same way, face to face along one of the
            # copy's horizontal axes, with a gap of at most FLUSH_GAP_M: tops in one plane.
            if other.spec != spec or spec.shape != "box" or other.arrangement == "fixture":
                continue
            horiz = [i for i in range(3) if abs(other.pose[2, i]) < 0.5]
            axis = horiz[int(rng.integers(len(horiz)))]
            sign = float(rng.choice([-1.0, 1.0]))
            pose = other.pose.copy()
            pose[:3, 3] += sign * other.pose[:3, axis] * (2 * spec.half_extents[axis] + rng.uniform(1e-4, FLUSH_GAP_M))
            margin = 0.0
        elif kind == "pile":
            # Dropped at a random orientation into the region (a bin's inside): of PILE_SPOTS
            # random spots, where it comes to rest lowest, falling straight down from above
            # everything until it touches something (it is not turned by what it meets).
            R = Rotation.random(random_state=rng).as_matrix()
            reach = np.abs(R) @ spec.half_extents                # half sizes of its upright bounding box
            room = np.maximum(half - reach[:2], 0.0)
            best = None
            for _spot in range(PILE_SPOTS):
                pose = make_transform(R, [rng.uniform(-room[0], room[0]), rng.uniform(-room[1], room[1]), 0.0])
                rest = _drop(pose, spec.half_extents, float(reach[2]), table.placed)
                if best is None or rest[2, 3] < best[2, 3]:
                    best = rest
            return Placement(spec, best, label, kind)
        elif kind == "touching":
            pose = make_transform(_resting_rotation(spec, up, rng.uniform(0, 2 * np.pi), rng), [0, 0, 0])
            pose[2, 3] -= _lowest_z(pose, spec.half_extents)
            a = rng.uniform(0, 2 * np.pi)
            direction = np.array([np.cos(a), np.sin(a), 0.0])
            pose = table.slide_to_contact(pose, spec.half_extents, other.pose[:3, 3], direction, other)
        elif kind == "stacked":
            # On a flat top (a box, or a can standing up), lying on its largest face, its
            # centre over the support so it would stay there.
            if other.spec.shape == "cylinder" and abs(other.pose[2, 2]) < 0.99:
                continue
            if other.arrangement == "leaning":
                continue
            top_half = other.spec.half_extents
            flat = max(spec.resting, key=lambda r: r[1])[0]
            pose = make_transform(_resting_rotation(spec, flat, rng.uniform(0, 2 * np.pi), rng), [0, 0, 0])
            # Offset within the support's top face (in the support's frame, horizontal axes).
            horiz = [i for i in range(3) if abs(other.pose[2, i]) < 0.5]
            local = np.zeros(3)
            for i in horiz:
                local[i] = rng.uniform(-0.4, 0.4) * top_half[i]
            centre = other.pose[:3, :3] @ local + other.pose[:3, 3]
            pose[:2, 3] = centre[:2]
            pose[2, 3] = _top_z(other.pose, top_half) - _lowest_z(pose, spec.half_extents) + 1e-3
        else:  # leaning: a box standing on its end, tilted until it rests on a taller object
            if spec.shape != "box" or other.arrangement == "leaning":
                continue
            tall = ["+x", "+y", "+z"][int(np.argmax(spec.dimensions_m))]
            other_height = _top_z(other.pose, other.spec.half_extents)
            if other_height < 0.3 * max(spec.dimensions_m):
                continue
            a = rng.uniform(0, 2 * np.pi)
            direction = np.array([np.cos(a), np.sin(a), 0.0])    # from the leaner to the support
            tilt = np.radians(rng.uniform(12, 28))
            # _rot_x(-tilt) moves the top towards +y; yaw turns +y onto ``direction``.
            R = _rot_z(a - np.pi / 2) @ _rot_x(-tilt) @ _UP_AXIS_ROTATION[tall]
            pose = make_transform(R, [0, 0, 0])
            pose[2, 3] -= _lowest_z(pose, spec.half_extents)
            pose = table.slide_to_contact(pose, spec.half_extents, other.pose[:3, 3], direction, other)
        if pose is None:
            continue
        if np.any(np.abs(pose[:2, 3]) > 1.6 * half):
            continue
        if table.collides(pose, spec.half_extents, margin):
            continue
        return Placement(spec, pose, label, kind)
    return None


BIN_PANEL_M = 0.012             # wall and floor thickness of a bin
BIN_HEIGHT_M = (0.12, 0.2)      # inside height, drawn per seed
BIN_FILL = (1.5, 2.5)           # inside floor area / the objects' summed footprints, drawn per seed
                                # (1.5: a heap two or three deep; 2.5: mostly one layer)


def bin_fixtures(specs: list[ObjectSpec], rng) -> tuple[list[Placement], np.ndarray]:
    """An open bin around the origin for ``specs`` to be piled in: its floor and four walls
    (``PROPS["bin_panel"]``, fixtures labelled -1 like the table), the inside BIN_FILL times
    the objects' footprints (4:3) and BIN_HEIGHT_M high. Returns (panels, inside half sizes)."""
    area = max(0.03, rng.uniform(*BIN_FILL) * footprint_area(specs))
    inside = np.array([np.sqrt(area * 4 / 3), np.sqrt(area * 3 / 4)])
    height = rng.uniform(*BIN_HEIGHT_M)
    t = BIN_PANEL_M
    panel = PROPS["bin_panel"]
    ox, oy = inside / 2 + t / 2                    # wall centres
    boxes = [((0.0, 0.0, t / 2), (inside[0] + 2 * t, inside[1] + 2 * t, t)),
             ((ox, 0.0, t + height / 2), (t, inside[1] + 2 * t, height)),
             ((-ox, 0.0, t + height / 2), (t, inside[1] + 2 * t, height)),
             ((0.0, oy, t + height / 2), (inside[0], t, height)),
             ((0.0, -oy, t + height / 2), (inside[0], t, height))]
    panels = [Placement(replace(panel, dimensions_m=tuple(float(v) for v in dims)), make_transform(np.eye(3), centre),
                        -1, "fixture") for centre, dims in boxes]
    return panels, inside / 2


# ----------------------------------------------------------------------------------------------
# Camera paths


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera -> world pose of an optical frame (z forward, x right, y down) at ``eye``
    looking at ``target`` with world z up, rolled by ``roll`` radians about its axis."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    c, s = np.cos(roll), np.sin(roll)
    R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return make_transform(R, eye)


def _spherical(centre, r, az, el):
    return centre + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _clearance(eye: np.ndarray, placements: list[Placement]) -> float:
    return min((np.linalg.norm(eye - p.pose[:3, 3]) - np.linalg.norm(p.spec.half_extents)
                for p in placements), default=np.inf)


def _view_centre_and_distance(placements: list[Placement], rng) -> tuple[np.ndarray, float]:
    """Where a hand-held camera looks (the objects' centre, 3 cm up) and from how far: 0.6-0.75
    m, backing off for crowded tables so that most of them fits in the view (up to 1.2 m)."""
    centres = np.array([p.pose[:3, 3] for p in placements])
    centre = np.array([centres[:, 0].mean(), centres[:, 1].mean(), 0.03])
    spread = np.percentile(np.linalg.norm(centres[:, :2] - centre[:2], axis=1), 80)
    return centre, min(max(rng.uniform(0.6, 0.75), 0.9 * spread), 1.2)


def sweep_trajectory(placements: list[Placement], frames: int, rng, rate_hz: float = FRAME_RATE_HZ) -> list[np.ndarray]:
    """A smooth hand-held sweep over the table from the front: camera -> world poses at
    ``rate_hz`` (a function of time: at a lower rate each frame moves more).

    Distance to the looked-at point 0.5-0.9 m (up to ~1.35 m for crowded tables), elevation
    ~40-70 deg, azimuth swinging +-12-22 deg, plus a few millimetres of hand shake. Most
    instances end up 0.5-1.0 m from the camera.
    """
    centre, r0 = _view_centre_and_distance(placements, rng)
    el0 = np.radians(rng.uniform(45, 62))
    az0 = np.radians(-90 + rng.uniform(-20, 20))
    amp_az = np.radians(rng.uniform(12, 22))
    amp_el = np.radians(rng.uniform(4, 8))
    amp_r = rng.uniform(0.06, 0.13)
    period = rng.uniform(5.0, 8.0, size=3)
    phase = rng.uniform(0, 2 * np.pi, size=8)
    shake_f = rng.uniform(0.8, 2.5, size=(3, 3))
    shake_p = rng.uniform(0, 2 * np.pi, size=(3, 3))
    drift = rng.uniform(0.03, 0.07)
    for _attempt in range(20):
        poses = []
        for i in range(frames):
            tsec = i / rate_hz
            w = 2 * np.pi * tsec
            r = r0 + amp_r * np.sin(w / period[0] + phase[0])
            az = az0 + amp_az * np.sin(w / period[1] + phase[1])
            el = el0 + amp_el * np.sin(w / period[2] + phase[2])
            target = centre + drift * np.array([np.sin(w / 7.0 + phase[3]), np.sin(w / 9.0 + phase[4]), 0.0])
            shake = 0.0025 * np.sin(w * shake_f + shake_p).sum(axis=1)
            eye = _spherical(target, r, az, el) + shake
            roll = np.radians(2.0) * np.sin(w / 3.0 + phase[5])
            poses.append(look_at(eye, target, roll))
        if min(_clearance(P[:3, 3], placements) for P in poses) >= MIN_CAMERA_CLEARANCE_M:
            return poses
        r0 += 0.05          # too close to a tall object somewhere: back off
    return poses


def overhead_trajectory(placements: list[Placement], frames: int, rng, rate_hz: float = FRAME_RATE_HZ,
                        distance=(1.3, 1.8)) -> list[np.ndarray]:
    """Camera -> world poses from above (a pallet, boxes packed flush, a bin): ``distance``
    metres (drawn per seed; the ends of a slow wobble of +-8 cm) from the top of the load,
    tilted 5-30 deg off vertical, drifting a few centimetres and turning slowly over time."""
    load = [p for p in placements if p.spec.name != "pallet"] or placements
    tops = np.array([p.pose[2, 3] + p.spec.dimensions_m[2] / 2 for p in load])
    centre = np.array([np.mean([p.pose[0, 3] for p in placements]), np.mean([p.pose[1, 3] for p in placements]),
                       float(tops.max())])
    r0 = rng.uniform(*distance)
    el0 = np.radians(90 - rng.uniform(5, 30))
    az0 = rng.uniform(0, 2 * np.pi)
    phase = rng.uniform(0, 2 * np.pi, size=4)
    poses = []
    for i in range(frames):
        w = 2 * np.pi * i / rate_hz
        r = r0 + 0.08 * np.sin(w / 6.0 + phase[0])
        az = az0 + np.radians(10) * np.sin(w / 8.0 + phase[1])
        el = el0 + np.radians(3) * np.sin(w / 5.0 + phase[2])
        target = centre + 0.04 * np.array([np.sin(w / 7.0 + phase[3]), np.cos(w / 9.0 + phase[3]), 0.0])
        poses.append(look_at(_spherical(target, r, az, el), target, np.radians(2.0) * np.sin(w / 3.0)))
    return poses


def static_viewpoint(placements: list[Placement], frames: int, rng) -> list[np.ndarray]:
    """A camera that does not move (on a tripod): one pose, chosen like the middle of a sweep
    (``sweep_trajectory``), repeated for every frame."""
    centre, r = _view_centre_and_distance(placements, rng)
    el = np.radians(rng.uniform(45, 62))
    az = np.radians(-90 + rng.uniform(-20, 20))
    for _attempt in range(20):
        pose = look_at(_spherical(centre, r, az, el), centre)
        if _clearance(pose[:3, 3], placements) >= MIN_CAMERA_CLEARANCE_M:
            break
        r += 0.05           # too close to a tall object: back off
    return [pose.copy() for _ in range(frames)]


PAN_SECONDS = 5.0           # one pass of a pan along the table; longer sequences pan back


@dataclass
class PanPlan:
    """A slow hand-held pan along the table (world x), drawn before the objects are placed
    because the objects are spread to suit it (``region_half``)."""
    distance: float         # camera to looked-at point (m)
    elevation: float        # rad
    azimuth: float          # rad, about -90 deg: from the front of the table
    travel: float           # how far the looked-at point moves along x in one pass (m)
    direction: float        # +1 left to right, -1 right to left
    shake_f: np.ndarray     # (3, 3) Hz, hand shake
    shake_p: np.ndarray     # (3, 3) rad
    phase: np.ndarray       # (3,) rad, slow wobble of distance, elevation and roll

    @classmethod
    def draw(cls, rng) -> "PanPlan":
        return cls(distance=rng.uniform(0.55, 0.7), elevation=np.radians(rng.uniform(45, 58)),
                   azimuth=np.radians(-90 + rng.uniform(-10, 10)), travel=rng.uniform(0.45, 0.7),
                   direction=float(rng.choice([-1.0, 1.0])), shake_f=rng.uniform(0.8, 2.5, size=(3, 3)),
                   shake_p=rng.uniform(0, 2 * np.pi, size=(3, 3)), phase=rng.uniform(0, 2 * np.pi, size=3))

    def region_half(self, intrinsics: CameraIntrinsics, footprint_area: float) -> tuple[float, float]:
        """Half sizes (x, y) of the strip to place the objects in: as wide as the view at the
        looked-at point plus the travel, so that objects at either end are out of view at the
        start or at the end of a pass (they enter and leave); as deep as the objects need at
        the usual density (2.4 times their footprints), at least 0.36 m."""
        view_width = self.distance * intrinsics.width / float(intrinsics.K[0, 0])
        hx = 0.5 * (view_width + self.travel)
        return hx, max(0.18, 2.4 * footprint_area / (4 * hx))

    def trajectory(self, placements: list[Placement], frames: int, rate_hz: float = FRAME_RATE_HZ) -> list[np.ndarray]:
        """Camera -> world poses at ``rate_hz``. The looked-at point eases along x from one end of
        the travel to the other in ``PAN_SECONDS`` (then back), with the distance and the
        elevation wobbling by a few percent and a few millimetres of hand shake."""
        centres = np.array([p.pose[:3, 3] for p in placements])
        mid = np.array([0.5 * (centres[:, 0].min() + centres[:, 0].max()), centres[:, 1].mean(), 0.03])
        distance = self.distance
        for _attempt in range(20):
            poses = []
            for i in range(frames):
                tsec = i / rate_hz
                w = 2 * np.pi * tsec
                along = 0.5 * (1 - np.cos(np.pi * tsec / PAN_SECONDS)) - 0.5      # -0.5 .. 0.5
                target = mid + np.array([self.direction * self.travel * along, 0.0, 0.0])
                r = distance * (1 + 0.03 * np.sin(w / 4.0 + self.phase[0]))
                el = self.elevation + np.radians(2.0) * np.sin(w / 5.0 + self.phase[1])
                shake = 0.0025 * np.sin(w * self.shake_f + self.shake_p).sum(axis=1)
                roll = np.radians(1.5) * np.sin(w / 3.0 + self.phase[2])
                poses.append(look_at(_spherical(target, r, self.azimuth, el) + shake, target, roll))
            if min(_clearance(P[:3, 3], placements) for P in poses) >= MIN_CAMERA_CLEARANCE_M:
                return poses
            distance += 0.05        # too close to a tall object somewhere: back off
        return poses


# Hand-held shaky pan and arm jumps: the camera paths of the tracker benchmark (issue 35). Both
# are functions of time, so at 5-15 Hz each frame moves more than at 30 Hz; their random draws
# come from the motion stream only (the objects lie where the sweep of the same seed puts them).
SHAKY_ARC_DEG = 30.0            # the pan's arc about the objects' centre, in PAN_SECONDS
SHAKE_STEP_M = (0.0025, 0.0035)     # mean frame-to-frame shake translation, drawn per seed
SHAKE_STEP_DEG = (0.3, 0.5)         # mean frame-to-frame shake rotation, drawn per seed
# A 3-D offset that is white per frame with sigma s per axis changes between two frames by
# s * sqrt(2) per axis, i.e. by s * sqrt(2) * sqrt(8 / pi) = 2.257 s on average in length.
_WHITE_STEP_PER_SIGMA = float(np.sqrt(2.0) * np.sqrt(8.0 / np.pi))


@dataclass
class ShakyPanPlan:
    """A hand-held camera swung slowly along a 30 deg arc about the objects' centre, with
    hand shake that is not smooth: every frame's pose is off the smooth arc by fresh white
    noise (mean frame-to-frame change ``step_m`` in position, ``step_deg`` in orientation)
    on top of a slowly varying offset (a few mm, under 1 Hz)."""
    distance: float
    elevation: float            # rad
    azimuth: float              # rad, centre of the arc, about -90 deg: from the front
    direction: float            # +1 or -1: which way the arc runs first
    step_m: float
    step_deg: float
    slow_f: np.ndarray          # (3, 2) Hz of the slowly varying offset
    slow_p: np.ndarray          # (3, 2) rad
    noise_seed: int

    @classmethod
    def draw(cls, rng) -> "ShakyPanPlan":
        return cls(distance=rng.uniform(0.6, 0.75), elevation=np.radians(rng.uniform(42, 58)),
                   azimuth=np.radians(-90 + rng.uniform(-15, 15)), direction=float(rng.choice([-1.0, 1.0])),
                   step_m=rng.uniform(*SHAKE_STEP_M), step_deg=rng.uniform(*SHAKE_STEP_DEG),
                   slow_f=rng.uniform(0.15, 0.7, size=(3, 2)), slow_p=rng.uniform(0, 2 * np.pi, size=(3, 2)),
                   noise_seed=int(rng.integers(2 ** 31)))

    def trajectory(self, placements: list[Placement], frames: int, rate_hz: float = FRAME_RATE_HZ,
                   shake: bool = True) -> list[np.ndarray]:
        """Camera -> world poses at ``rate_hz``: the azimuth eases over SHAKY_ARC_DEG in
        PAN_SECONDS (then back), looking at the objects' centre; ``shake=False``: the smooth
        arc alone (what the shake is measured against)."""
        centres = np.array([p.pose[:3, 3] for p in placements])
        centre = np.array([centres[:, 0].mean(), centres[:, 1].mean(), 0.03])
        noise = np.random.default_rng(self.noise_seed).standard_normal((frames, 6))
        sigma_t = self.step_m / _WHITE_STEP_PER_SIGMA
        sigma_r = np.radians(self.step_deg) / _WHITE_STEP_PER_SIGMA
        distance = self.distance
        for _attempt in range(20):
            poses = []
            for i in range(frames):
                tsec = i / rate_hz
                along = 0.5 * (1 - np.cos(np.pi * tsec / PAN_SECONDS)) - 0.5      # -0.5 .. 0.5
                az = self.azimuth + self.direction * np.radians(SHAKY_ARC_DEG) * along
                pose = look_at(_spherical(centre, distance, az, self.elevation), centre)
                if shake:
                    slow = 0.0015 * np.sin(2 * np.pi * tsec * self.slow_f + self.slow_p).sum(axis=1)
                    pose[:3, 3] += slow + sigma_t * noise[i, :3]
                    # Rotation noise about the camera's own axes (the hand turns the camera).
                    pose[:3, :3] = pose[:3, :3] @ cv2.Rodrigues(sigma_r * noise[i, 3:])[0]
                poses.append(pose)
            if min(_clearance(P[:3, 3], placements) for P in poses) >= MIN_CAMERA_CLEARANCE_M:
                return poses
            distance += 0.05        # too close to a tall object somewhere: back off
        return poses


ARM_TICK_HZ = 30.0              # the arm's motion is planned on this grid (exact at 30/15/10/5 Hz)
ARM_STEP_DEG = (3.0, 8.0)       # per tick while moving, drawn per burst
ARM_BURST_TICKS = (2, 6)        # ticks a burst lasts
ARM_HOLD_TICKS = (6, 24)        # ticks the arm holds still between bursts (0.2-0.8 s)


def jumps_trajectory(placements: list[Placement], frames: int, rng, rate_hz: float = FRAME_RATE_HZ) -> list[np.ndarray]:
    """A camera on a robot arm that moves in bursts: it holds still for 0.2-0.8 s, then moves
    2-6 ticks of 1/30 s at 3-8 deg per tick (drawn per burst; 90-240 deg/s) over the sphere
    about the objects' centre, and holds again. At 30 Hz consecutive frames differ by 0 or by
    3-8 deg (the camera's rotation; its position moves distance x angle, 3-10 cm); at lower
    rates a burst falls between two frames. Elevation stays 35-75 deg, azimuth within 40 deg
    of the start; the arm does not shake."""
    centre, r0 = _view_centre_and_distance(placements, rng)
    el_home = np.radians(rng.uniform(45, 62))
    az_home = np.radians(-90 + rng.uniform(-20, 20))
    duration_ticks = int(np.ceil((frames - 1) / rate_hz * ARM_TICK_HZ)) + 2
    az, el = [az_home], [el_home]
    hold = int(rng.integers(ARM_HOLD_TICKS[0] // 2, ARM_HOLD_TICKS[1] + 1))   # first burst comes sooner
    while len(az) < duration_ticks:
        az.extend([az[-1]] * hold)
        el.extend([el[-1]] * hold)
        ticks = int(rng.integers(ARM_BURST_TICKS[0], ARM_BURST_TICKS[1] + 1))
        step = np.radians(rng.uniform(*ARM_STEP_DEG))
        # Head back towards home when a burst could leave the allowed range.
        home = np.arctan2(el_home - el[-1], az_home - az[-1])
        far = np.hypot(az_home - az[-1], el_home - el[-1]) > np.radians(15)
        theta = home + rng.uniform(-1, 1) * np.radians(60) if far else rng.uniform(0, 2 * np.pi)
        for _ in range(ticks):
            a, e = az[-1] + step * np.cos(theta), el[-1] + step * np.sin(theta)
            if not (np.radians(35) <= e <= np.radians(75)) or abs(a - az_home) > np.radians(40):
                theta = np.arctan2(el_home - el[-1], az_home - az[-1])      # turn home mid-burst
                a, e = az[-1] + step * np.cos(theta), el[-1] + step * np.sin(theta)
            az.append(a)
            el.append(e)
        hold = int(rng.integers(ARM_HOLD_TICKS[0], ARM_HOLD_TICKS[1] + 1))
    tick_times = np.arange(len(az)) / ARM_TICK_HZ
    times = np.arange(frames) / rate_hz
    az_t, el_t = np.interp(times, tick_times, az), np.interp(times, tick_times, el)
    r = r0
    for _attempt in range(20):
        poses = [look_at(_spherical(centre, r, a, e), centre) for a, e in zip(az_t, el_t)]
        if min(_clearance(P[:3, 3], placements) for P in poses) >= MIN_CAMERA_CLEARANCE_M:
            return poses
        r += 0.05           # too close to a tall object somewhere: back off
    return poses


def frame_timeline(frames: int, drop: float, loop: bool, rng) -> tuple[list[int], list[int]]:
    """Which frames of a ``frames``-long camera path are written, and when: (stamp slots,
    log slots), one per written frame, in frame periods from the first frame. ``drop`` > 0
    leaves out about that share of the frames after the first, in runs of 1-3 (a gap in the
    stamps, the camera moving on); ``loop`` plays the kept frames twice, the second time with
    the same stamps (they jump back once) and later log times (bag time runs on)."""
    slots = list(range(frames))
    if drop > 0 and frames > 2:
        dropped = np.zeros(frames, bool)
        target = int(round(drop * (frames - 1)))
        while dropped.sum() < target:
            start = int(rng.integers(1, frames))
            dropped[start:start + int(rng.integers(1, 4))] = True
            dropped[0] = False
            excess = int(dropped.sum()) - target
            if excess > 0:      # trim the last run so that the share is what was asked
                dropped[np.flatnonzero(dropped)[-excess:]] = False
        slots = [i for i in range(frames) if not dropped[i]]
    if loop:
        return slots + slots, slots + [s + frames for s in slots]
    return slots, slots


@dataclass
class MovingObject:
    """Something that moves through the scene and is not in the ground truth, e.g. an arm
    passing in front of the camera: its object -> world pose per frame, None while it is
    out of the scene. Rendered with a distractor label, so it hides what is behind it in
    the ground-truth visibility too."""
    spec: ObjectSpec
    poses: list                     # per frame (4, 4) or None
    label: int = _DISTRACTOR_LABEL0 + MAX_DISTRACTORS

    @property
    def frames(self) -> tuple[int, int]:
        """First and last frame in which it is in the scene."""
        present = [i for i, p in enumerate(self.poses) if p is not None]
        return present[0], present[-1]

    def primitives(self, index: int) -> list:
        pose = self.poses[index]
        return [] if pose is None else object_primitives(Placement(self.spec, pose, self.label))


OCCLUDER_MIN_RANGE_M = 0.34      # where the arm may, it stays in the depth range (0.3 m) and a bit


def _outside_view(T_world_camera: np.ndarray, pose: np.ndarray, spec: ObjectSpec,
                  intrinsics: CameraIntrinsics) -> bool:
    """Is the object's bounding box wholly beside the image (left or right) or behind?"""
    T = invert_transform(T_world_camera) @ pose
    pts = box_corners(spec.dimensions_m) @ T[:3, :3].T + T[:3, 3]
    if np.all(pts[:, 2] <= 0.02):
        return True
    if np.any(pts[:, 2] <= 0.02):
        return False
    u = intrinsics.K[0, 0] * pts[:, 0] / pts[:, 2] + intrinsics.K[0, 2]
    return bool(np.all(u < 0) or np.all(u > intrinsics.width))


def occluder_path(camera_poses: list[np.ndarray], placements: list[Placement], intrinsics: CameraIntrinsics,
                  rng) -> MovingObject:
    """A forearm (``PROPS["forearm"]``) held level, pointing away from the camera, that
    sweeps sideways across the view between the camera and the table: it enters from one
    side at about a third of the sequence, crosses at constant speed and has left by about
    two thirds. It touches no object, and passes as near the camera as the depth range lets
    it (0.34 m), so that it hides whole instances (nearer parts have no depth, as on a D455).
    InputError if objects stand so high that it cannot pass between them and the camera."""
    spec = PROPS["forearm"]
    n = len(camera_poses)
    if n < 3:
        raise InputError(f"an occluder needs at least 3 frames, got {n}")
    first = min(n - 2, max(1, int(round(n * rng.uniform(0.3, 0.37)))))
    last = min(n - 1, max(first + 1, int(round(n * rng.uniform(0.6, 0.67)))))
    side = float(rng.choice([-1.0, 1.0]))           # +1: enters on the left, leaves on the right
    yaw = np.radians(rng.uniform(-20, 20))
    height_share = rng.uniform(0.5, 1.0)
    radius = spec.radius
    mid = camera_poses[(first + last) // 2]
    eye, forward, right = mid[:3, 3], mid[:3, 2], mid[:3, 0]
    across = np.array([right[0], right[1], 0.0]) / np.hypot(right[0], right[1])
    axis = _rot_z(yaw) @ np.array([-across[1], across[0], 0.0])         # away from the camera
    R = np.column_stack([[0.0, 0.0, 1.0], np.cross(axis, [0.0, 0.0, 1.0]), axis])
    window = range(first, last + 1)

    def path_at(z, back=0.0):
        """Poses over the window with the arm at height z, centred where the middle frame's
        optical axis crosses that height (or ``back`` metres nearer the camera along the arm);
        it starts and ends just out of view of the cameras at the first and last frame."""
        crossing = eye + forward * (eye[2] - z) / -forward[2] - back * axis

        def pose_at(offset):
            return make_transform(R, crossing + offset * across)
        start, end = -0.1 * side, 0.1 * side
        while not _outside_view(camera_poses[first], pose_at(start), spec, intrinsics) and abs(start) < 3:
            start -= 0.02 * side
        while not _outside_view(camera_poses[last], pose_at(end), spec, intrinsics) and abs(end) < 3:
            end += 0.02 * side
        return [pose_at(start + (end - start) * (i - first) / (last - first)) for i in window]

    def touches_an_object(path):
        centres = np.array([P[:3, 3] for P in path])
        for p in placements:
            # Exact box test only where the object's bounding sphere comes near the arm's axis.
            d = p.pose[:3, 3] - centres
            along = np.clip(d @ axis, -spec.half_extents[2], spec.half_extents[2])
            gap = np.linalg.norm(d - along[:, None] * axis, axis=1) - radius - np.linalg.norm(p.spec.half_extents)
            if any(_obb_overlap(path[j], spec.half_extents, p.pose, p.spec.half_extents, margin=0.015)
                   for j in np.flatnonzero(gap < 0.03)):
                return True
        return False

    # Height: 3 cm above every object and, if that leaves room, low enough for the depth range
    # where the optical axis crosses it; never within 8 cm of the camera's height. When some
    # objects stand too high for that, the highest height at which the arm passes in front of
    # or beside them touching none, drawn back towards the camera if need be.
    above_all = max(_top_z(p.pose, p.spec.half_extents) for p in placements) + radius + 0.03
    in_range = eye[2] + (OCCLUDER_MIN_RANGE_M + radius) * forward[2]
    highest = min(camera_poses[i][2, 3] for i in window) - radius - 0.08
    if above_all <= highest:
        z = above_all + height_share * (in_range - above_all) if in_range > above_all else above_all
        path = path_at(min(z, highest))
    else:
        for back in (0.0, 0.1, 0.2):
            for z in np.arange(highest, radius + 0.02, -0.01):
                path = path_at(z, back)
                if not touches_an_object(path):
                    break
            else:
                continue
            break
        else:
            raise InputError("the occluder does not fit between the camera and the objects (they stand too "
                             "high for this camera path); use another seed, fewer or lower objects")
    poses = [None] * n
    for i, P in zip(window, path):
        poses[i] = P
    return MovingObject(spec, poses)


def capture_viewpoints(placement: Placement, views: int, rng) -> list[np.ndarray]:
    """Camera -> world poses around one object: evenly spread azimuths with jitter,
    elevations alternating within 30-60 deg, 0.4-0.6 m from the object's centre."""
    centre = placement.pose[:3, 3].copy()
    az0 = rng.uniform(0, 2 * np.pi)
    poses = []
    for i in range(views):
        az = az0 + 2 * np.pi * i / views + np.radians(rng.uniform(-8, 8))
        el = np.radians((rng.uniform(30, 42) if i % 2 == 0 else rng.uniform(48, 60)))
        r = rng.uniform(0.4, 0.6)
        target = centre + rng.uniform(-0.01, 0.01, size=3)
        poses.append(look_at(_spherical(target, r, az, el), target, np.radians(rng.uniform(-4, 4))))
    return poses


# ----------------------------------------------------------------------------------------------
# Primitives


@functools.lru_cache(maxsize=None)
def _object_texture(name: str, face: str) -> Texture:
    spec = PROPS[name] if name in PROPS else get_object(name)
    return Texture(object_textures(name)[face], wrap=(spec.shape == "cylinder" and face == "side"))


@functools.lru_cache(maxsize=None)
def _environment_texture(kind: str) -> Texture:
    return Texture(environment_texture(kind))


def _quad_world(pose, centre, e1, e2, normal, texture, label, disc=False) -> Quad:
    R, t = pose[:3, :3], pose[:3, 3]
    origin = centre - 0.5 * e1 - 0.5 * e2
    return Quad(origin=R @ origin + t, e1=R @ e1, e2=R @ e2, normal=R @ normal, texture=texture,
                tex_rect=(0.0, 0.0, float(texture.width), float(texture.height)), label=label, disc=disc)


def object_primitives(placement: Placement) -> list:
    """Quads (and a cylinder side) of one placed object, in the world frame."""
    spec, pose, label = placement.spec, placement.pose, placement.label
    half = spec.half_extents
    prims = []
    if spec.parts:                          # made of boxes (a bracket): each drawn as a box
        for centre, dims in spec.parts:
            part_pose = pose @ make_transform(np.eye(3), centre)
            part = ObjectSpec(spec.name, "box", dims, spec.faces, spec.resting, spec.tint)
            prims += object_primitives(Placement(part, part_pose, label, placement.arrangement))
        return prims
    if spec.shape == "box":
        for face, normal, up in BOX_FACES:
            n = np.asarray(normal, dtype=np.float64)
            upv = np.asarray(up, dtype=np.float64)
            right = np.cross(upv, n)            # picture rows run left to right seen from outside
            width = 2 * np.abs(right) @ half
            height = 2 * np.abs(upv) @ half
            centre = n * (np.abs(n) @ half)
            prims.append(_quad_world(pose, centre, right * width, -upv * height, n,
                                     _object_texture(spec.name, face), label))
    else:
        r, hh = spec.radius, half[2]
        prims.append(CylinderSide(pose=pose, radius=r, height=2 * hh,
                                  texture=_object_texture(spec.name, "side"), label=label))
        for face, sign in (("+z", 1.0), ("-z", -1.0)):
            n = np.array([0.0, 0.0, sign])
            right = np.cross([0.0, 1.0, 0.0], n)
            prims.append(_quad_world(pose, n * hh, right * 2 * r, np.array([0.0, -2 * r, 0.0]), n,
                                     _object_texture(spec.name, face), label, disc=True))
    return prims


SHADOW_METRES_PER_TEXEL = 0.004


def table_lightmap(placements: list[Placement], wall_y: float, size_m: tuple[float, float]) -> np.ndarray:
    """Brightness of the table top (1 = lit): soft shadows cast by the objects along the
    light direction, plus darkening right around their footprints (skylight they block).
    Rows run from the wall (y = wall_y) towards the front, columns from x = -TABLE_HALF_X."""
    sx, sy = size_m
    w, h = int(round(sx / SHADOW_METRES_PER_TEXEL)), int(round(sy / SHADOW_METRES_PER_TEXEL))
    shadow = np.zeros((h, w), np.float32)
    contact = np.zeros((h, w), np.float32)
    L = LIGHT_DIR_WORLD
    ring = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    for p in placements:
        half = p.spec.half_extents
        if p.spec.shape == "cylinder":
            local = np.array([[half[0] * np.cos(a), half[0] * np.sin(a), sz * half[2]]
                              for a in ring for sz in (-1, 1)])
        else:
            local = np.array([[sx_ * half[0], sy_ * half[1], sz * half[2]]
                              for sx_ in (-1, 1) for sy_ in (-1, 1) for sz in (-1, 1)])
        pts = local @ p.pose[:3, :3].T + p.pose[:3, 3]
        cast = pts[:, :2] - (pts[:, 2:3] / L[2]) * L[:2]             # along the light onto z = 0
        for target, xy in ((shadow, cast), (contact, pts[pts[:, 2] < 0.01 + pts[:, 2].min(), :2])):
            px = np.stack([(xy[:, 0] + TABLE_HALF_X) / SHADOW_METRES_PER_TEXEL,
                           (wall_y - xy[:, 1]) / SHADOW_METRES_PER_TEXEL], axis=1)
            hull = cv2.convexHull(np.round(px * 16).astype(np.int32))
            cv2.fillConvexPoly(target, hull, 1.0, lineType=cv2.LINE_AA, shift=4)
    shadow = cv2.GaussianBlur(shadow, (0, 0), 0.006 / SHADOW_METRES_PER_TEXEL)
    contact = cv2.GaussianBlur(contact, (0, 0), 0.02 / SHADOW_METRES_PER_TEXEL)
    # In full shadow only the ambient term remains: AMBIENT / (AMBIENT + DIFFUSE * L_z).
    direct = 1.0 - AMBIENT / (AMBIENT + DIFFUSE * L[2])
    return np.clip(1.0 - direct * shadow - 0.25 * contact, 0.3, 1.0).astype(np.float32)


FLOOR_BELOW_TABLE_M = 0.75
CLUTTER_DISTANCE_M = (2.0, 3.0)     # the far wall behind the table's back edge, drawn per seed


def clutter_primitives(table_back_y: float, rng) -> tuple[list, float]:
    """A room behind the table (background "clutter"): a floor FLOOR_BELOW_TABLE_M below the
    table top, 3-5 pieces of furniture (``objects.FURNITURE``: textured boxes standing on the
    floor, most against the far wall) and the far wall's y, CLUTTER_DISTANCE_M behind the
    table's back edge. Returns (primitives, far wall y)."""
    far_y = table_back_y + rng.uniform(*CLUTTER_DISTANCE_M)
    floor_z = -FLOOR_BELOW_TABLE_M
    size = ENVIRONMENT_SIZE["floor"]
    prims = [Quad(origin=np.array([-size[0] / 2, far_y, floor_z]), e1=np.array([size[0], 0.0, 0.0]),
                  e2=np.array([0.0, -size[1], 0.0]), normal=np.array([0.0, 0.0, 1.0]),
                  texture=_environment_texture("floor"), tex_rect=(0.0, 0.0, size[0] * size[2], size[1] * size[2]))]
    placed: list[Placement] = []
    for _ in range(int(rng.integers(3, 6))):
        spec = PROPS[FURNITURE[int(rng.integers(len(FURNITURE)))]]
        half = spec.half_extents
        for _attempt in range(30):
            against_wall = rng.random() < 0.7
            yaw = rng.normal(0.0, np.radians(4)) if against_wall else rng.uniform(-0.6, 0.6)
            y = far_y - half[1] - 0.02 if against_wall else rng.uniform(table_back_y + 0.6, far_y - 0.5)
            pose = make_transform(_rot_z(yaw), [rng.uniform(-2.4, 2.4), y, floor_z + half[2]])
            if y - half[1] > table_back_y + 0.3 and not any(
                    _obb_overlap(pose, half, q.pose, q.spec.half_extents, 0.02) for q in placed):
                placed.append(Placement(spec, pose, -1, "fixture"))
                break
    for q in placed:
        prims += object_primitives(q)
    return prims, far_y


def environment_primitives(wall_y: float, placements: list[Placement] = (), clutter_rng=None) -> list:
    """The table top (z = 0) and the wall behind it (y = wall_y), both textured; the
    placements cast shadows on the table. With ``clutter_rng``, the table ends at wall_y and
    a room lies behind it instead of the wall (``clutter_primitives``)."""
    table_tex = _environment_texture("table")
    wall_tex = _environment_texture("wall")
    table_per_m = ENVIRONMENT_SIZE["table"][2]
    wall_per_m = ENVIRONMENT_SIZE["wall"][2]
    sx, sy = 2 * TABLE_HALF_X, min(wall_y - TABLE_FRONT_Y, ENVIRONMENT_SIZE["table"][1])
    table = Quad(origin=np.array([-TABLE_HALF_X, wall_y, 0.0]), e1=np.array([sx, 0.0, 0.0]),
                 e2=np.array([0.0, -sy, 0.0]), normal=np.array([0.0, 0.0, 1.0]), texture=table_tex,
                 tex_rect=(0.0, 0.0, sx * table_per_m, sy * table_per_m),
                 lightmap=table_lightmap(list(placements), wall_y, (sx, sy)) if placements else None)
    wall_w, wall_h = ENVIRONMENT_SIZE["wall"][:2]
    room, bottom = [], -0.02
    if clutter_rng is not None:
        room, wall_y = clutter_primitives(wall_y, clutter_rng)
        bottom = -FLOOR_BELOW_TABLE_M - 0.02
    # The wall stops just below the table top (the floor): anything lower is hidden and costs time.
    wall = Quad(origin=np.array([-wall_w / 2, wall_y, wall_h + bottom]), e1=np.array([wall_w, 0.0, 0.0]),
                e2=np.array([0.0, 0.0, -wall_h]), normal=np.array([0.0, -1.0, 0.0]), texture=wall_tex,
                tex_rect=(0.0, 0.0, wall_w * wall_per_m, wall_h * wall_per_m))
    return [table, wall] + room


# ----------------------------------------------------------------------------------------------
# Scenes and frames


@dataclass
class RenderedFrame:
    index: int
    stamp_ns: int
    rgb: np.ndarray              # (H, W, 3) uint8
    depth_mm: np.ndarray         # (H, W) uint16, 0 = invalid
    depth_true_m: np.ndarray     # (H, W) float32, noise-free, 0 = nothing
    K: np.ndarray                # (3, 3)
    poses: np.ndarray            # (K, 4, 4) object -> colour optical frame
    instance_mask: np.ndarray    # (H, W) int16: k instance k, -1 table/wall, -2 distractor
    visibility: np.ndarray       # (K,) float32 in [0, 1]
    T_world_camera: np.ndarray   # (4, 4) camera -> world


@dataclass
class SyntheticScene:
    """A placed scene plus its camera path; render frames on demand."""
    kind: str                            # "scene" | "capture"
    target: ObjectSpec
    placements: list[Placement]
    camera_poses: list[np.ndarray]       # camera -> world, one per frame
    intrinsics: CameraIntrinsics
    seed: int
    # (first frame, placements) from which frame on the objects lie differently, e.g. a
    # capture where the user turns the object over half way; same objects, same labels.
    later_placements: list = field(default_factory=list)
    motion: str = "sweep"                # camera path of a "scene": sweep | static | pan
    occluder: MovingObject | None = None
    more_targets: tuple = ()             # further target objects of a mixed scene (ObjectSpec)
    depth_noise_correlation_px: float = 0.0   # > 0: depth noise smooth over this many pixels (sensor.simulate_depth)
    # When frames are written (``frame_timeline``): the camera path at ``frame_rate_hz`` has
    # one pose per slot (``path_poses``); frame i is slot ``frame_slots[i]`` (its stamp, its
    # noise) written at bag time slot ``log_slots[i]``. None: frame i is slot i (every frame
    # of the path, once), ``camera_poses`` is the path.
    frame_rate_hz: float = FRAME_RATE_HZ
    frame_slots: list | None = None
    log_slots: list | None = None
    path_poses: list | None = None
    sensor: SensorProfile = SENSOR_PROFILES["d455"]     # how the depth is made (sensor.simulate_depth)
    layout: str = "table"                # how the objects lie: table | flush | bin (make_tabletop_scene)
    background: str = "wall"             # behind the table: wall | clutter (a room 2-3 m behind)

    def __post_init__(self):
        wall_y = max(0.45, max(p.pose[1, 3] for p in self.placements) + 0.3)
        if self.kind == "capture":
            wall_y = 1.0
        self._stages = []           # (first frame, placements, primitives)
        for start, placements in [(0, self.placements)] + sorted(self.later_placements, key=lambda s: s[0]):
            clutter_rng = np.random.default_rng([self.seed, 10]) if self.background == "clutter" else None
            prims = environment_primitives(wall_y, placements, clutter_rng)
            for p in placements:
                prims += object_primitives(p)
            self._stages.append((start, placements, prims))
        self._renderer = Renderer(self.intrinsics.K, self.intrinsics.width, self.intrinsics.height)

    @property
    def instances(self) -> list[Placement]:
        return [p for p in self.placements if p.is_instance]

    @property
    def instance_objects(self) -> list[str]:
        """Object name of each instance, in ground-truth order."""
        return [p.spec.name for p in self.instances]

    @property
    def num_frames(self) -> int:
        return len(self.camera_poses)

    def description(self) -> dict:
        """The /ground_truth/object JSON: the shared convention plus what else was placed."""
        d = self.target.description()
        d.update({"instances": len(self.instances), "kind": self.kind, "seed": int(self.seed),
                  "distractors": [p.spec.name for p in self.placements if p.is_distractor],
                  "arrangements": [p.arrangement for p in self.instances],
                  "generator": "multi_instance_reg.synthetic"})
        # Only when not the defaults, so that default bags stay byte for byte what they were.
        if self.motion != "sweep":
            d["motion"] = self.motion
        if self.layout != "table":
            d["layout"] = self.layout
        if self.background != "wall":
            d["background"] = self.background
        if self.more_targets:
            # A mixed scene: every target object, and which one each ground-truth index is.
            d["objects"] = [spec.description() for spec in (self.target,) + tuple(self.more_targets)]
            d["instance_objects"] = self.instance_objects
        if self.depth_noise_correlation_px > 0:
            d["depth_noise_correlation_px"] = float(self.depth_noise_correlation_px)
        if self.sensor != SENSOR_PROFILES["d455"]:
            d["sensor"] = self.sensor.description()
        if self.frame_rate_hz != FRAME_RATE_HZ:
            d["frame_rate_hz"] = float(self.frame_rate_hz)
        if self.frame_slots is not None:
            path_frames = len(self._path())
            d["path_frames"] = path_frames
            d["dropped_frames"] = path_frames - len(set(self.frame_slots))
            if self.log_slots != self.frame_slots:
                d["loop"] = True
        if self.occluder is not None:
            first, last = self.occluder.frames
            d["occluder"] = {"name": self.occluder.spec.name, "shape": self.occluder.spec.shape,
                             "dimensions_m": [float(v) for v in self.occluder.spec.dimensions_m],
                             "frames": [first, last]}
        return d

    def slot(self, index: int) -> int:
        """Frame ``index``'s place on the camera path (frame periods from the first frame)."""
        return index if self.frame_slots is None else int(self.frame_slots[index])

    def _path(self) -> list:
        return self.camera_poses if self.path_poses is None else self.path_poses

    def stamp_ns(self, index: int) -> int:
        """Header stamp of frame ``index``: its slot at ``frame_rate_hz`` (gaps where frames
        were dropped; back to the start where a loop begins again)."""
        return START_STAMP_NS + int(round(self.slot(index) * 1e9 / self.frame_rate_hz))

    def log_time_ns(self, index: int) -> int:
        """Bag time of frame ``index``: its stamp, except in a loop's second play, which is
        recorded after the first (bag time never runs back)."""
        if self.log_slots is None:
            return self.stamp_ns(index)
        return START_STAMP_NS + int(round(int(self.log_slots[index]) * 1e9 / self.frame_rate_hz))

    def set_depth_noise_correlation(self, pixels: float) -> "SyntheticScene":
        """Depth noise smooth over about ``pixels`` pixels from now on (0 = independent per
        pixel; ``sensor.simulate_depth``), checked. Returns the scene."""
        pixels = float(pixels)
        if not 0.0 <= pixels <= 20.0:
            raise InputError(f"depth noise correlation must be 0 (independent per pixel) to 20 pixels, got {pixels:g}")
        self.depth_noise_correlation_px = pixels
        return self

    def set_sensor(self, name: str = "d455", randomise: bool = False) -> "SyntheticScene":
        """Depth as the named sensor profile makes it from now on (``sensor.SENSOR_PROFILES``:
        "d455", "realistic"); with ``randomise`` each of its figures drawn per seed from
        ``sensor.PROFILE_RANGES``. Returns the scene."""
        self.sensor = sensor_profile(name, self.seed, randomise)
        return self

    def _primitives(self, index: int) -> tuple[list[Placement], list]:
        _, placements, primitives = [st for st in self._stages if st[0] <= index][-1]
        if self.occluder is not None:
            primitives = primitives + self.occluder.primitives(index)
        return placements, primitives

    def _noise_seed(self, index: int) -> int:
        # Keyed by the slot: a loop's second play is the same recording, byte for byte.
        return int(np.random.SeedSequence([self.seed, self.slot(index), 17]).generate_state(1)[0])

    def render_unaligned_depth(self, index: int, sensor: UnalignedDepth) -> np.ndarray:
        """Frame ``index``'s depth as ``sensor``'s own depth imager records it (16UC1 mm in its
        pixels; the same sensor profile and noise streams as the aligned depth)."""
        if getattr(self, "_depth_renderer_for", None) is not sensor:
            K, intr = sensor.intrinsics.K, sensor.intrinsics
            self._depth_renderer, self._depth_renderer_for = Renderer(K, intr.width, intr.height), sensor
        _, primitives = self._primitives(index)
        T_depth_world = invert_transform(sensor.colour_from_depth) @ invert_transform(self.camera_poses[index])
        out = self._depth_renderer.render(primitives, T_depth_world)
        return simulate_depth(out.depth_m, float(sensor.intrinsics.K[0, 0]), self._noise_seed(index) + 1,
                              self.depth_noise_correlation_px, self.sensor)

    def render_frame(self, index: int) -> RenderedFrame:
        T_wc = self.camera_poses[index]
        T_cw = invert_transform(T_wc)
        placements, primitives = self._primitives(index)
        instances = [p for p in placements if p.is_instance]
        out = self._renderer.render(primitives, T_cw, count_labels=[p.label for p in instances])
        noise_seed = self._noise_seed(index)
        rgb = simulate_colour(out.radiance, noise_seed)
        depth_mm = simulate_depth(out.depth_m, float(self.intrinsics.K[0, 0]), noise_seed + 1,
                                  self.depth_noise_correlation_px, self.sensor)
        mask = out.labels.copy()
        mask[mask >= _DISTRACTOR_LABEL0] = LABEL_DISTRACTOR
        counts = np.bincount(mask[mask >= 0].ravel(), minlength=len(instances))
        vis = np.array([counts[p.label] / out.coverage[p.label] if out.coverage[p.label] else 0.0
                        for p in instances], dtype=np.float32)
        poses = np.stack([T_cw @ p.pose for p in instances]) if instances else np.zeros((0, 4, 4))
        depth_true = np.where(np.isfinite(out.depth_m), out.depth_m, 0).astype(np.float32)
        return RenderedFrame(index=index, stamp_ns=self.stamp_ns(index), rgb=rgb, depth_mm=depth_mm,
                             depth_true_m=depth_true, K=self.intrinsics.K.copy(), poses=poses,
                             instance_mask=mask, visibility=vis, T_world_camera=T_wc)

    def frames(self):
        for i in range(self.num_frames):
            yield self.render_frame(i)

    def accel_samples(self, index: int, rate_hz: float = ACCEL_RATE_HZ) -> tuple[np.ndarray, np.ndarray]:
        """The accelerometer samples between frame ``index - 1`` and frame ``index`` (for the
        first frame, the frame interval before it): (offsets from the frame's stamp, ns, <= 0;
        (N, 3) m/s^2 in the optical frame). Each is the specific force a still or moving
        camera feels: world up x 9.81 plus the camera path's acceleration (second differences
        of the frame positions, linear between frames; a capture's views are still ones),
        turned into the optical frame (between frames, the two frames' readings blended), plus
        a bias per recording and white noise, each from streams of their own (the images do not
        change). The reading's axes are those of the colour optical frame, as librealsense
        gives a D455's IMU samples up to a fraction of a degree."""
        period = 1.0 / self.frame_rate_hz
        slot = self.slot(index)
        # Since the previous frame: every path period up to this frame's slot (more than one
        # after dropped frames; one at the first frame and where a loop starts again).
        first = self.slot(index - 1) + 1 if index > 0 and self.slot(index - 1) < slot else slot
        acc = self._path_acceleration()
        path = self._path()
        lift = np.array([0.0, 0.0, GRAVITY_M_S2])
        k_all, times_all, force_all = [], [], []
        for q in range(first, slot + 1):
            t1 = q * period
            k = np.arange(int(np.floor((t1 - period) * rate_hz + 1e-9)) + 1, int(np.floor(t1 * rate_hz + 1e-9)) + 1)
            times = k / rate_hz
            s = (times - (t1 - period)) / period                 # 0 at the previous path pose, 1 at this one
            prev = max(q - 1, 0)
            f_prev = path[prev][:3, :3].T @ (acc[prev] + lift)
            f_this = path[q][:3, :3].T @ (acc[q] + lift)
            if self.kind != "scene":
                f_prev = f_this                                  # views, not a path: still at each
            k_all.append(k)
            times_all.append(times)
            force_all.append((1.0 - s)[:, None] * f_prev + s[:, None] * f_this)
        k, times = np.concatenate(k_all), np.concatenate(times_all)
        force = np.concatenate(force_all)
        bias = np.clip(np.random.default_rng([self.seed, 41]).normal(0.0, ACCEL_BIAS_M_S2, 3),
                       -3 * ACCEL_BIAS_M_S2, 3 * ACCEL_BIAS_M_S2)
        noise = np.random.default_rng([self.seed, slot, 43]).normal(0.0, ACCEL_NOISE_M_S2, (len(k), 3))
        # Each rounded as the frame stamps are: in a scene's own bag the samples fall on an exact 5 ms grid.
        offsets = np.round(times * 1e9).astype(np.int64) - int(round(slot * period * 1e9))
        return offsets, force + bias + noise

    def _path_acceleration(self) -> np.ndarray:
        """(path slots, 3) world acceleration of the camera at each slot of its path (m/s^2):
        second differences of its positions at ``frame_rate_hz`` (the ends take their
        neighbour's); zero for a capture's separate views or fewer than three slots."""
        path = self._path()
        n = len(path)
        acc = np.zeros((n, 3))
        if self.kind == "scene" and n >= 3:
            p = np.array([P[:3, 3] for P in path])
            acc[1:-1] = (p[2:] - 2.0 * p[1:-1] + p[:-2]) * self.frame_rate_hz ** 2
            acc[0], acc[-1] = acc[1], acc[-2]
        return acc


def _check_common(object_name: str, seed: int, resolution: str) -> ObjectSpec:
    spec = get_object(object_name)
    d455_intrinsics(resolution)        # validates the resolution
    if int(seed) < 0:
        raise InputError(f"seed must be >= 0, got {seed}")
    return spec


def make_tabletop_scene(object_name: str | list[str] = DEFAULT_OBJECT, instances: int = 6, distractors: int = 3,
                        frames: int = 60, seed: int = 0, resolution: str = "640x480", motion: str = "sweep",
                        occluder: bool = False, frame_rate: float = FRAME_RATE_HZ, drop: float = 0.0,
                        loop: bool = False, sensor: str = "d455", randomise: bool = False, layout: str = "table",
                        background: str = "wall") -> SyntheticScene:
    names = [object_name] if isinstance(object_name, str) else list(object_name)
    if not names or len(set(names)) != len(names):
        raise InputError(f"target objects must be given once each, got {names}")
    spec = _check_common(names[0], seed, resolution)
    more = tuple(get_object(n) for n in names[1:])
    if motion not in MOTIONS:
        raise InputError(f"motion must be one of {', '.join(MOTIONS)}, got '{motion}'")
    if layout not in LAYOUTS:
        raise InputError(f"layout must be one of {', '.join(LAYOUTS)}, got '{layout}'")
    if background not in BACKGROUNDS:
        raise InputError(f"background must be one of {', '.join(BACKGROUNDS)}, got '{background}'")
    if motion == "pan" and layout != "table":
        raise InputError(f"motion pan spreads the objects along the table: it needs layout table, not {layout}")
    if layout == "flush" and not all(s.shape == "box" for s in (spec, *more)):
        raise InputError("layout flush packs boxes: choose box objects (e.g. snack_box, cereal_box, snack_bar)")
    if not 1 <= int(instances) * len(names) <= MAX_INSTANCES:
        raise InputError(f"instances must be 1 to {MAX_INSTANCES} in all ({len(names)} object(s) x {instances})"
                         if len(names) > 1 else f"instances must be 1 to {MAX_INSTANCES}, got {instances}")
    if not 0 <= int(distractors) <= MAX_DISTRACTORS:
        raise InputError(f"distractors must be 0 to {MAX_DISTRACTORS}, got {distractors}")
    if int(frames) < 1:
        raise InputError(f"frames must be at least 1, got {frames}")
    frame_rate = float(frame_rate)
    if not MIN_FRAME_RATE_HZ <= frame_rate <= MAX_FRAME_RATE_HZ:
        raise InputError(f"frame rate must be {MIN_FRAME_RATE_HZ:g} to {MAX_FRAME_RATE_HZ:g} Hz, got {frame_rate:g}")
    if not 0.0 <= float(drop) <= MAX_DROP:
        raise InputError(f"drop (share of frames left out) must be 0 to {MAX_DROP:g}, got {drop:g}")
    # Independent streams, so that e.g. the frame count does not change the placement, and
    # the static camera, the pan and the occluder take nothing from the sweep's streams.
    rng_choose, rng_place, rng_path, rng_motion, rng_occluder, rng_drop, rng_layout = (
        np.random.default_rng([int(seed), k]) for k in (1, 2, 3, 6, 7, 8, 11))
    intrinsics = d455_intrinsics(resolution)
    pool = [s for s in OBJECTS.values() if s.name not in names]
    distractor_specs = [pool[int(i)] for i in rng_choose.integers(len(pool), size=int(distractors))]
    if motion == "pan":
        pan = PanPlan.draw(rng_motion)
        footprint = footprint_area([spec, *more] * int(instances) + distractor_specs)
        placements = place_objects(spec, int(instances), distractor_specs, rng_place,
                                   region_half=pan.region_half(intrinsics, footprint), more_targets=more)
        poses = pan.trajectory(placements, int(frames), frame_rate)
    else:
        if layout == "flush":
            # Every box against a copy of itself, all lying on their most likely face (as on a
            # pallet: the first of each object sets the way; the copies follow it); the
            # distractors fall back to free.
            def lying(s):
                return replace(s, resting=(max(s.resting, key=lambda r: r[1]),))
            flat = [lying(s) for s in (spec, *more)]
            placements = place_objects(flat[0], int(instances), distractor_specs, rng_place, more_targets=tuple(flat[1:]),
                                       arrangement_probs=(0.0, 0.0, 0.0, 0.0, 1.0))
        elif layout == "bin":       # everything dropped into a bin at random orientations
            panels, inside = bin_fixtures([spec, *more] * int(instances) + distractor_specs, rng_layout)
            placements = place_objects(spec, int(instances), distractor_specs, rng_place, more_targets=more,
                                       arrangement_probs=(0.0, 0.0, 0.0, 0.0, 0.0, 1.0), region_half=inside,
                                       fixtures=tuple(panels))
        else:
            placements = place_objects(spec, int(instances), distractor_specs, rng_place, more_targets=more)
        if motion == "overhead":    # closer over a bin (it fills the view, as in bin-picking cells)
            poses = overhead_trajectory(placements, int(frames), rng_motion, frame_rate,
                                        distance=(0.55, 0.75) if layout == "bin" else (0.7, 1.0))
        elif motion == "static":
            poses = static_viewpoint(placements, int(frames), rng_motion)
        elif motion == "shaky_pan":
            poses = ShakyPanPlan.draw(rng_motion).trajectory(placements, int(frames), frame_rate)
        elif motion == "jumps":
            poses = jumps_trajectory(placements, int(frames), rng_motion, frame_rate)
        else:
            poses = sweep_trajectory(placements, int(frames), rng_path, frame_rate)
    timeline = {}
    if drop > 0 or loop:
        slots, log_slots = frame_timeline(int(frames), float(drop), bool(loop), rng_drop)
        timeline = dict(frame_slots=slots, log_slots=log_slots, path_poses=poses)
        poses = [poses[s] for s in slots]
    if occluder:
        # On the written frames (a loop's first play; the second repeats it).
        first_play = poses[:len(poses) // 2] if loop else poses
        moving = occluder_path(first_play, placements, intrinsics, rng_occluder)
        if loop:
            moving.poses = moving.poses + moving.poses
    else:
        moving = None
    return SyntheticScene("scene", spec, placements, poses, intrinsics, int(seed), motion=motion,
                          occluder=moving, more_targets=more, frame_rate_hz=frame_rate,
                          sensor=sensor_profile(sensor, int(seed), randomise), layout=layout, background=background,
                          **timeline)


def make_capture_scene(object_name: str = DEFAULT_OBJECT, seed: int = 0, views: int = 10,
                       resolution: str = "640x480") -> SyntheticScene:
    spec = _check_common(object_name, seed, resolution)
    if not 3 <= int(views) <= 100:
        raise InputError(f"views must be 3 to 100, got {views}")
    rng = np.random.default_rng([int(seed), 4])
    up = max(spec.resting, key=lambda r: r[1])[0]
    pose = make_transform(_resting_rotation(spec, up, rng.uniform(0, 2 * np.pi), rng), [0.0, 0.0, 0.0])
    pose[2, 3] -= _lowest_z(pose, spec.half_extents)
    placement = Placement(spec, pose, 0, "free")
    # Half way the user turns the object over (180 deg about a horizontal axis, same spot),
    # so that the model also holds the face it first stood on; each half goes all around.
    flipped = placement.pose.copy()
    flipped[:3, :3] = _rot_x(np.pi) @ flipped[:3, :3]
    flipped[2, 3] -= _lowest_z(flipped, spec.half_extents)
    turned = Placement(spec, flipped, 0, "free")
    first = int(views) - int(views) // 2
    poses = capture_viewpoints(placement, first, rng) + capture_viewpoints(turned, int(views) - first, rng)
    later = [(first, [turned])]
    return SyntheticScene("capture", spec, [placement], poses, d455_intrinsics(resolution), int(seed),
                          later_placements=later)


# ----------------------------------------------------------------------------------------------
# Bags


# How the depth is recorded (write_scene_bag).
RECORDINGS = ("aligned", "unaligned", "viewer")


@dataclass
class BagSummary:
    path: Path
    frames: int
    seconds: float
    instances: int
    storage: str

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("inf")

    def line(self) -> str:
        return (f"wrote {self.frames} frames ({self.instances} instance(s)) to {self.path} "
                f"[{self.storage}] at {self.fps:.1f} frames/s")


def write_scene_bag(scene: SyntheticScene, out_path, storage: str = "sqlite3", preview_dir=None,
                    preview_frames=None, transport: str = "raw", imu: bool = True, bop_dir=None,
                    bop_scene: int | None = None, recording: str = "aligned") -> BagSummary:
    """Render every frame of ``scene`` into a new rosbag2 at ``out_path``, its images raw or,
    with ``transport`` "compressed", as image_transport's compressed topics; with ``imu``,
    the accelerometer's samples before each frame (``SyntheticScene.accel_samples``); with
    ``bop_dir``, the same frames also as scene ``bop_scene`` (default: the seed) of a BOP
    dataset there (``bop_export.SceneBopExport``). ``recording`` (``RECORDINGS``): "aligned"
    depth as realsense-ros with align_depth.enable; "unaligned" the depth imager's own
    (``sensor.unaligned_depth_sensor``) as realsense-ros records it without; "viewer" the
    same as a RealSense Viewer ROS 1 .bag at ``out_path`` (no IMU, no compression)."""
    from ..datasets.bag_writer import RealSenseBagWriter
    from ..datasets.realsense_viewer import ViewerBagWriter
    from .preview import write_preview

    if recording not in RECORDINGS:
        raise InputError(f"recording '{recording}' is not one of: {', '.join(RECORDINGS)}")
    depth_sensor = unaligned_depth_sensor() if recording != "aligned" else None

    bop = None
    if bop_dir is not None:
        from .bop_export import SceneBopExport

        bop = SceneBopExport(bop_dir, scene, scene.seed if bop_scene is None else bop_scene)

    n = scene.num_frames
    if preview_frames is None:
        preview_frames = sorted({0, n // 2, n - 1})
    if preview_dir is not None:
        Path(preview_dir).mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    writer = ViewerBagWriter(out_path, depth_sensor.colour_from_depth) if recording == "viewer" else \
        RealSenseBagWriter(out_path, storage=storage, transport=transport)
    with writer as bag:
        bag.write_object_description(scene.stamp_ns(0), scene.description())
        for frame in scene.frames():
            log_time = scene.log_time_ns(frame.index)
            if imu and recording != "viewer":
                bag.write_accel_samples(frame.stamp_ns, *scene.accel_samples(frame.index),
                                        log_offset_ns=log_time - frame.stamp_ns)
            if recording == "viewer":
                # The Viewer's depth and colour come from two sensors' clocks: 1 ms apart here.
                bag.write_frame(frame.stamp_ns, frame.rgb, scene.render_unaligned_depth(frame.index, depth_sensor),
                                scene.intrinsics, depth_sensor.intrinsics, poses=frame.poses,
                                visibility=frame.visibility, depth_stamp_ns=frame.stamp_ns + 1_000_000)
            elif recording == "unaligned":
                bag.write_frame(frame.stamp_ns, frame.rgb, scene.render_unaligned_depth(frame.index, depth_sensor),
                                scene.intrinsics, poses=frame.poses, visibility=frame.visibility,
                                log_time_ns=log_time, depth_intrinsics=depth_sensor.intrinsics,
                                colour_from_depth=depth_sensor.colour_from_depth)
            else:
                bag.write_frame(frame.stamp_ns, frame.rgb, frame.depth_mm, scene.intrinsics,
                                poses=frame.poses, visibility=frame.visibility, log_time_ns=log_time)
            if bop is not None:
                bop.add(frame)
            if preview_dir is not None and frame.index in preview_frames:
                write_preview(preview_dir, frame, scene)
    if bop is not None:
        bop.close()
    return BagSummary(Path(out_path), n, time.perf_counter() - t0, len(scene.instances),
                      "ROS 1, RealSense Viewer layout" if recording == "viewer" else storage)


def generate_scene_bag(out_path, object_name: str | list[str] = DEFAULT_OBJECT, instances: int = 6,
                       distractors: int = 3, frames: int = 60, seed: int = 0, storage: str = "sqlite3",
                       resolution: str = "640x480", preview_dir=None, motion: str = "sweep",
                       occluder: bool = False, depth_noise_correlation_px: float = 0.0,
                       transport: str = "raw", imu: bool = True, frame_rate: float = FRAME_RATE_HZ,
                       drop: float = 0.0, loop: bool = False, sensor: str = "d455",
                       randomise: bool = False, layout: str = "table", background: str = "wall",
                       bop_dir=None, bop_scene: int | None = None, recording: str = "aligned") -> BagSummary:
    """Make a tabletop scene (see ``make_tabletop_scene``) and write it as a rosbag2 (and, with
    ``bop_dir``, as a BOP scene; ``recording``: aligned, unaligned or viewer: ``write_scene_bag``)."""
    scene = make_tabletop_scene(object_name, instances, distractors, frames, seed, resolution,
                                motion=motion, occluder=occluder, frame_rate=frame_rate, drop=drop, loop=loop,
                                sensor=sensor, randomise=randomise, layout=layout, background=background)
    scene.set_depth_noise_correlation(depth_noise_correlation_px)
    return write_scene_bag(scene, out_path, storage, preview_dir, transport=transport, imu=imu,
                           bop_dir=bop_dir, bop_scene=bop_scene, recording=recording)


def generate_capture_bag(out_path, object_name: str = DEFAULT_OBJECT, seed: int = 0, views: int = 10,
                         storage: str = "sqlite3", resolution: str = "640x480", preview_dir=None,
                         transport: str = "raw", imu: bool = True, bop_dir=None,
                         bop_scene: int | None = None) -> BagSummary:
    """Make a capture sequence (see ``make_capture_scene``) and write it as a rosbag2 (and, with
    ``bop_dir``, as a BOP scene: ``write_scene_bag``)."""
    scene = make_capture_scene(object_name, seed, views, resolution)
    return write_scene_bag(scene, out_path, storage, preview_dir,
                           preview_frames=list(range(min(views, 4))), transport=transport, imu=imu,
                           bop_dir=bop_dir, bop_scene=bop_scene)
