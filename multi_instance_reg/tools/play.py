"""``mireg play BAG``: publish a bag into the ROS graph with its original timing.

The ros2 command line (and so ``ros2 bag play``) is not available from pip; this is the
small replacement the node needs. Messages go out exactly as stored (raw CDR, nothing
rewritten), one reliable publisher per topic with the bag's message type, at the bag's
receive times scaled by ``--rate``.
"""
from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

from ..errors import InputError
from ..ros.names import add_namespace_argument, checked_namespace, relative

HELP = "publish a rosbag2 (or ROS 1) bag into the ROS graph with its original timing"


def add_arguments(parser) -> None:
    parser.add_argument("bag", type=Path, help="bag directory, .db3, .mcap or ROS 1 .bag")
    parser.add_argument("--rate", type=float, default=1.0, help="speed factor (2 = twice as fast; default 1)")
    parser.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="publish only these topics")
    parser.add_argument("--start-delay", type=float, default=0.5, metavar="S",
                        help="seconds between creating the publishers and the first message (discovery)")
    parser.add_argument("--wait-for", nargs="+", default=[], metavar="TOPIC",
                        help="before starting, wait until each of these topics has a subscriber")
    parser.add_argument("--wait-timeout", type=float, default=30.0, metavar="S",
                        help="give up waiting for subscribers after this long (default 30)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_namespace_argument(parser, "publish the bag's topics under this namespace")


def message_class(msgtype: str):
    """'sensor_msgs/msg/Image' -> the rclpy class sensor_msgs.msg.Image."""
    parts = msgtype.split("/")
    if len(parts) == 2:  # ROS 1 style 'sensor_msgs/Image'
        parts = [parts[0], "msg", parts[1]]
    package, kind, name = parts[0], parts[1], parts[-1]
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise InputError(f"message type {msgtype} is not installed for rclpy; "
                         f"install its interface package or leave its topic out with --topics") from None


def run(args) -> int:
    if not args.rate > 0:
        raise InputError(f"--rate must be positive, got {args.rate}")
    args.namespace = checked_namespace(args.namespace)
    from ..datasets.rgbd_bag import _open_reader

    reader = _open_reader(args.bag)
    if not reader.is2:
        reader.close()
        raise InputError(f"{args.bag} is a ROS 1 bag (a RealSense Viewer recording?): mireg play publishes rosbag2 "
                         "bags only; run `mireg offline` on it instead")
    try:
        return _play(reader, args)
    except KeyboardInterrupt:
        return 0
    finally:
        reader.close()


def _play(reader, args) -> int:
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    connections = [c for c in reader.connections if not args.topics or c.topic in args.topics]
    if args.topics:
        missing = sorted(set(args.topics) - {c.topic for c in connections})
        if missing:
            raise InputError(f"bag {args.bag} has no topic {', '.join(missing)}; "
                             f"it has {', '.join(sorted(reader.topics))}")
    if not connections:
        raise InputError(f"bag {args.bag} has no messages to play")
    types = {c.topic: message_class(c.msgtype) for c in connections}

    from ..ros.transport import use_large_data_profile

    use_large_data_profile()   # images through shared memory (ros/transport.py)
    rclpy.init()
    node = rclpy.create_node("mireg_play", namespace=args.namespace)
    try:
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        # What was recorded latched (realsense-ros' extrinsics, published once) goes out latched
        # too, so a subscriber that comes late still gets it.
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # Relative names: /camera/... goes out as <namespace>/camera/... (the same in the root namespace).
        publishers = {topic: node.create_publisher(cls, relative(topic), latched if topic in _latched_topics(connections)
                                                   else qos) for topic, cls in types.items()}
        _wait_for_subscribers(node, publishers, args)
        time.sleep(args.start_delay)
        if not args.quiet:
            print(f"playing {args.bag}: {len(publishers)} topics at rate {args.rate:g}"
                  + (" (looping)" if args.loop else ""), file=sys.stderr, flush=True)
        count, wall_start, rounds = 0, time.monotonic(), 0
        while True:
            count += _play_once(reader, connections, publishers, args.rate)
            rounds += 1
            if not args.loop or not rclpy.ok():
                break
        if not args.quiet:
            print(f"published {count} messages in {time.monotonic() - wall_start:.1f} s"
                  + (f" ({rounds} rounds)" if rounds > 1 else ""), file=sys.stderr, flush=True)
        # Reliable delivery of the last messages needs the publishers alive until every
        # subscriber has acknowledged them (a lost fragment is repaired on the next heartbeat).
        from rclpy.duration import Duration

        deadline = time.monotonic() + 5.0
        for pub in publishers.values():
            pub.wait_for_all_acked(Duration(seconds=max(0.1, deadline - time.monotonic())))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _latched_topics(connections) -> set[str]:
    """Topics a rosbag2 recorded from a transient-local publisher (the extrinsics the node
    needs for unaligned depth are published once)."""
    from rosbags.interfaces import QosDurability

    return {c.topic for c in connections
            if any(q.durability == QosDurability.TRANSIENT_LOCAL for q in getattr(c.ext, "offered_qos_profiles", None) or ())}


def _wait_for_subscribers(node, publishers, args) -> None:
    for topic in args.wait_for:
        if topic not in publishers:
            raise InputError(f"--wait-for {topic}: the bag does not publish that topic")
    deadline = time.monotonic() + args.wait_timeout
    while any(publishers[t].get_subscription_count() == 0 for t in args.wait_for):
        if time.monotonic() > deadline:
            waiting = [t for t in args.wait_for if publishers[t].get_subscription_count() == 0]
            raise InputError(f"no subscriber on {', '.join(waiting)} after {args.wait_timeout:g} s; "
                             "is the node running with the same ROS_DOMAIN_ID?")
        time.sleep(0.05)


def _play_once(reader, connections, publishers, rate: float) -> int:
    import rclpy

    start_ns, wall_start, count = None, time.monotonic(), 0
    for connection, timestamp, raw in reader.messages(connections=connections):
        if start_ns is None:
            start_ns = timestamp
        due = wall_start + (timestamp - start_ns) / 1e9 / rate
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if not rclpy.ok():
            break
        publishers[connection.topic].publish(bytes(raw))
        count += 1
    return count
