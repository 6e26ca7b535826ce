"""``mireg synth``: make synthetic D455 tabletop recordings with ground truth.

    mireg synth scene -o OUT [--object NAME [--object NAME2 ...]] [--instances K] [--distractors D] [--frames F]
                      [--layout table|flush|bin] [--background wall|clutter] [--sensor d455|realistic] [--randomise]
                      [--motion sweep|static|pan|shaky_pan|jumps|overhead] [--frame-rate HZ] [--drop SHARE] [--loop]
                      [--occluder] [--unaligned | --viewer-bag]
                      [--seed S] [--storage sqlite3|mcap] [--image-transport raw|compressed]
                      [--resolution 640x480|1280x720] [--preview DIR] [--bop DIR [--bop-scene ID]]
    mireg synth capture -o OUT --object NAME [--seed S] [--views N] [...]
    mireg synth untextured -o OUT --preset pallet|flush|cylinders|bracket|channel|stairs|tee [--instances K] [--distractors D]
                      [--frames F] [--seed S] [--mesh FILE.ply|.stl|.obj [--units m|mm]]
    mireg synth mesh --object NAME -o FILE.ply|.stl|.obj [--units m|mm]
"""
from __future__ import annotations

HELP = "make synthetic D455 tabletop bags with ground truth (scene, capture, untextured) and object meshes"


