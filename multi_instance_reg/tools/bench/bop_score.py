"""``mireg bench bop-score``: what BOP scoring (``evaluation``) costs per image.

Writes a small BOP dataset in a temporary folder: images of ``--instances`` copies of one
mesh at random poses 0.55-0.85 m in front of a 640x480 camera (IC-BIN's intrinsics), depth
rendered by the scorer's own rasteriser, visib_fract from it; results = every instance with
a small pose error (``--noise-mm``, ``--noise-deg``) plus ``--wrong`` estimates per image at
random poses; then scores them as ``mireg bop score`` does and prints seconds per image by
step. The mesh: ``--mesh`` (a PLY/STL/OBJ in mm; its symmetries from the models_info.json
beside it when it is a BOP ``models/obj_NNNNNN.ply``) or the default box 10 x 6 x 4 cm
(180 deg flips about its axes).
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "seconds per image of BOP scoring (VSD, MSSD, MSPD, MHF1) on a generated BOP dataset of one mesh"

K_ICBIN = np.array([[550.0, 0, 316.0], [0, 540.0, 244.0], [0, 0, 1]])
WIDTH, HEIGHT = 640, 480


def add_arguments(parser) -> None:
    parser.add_argument("--mesh", default=None, help="mesh in mm (default: a 10 x 6 x 4 cm box)")
    parser.add_argument("--instances", type=int, default=8, help="instances per image (default 8)")
    parser.add_argument("--images", type=int, default=3, help="images (default 3)")
    parser.add_argument("--wrong", type=int, default=2, help="extra wrong estimates per image (default 2)")
    parser.add_argument("--noise-mm", type=float, default=2.0, help="translation error of the estimates (default 2)")
    parser.add_argument("--noise-deg", type=float, default=1.0, help="rotation error of the estimates (default 1)")
    parser.add_argument("--seed", type=int, default=0)


def _mesh_and_symmetries(path):
    from ...datasets.bop import read_models_info
    from ...meshes import box_mesh, load_mesh
    from ...symmetry import parse_symmetry_text

    if path is None:
        return "box 10x6x4 cm", box_mesh(0.10, 0.06, 0.04), parse_symmetry_text("x:2,y:2", np.zeros(3))
    path = Path(path)
    mesh = load_mesh(path, "mm")
    info_path = path.parent / "models_info.json"
    sym = None
    if info_path.is_file() and path.stem.startswith("obj_"):
        info = read_models_info(info_path).get(int(path.stem[4:]))
        sym = None if info is None else info.symmetries()
    return path.name, mesh, sym


def _random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _small_turn(rng, deg: float) -> np.ndarray:
    from ...symmetry import turn_about

    return turn_about(rng.normal(size=3), np.zeros(3), np.radians(deg))[:3, :3]


def make_dataset(root: Path, mesh, sym, instances: int, images: int, wrong: int, noise_mm: float, noise_deg: float,
                 seed: int) -> list:
    """Write the dataset to ``root``; return its results rows (``BopEstimate``)."""
    from ...datasets.bop import BopEstimate, BopWriter, gt_info_from_mask
    from ...evaluation.render import render_scene

    rng = np.random.default_rng(seed)
    writer = BopWriter(root, "test")
    writer.add_model(1, mesh, sym)
    rows = []
    targets = []
    with writer.scene(1) as scene:
        for im in range(images):
            poses = []
            for _ in range(instances):
                T = np.eye(4)
                T[:3, :3] = _random_rotation(rng)
                z = rng.uniform(0.55, 0.85)
                T[:3, 3] = [rng.uniform(-0.18, 0.18) * z / 0.7, rng.uniform(-0.13, 0.13) * z / 0.7, z]
                poses.append(T)
            depth, fractions, masks = render_scene([mesh] * instances, poses, K_ICBIN, WIDTH, HEIGHT)
            depth_mm = np.round(depth * 1000).astype(np.uint16)
            scene.add_image(im, np.zeros((HEIGHT, WIDTH, 3), np.uint8), depth_mm, K_ICBIN,
                            gt=[(1, T) for T in poses],
                            gt_info=[gt_info_from_mask(m, depth_mm, f) for m, f in zip(masks, fractions)])
            targets.append({"scene_id": 1, "im_id": im, "obj_id": 1, "inst_count": int((fractions >= 0.1).sum())})
            for T in poses:
                E = T.copy()
                E[:3, :3] = _small_turn(rng, noise_deg) @ T[:3, :3]
                E[:3, 3] += rng.normal(size=3) * noise_mm / 1000.0 / np.sqrt(3)
                rows.append(BopEstimate.from_pose(1, im, 1, rng.uniform(0.5, 1.0), E, 0.1))
            for _ in range(wrong):
                E = np.eye(4)
                E[:3, :3] = _random_rotation(rng)
                E[:3, 3] = [rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), rng.uniform(0.55, 0.85)]
                rows.append(BopEstimate.from_pose(1, im, 1, rng.uniform(0.0, 1.0), E, 0.1))
    (root / "test_targets_bop19.json").write_text(json.dumps(targets))
    return rows


def run(args) -> int:
    from ...datasets.bop import BopDataset
    from ...errors import InputError
    from ...evaluation.bop_scoring import BopScorer

    if args.instances < 1 or args.images < 1 or args.wrong < 0:
        raise InputError("--instances and --images must be at least 1, --wrong at least 0")
    name, mesh, sym = _mesh_and_symmetries(args.mesh)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        rows = make_dataset(Path(tmp) / "bench", mesh, sym, args.instances, args.images, args.wrong,
                            args.noise_mm, args.noise_deg, args.seed)
        made = time.perf_counter() - t
        scorer = BopScorer(BopDataset(Path(tmp) / "bench", "test"))
        scorer.model(1)                       # the mesh read once per run, not per image
        cpu = time.process_time()
        report = scorer.score(rows)
        cpu = time.process_time() - cpu       # CPU time: less swayed than wall time by other jobs
    steps = report["scoring_seconds_by_step"]
    n = max(1, report["images"])
    print(f"mireg bench bop-score: {name} ({len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles, "
          f"{'symmetries: ' + sym.describe() if sym is not None else 'no symmetries'}), {args.images} images x "
          f"{args.instances} instances + {args.wrong} wrong estimates, 640x480 (dataset written in {made:.1f} s)")
    print(f"  model load (once): {steps['models']:.2f} s; per image: "
          + ", ".join(f"{k} {1000 * steps[k] / n:.0f} ms" for k in ("read", "render", "vsd", "mssd", "mspd", "mh"))
          + f"; total {1000 * sum(v for k, v in steps.items() if k != 'models') / n:.0f} ms "
          f"(CPU {1000 * cpu / n:.0f} ms)")
    print(f"  AR {report['AR']:.3f} (VSD {report['AR_VSD']:.3f}, MSSD {report['AR_MSSD']:.3f}, MSPD "
          f"{report['AR_MSPD']:.3f}); MHR {report['MHR']:.3f} MHP {report['MHP']:.3f} MHF1 {report['MHF1']:.3f}; "
          f"{report['instances']} instances counted, {report['estimates_evaluated']} estimates evaluated")
    return 0
