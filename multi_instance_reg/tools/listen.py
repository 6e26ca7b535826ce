"""``mireg listen``: print what the node publishes, frame by frame; score it against a bag.

Subscribes to ``instances/poses`` and ``instances/details`` in ``--namespace`` (the root by
default; joined on the header stamp), prints one line per frame, and at the end a summary:
frames, mean node latency, frames dropped by the node and, with ``--ground-truth BAG``,
MHR / MHP / MHF1 against the bag's ``/ground_truth/poses`` (same stamps: ``mireg play``
rewrites nothing). With the node's models (``--model``, once per object), each instance is
scored against the ground-truth instances of its own object (the ``object`` of the details;
the bag's /ground_truth/object names each ground-truth instance's), per object and over all,
as ``mireg offline`` does. ``--save-overlays DIR`` also subscribes to the node's debug image and
writes it as PNG.
"""
from __future__ import annotations

import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..ros.names import add_namespace_argument, checked_namespace

HELP = "print the node's instances per frame; MHF1 against a bag's ground truth"
GT_TOPIC = "/ground_truth/poses"


def add_arguments(parser) -> None:
    parser.add_argument("--ground-truth", type=Path, metavar="BAG",
                        help="bag with /ground_truth/poses to score the poses against (MHF1)")
    parser.add_argument("--frames", type=int, default=0, metavar="N", help="stop after N frames (0 = no limit)")
    parser.add_argument("--idle-timeout", type=float, default=0.0, metavar="S",
                        help="stop when nothing arrived for S seconds after the first frame (0 = never)")
    parser.add_argument("--timeout", type=float, default=0.0, metavar="S",
                        help="stop after S seconds in all (0 = never)")
    parser.add_argument("--save-overlays", type=Path, metavar="DIR",
                        help="write the node's debug images there (every --overlay-every-th)")
    parser.add_argument("--overlay-every", type=int, default=5, metavar="K")
    parser.add_argument("--summary", type=Path, metavar="JSON", help="also write the summary to this file")
    parser.add_argument("--poses", type=Path, metavar="JSON",
                        help="also write every frame's instances there, as `mireg offline`'s poses.json (plus each "
                             "frame's latency and the node's details)")
    parser.add_argument("--model", type=Path, metavar="MODEL", action="append", default=[],
                        help="the node's model file, once per object: its T_object_model maps the published model "
                             "frame to the ground truth's object frame (without it the two are taken to be the "
                             "same), and its name says which poses are scored against which ground truth")
    parser.add_argument("--max-rre-deg", type=float, default=10.0, metavar="DEG",
                        help="a hit needs a rotation error below this (default 10, as mireg offline)")
    parser.add_argument("--max-rte", type=float, default=0.02, metavar="M",
                        help="a hit needs a translation error below this (default 0.02 m, as mireg offline)")
    parser.add_argument("--min-visibility", type=float, default=0.25, metavar="F",
                        help="instances less visible than this (/ground_truth/visibility) do not count "
                             "(default 0.25, as mireg offline)")
    parser.add_argument("--wait-for-node", type=float, default=0.0, metavar="S",
                        help="first wait up to S seconds for the node's poses publisher, then print 'listening'")
    parser.add_argument("--quiet", action="store_true", help="only the summary")
    add_namespace_argument(parser, "listen to the node in this namespace")


