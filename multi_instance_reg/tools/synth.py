"""``mireg synth``: make synthetic D455 tabletop recordings with ground truth.

    mireg synth scene -o OUT [--object NAME] [--instances K] [--distractors D] [--frames F]
                      [--motion sweep|static|pan] [--occluder]
                      [--seed S] [--storage sqlite3|mcap] [--resolution 640x480|1280x720]
                      [--preview DIR]
    mireg synth capture -o OUT --object NAME [--seed S] [--views N] [...]
"""
from __future__ import annotations

HELP = "make synthetic D455 tabletop bags with ground truth (scene, capture)"


def add_arguments(parser) -> None:
    from ..synthetic.objects import DEFAULT_OBJECT, OBJECTS
    from ..synthetic.scene import MOTIONS, PAN_SECONDS
    from ..synthetic.sensor import RESOLUTIONS

    sub = parser.add_subparsers(dest="synth_command", metavar="{scene,capture}", required=True)
    objects = ", ".join(f"{name} ({spec.shape} {'x'.join(f'{d:g}' for d in spec.dimensions_m)} m)"
                        for name, spec in OBJECTS.items())

    def common(p, object_required: bool):
        p.add_argument("-o", "--output", required=True, help="bag directory to create (must not exist)")
        if object_required:
            p.add_argument("--object", required=True, metavar="NAME", help=f"object to scan: {objects}")
        else:
            p.add_argument("--object", default=DEFAULT_OBJECT, metavar="NAME",
                           help=f"object of which K identical instances are placed (default {DEFAULT_OBJECT}): {objects}")
        p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same bag (default 0)")
        p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="rosbag2 storage (default sqlite3)")
        p.add_argument("--resolution", choices=RESOLUTIONS, default="640x480", help="colour/depth size (default 640x480)")
        p.add_argument("--preview", metavar="DIR", default=None,
                       help="also write PNGs of a few frames: colour, colourised depth, ground-truth boxes")

    scene = sub.add_parser("scene", help="K identical objects plus distractors, seen at 30 Hz by a moving or still camera",
                           description="K identical instances of an object and D distractors on a table, "
                                       "seen by a D455 at 30 Hz (hand-held sweep, tripod or slow pan, "
                                       "optionally with an arm passing in front); written as a rosbag2 "
                                       "with ground-truth poses.")
    common(scene, object_required=False)
    scene.add_argument("--instances", type=int, default=6, metavar="K", help="instances of the object, 1-20 (default 6)")
    scene.add_argument("--distractors", type=int, default=3, metavar="D", help="other objects, 0-20 (default 3)")
    scene.add_argument("--frames", type=int, default=60, metavar="F", help="frames at 30 Hz (default 60)")
    scene.add_argument("--motion", choices=MOTIONS, default="sweep",
                       help="camera path: sweep = hand-held, swinging over the table (default); static = "
                            "fixed on a tripod, only the sensor noise changes (pose jitter); pan = slow "
                            f"hand-held pan along the table, 0.45-0.7 m in {PAN_SECONDS:g} s and back, objects "
                            "spread along it so that instances enter and leave the view")
    scene.add_argument("--occluder", action="store_true",
                       help="an arm (a distractor, not in the ground truth) passes between the camera and "
                            "the table from about 1/3 to 2/3 of the frames, hiding instances for a few "
                            "frames each (needs at least 3 frames)")

    capture = sub.add_parser("capture", help="the object alone, seen from viewpoints around it (to build a model)",
                             description="The object alone on the table, seen from a few viewpoints around it, "
                                         "the way a user scans it to build the stored model.")
    common(capture, object_required=True)
    capture.add_argument("--views", type=int, default=10, metavar="N", help="viewpoints, 3-100 (default 10)")


def run(args) -> int:
    from ..synthetic.scene import generate_capture_bag, generate_scene_bag

    if args.synth_command == "scene":
        summary = generate_scene_bag(args.output, object_name=args.object, instances=args.instances,
                                     distractors=args.distractors, frames=args.frames, seed=args.seed,
                                     storage=args.storage, resolution=args.resolution, preview_dir=args.preview,
                                     motion=args.motion, occluder=args.occluder)
    else:
        summary = generate_capture_bag(args.output, object_name=args.object, seed=args.seed, views=args.views,
                                       storage=args.storage, resolution=args.resolution, preview_dir=args.preview)
    print(f"mireg synth {args.synth_command}: {summary.line()}")
    return 0