def add_arguments(parser) -> None:
    from ..datasets.bag_writer import TRANSPORTS
    from ..synthetic.objects import DEFAULT_OBJECT, OBJECTS, UNTEXTURED_OBJECTS
    from ..synthetic.scene import (BACKGROUNDS, FRAME_RATE_HZ, LAYOUTS, MAX_DROP, MOTIONS, PAN_SECONDS,
                                   SHAKY_ARC_DEG)
    from ..synthetic.sensor import RESOLUTIONS, SENSOR_PROFILES
    from ..synthetic.untextured import PRESETS

    sub = parser.add_subparsers(dest="synth_command", metavar="{scene,capture,untextured,mesh}", required=True)
    objects = ", ".join(f"{name} ({spec.shape} {'x'.join(f'{d:g}' for d in spec.dimensions_m)} m)"
                        for name, spec in OBJECTS.items())

    def image_transport(p):
        p.add_argument("--image-transport", choices=TRANSPORTS, default="raw",
                       help="raw: sensor_msgs/Image on the realsense-ros topics (default); compressed: as image_transport's "
                            "compressed topics, colour JPEG on .../image_raw/compressed, depth PNG on .../image_raw/compressedDepth")

    def common(p, object_required: bool):
        p.add_argument("-o", "--output", required=True, help="bag directory to create (must not exist)")
        if object_required:
            p.add_argument("--object", required=True, metavar="NAME", help=f"object to scan: {objects}")
        else:
            p.add_argument("--object", action="append", default=None, metavar="NAME",
                           help=f"object of which K identical instances are placed (default {DEFAULT_OBJECT}); give it "
                                f"again for a mixed scene (K of each, ground truth naming each instance's object): {objects}")
        p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same bag (default 0)")
        p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="rosbag2 storage (default sqlite3)")
        image_transport(p)
        no_imu(p)
        bop(p)
        p.add_argument("--resolution", choices=RESOLUTIONS, default="640x480", help="colour/depth size (default 640x480)")
        p.add_argument("--preview", metavar="DIR", default=None,
                       help="also write PNGs of a few frames: colour, colourised depth, ground-truth boxes")

    def bop(p):
        p.add_argument("--bop", metavar="DIR", default=None,
                       help="also write the frames as a BOP dataset in DIR (camera.json, models/ from the objects' meshes "
                            "in mm, test/<scene>/ with ground truth), for BOP tools and `mireg bop`; DIR may hold "
                            "other scenes (object ids are the catalogue's)")
        p.add_argument("--bop-scene", type=int, default=None, metavar="ID",
                       help="BOP scene id of the frames (default: the seed)")

    def no_imu(p):
        p.add_argument("--no-imu", action="store_true",
                       help="leave out the accelerometer (default: sensor_msgs/Imu at 200 Hz on /camera/camera/accel/sample, "
                            "as realsense-ros with enable_accel:=true: gravity and the camera's motion, with noise and bias)")

    def sensor(p):
        p.add_argument("--sensor", choices=tuple(SENSOR_PROFILES), default="d455",
                       help="depth sensor profile: d455 = the model the project was tuned on (default); realistic = "
                            "noise 0.004 z^2 + 0.5 mm, 70 %% of depth-edge pixels dropped and half the rest between "
                            "foreground and background (flying pixels), 1.5 %% single-pixel dropouts, depth in "
                            "disparity steps (a few mm at 1-2 m)")
        p.add_argument("--randomise", action="store_true",
                       help="draw each figure of the sensor profile per seed from a range around the realistic one")

    def depth_noise(p):
        p.add_argument("--depth-noise-correlation", type=float, default=0.0, metavar="PX",
                       help="depth noise shared by neighbouring pixels over about PX pixels, as a stereo "
                            "matcher's window makes it (the same noise per pixel; default 0: independent per pixel)")

    scene = sub.add_parser("scene", help="K identical objects plus distractors, seen at 30 Hz by a moving or still camera",
                           description="K identical instances of an object and D distractors on a table, "
                                       "seen by a D455 at 30 Hz (hand-held sweep, tripod or slow pan, "
                                       "optionally with an arm passing in front); written as a rosbag2 "
                                       "with ground-truth poses.")
    common(scene, object_required=False)
    scene.add_argument("--instances", type=int, default=6, metavar="K",
                       help="instances of each object, 1-20 in all (default 6)")
    scene.add_argument("--distractors", type=int, default=3, metavar="D", help="other objects, 0-20 (default 3)")
    scene.add_argument("--frames", type=int, default=60, metavar="F",
                       help="frames of the camera path at --frame-rate (default 60); --loop writes them twice, "
                            "--drop leaves some out")
    scene.add_argument("--motion", choices=MOTIONS, default="sweep",
                       help="camera path: sweep = hand-held, swinging over the table (default); static = "
                            "fixed on a tripod, only the sensor noise changes (pose jitter); pan = slow "
                            f"hand-held pan along the table, 0.45-0.7 m in {PAN_SECONDS:g} s and back, objects "
                            "spread along it so that instances enter and leave the view; shaky_pan = hand-held, "
                            f"a {SHAKY_ARC_DEG:g} deg arc about the objects in {PAN_SECONDS:g} s (and back) with "
                            "shake that is new every frame (2.5-3.5 mm, 0.3-0.5 deg mean frame-to-frame); jumps = "
                            "on a robot arm moving in bursts, 3-8 deg per 1/30 s, still in between; overhead = "
                            "from above, tilted 5-30 deg, drifting slowly (0.7-1 m; 0.55-0.75 m over a bin)")
    scene.add_argument("--layout", choices=LAYOUTS, default="table",
                       help="how the objects lie: table = free, touching, stacked or leaning (default); flush = boxes "
                            "packed face to face with no gap, all lying the same way (their tops one plane: outlines "
                            "only in colour; with --motion overhead: a pallet seen from above); bin = dropped at random "
                            "orientations into an open bin (all objects, distractors too)")
    scene.add_argument("--background", choices=BACKGROUNDS, default="wall",
                       help="behind the table: wall = a brick wall just behind the objects (default); clutter = the "
                            "table ends there and a room lies 2-3 m behind it: floor, furniture, a brick wall")
    scene.add_argument("--frame-rate", type=float, default=FRAME_RATE_HZ, metavar="HZ",
                       help=f"frames per second, 1-90 (default {FRAME_RATE_HZ:g}; a recorded bag is often throttled to "
                            "5-15): stamps 1/HZ apart, the camera moving as far per frame as the time lets it")
    scene.add_argument("--drop", type=float, default=0.0, metavar="SHARE",
                       help=f"leave out this share of the frames (0-{MAX_DROP:g}) in runs of 1-3: gaps in the stamps "
                            "while the camera moves on (default 0)")
    scene.add_argument("--loop", action="store_true",
                       help="write the frames twice, the second time with the same stamps (they jump back once, "
                            "as a bag played with --loop does); bag time runs on")
    depth_noise(scene)
    sensor(scene)
    scene.add_argument("--occluder", action="store_true",
                       help="an arm (a distractor, not in the ground truth) passes between the camera and "
                            "the table from about 1/3 to 2/3 of the frames, hiding instances for a few "
                            "frames each (needs at least 3 frames)")
    recording = scene.add_mutually_exclusive_group()
    recording.add_argument("--unaligned", action="store_true",
                           help="record depth as the depth imager sees it, as realsense-ros does without "
                                "align_depth.enable: /camera/camera/depth/image_rect_raw (848x480, its own "
                                "camera_info) and /camera/camera/extrinsics/depth_to_color (colour 15 mm along x)")
    recording.add_argument("--viewer-bag", action="store_true",
                           help="write a RealSense Viewer recording instead of a rosbag2: a ROS 1 .bag file at "
                                "OUTPUT (/device_0/sensor_0/Depth_0/..., /device_0/sensor_1/Color_0/..., depth "
                                "unaligned as with --unaligned), ground truth on the usual topics; no IMU")

    capture = sub.add_parser("capture", help="the object alone, seen from viewpoints around it (to build a model)",
                             description="The object alone on the table, seen from a few viewpoints around it, "
                                         "the way a user scans it to build the stored model.")
    common(capture, object_required=True)
    capture.add_argument("--views", type=int, default=10, metavar="N", help="viewpoints, 3-100 (default 10)")

    untextured = sub.add_parser(
        "untextured", help="objects without texture: cartons on a pallet from above, cylinders or brackets on a table",
        description="Flat-coloured objects with ground truth: " + "; ".join(
            f"{k}: {v}" for k, v in {"pallet": "cartons in one or two layers on a pallet, seen from above at 1.2-2 m "
                                                "(--instances 0: other boxes only)",
                                      "flush": "the same cartons packed flush in one layer on the pallet, hairline "
                                               "gaps, taped tops, worn dark edges",
                                      "cylinders": "grey cylinders and plain distractors on a table, 0.5-1 m",
                                      "bracket": "L-shaped brackets and plain distractors on a table, 0.5-1 m",
                                      "channel, stairs, tee": "U channels, blocks of three steps or T profiles, "
                                                              "the same way"}.items()))
    untextured.add_argument("-o", "--output", required=True, help="bag directory to create (must not exist)")
    untextured.add_argument("--preset", choices=tuple(PRESETS), required=True, help="which scene")
    untextured.add_argument("--instances", type=int, default=8, metavar="K", help="instances of the object, 0-20 (default 8)")
    untextured.add_argument("--distractors", type=int, default=3, metavar="D", help="other objects, 0-20 (default 3)")
    untextured.add_argument("--frames", type=int, default=30, metavar="F", help="frames at 30 Hz (default 30)")
    untextured.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    untextured.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="rosbag2 storage (default sqlite3)")
    image_transport(untextured)
    no_imu(untextured)
    bop(untextured)
    untextured.add_argument("--resolution", choices=RESOLUTIONS, default="640x480", help="colour/depth size (default 640x480)")
    untextured.add_argument("--preview", metavar="DIR", default=None, help="also write PNGs of a few frames")
    depth_noise(untextured)
    sensor(untextured)
    untextured.add_argument("--mesh", metavar="FILE", default=None,
                            help="also write the object's mesh (.ply, .stl or .obj; object frame of the ground truth)")
    untextured.add_argument("--units", choices=("m", "mm"), default="m", help="units of the written mesh (default m)")
    untextured.add_argument("--size-error", type=float, default=0.0, metavar="SHARE",
                            help="the objects are not the size of their mesh: all of them larger or smaller along "
                                 "each axis by a share drawn per seed within +-SHARE (0.03: a carton 9 mm off on "
                                 "30 cm, as one measured by hand); the ground truth and --mesh stay the nominal "
                                 "object's (default 0: the mesh's size)")

    mesh = sub.add_parser("mesh", help="write a catalogue object's mesh (PLY, STL or OBJ)",
                          description="The surface of a catalogue object as a triangle mesh in its object frame "
                                      "(the frame of the bags' ground truth); a textured box as PLY comes with its "
                                      "pictures (a texture beside it), as the renders show it.")
    mesh.add_argument("--object", required=True, metavar="NAME",
                      help="one of: " + ", ".join(list(OBJECTS) + list(UNTEXTURED_OBJECTS)))
    mesh.add_argument("-o", "--output", required=True, help="mesh file to write (.ply, .stl or .obj)")
    mesh.add_argument("--units", choices=("m", "mm"), default="m", help="units of the coordinates (default m)")