def read_ground_truth(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray | None, list[str]]]:
    """stamp_ns -> ((K, 4, 4) ground-truth poses, object frame in the camera optical frame;
    (K,) visible fraction of each instance, or None when the bag has no visibility; the K
    instances' object names, "" when the bag does not say)."""
    from ..datasets.rgbd_bag import GT_VISIBILITY_TOPIC, _object_description, _open_reader, instance_objects
    from ..transforms import pose_to_matrix

    reader = _open_reader(path)
    try:
        connections = [c for c in reader.connections if c.topic in (GT_TOPIC, GT_VISIBILITY_TOPIC)]
        if not any(c.topic == GT_TOPIC for c in connections):
            raise InputError(f"bag {path} has no {GT_TOPIC} topic to score against")
        poses, visibility, stamp_at = {}, {}, {}
        for connection, bag_time, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            if connection.topic == GT_VISIBILITY_TOPIC:
                # Float32MultiArray has no header: it shares the bag time of its frame's poses.
                visibility[bag_time] = np.asarray(msg.data, dtype=np.float32)
                continue
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            stamp_at[bag_time] = stamp
            poses[stamp] = np.array([
                pose_to_matrix((p.position.x, p.position.y, p.position.z),
                               (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
                for p in msg.poses]).reshape(-1, 4, 4)
        description = _object_description(reader, path)
        return {stamp: (poses[stamp], visibility.get(bag_time), instance_objects(description, len(poses[stamp])))
                for bag_time, stamp in stamp_at.items()}
    finally:
        reader.close()


def pose_array_to_matrices(msg) -> np.ndarray:
    from ..transforms import pose_to_matrix

    return np.array([pose_to_matrix((p.position.x, p.position.y, p.position.z),
                                    (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
                     for p in msg.poses]).reshape(-1, 4, 4)


class Listener:
    """Joins poses and details by stamp; keeps what the summary needs."""

    def __init__(self, truth=None, quiet=False, overlay_dir=None, overlay_every=5, models=()):
        self.truth = truth
        self.models = list(models)
        self.quiet = quiet
        self.overlay_dir = overlay_dir
        self.overlay_every = max(1, overlay_every)
        self.poses: dict[int, np.ndarray] = {}
        self.details: dict[int, dict] = {}
        self.frames: list[dict] = []   # joined frames in arrival order
        self.last_counters: dict = {}
        self.last_stats: dict = {}
        self.last_arrival = None
        self.overlays_seen = 0
        self.overlays_written: list[str] = []

    def on_poses(self, msg) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.poses[stamp] = pose_array_to_matrices(msg)
        self._join(stamp)

    def on_details(self, msg) -> None:
        data = json.loads(msg.data)
        self.details[data["stamp_ns"]] = data
        self.last_counters = data.get("counters", self.last_counters)
        self._join(data["stamp_ns"])

    def on_stats(self, msg) -> None:
        self.last_stats = json.loads(msg.data)

    def on_overlay(self, msg) -> None:
        from ..messages import colour_to_rgb

        self.overlays_seen += 1
        if (self.overlays_seen - 1) % self.overlay_every:
            return
        import cv2

        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        path = self.overlay_dir / f"overlay_{stamp}.png"
        cv2.imwrite(str(path), colour_to_rgb(msg)[:, :, ::-1])
        self.overlays_written.append(str(path))


    def _join(self, stamp: int) -> None:
        if stamp not in self.poses or stamp not in self.details:
            return
        self.last_arrival = time.monotonic()
        poses, details = self.poses.pop(stamp), self.details.pop(stamp)
        frame = {"stamp_ns": stamp, "poses": poses, "details": details}
        self.frames.append(frame)
        if not self.quiet:
            insts = ", ".join(
                (f"{i['object']} " if len(self.models) > 1 and "object" in i else "") + f"#{i['id']} ({i['inliers']} inl, {i['score']:.2f}) at "
                f"[{T[0, 3]:+.3f} {T[1, 3]:+.3f} {T[2, 3]:+.3f}]"
                for i, T in zip(details["instances"], poses))
            gt = ""
            if self.truth is not None and stamp in self.truth:
                gt = f" (truth: {len(self.truth[stamp][0])})"
            print(f"{stamp / 1e9:.3f} s: {len(poses)} instance(s){gt}, "
                  f"{details['latency_ms']:.0f} ms{': ' + insts if insts else ''}", flush=True)

    def poses_json(self) -> dict:
        """The frames received, in the layout of ``mireg offline``'s poses.json: the same
        tools read both (what the node published live beside what the bag gives offline)."""
        frames = []
        for f in self.frames:
            details = f["details"]
            instances = [{**{k: v for k, v in i.items() if k not in ("T",)}, "T": T.tolist()}
                         for i, T in zip(details["instances"], f["poses"])]
            frames.append({"stamp_ns": f["stamp_ns"], "frame_id": details.get("frame_id", ""),
                           "latency_ms": details.get("latency_ms"), "instances": instances})
        return {"frames": frames}

    def summary(self, max_rre_deg: float = 10.0, max_rte: float = 0.02, min_visibility: float = 0.25) -> dict:
        latencies = [f["details"]["latency_ms"] for f in self.frames]
        # The newer of the two: details come with every processed frame, stats periodically.
        def seen(c):
            return sum(c.get(k, 0) for k in ("processed", "dropped", "bad", "no_camera_info", "failed"))
        counters = max(self.last_counters, self.last_stats, key=seen)
        out = {
            "frames": len(self.frames),
            "latency_ms_mean": round(float(np.mean(latencies)), 1) if latencies else None,
            "latency_ms_p50": round(float(np.median(latencies)), 1) if latencies else None,
            "frames_dropped": counters.get("dropped"),
            "frames_bad": counters.get("bad"),
            "node_counters": counters,
            "overlays": self.overlays_written,
        }
        # The frames before the first pose are the time the detector takes to start (its first
        # result comes a detection's latency after the first frame): a figure of their own.
        first = next((k for k, f in enumerate(self.frames) if len(f["poses"])), None)
        if first is not None:
            out["frames_before_first_pose"] = first
            out["seconds_to_first_pose"] = round((self.frames[first]["stamp_ns"] - self.frames[0]["stamp_ns"]) * 1e-9, 3)
        if self.truth is not None:
            scored = [(f["poses"], [i.get("object", "") for i in f["details"]["instances"]], *self.truth[f["stamp_ns"]])
                      for f in self.frames if f["stamp_ns"] in self.truth]
            out.update(score_frames(scored, self.models, max_rre_deg, max_rte, min_visibility))
            later = [(f["poses"], [i.get("object", "") for i in f["details"]["instances"]], *self.truth[f["stamp_ns"]])
                     for f in self.frames[first:] if f["stamp_ns"] in self.truth] if first is not None else []
            if later:
                out["from_first_pose"] = score_frames(later, self.models, max_rre_deg, max_rte, min_visibility)
        return out


def score_frames(frames, models=(), max_rre_deg: float = 10.0, max_rte: float = 0.02,
                 min_visibility: float = 0.25) -> dict:
    """MHR / MHP / MHF1 in % (means over frames) of frames given as (published poses (model
    frame), their object names, ground truth (object frame), its visibility, its object names),
    scored as ``mireg offline`` does: with models, each object's poses against its own ground
    truth (per object under "objects", and all together); without, all against all."""
    from ..metrics import combine_scores, summarize
    from .offline import estimates_in_object_frame, evaluate_frame, ground_truth_owners

    per_object: dict[str, list] = {m.name: [] for m in models}
    overall = []
    for poses, names, gt, vis, gt_names in frames:
        if not models:
            overall.append(evaluate_frame(gt, poses, vis, min_visibility, max_rre_deg, max_rte))
            continue
        owners = ground_truth_owners(models, gt_names)
        scores = []
        for k, m in enumerate(models):
            # A node with one model publishes unnamed instances only if it predates names: all are its.
            mine = [e for e, n in enumerate(names) if n == m.name or (len(models) == 1 and not n)]
            g = np.flatnonzero(owners == k)
            score = evaluate_frame(gt[g], estimates_in_object_frame(m, poses[mine]), None if vis is None else vis[g],
                                   min_visibility, max_rre_deg, max_rte)
            per_object[m.name].append(score)
            scores.append(score)
        overall.append(combine_scores(scores))
    out = _percentages(summarize(overall), len(frames), max_rre_deg, max_rte, min_visibility)
    if len(models) > 1:
        out["objects"] = {name: _percentages(summarize(s), len(frames), max_rre_deg, max_rte, min_visibility)
                          for name, s in per_object.items()}
    return out


def _percentages(s: dict, frames: int, max_rre_deg: float, max_rte: float, min_visibility: float) -> dict:
    return {"frames_scored": frames, "MHR": round(100 * s["MHR"], 1), "MHP": round(100 * s["MHP"], 1),
            "MHF1": round(100 * s["MHF1"], 1), "MF": round(100 * s["MF"], 1),
            "max_rre_deg": max_rre_deg, "max_rte": max_rte, "min_visibility": min_visibility,
            "median_rre_deg": s["median_rre_deg"], "median_rte_m": s["median_rte"]}


def format_summary(summary: dict) -> str:
    lines = [f"frames received: {summary['frames']}",
             f"mean node latency: {summary['latency_ms_mean']} ms (p50 {summary['latency_ms_p50']} ms)",
             f"frames dropped by the node: {summary['frames_dropped']}"]
    if "MHF1" in summary:
        lines.insert(0, f"MHF1 {summary['MHF1']} % (MHR {summary['MHR']} %, MHP {summary['MHP']} %) over "
                        f"{summary['frames_scored']} frames with ground truth (hit: rotation < "
                        f"{summary['max_rre_deg']:g} deg, translation < {summary['max_rte']:g} m; instances at least "
                        f"{summary['min_visibility']:g} visible)")
        for k, (name, s) in enumerate(summary.get("objects", {}).items()):
            lines.insert(1 + k, f"  {name}: MHF1 {s['MHF1']} % (MHR {s['MHR']} %, MHP {s['MHP']} %)")
        later = summary.get("from_first_pose")
        if later:
            lines.insert(1 + len(summary.get("objects", {})),
                         f"from the first pose on (frame {summary['frames_before_first_pose']}, "
                         f"{summary['seconds_to_first_pose']:g} s after the first): MHF1 {later['MHF1']} % "
                         f"(MHR {later['MHR']} %, MHP {later['MHP']} %) over {later['frames_scored']} frames")
    return "\n".join(lines)


def run(args) -> int:
    namespace = checked_namespace(args.namespace)
    truth = read_ground_truth(args.ground_truth) if args.ground_truth else None
    models = []
    if args.model:
        from ..rgbd.multi_model import load_models

        models = load_models(args.model)
    if args.save_overlays:
        args.save_overlays.mkdir(parents=True, exist_ok=True)

    import rclpy
    from geometry_msgs.msg import PoseArray
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    listener = Listener(truth, args.quiet, args.save_overlays, args.overlay_every, models)
    from ..ros.transport import use_large_data_profile

    use_large_data_profile()   # images through shared memory (ros/transport.py)
    rclpy.init()
    node = rclpy.create_node("mireg_listen", namespace=namespace)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)
    # Relative names, resolved in --namespace like the node's own.
    node.create_subscription(PoseArray, "instances/poses", listener.on_poses, qos)
    node.create_subscription(String, "instances/details", listener.on_details, qos)
    node.create_subscription(String, "instance_registration/stats", listener.on_stats, qos)
    if args.save_overlays:
        node.create_subscription(Image, "instances/debug_image", listener.on_overlay, qos)
    if args.wait_for_node:
        deadline = time.monotonic() + args.wait_for_node
        poses_topic = node.resolve_topic_name("instances/poses")
        while node.count_publishers(poses_topic) == 0:
            if time.monotonic() > deadline:
                node.destroy_node()
                rclpy.try_shutdown()
                raise InputError(f"no node publishes {poses_topic} after {args.wait_for_node:g} s; "
                                 "is it running with the same ROS_DOMAIN_ID and namespace?")
            rclpy.spin_once(node, timeout_sec=0.1)
        # Discovery is mutual: give the node's publishers a moment to match our subscriptions.
        # Frames may already arrive meanwhile: they count towards --frames.
        end = time.monotonic() + 0.5
        while time.monotonic() < end and not (args.frames and len(listener.frames) >= args.frames):
            rclpy.spin_once(node, timeout_sec=0.1)
    print("listening for the node's output", file=sys.stderr, flush=True)
    start = time.monotonic()
    # SIGTERM (from a script that started us) ends the loop like Ctrl-C: print the summary.
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    try:
        while rclpy.ok():
            if args.frames and len(listener.frames) >= args.frames:
                break
            rclpy.spin_once(node, timeout_sec=0.1)
            now = time.monotonic()
            if args.frames and len(listener.frames) >= args.frames:
                break
            if args.timeout and now - start > args.timeout:
                break
            if args.idle_timeout and listener.last_arrival and now - listener.last_arrival > args.idle_timeout:
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    summary = listener.summary(args.max_rre_deg, args.max_rte, args.min_visibility)
    print(format_summary(summary), flush=True)
    if args.summary:
        args.summary.parent.mkdir(parents=True, exist_ok=True)
        args.summary.write_text(json.dumps(summary, indent=2) + "\n")
    if args.poses:
        args.poses.parent.mkdir(parents=True, exist_ok=True)
        args.poses.write_text(json.dumps(listener.poses_json()) + "\n")
    return 0
