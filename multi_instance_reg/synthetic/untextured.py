"""Scenes of objects without texture, with ground truth, for the shape front end.

Presets (``make_untextured_scene(preset, ...)``):
- ``pallet``: plain cartons (:data:`.objects.UNTEXTURED_OBJECTS` ``carton``) in one or two
  layers on a pallet on the floor, a few centimetres apart, some slots empty, seen from above
  by a slowly drifting camera 1.2-2 m from the cartons (tilted 5-30 deg off vertical).
  With ``instances=0`` the pallet carries other plain boxes only (distractor-only frames).
- ``flush``: the same cartons packed flush on the pallet, side by side in one layer with
  hairline gaps (as real ones are: from above their tops form one plane, and only their
  worn, darker edges show where one ends), some slots empty; the same camera.
- ``cylinders`` / ``bracket``: grey cylinders or L-shaped brackets with plain distractors on a
  table, seen by the hand-held sweep of the tabletop scenes (0.5-1 m).
- ``channel`` / ``stairs`` / ``tee``: a U channel, a block of three steps or a T profile,
  the same way (objects nobody tuned the shape front end on).

Every object is flat-coloured all over; the floor and table keep their texture (the
shape front end never looks at colour). The objects' meshes come from
:func:`.objects.object_mesh`, in the same object frame as the ground-truth poses.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..transforms import make_transform
from .objects import UNTEXTURED_OBJECTS, get_object, scaled
from .scene import (MAX_DISTRACTORS, MAX_INSTANCES, Placement, SyntheticScene, _DISTRACTOR_LABEL0, _rot_z,
                    overhead_trajectory, place_objects, sweep_trajectory)
from .sensor import d455_intrinsics

PRESETS = {
    "pallet": "carton",
    "flush": "carton",
    "cylinders": "grey_cylinder",
    "bracket": "bracket",
    # Objects the shape front end was not developed on (session 12): on the table like the
    # brackets, with the same distractors.
    "channel": "channel",
    "stairs": "stairs",
    "tee": "tee",
}
# What ``mireg bench frames --untextured all`` runs (and ``make bench``): the three presets the
# shape front end was developed on, so that its figures and time stay comparable across
# sessions; the others are run by name.
BENCH_ALL = ("pallet", "cylinders", "bracket")
TABLE_DISTRACTORS = ("grey_block", "wide_cylinder", "grey_cylinder", "bracket")
PALLET_DISTRACTORS = ("crate", "grey_block")
PALLET_GRID = (3, 3)            # slots along the pallet's x and y per layer
# Cartons packed flush: the gap between neighbours (a hairline: none in the depth), the
# step between their tops (bulging cardboard) and their tilt.
FLUSH_GAP_M = (1e-4, 2e-3)
FLUSH_STEP_M = 2e-3
FLUSH_TILT_RAD = np.radians(0.7)
# ``size_error``: at most this share of each side.
MAX_SIZE_ERROR = 0.2


def preset_object(preset: str) -> str:
    if preset not in PRESETS:
        raise InputError(f"unknown untextured scene preset '{preset}'; choose one of: {', '.join(PRESETS)}")
    return PRESETS[preset]


def make_untextured_scene(preset: str, instances: int = 8, distractors: int = 3, frames: int = 30,
                          seed: int = 0, resolution: str = "640x480", size_error: float = 0.0) -> SyntheticScene:
    """``size_error``: the instances are not the size of the object's mesh: all of them
    (one product) larger or smaller along each axis by a share drawn per seed within
    +-``size_error``; the ground truth and the mesh written stay the nominal object's."""
    target = get_object(preset_object(preset))
    d455_intrinsics(resolution)
    if int(seed) < 0:
        raise InputError(f"seed must be >= 0, got {seed}")
    if not 0 <= int(instances) <= MAX_INSTANCES:
        raise InputError(f"instances must be 0 to {MAX_INSTANCES}, got {instances}")
    if not 0 <= int(distractors) <= MAX_DISTRACTORS:
        raise InputError(f"distractors must be 0 to {MAX_DISTRACTORS}, got {distractors}")
    if int(frames) < 1:
        raise InputError(f"frames must be at least 1, got {frames}")
    if not 0.0 <= float(size_error) <= MAX_SIZE_ERROR:
        raise InputError(f"size error must be 0 to {MAX_SIZE_ERROR} (a share of each side), got {size_error}")
    nominal = target
    if size_error > 0:
        target = scaled(target, 1.0 + np.random.default_rng([int(seed), 30]).uniform(-size_error, size_error, 3))
    rng_choose, rng_place, rng_path = (np.random.default_rng([int(seed), 20 + k]) for k in range(3))
    if preset == "flush" and int(instances) > 0:
        placements = _flush_placements(target, int(instances), rng_place)
        poses = overhead_trajectory(placements, int(frames), rng_path)
    elif preset in ("pallet", "flush"):
        placements = _pallet_placements(target, int(instances), int(distractors), rng_place)
        poses = overhead_trajectory(placements, int(frames), rng_path)
    else:
        pool = [get_object(n) for n in TABLE_DISTRACTORS if n != target.name]
        specs = [pool[int(i)] for i in rng_choose.integers(len(pool), size=int(distractors))]
        # Free or touching only: stacking on (or leaning against) a bracket's box would float.
        placements = place_objects(target, max(int(instances), 0), specs, rng_place,
                                   arrangement_probs=(0.7, 0.3, 0.0, 0.0))
        poses = sweep_trajectory(placements, int(frames), rng_path)
    return SyntheticScene("scene", nominal, placements, poses, d455_intrinsics(resolution), int(seed))


