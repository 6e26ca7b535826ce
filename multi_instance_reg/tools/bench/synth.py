"""``mireg bench synth``: how fast the synthetic D455 generator makes bags (frames/s).

Times the whole path a test or the demo pays for: render, sensor noise, serialisation and
writing the rosbag2, for the default scene (6 instances, 3 distractors) at each resolution,
or for a tracking scene (``--motion``, ``--occluder``).
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

HELP = "frames/s of `mireg synth scene` (render + noise + bag writing) at 640x480 and 1280x720"


def add_arguments(parser) -> None:
    from ...synthetic.scene import MOTIONS

    parser.add_argument("--frames", type=int, default=60, help="frames per run (default 60)")
    parser.add_argument("--resolutions", nargs="+", default=["640x480", "1280x720"],
                        help="resolutions to time (default 640x480 1280x720)")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--motion", choices=MOTIONS, default="sweep",
                        help="camera path of the timed scene (default sweep, see `mireg synth scene --help`)")
    parser.add_argument("--occluder", action="store_true", help="time the scene with an arm passing in front")


def run(args) -> int:
    from ...errors import InputError
    from ...synthetic.scene import make_tabletop_scene, write_scene_bag

    if args.frames < 1:
        raise InputError(f"--frames must be at least 1, got {args.frames}")
    extra = "" if args.motion == "sweep" and not args.occluder else \
        f", motion {args.motion}{' with occluder' if args.occluder else ''}"
    print(f"mireg bench synth: default scene (snack_box x6, 3 distractors){extra}, {args.frames} frames, "
          f"{args.storage}, seed {args.seed}")
    print(f"{'resolution':>10}  {'bag frames/s':>12}  {'render+noise frames/s':>21}  {'CPU s/frame':>11}")
    for res in args.resolutions:
        scene = make_tabletop_scene(frames=args.frames, seed=args.seed, resolution=res, motion=args.motion,
                                    occluder=args.occluder)
        scene.render_frame(0)                       # warm the texture caches
        t0 = time.perf_counter()
        c0 = time.process_time()
        for i in range(scene.num_frames):
            scene.render_frame(i)
        render_fps = scene.num_frames / (time.perf_counter() - t0)
        cpu = (time.process_time() - c0) / scene.num_frames
        with tempfile.TemporaryDirectory() as tmp:
            summary = write_scene_bag(scene, Path(tmp) / "bag", storage=args.storage)
        print(f"{res:>10}  {summary.fps:12.1f}  {render_fps:21.1f}  {cpu:11.3f}")
    return 0
