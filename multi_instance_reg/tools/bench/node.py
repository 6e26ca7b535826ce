"""``mireg bench node``: the node's end-to-end latency, its behaviour under overload, its memory.

Starts the node as a real process (its own ROS_DOMAIN_ID, localhost discovery), publishes
the frames of a scene bag from this process with fresh stamps (time of publishing), and
measures on the same machine clock:

1. at the camera's rate (30 Hz): the share of camera frames that get poses (a PoseArray,
   and one with at least one pose), end-to-end latency = poses received - image stamp,
   p50/p95, and how often the full detector ran;
2. with the camera outrunning the node (60 Hz): latency in the first and last thirds of
   the run (it must not grow) and frames dropped;
3. over a long replay (``--rss-frames``, 5,000 by default): the same share and latency by
   tenth of the run (a queue growing would show as latency growing), and the node's resident
   memory (VmRSS from /proc, node + pipeline process) at the start, the end and its maximum.

The node runs with its defaults (tracking on: poses published for every frame by the
tracker) unless ``-p`` says otherwise, e.g. ``-p tracking.enabled:=false`` for the
per-detection behaviour.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...ros.background import BackgroundNode

HELP = "the ROS node's end-to-end latency, latency under overload and memory over a long replay"
COLOUR_TOPIC = "/camera/camera/color/image_raw"
DEPTH_TOPIC = "/camera/camera/aligned_depth_to_color/image_raw"
INFO_TOPIC = "/camera/camera/color/camera_info"


def add_arguments(parser) -> None:
    parser.add_argument("--bag", type=Path, help="scene bag whose frames are replayed (default: make the demo's)")
    parser.add_argument("--model", type=Path, action="append", default=[],
                        help="model file, once per object (default: make the demo's one-object data)")
    parser.add_argument("--frames", type=int, default=300, metavar="N", help="frames at 30 Hz for the latency figures")
    parser.add_argument("--overload-frames", type=int, default=300, metavar="N", help="frames at --overload-rate (0 = skip)")
    parser.add_argument("--overload-rate", type=float, default=60.0, metavar="HZ")
    parser.add_argument("--rss-frames", type=int, default=5000, metavar="N",
                        help="frames at 30 Hz for the memory figures (0 = skip)")
    parser.add_argument("--distinct-frames", type=int, default=90, metavar="N",
                        help="how many of the bag's frames to replay, forwards then backwards (the motion stays "
                             "continuous for the tracker)")
    parser.add_argument("--domain-id", type=int, default=77, help="ROS_DOMAIN_ID of the benchmark")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a node parameter, as after --ros-args -p (repeatable)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the figures here")


def _load_frames(bag: Path, count: int):
    from ...datasets.rgbd_bag import RGBDBag

    frames = []
    with RGBDBag(bag) as reader:
        for frame in reader:
            frames.append(frame)
            if len(frames) >= count:
                break
    if not frames:
        raise InputError(f"bag {bag} has no complete RGB-D frame to replay")
    return frames


def _messages(frames):
    from sensor_msgs.msg import CameraInfo, Image

    from ...messages import array_to_image_fields

    out = []
    for f in frames:
        colour = array_to_image_fields(f.rgb, "rgb8")
        depth = array_to_image_fields(np.round(f.depth_m * 1000).astype(np.uint16), "16UC1")
        colour["data"], depth["data"] = colour["data"].tobytes(), depth["data"].tobytes()
        info = CameraInfo(width=f.intrinsics.width, height=f.intrinsics.height,
                          k=f.intrinsics.K.reshape(-1).tolist(), distortion_model=f.intrinsics.distortion_model,
                          d=[float(v) for v in f.intrinsics.D])
        msgs = (Image(**colour), Image(**depth), info)
        for m in msgs:
            m.header.frame_id = f.frame_id
        out.append(msgs)
    return out


def _process_tree(pid: int) -> list[int]:
    """pid and all its descendants (the node has a pipeline process)."""
    children = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            children += [int(c) for c in (task / "children").read_text().split()]
    except FileNotFoundError:  # exited meanwhile
        return []
    return [pid] + [d for c in children for d in _process_tree(c)]


def rss_mb(pid: int) -> float:
    """Resident memory (VmRSS) of a process and its descendants, MB."""
    total = 0.0
    for p in _process_tree(pid):
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024.0
        except FileNotFoundError:
            continue
    return total


class _Bench(BackgroundNode):
    def __init__(self, messages, domain_id: int):
        from geometry_msgs.msg import PoseArray
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image
        from std_msgs.msg import String

        super().__init__("mireg_bench_node", domain_id)
        self.messages = messages
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_colour = self.node.create_publisher(Image, COLOUR_TOPIC, qos)
        self.pub_depth = self.node.create_publisher(Image, DEPTH_TOPIC, qos)
        self.pub_info = self.node.create_publisher(CameraInfo, INFO_TOPIC, qos)
        self.latencies: list[tuple[int, float]] = []   # (stamp_ns, ms)
        self.counters: dict = {}
        self.pipeline_ms: dict[int, float] = {}        # stamp_ns -> the pipeline's own time
        self.node_ms: dict[int, float] = {}            # stamp_ns -> pair complete in the node -> poses out
        self.wall: dict[int, tuple] = {}               # stamp_ns -> (pair complete, poses out) wall clock ns
        self.received_at: dict[int, int] = {}          # stamp_ns -> poses received here, wall clock ns
        self.pose_counts: dict[int, int] = {}          # stamp_ns -> poses in the PoseArray
        self._sent = 0                                 # frames published so far (where the replay is)
        self.node.create_subscription(PoseArray, "/instances/poses", self._on_poses, qos)
        self.node.create_subscription(String, "/instances/details", self._on_details, qos)
        self.start()

    def _on_poses(self, msg):
        now = time.time_ns()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.latencies.append((stamp, (now - stamp) / 1e6))
        self.received_at[stamp] = now
        self.pose_counts[stamp] = len(msg.poses)

    def _on_details(self, msg):
        data = json.loads(msg.data)
        self.counters = data.get("counters", self.counters)
        self.pipeline_ms[data["stamp_ns"]] = data.get("timings_ms", {}).get("total")
        self.node_ms[data["stamp_ns"]] = data.get("latency_ms")
        self.wall[data["stamp_ns"]] = (data.get("received_ns"), data.get("published_ns"))

    def wait_for_node(self, timeout: float, proc) -> None:
        deadline = time.monotonic() + timeout
        pubs = (self.pub_colour, self.pub_depth, self.pub_info)
        while any(p.get_subscription_count() == 0 for p in pubs):
            if proc.poll() is not None:
                raise InputError(f"the node exited with code {proc.returncode} before subscribing")
            if time.monotonic() > deadline:
                raise InputError("the node did not subscribe to the camera topics in time")
            time.sleep(0.05)
        time.sleep(0.5)

    def publish(self, count: int, rate: float, on_tick=None) -> tuple[int, int]:
        """Publish ``count`` frames at ``rate``; returns the (first, last) stamps sent."""
        from builtin_interfaces.msg import Time

        start = time.monotonic()
        first = last = None
        for k in range(count):
            colour, depth, info = self.messages[_ping_pong(self._sent + k, len(self.messages))]
            ns = time.time_ns()
            stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            for m in (info, colour, depth):
                m.header.stamp = stamp
            self.pub_info.publish(info)
            self.pub_colour.publish(colour)
            self.pub_depth.publish(depth)
            first = ns if first is None else first
            last = ns
            if on_tick is not None:
                on_tick(k)
            delay = start + (k + 1) / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        self._sent += count
        return first, last

    def window(self, first: int, last: int) -> np.ndarray:
        return np.array([ms for stamp, ms in self.latencies if first <= stamp <= last])

    def with_a_pose(self, first: int, last: int) -> int:
        """Frames in the window whose PoseArray held at least one pose."""
        return sum(1 for stamp, n in self.pose_counts.items() if first <= stamp <= last and n > 0)

    def poses_per_frame(self, first: int, last: int) -> float | None:
        counts = [n for stamp, n in self.pose_counts.items() if first <= stamp <= last]
        return round(float(np.mean(counts)), 2) if counts else None

    def overhead(self, first: int, last: int) -> tuple[np.ndarray, np.ndarray]:
        """(pipeline ms, end-to-end minus pipeline ms) of the frames processed in the window:
        the second is what the node and DDS add (transfer, conversion, waiting for the worker)."""
        pairs = [(self.pipeline_ms[stamp], ms) for stamp, ms in self.latencies
                 if first <= stamp <= last and self.pipeline_ms.get(stamp) is not None]
        pipe = np.array([p for p, _ in pairs])
        return pipe, np.array([e - p for p, e in pairs])

def _ping_pong(k: int, n: int) -> int:
    """The k-th frame of a replay of n frames forwards, backwards, forwards...: no jump."""
    if n < 2:
        return 0
    k %= 2 * n - 2
    return k if k < n else 2 * n - 2 - k


def _settle(bench: _Bench, last_stamp: int, seconds: float = 20.0) -> None:
    """Wait for the poses of the last frame sent: the node always processes the newest one."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not any(stamp == last_stamp for stamp, _ in bench.latencies[-5:]):
        time.sleep(0.05)