def _pallet_placements(carton, instances: int, distractors: int, rng) -> list[Placement]:
    """The pallet (a distractor) and, on it, ``instances`` cartons in a 3 x 3 grid per layer
    (the first layer filled first, the rest on top of first-layer cartons); with no cartons,
    ``distractors`` other boxes on the pallet instead."""
    pallet, pallet_pose, placements = _pallet_on_the_floor(rng)
    top = pallet.dimensions_m[2]
    if instances == 0:
        names = [PALLET_DISTRACTORS[int(i)] for i in rng.integers(len(PALLET_DISTRACTORS), size=max(distractors, 1))]
        slots = rng.permutation(PALLET_GRID[0] * PALLET_GRID[1])
        for j, name in enumerate(names[:len(slots)]):
            spec = get_object(name)
            centre = _slot_centre(pallet, int(slots[j]), rng)
            pose = pallet_pose @ make_transform(_rot_z(rng.uniform(-0.3, 0.3) + np.pi / 2 * int(rng.integers(2))),
                                                [centre[0], centre[1], 0.0])
            pose[2, 3] = top + spec.dimensions_m[2] / 2
            placements.append(Placement(spec, pose, _DISTRACTOR_LABEL0 + 1 + j, "free"))
        return placements
    n_slots = PALLET_GRID[0] * PALLET_GRID[1]
    first = min(instances, n_slots)
    second = min(instances - first, n_slots)
    if first == n_slots and second == 0 and instances < 2 * n_slots:
        first, second = n_slots - 1, 1       # a full flat layer shows no sides at all: leave a gap
    slots = rng.permutation(n_slots)[:first]
    label = 0
    h = carton.dimensions_m[2]
    layer1 = []
    for slot in slots:
        c = _slot_centre(pallet, int(slot), rng)
        pose = pallet_pose @ make_transform(_rot_z(rng.uniform(-0.06, 0.06) + np.pi * int(rng.integers(2))),
                                            [c[0], c[1], 0.0])
        pose[2, 3] = top + h / 2
        placements.append(Placement(carton, pose, label, "free"))
        layer1.append(pose)
        label += 1
    for k in rng.permutation(len(layer1))[:second]:
        below = layer1[int(k)]
        shift = rng.uniform(-0.02, 0.02, size=2)
        pose = below @ make_transform(_rot_z(rng.uniform(-0.05, 0.05) + np.pi * int(rng.integers(2))),
                                      [shift[0], shift[1], h + 0.001])
        placements.append(Placement(carton, pose, label, "stacked"))
        label += 1
    return placements


def _pallet_on_the_floor(rng):
    """The pallet (a distractor), turned up to 0.2 rad about the vertical: (spec, pose,
    [its placement])."""
    pallet = get_object("pallet")
    pallet_pose = make_transform(_rot_z(rng.uniform(-0.2, 0.2)), [0.0, 0.0, pallet.dimensions_m[2] / 2])
    return pallet, pallet_pose, [Placement(pallet, pallet_pose, _DISTRACTOR_LABEL0, "free")]