def run(args) -> int:
    from ..synthetic.objects import DEFAULT_OBJECT
    from ..synthetic.scene import generate_capture_bag, generate_scene_bag

    if args.synth_command == "mesh":
        from ..meshes import save_mesh
        from ..synthetic.objects import get_object, textured_object_mesh

        mesh = textured_object_mesh(get_object(args.object))
        path = save_mesh(mesh, args.output, args.units)
        textured = mesh.texture is not None and path.suffix.lower() == ".ply"
        print(f"mireg synth mesh: wrote {args.object} ({len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles, "
              f"{args.units}) to {args.output}" + (f" with its texture {path.stem}_texture.png" if textured else ""))
        return 0
    if args.synth_command == "untextured":
        from ..synthetic.untextured import generate_untextured_bag

        summary = generate_untextured_bag(args.output, args.preset, args.instances, args.distractors, args.frames,
                                          args.seed, args.storage, args.resolution, args.preview, args.mesh, args.units,
                                          args.depth_noise_correlation, args.image_transport, imu=not args.no_imu,
                                          sensor=args.sensor, randomise=args.randomise,
                                          bop_dir=args.bop, bop_scene=args.bop_scene, size_error=args.size_error)
        print(f"mireg synth untextured: {summary.line()}" + (f"; mesh {args.mesh}" if args.mesh else "")
              + (f"; BOP scene in {args.bop}" if args.bop else ""))
        return 0
    if args.synth_command == "scene":
        from ..errors import InputError

        objects = args.object or [DEFAULT_OBJECT]
        if args.viewer_bag and (args.loop or args.image_transport != "raw" or args.storage != "sqlite3"):
            raise InputError("--viewer-bag writes a ROS 1 .bag as the RealSense Viewer does: it takes no --loop, "
                             "--image-transport or --storage")
        summary = generate_scene_bag(args.output, object_name=objects[0] if len(objects) == 1 else objects,
                                     instances=args.instances,
                                     distractors=args.distractors, frames=args.frames, seed=args.seed,
                                     storage=args.storage, resolution=args.resolution, preview_dir=args.preview,
                                     motion=args.motion, occluder=args.occluder,
                                     depth_noise_correlation_px=args.depth_noise_correlation,
                                     transport=args.image_transport, imu=not args.no_imu,
                                     frame_rate=args.frame_rate, drop=args.drop, loop=args.loop,
                                     sensor=args.sensor, randomise=args.randomise, layout=args.layout,
                                     background=args.background, bop_dir=args.bop, bop_scene=args.bop_scene,
                                     recording="viewer" if args.viewer_bag else
                                     "unaligned" if args.unaligned else "aligned")
    else:
        summary = generate_capture_bag(args.output, object_name=args.object, seed=args.seed, views=args.views,
                                       storage=args.storage, resolution=args.resolution, preview_dir=args.preview,
                                       transport=args.image_transport, imu=not args.no_imu,
                                       bop_dir=args.bop, bop_scene=args.bop_scene)
    print(f"mireg synth {args.synth_command}: {summary.line()}" + (f"; BOP scene in {args.bop}" if args.bop else ""))
    return 0