def _pct(values: np.ndarray, q: float):
    return round(float(np.percentile(values, q)), 1) if len(values) else None


def run(args) -> int:
    if args.bag is None or not args.model:
        from ..demo import prepare_data

        data = prepare_data(Path("out/bench_node"), quiet=False)
        args.bag = args.bag or data["scene_bag"]
        args.model = args.model or [data["model"]]
    frames = _load_frames(args.bag, args.distinct_frames)
    messages = _messages(frames)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    import tempfile

    # The node's log goes to a file: an unread pipe would fill up and stall it on a long run.
    log = tempfile.NamedTemporaryFile("w+", prefix="bench_node_", suffix=".log")
    node = subprocess.Popen([sys.executable, "-m", "multi_instance_reg.ros.node", "--ros-args",
                             "-p", f"model_paths:=[{', '.join(map(str, args.model))}]", "-p", "stats_log_period_s:=10.0",
                             *[a for p in args.param for a in ("-p", p)]],
                            env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    bench = _Bench(messages, args.domain_id)
    figures: dict = {"node_params": args.param, "models": [str(m) for m in args.model], "load_average_start": os.getloadavg()[0],
                     "frames_distinct": len(messages), "image_size": [frames[0].rgb.shape[1], frames[0].rgb.shape[0]]}
    try:
        bench.wait_for_node(60.0, node)
        _, last = bench.publish(10, 10.0)   # warm-up: first-frame costs out of the figures
        _settle(bench, last)

        # 1. the camera's rate. Frames without poses were dropped by the node (newest kept).
        received_before = bench.counters.get("colour_received", 0)
        detected_before = bench.counters.get("detected", 0)
        first, last = bench.publish(args.frames, 30.0)
        _settle(bench, last)
        lat = bench.window(first, last)
        received = bench.counters.get("colour_received", 0) - received_before
        pipe, extra = bench.overhead(first, last)
        figures["rate_30hz"] = {
            "pipeline_ms_p50": _pct(pipe, 50), "node_and_dds_ms_p50": _pct(extra, 50),
            "frames_sent": args.frames, "frames_with_poses": int(len(lat)),
            "share_with_poses": round(len(lat) / args.frames, 4),
            "share_with_a_pose": round(bench.with_a_pose(first, last) / args.frames, 4),
            "poses_per_frame_mean": bench.poses_per_frame(first, last),
            "detections": bench.counters.get("detected", 0) - detected_before,
            "dropped": args.frames - int(len(lat)), "colour_images_received_by_node": received,
            "e2e_ms_p50": _pct(lat, 50), "e2e_ms_p95": _pct(lat, 95), "e2e_ms_mean": round(float(lat.mean()), 1) if len(lat) else None}

        # 2. overload.
        if args.overload_frames:
            first, last = bench.publish(args.overload_frames, args.overload_rate)
            _settle(bench, last)
            span = (last - first) / 3
            early, late = bench.window(first, first + span), bench.window(last - span, last)
            figures["overload"] = {
                "rate_hz": args.overload_rate, "frames_sent": args.overload_frames,
                "frames_with_poses": int(len(bench.window(first, last))),
                "dropped": args.overload_frames - int(len(bench.window(first, last))),
                "e2e_ms_p50_first_third": _pct(early, 50), "e2e_ms_p50_last_third": _pct(late, 50),
                "e2e_ms_p95_first_third": _pct(early, 95), "e2e_ms_p95_last_third": _pct(late, 95)}

        # 3. memory over a long replay.
        if args.rss_frames:
            samples = []

            def sample(k):
                if k % 100 == 0:
                    samples.append((k, rss_mb(node.pid)))
            first, last = bench.publish(args.rss_frames, 30.0, on_tick=sample)
            _settle(bench, last)
            samples.append((args.rss_frames, rss_mb(node.pid)))
            rss = np.array([mb for _, mb in samples])
            lat = bench.window(first, last)
            tenth = max(1, len(lat) // 10)
            pipe, extra = bench.overhead(first, last)
            stamps = [stamp for stamp, _ in bench.latencies if first <= stamp <= last]
            node_ms = np.array([bench.node_ms.get(s, np.nan) for s in stamps])
            # Images in: stamp -> pair complete in the node; poses out: node publishes -> received here.
            inbound = np.array([(bench.wall.get(s, (None,))[0] or np.nan) - s for s in stamps], float) / 1e6
            outbound = np.array([bench.received_at[s] - (bench.wall.get(s, (0, None))[1] or np.nan) for s in stamps],
                                float) / 1e6
            tenths = [tuple(x[k * tenth:(k + 1) * tenth] for x in (lat, pipe, extra, node_ms, inbound, outbound))
                      for k in range(10)]
            figures["long_replay"] = {
                "frames_sent": args.rss_frames, "frames_with_poses": int(len(lat)),
                "share_with_poses": round(len(lat) / args.rss_frames, 4),
                "share_with_a_pose": round(bench.with_a_pose(first, last) / args.rss_frames, 4),
                "e2e_ms_p50": _pct(lat, 50), "e2e_ms_p95": _pct(lat, 95),
                "rss_mb_start": round(float(rss[0]), 1), "rss_mb_end": round(float(rss[-1]), 1),
                "rss_mb_max": round(float(rss.max()), 1),
                "rss_mb_samples": [(k, round(mb, 1)) for k, mb in samples],
                "e2e_ms_p50_first_tenth": _pct(lat[:tenth], 50), "e2e_ms_p50_last_tenth": _pct(lat[-tenth:], 50),
                "by_tenth_p50_ms": [{"e2e": _pct(a, 50), "pipeline": _pct(b, 50), "node_and_dds": _pct(c, 50),
                                     "in_node": _pct(d[np.isfinite(d)], 50), "images_in": _pct(e[np.isfinite(e)], 50),
                                     "poses_out": _pct(f[np.isfinite(f)], 50)} for a, b, c, d, e, f in tenths]}
        figures["node_counters"] = bench.counters
    finally:
        bench.close()
        node.terminate()
        try:
            node.wait(10)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()
        log.seek(0)
        node_log = log.read()
        log.close()
        if node.returncode not in (0, -15):
            print(node_log[-3000:], file=sys.stderr)
    _print(figures)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


def _print(f: dict) -> None:
    w, h = f["image_size"]
    r = f["rate_30hz"]
    print(f"node params: {' '.join(f['node_params']) or '(defaults)'}; models: {', '.join(f['models'])}")
    print(f"node at 30 Hz, {w}x{h}: poses for {100 * r['share_with_poses']:.1f} % of camera frames "
          f"({r['frames_with_poses']}/{r['frames_sent']}; at least one pose in {100 * r['share_with_a_pose']:.1f} %, "
          f"{r['poses_per_frame_mean']} poses a frame on average), "
          f"full detection on {r['detections']} of them")
    print(f"  end-to-end latency (image published -> poses received): p50 {r['e2e_ms_p50']} ms, "
          f"p95 {r['e2e_ms_p95']} ms, mean {r['e2e_ms_mean']} ms; {r['dropped']} frames without poses (newest kept); "
          f"{r['colour_images_received_by_node']} colour images arrived at the node")
    print(f"  of which the node's per-frame work (tracking; without tracking the pipeline) p50 {r['pipeline_ms_p50']} ms; "
          f"node + DDS + waiting p50 {r['node_and_dds_ms_p50']} ms")
    if "overload" in f:
        o = f["overload"]
        print(f"camera outrunning the pipeline ({o['rate_hz']:g} Hz, {o['frames_sent']} frames):")
        print(f"  p50 {o['e2e_ms_p50_first_third']} ms in the first third, {o['e2e_ms_p50_last_third']} ms in the last; "
              f"p95 {o['e2e_ms_p95_first_third']} / {o['e2e_ms_p95_last_third']} ms; "
              f"{o['frames_with_poses']} processed, {o['dropped']} dropped")
    if "long_replay" in f:
        m = f["long_replay"]
        print(f"{m['frames_sent']} frames at 30 Hz: poses for {100 * m['share_with_poses']:.1f} % of them "
              f"(at least one pose in {100 * m['share_with_a_pose']:.1f} %), latency p50 {m['e2e_ms_p50']} ms, "
              f"p95 {m['e2e_ms_p95']} ms; p50 {m['e2e_ms_p50_first_tenth']} ms (first tenth) -> "
              f"{m['e2e_ms_p50_last_tenth']} ms (last tenth)")
        print(f"  resident memory (node + its pipeline process): start {m['rss_mb_start']} MB, "
              f"end {m['rss_mb_end']} MB, max {m['rss_mb_max']} MB")


if __name__ == "__main__":  # also `mireg bench node` once the bench registry lists it
    import argparse

    _parser = argparse.ArgumentParser(prog="mireg bench node", description=HELP)
    add_arguments(_parser)
    try:
        sys.exit(run(_parser.parse_args()))
    except InputError as exc:
        print(f"mireg bench node: error: {exc}", file=sys.stderr)
        sys.exit(2)
