"""``make demo``: the whole product in a few minutes, on synthetic data made on the spot.

1. renders capture bags of two objects (each alone: a snack box and a can) and a scene bag
   with instances of both, distractors and ground truth, and builds one model per object;
2. starts the ROS node with both models, a separate listener (``mireg listen``) and plays
   the scene into the node in real time (``mireg play``), all as real processes on a DDS
   domain of their own;
3. prints each frame's instances as they arrive, then MHF1 against the ground truth (per
   object and over both), the mean latency and the frames the node dropped; leaves overlays
   and a summary in ``out/demo/``.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from ..errors import InputError

HELP = "the end-to-end demo: synthetic bags, two models, node, live replay, MHF1 per object and latency"
REPO = Path(__file__).resolve().parents[2]
DOMAIN_ID = 87
MAX_DOMAIN_ID = 232
COLOUR, DEPTH, INFO = ("/camera/camera/color/image_raw", "/camera/camera/aligned_depth_to_color/image_raw",
                       "/camera/camera/color/camera_info")
DEMO_OBJECTS = ("snack_box", "can")
# Resting poses of the captures a model is built from: the can is round, one side is enough.
CAPTURE_SIDES = {"can": ("+z", "-z", "+y")}


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="where bags, model and results go")
    # 10 s at 15 Hz (a D455 mode): the detector's first result takes 0.3-1.5 s on a loaded two-core
    # host (its own figure) and then has time for some ten rounds; 3 s at 30 Hz left the figure
    # to the one or two detections a loaded host managed (86-91 %, or no pose at all).
    parser.add_argument("--frames", type=int, default=150, help="frames in the scene bag")
    parser.add_argument("--fps", type=float, default=15.0, help="frame rate of the scene bag (camera frames a second)")
    parser.add_argument("--instances", type=int, default=3, help="instances of each object in the scene")
    parser.add_argument("--object", dest="objects", action="append", metavar="NAME",
                        help=f"an object of the scene (give it again for each; default: {' and '.join(DEMO_OBJECTS)}); "
                             "see `mireg synth objects`")
    parser.add_argument("--rate", type=float, default=1.0, help="replay speed (1 = real time)")
    parser.add_argument("--domain-id", type=int, default=DOMAIN_ID, help="ROS_DOMAIN_ID for the demo's processes")
    parser.add_argument("--fresh", action="store_true", help="render the bags and build the model again")


def _say(text: str) -> None:
    print(f"\033[1m== {text}\033[0m" if sys.stdout.isatty() else f"== {text}", flush=True)


def prepare_data(out: Path, frames: int = 90, instances: int = 6, fresh: bool = False, quiet: bool = False,
                 objects=("snack_box",), fps: float = 30.0) -> dict:
    """Capture bags, scene bag and one model per object under ``out`` (reused if already
    there; another scene keeps the models). One object: ``instances`` of it; several:
    ``instances`` of each (a mixed scene)."""
    import shutil

    from ..models.model import save_model
    from ..synthetic.scene import generate_scene_bag
    from .bench.scenes import CAPTURE_POSES, generate_capture_bags, model_from_captures

    objects = list(objects)
    out.mkdir(parents=True, exist_ok=True)
    captures, scene = out / "captures", out / "scene"
    model_paths = [out / f"{name}.npz" for name in objects]
    marker = out / "data.json"
    wanted = {"frames": frames, "instances": instances, "objects": objects, "fps": fps}
    had = json.loads(marker.read_text()) if marker.exists() and not fresh else {}
    if had != wanted:
        shutil.rmtree(scene, ignore_errors=True)
        if had.get("objects") != objects:
            shutil.rmtree(captures, ignore_errors=True)
            for path in [*model_paths, out / "model.npz"]:   # (model.npz: the one model of earlier demos)
                path.unlink(missing_ok=True)
        marker.unlink(missing_ok=True)
    for name, model_path in zip(objects, model_paths):
        folder = captures / name
        sides = CAPTURE_SIDES.get(name, CAPTURE_POSES)
        if not folder.exists():
            quiet or _say(f"rendering {len(sides)} capture bags of the {name} (alone, resting on different "
                          "sides, several views each)")
            generate_capture_bags(folder, name, seed=0, views=8, poses=sides)
        if not model_path.exists():
            quiet or _say(f"building the {name} model from its capture bags")
            save_model(model_from_captures(sorted(p for p in folder.iterdir() if p.is_dir())), model_path)
    if not scene.exists():
        each = " of each" if len(objects) > 1 else ""
        quiet or _say(f"rendering the scene bag ({frames} frames at {fps:g} Hz, {instances} instances{each} of "
                      f"{' and '.join(objects)}, distractors)")
        generate_scene_bag(scene, objects if len(objects) > 1 else objects[0], instances=instances, distractors=3,
                           frames=frames, seed=1, frame_rate=fps)
    marker.write_text(json.dumps(wanted))
    return {"captures": captures, "scene_bag": scene, "models": model_paths, "model": model_paths[0]}


class _Process:
    """A child process whose output is echoed (optionally) and kept, line by line."""

    def __init__(self, name: str, args: list[str], env: dict, echo: bool, log: Path, own_session: bool = False):
        self.name, self.lines, self.echo = name, [], echo
        self.log = log.open("w")
        self.proc = subprocess.Popen([sys.executable, "-m", *args], env=env, cwd=REPO, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=own_session)
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self):
        for line in self.proc.stdout:
            self.lines.append(line)
            self.log.write(line)
            self.log.flush()
            if self.echo:
                print(f"  {line}", end="", flush=True)

    def wait_for_line(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in line for line in self.lines):
                return True
            if self.proc.poll() is not None:
                time.sleep(0.2)
                return any(text in line for line in self.lines)
            time.sleep(0.1)
        return False

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._thread.join(2)
        self.log.close()
        return self.proc.returncode


def run(args) -> int:
    started = time.monotonic()
    if not 0 <= args.domain_id <= MAX_DOMAIN_ID:
        # Above it Fast DDS computes no valid port and the node stops on a multi-line RTPS error.
        raise InputError(f"--domain-id must be 0 to {MAX_DOMAIN_ID} (the largest ROS_DOMAIN_ID Fast DDS can use), "
                         f"got {args.domain_id}")
    out = args.out
    objects = args.objects or list(DEMO_OBJECTS)
    data = prepare_data(out, args.frames, args.instances, args.fresh, objects=objects, fps=args.fps)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    params = REPO / "config" / "params.yaml"
    node_args = ["multi_instance_reg.ros.node", "--ros-args"]
    if params.exists():
        node_args += ["--params-file", str(params)]
    node_args += ["-p", f"model_paths:=[{', '.join(str(p) for p in data['models'])}]"]
    overlays = out / "overlays"
    summary_path = out / "summary.json"
    summary_path.unlink(missing_ok=True)

    _say("starting the node: " + " ".join(["instance_registration_node", *node_args[1:]]))
    # In a session of its own, as a service or a launch on a robot runs: with the kernel's
    # autogroups (the default of desktop kernels) the node and its niced detector then share
    # the CPU with the terminal's other jobs as one group; in the terminal's group a busy job
    # outweighed the detector 10:1 (detector_niceness) and the demo saw 0-1 detections in 10 s.
    node = _Process("node", node_args, env, echo=False, log=out / "node.log", own_session=True)
    listener = play = None
    try:
        if not node.wait_for_line("ready:", 300):   # a first run compiles its kernels, slow on a loaded host
            raise InputError("the node did not start; see " + str(out / "node.log") + ":\n" + "".join(node.lines[-5:]))
        _say("starting the listener (a separate process) and playing the scene into the node")
        listener = _Process("listen", [
            "multi_instance_reg.tools.cli", "listen", "--ground-truth", str(data["scene_bag"]),
            *[a for p in data["models"] for a in ("--model", str(p))],
            "--save-overlays", str(overlays), "--overlay-every", "3",
            "--summary", str(summary_path), "--poses", str(out / "poses.json"), "--idle-timeout", "4", "--wait-for-node", "60"],
            env, echo=True, log=out / "listen.log")
        if not listener.wait_for_line("listening", 90):
            raise InputError("the listener did not find the node; see " + str(out / "listen.log"))
        play = _Process("play", [
            "multi_instance_reg.tools.cli", "play", str(data["scene_bag"]), "--rate", str(args.rate),
            "--wait-for", COLOUR, DEPTH, INFO], env, echo=False, log=out / "play.log")
        if play.proc.wait(600) != 0:
            raise InputError("mireg play failed:\n" + "".join(play.lines[-5:]))
        listener.proc.wait(120)
    finally:
        for proc in (play, listener, node):
            if proc is not None:
                proc.stop()
    if not summary_path.exists():
        raise InputError("the listener wrote no summary; see " + str(out / "listen.log"))
    summary = json.loads(summary_path.read_text())
    summary["frames_in_bag"] = args.frames
    summary["demo_seconds"] = round(time.monotonic() - started, 1)
    summary_path.write_text(json.dumps(summary, indent=2) + "\n")
    _say("result")
    later = summary.get("from_first_pose")
    if later:
        # The node's figure once it runs: before its first pose the detector is still on its
        # first frame (how long that takes depends on the host, not on the tracking).
        print(f"  MHF1 {later['MHF1']} % (MHR {later['MHR']} %, MHP {later['MHP']} %) over the "
              f"{later['frames_scored']} frames from the first pose on; the first pose came "
              f"{summary['seconds_to_first_pose']:g} s ({summary['frames_before_first_pose']} frames) after the first frame")
        for name, s in later.get("objects", {}).items():
            print(f"    {name}: MHF1 {s['MHF1']} % (MHR {s['MHR']} %, MHP {s['MHP']} %)")
    print(f"  MHF1 {summary.get('MHF1')} % (MHR {summary.get('MHR')} %, MHP {summary.get('MHP')} %) over all "
          f"{summary.get('frames_scored')} frames the node processed (of {args.frames} played at "
          f"{args.fps * args.rate:g} Hz), the frames before the first pose counted as misses")
    print(f"  mean latency {summary['latency_ms_mean']} ms (p50 {summary['latency_ms_p50']} ms), "
          f"frames dropped by the node: {summary['frames_dropped']} (it always works on the newest frame)")
    print(f"  overlays: {overlays}/, summary: {summary_path}, logs: {out}/*.log "
          f"({summary['demo_seconds']:.0f} s in all)")
    return 0


if __name__ == "__main__":  # what `make demo` runs; the same as `mireg demo`
    from .cli import main

    sys.exit(main(["demo", *sys.argv[1:]]))