def _flush_placements(carton, instances: int, rng) -> list[Placement]:
    """The pallet and on it ``instances`` cartons packed flush in one layer: the pallet's
    area cut into a grid of the carton's footprint (long side along the pallet's), the
    cartons in a random subset of its slots, each a hairline (FLUSH_GAP_M) from its
    neighbours' slots, its top up to FLUSH_STEP_M off theirs and tilted up to FLUSH_TILT_RAD."""
    pallet, pallet_pose, placements = _pallet_on_the_floor(rng)
    (px, py), (cx, cy, h) = pallet.dimensions_m[:2], carton.dimensions_m
    nx, ny = int(round(px / cx)), int(round(py / cy))        # the load may overhang by its gaps
    slots = rng.permutation(nx * ny)[:min(instances, nx * ny)]
    gaps_x, gaps_y = rng.uniform(*FLUSH_GAP_M, size=nx), rng.uniform(*FLUSH_GAP_M, size=ny)
    xs = np.cumsum(np.r_[0.0, cx + gaps_x[:-1]])
    ys = np.cumsum(np.r_[0.0, cy + gaps_y[:-1]])
    xs, ys = xs - xs.mean(), ys - ys.mean()
    for label, slot in enumerate(slots):
        tilt = rng.uniform(-FLUSH_TILT_RAD, FLUSH_TILT_RAD, size=2)
        R = _rot_z(np.pi * int(rng.integers(2))) @ Rotation.from_rotvec([tilt[0], tilt[1], 0.0]).as_matrix()
        pose = pallet_pose @ make_transform(R, [xs[slot % nx], ys[slot // nx], 0.0])
        lift = 0.5 * (abs(np.sin(tilt[1])) * cx + abs(np.sin(tilt[0])) * cy)      # the tilt's low corner on the pallet
        pose[2, 3] = pallet.dimensions_m[2] + h / 2 + lift + rng.uniform(0.0, FLUSH_STEP_M)
        placements.append(Placement(carton, pose, label, "flush"))
    return placements


def _slot_centre(pallet, slot: int, rng) -> np.ndarray:
    """Centre (x, y) in the pallet frame of grid slot ``slot``, jittered by up to 2 cm."""
    nx, ny = PALLET_GRID
    ix, iy = slot % nx, slot // nx
    px, py = pallet.dimensions_m[0], pallet.dimensions_m[1]
    x = (ix + 0.5) / nx * px - px / 2
    y = (iy + 0.5) / ny * py - py / 2
    return np.array([x, y]) + rng.uniform(-0.02, 0.02, size=2)


def generate_untextured_bag(out_path, preset: str, instances: int = 8, distractors: int = 3, frames: int = 30,
                            seed: int = 0, storage: str = "sqlite3", resolution: str = "640x480",
                            preview_dir=None, mesh_path=None, mesh_units: str = "m",
                            depth_noise_correlation_px: float = 0.0, transport: str = "raw", imu: bool = True,
                            sensor: str = "d455", randomise: bool = False, bop_dir=None, bop_scene: int | None = None,
                            size_error: float = 0.0):
    """Make an untextured scene and write it as a rosbag2; with ``mesh_path`` also the
    target object's mesh (.ply, .stl or .obj) in its object frame. ``depth_noise_correlation_px``:
    see ``sensor.simulate_depth``. ``imu``: with the accelerometer's samples; ``bop_dir``: also
    as a BOP scene (both: ``write_scene_bag``). ``sensor``, ``randomise``: the depth's sensor
    profile (``SyntheticScene.set_sensor``); ``size_error``: see ``make_untextured_scene``."""
    from ..meshes import save_mesh
    from .objects import object_mesh
    from .scene import write_scene_bag

    from ..meshes import MESH_SUFFIXES
    from pathlib import Path

    if mesh_path is not None and Path(mesh_path).suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"mesh file {mesh_path}: unknown format; use .ply, .stl or .obj")
    scene = make_untextured_scene(preset, instances, distractors, frames, seed, resolution, size_error)
    scene.set_depth_noise_correlation(depth_noise_correlation_px)
    scene.set_sensor(sensor, randomise)
    summary = write_scene_bag(scene, out_path, storage, preview_dir, transport=transport, imu=imu,
                              bop_dir=bop_dir, bop_scene=bop_scene)
    if mesh_path is not None:
        save_mesh(object_mesh(scene.target), mesh_path, mesh_units)
    return summary


__all__ = ["PRESETS", "BENCH_ALL", "make_untextured_scene", "generate_untextured_bag", "overhead_trajectory", "preset_object",
           "UNTEXTURED_OBJECTS"]
