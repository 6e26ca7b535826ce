"""``instance_registration_node``: every instance's pose from a live RGB-D stream.

Subscribes to colour, aligned depth and camera_info (realsense-ros names by default; remap
to change), pairs colour and depth by header stamp, runs the per-frame pipeline
(``multi_instance_reg.rgbd.pipeline``) in a worker thread and publishes:

- ``instances/poses`` (geometry_msgs/PoseArray): model frame in the camera optical frame;
- ``instances/detections`` (vision_msgs/Detection3DArray, when vision_msgs is installed) and
  ``instances/label_info`` (vision_msgs/LabelInfo, transient local): ``detections.py``;
- ``instances/markers`` (visualization_msgs/MarkerArray): box + id label per instance;
- ``instances/details`` (std_msgs/String, JSON): id, inliers, score per instance, latency;
- ``instances/debug_image`` (sensor_msgs/Image rgb8): only drawn when subscribed or asked;
- ``~/stats`` (std_msgs/String, JSON): frame counts and latency, also logged.
Names are relative to the node's namespace (root: ``/instances/poses``; with
``-r __ns:=/left``: ``/left/instances/poses`` and ``/left/camera/camera/...`` in).

Callbacks never wait for the pipeline: a synchronised pair goes into a one-frame mailbox
and the worker thread always takes the newest one (the pipeline itself runs in a child
process, ``worker.py``, so it never holds this process's GIL); pairs replaced before the worker got to them
are counted as dropped, so latency cannot queue up when the camera outruns the pipeline.

Run: ``instance_registration_node --ros-args --params-file config/params.yaml
-p model_path:=model.npz`` (or ``python -m multi_instance_reg.ros.node ...``).
"""
from __future__ import annotations

import json
import sys
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np
import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from geometry_msgs.msg import PoseArray
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from ..errors import InputError
from ..messages import array_to_image_fields, camera_info_to_intrinsics, colour_to_rgb, depth_to_metres
from ..params import param_specs, with_overrides
from . import conversions
from .detections import DetectionPublisher, ObjectClass
from .parameters import READ_ONLY, NodeSettings, check_parameters, declare, node_settings, node_specs
from .sync import ApproximateTimeSync, LatestSlot, stamp_to_ns
from .transport import use_large_data_profile

NODE_NAME = "instance_registration"
# Relative names: `--ros-args -r __ns:=/left` moves inputs and outputs together (one node per
# camera); in the root namespace they resolve to /camera/camera/... and /instances/...
COLOUR_TOPIC = "camera/camera/color/image_raw"
DEPTH_TOPIC = "camera/camera/aligned_depth_to_color/image_raw"
CAMERA_INFO_TOPIC = "camera/camera/color/camera_info"
LATENCY_WINDOW = 300  # frames kept for the latency percentiles


@dataclass
class FrameCounters:
    colour_received: int = 0
    depth_received: int = 0
    synchronised: int = 0
    processed: int = 0
    dropped: int = 0          # synchronised pairs replaced by a newer one before processing
    bad: int = 0              # malformed images (encoding, step, sizes), skipped
    no_camera_info: int = 0   # pairs skipped because no camera_info had arrived yet
    failed: int = 0           # pipeline raised on a frame, skipped


@dataclass
class _Pair:
    colour: Image
    depth: Image
    received: float  # time.monotonic() when the pair was complete
    received_ns: int  # the same moment on the wall clock (comparable with header stamps)
    sequence: int


class InstanceRegistrationNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        from ..rgbd.model import load_model
        from ..rgbd.pipeline import PipelineConfig
        from .worker import PipelineProcess

        node_values = declare(self, node_specs(), READ_ONLY)
        pipeline_values = declare(self, param_specs(PipelineConfig()))
        self._specs = {s.name: s for s in node_specs()}
        self._specs.update({s.name: s for s in param_specs(PipelineConfig())})
        self.settings = node_settings(node_values)
        self.config = with_overrides(PipelineConfig(), pipeline_values)
        if not self.settings.model_path:
            raise InputError("no model: pass -p model_path:=MODEL (build one with `mireg build-model`)")
        self.model = load_model(self.settings.model_path)
        # The pipeline runs in child processes (see worker.py): it never holds our GIL.
        self._pipelines = PipelineProcess.start_many(self.model, self.config, self.settings.pipeline_processes)

        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        reliability = (ReliabilityPolicy.BEST_EFFORT if self.settings.qos_reliability == "best_effort"
                       else ReliabilityPolicy.RELIABLE)
        sub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.settings.qos_depth,
                             reliability=reliability)
        pub_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.settings.qos_depth,
                             reliability=ReliabilityPolicy.RELIABLE)
        self.counters = FrameCounters()
        self._counters_lock = threading.Lock()
        self._sync = ApproximateTimeSync(2, int(self.settings.sync_slop_s * 1e9))
        self._slot = LatestSlot()
        self._intrinsics = None
        self._have_intrinsics = threading.Event()
        self._latencies = deque(maxlen=LATENCY_WINDOW)
        self._marker_ids: set = set()
        self._publish_lock = threading.Lock()
        self._sequence = 0          # of synchronised pairs, to publish results in order
        self._last_published = -1
        self._last_stats = time.monotonic()

        self._pub_poses = self.create_publisher(PoseArray, "instances/poses", pub_qos)
        self._pub_markers = self.create_publisher(MarkerArray, "instances/markers", pub_qos)
        self._pub_details = self.create_publisher(String, "instances/details", pub_qos)
        self._pub_debug = self.create_publisher(Image, "instances/debug_image", pub_qos)
        self._pub_detections = DetectionPublisher.create(
            self, pub_qos, [ObjectClass.of_model(self.model, self.settings.model_path)])
        self._pub_stats = self.create_publisher(String, "~/stats", pub_qos)
        self.create_subscription(Image, COLOUR_TOPIC, lambda m: self._on_image(0, m), sub_qos)
        self.create_subscription(Image, DEPTH_TOPIC, lambda m: self._on_image(1, m), sub_qos)
        self.create_subscription(CameraInfo, CAMERA_INFO_TOPIC, self._on_camera_info, sub_qos)
        self.create_timer(0.25, self._maybe_report)

        self._workers = [threading.Thread(target=self._work, args=(p,), name=f"pipeline{k}", daemon=True)
                         for k, p in enumerate(self._pipelines)]
        for worker in self._workers:
            worker.start()
        self.get_logger().info(
            f"ready: model {self.settings.model_path}, listening on "
            f"{self.resolve_topic_name(COLOUR_TOPIC)} + {self.resolve_topic_name(DEPTH_TOPIC)} "
            f"({self.settings.qos_reliability})")

    # ---- parameters -------------------------------------------------------------------
    def _validate_parameters(self, params) -> SetParametersResult:
        reason = check_parameters(self._specs, params)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply_parameters(self, params) -> None:
        pipeline_changes, node_changes = {}, {}
        for p in params:
            (node_changes if p.name in NodeSettings.__dataclass_fields__ else pipeline_changes)[p.name] = \
                self._specs[p.name].check(p.value)
        if node_changes:
            self.settings = node_settings({**asdict(self.settings), **node_changes})
            self._sync.set_slop(int(self.settings.sync_slop_s * 1e9))
        if pipeline_changes:
            # Takes effect on the next frame: it goes to the pipeline process with the frame.
            self.config = with_overrides(self.config, pipeline_changes)
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{k}={v!r}" for k, v in {**node_changes, **pipeline_changes}.items()))

    # ---- input ------------------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._intrinsics = camera_info_to_intrinsics(msg)
            self._have_intrinsics.set()
        except InputError as exc:
            self.get_logger().warn(f"ignoring camera_info: {exc}", throttle_duration_sec=5.0)

    def _on_image(self, stream: int, msg: Image) -> None:
        now = time.monotonic()
        with self._counters_lock:
            if stream == 0:
                self.counters.colour_received += 1
            else:
                self.counters.depth_received += 1
        pair = self._sync.add(stream, stamp_to_ns(msg.header.stamp), msg)
        if pair is None:
            return
        with self._counters_lock:
            self.counters.synchronised += 1
            self._sequence += 1
            if self._slot.put(_Pair(pair[0], pair[1], now, time.time_ns(), self._sequence)):
                self.counters.dropped += 1

    # ---- the worker -------------------------------------------------------------------
    def _work(self, pipeline) -> None:
        while not self._slot.closed:
            pair = self._slot.take(timeout=0.5, fresher=self.settings.wait_for_fresher)
            if pair is not None:
                self._process(pair, pipeline)

    def _count(self, name: str) -> None:
        with self._counters_lock:
            setattr(self.counters, name, getattr(self.counters, name) + 1)

    def _process(self, pair: _Pair, pipeline) -> None:
        log = self.get_logger()
        if self._intrinsics is None:
            # At start-up the first camera_info can trail the first images: a reliable reader
            # holds later samples back until a lost one is repaired (Fast DDS heartbeats: 3 s).
            self._have_intrinsics.wait(timeout=3.5)
        intrinsics = self._intrinsics
        if intrinsics is None:
            self._count("no_camera_info")
            log.warn(f"no camera_info received on {self.resolve_topic_name(CAMERA_INFO_TOPIC)} yet; "
                     "skipping frames until it arrives", throttle_duration_sec=5.0)
            return
        try:
            rgb = colour_to_rgb(pair.colour)
            depth = depth_to_metres(pair.depth, self.settings.depth_scale)
            result = pipeline.register(rgb, depth, intrinsics, self.config)  # checks sizes
        except InputError as exc:
            self._count("bad")
            log.warn(f"skipping a malformed frame: {exc}", throttle_duration_sec=2.0)
            return
        except RuntimeError as exc:  # a bug must not take the camera pipeline down with it
            self._count("failed")
            log.error(f"the pipeline failed on a frame: {exc}", throttle_duration_sec=2.0)
            return
        header = pair.colour.header
        with self._publish_lock:
            if pair.sequence < self._last_published:
                # With several pipeline processes a newer frame can finish first: never go back.
                self._count("dropped")
                return
            self._last_published = pair.sequence
            self._pub_poses.publish(conversions.pose_array(result.instances, header))
            if self._pub_detections is not None:
                self._pub_detections.publish(result.instances, header)
            # Latency as a user sees it: pair complete -> poses out (waiting for a worker included).
            latency_ms = (time.monotonic() - pair.received) * 1e3
            with self._counters_lock:
                self.counters.processed += 1
                self._latencies.append(latency_ms)
            counters = self.frame_counts()
            self._pub_details.publish(conversions.details_message(
                stamp_to_ns(header.stamp), header.frame_id, latency_ms, result.instances,
                timings_ms={k: round(float(v), 2) for k, v in result.timings_ms.items()},
                received_ns=pair.received_ns, published_ns=time.time_ns(), counters=counters))
            markers, self._marker_ids = conversions.marker_array(
                result.instances, header, np.zeros(3), self.model.extent, self._marker_ids)
            self._pub_markers.publish(markers)
        if self.settings.publish_debug_image or self._pub_debug.get_subscription_count() > 0:
            self._publish_debug_image(rgb, result, intrinsics, header)

    def _publish_debug_image(self, rgb, result, intrinsics, header) -> None:
        from ..rgbd.overlay import draw_overlay

        overlay = draw_overlay(rgb, result, intrinsics, self.model.box_corners(), conversions.instance_colour)
        fields = array_to_image_fields(overlay, "rgb8")
        fields["data"] = fields["data"].tobytes()
        msg = Image(**fields)
        msg.header = header
        self._pub_debug.publish(msg)

    # ---- statistics -------------------------------------------------------------------
    def frame_counts(self) -> dict:
        with self._counters_lock:
            counts = asdict(self.counters)
        sync = self._sync.counters
        counts["unmatched"] = sync.unmatched + sync.stale  # images that never found a partner
        return counts

    def stats(self) -> dict:
        stats = self.frame_counts()
        with self._counters_lock:
            lat = np.array(self._latencies) if self._latencies else None
        stats["latency_ms_p50"] = round(float(np.percentile(lat, 50)), 2) if lat is not None else None
        stats["latency_ms_p95"] = round(float(np.percentile(lat, 95)), 2) if lat is not None else None
        stats["latency_ms_mean"] = round(float(lat.mean()), 2) if lat is not None else None
        return stats

    def _maybe_report(self) -> None:
        now = time.monotonic()
        if now - self._last_stats < self.settings.stats_log_period_s:
            return
        self._last_stats = now
        stats = self.stats()
        self._pub_stats.publish(String(data=json.dumps(stats)))
        self.get_logger().info(
            f"frames: {stats['processed']} processed, {stats['dropped']} dropped, {stats['bad']} bad, "
            f"{stats['unmatched']} unmatched, {stats['no_camera_info']} without camera_info; "
            f"latency p50 {stats['latency_ms_p50']} ms, p95 {stats['latency_ms_p95']} ms")

    def destroy_node(self):
        self._slot.close()
        for worker in self._workers:
            worker.join(timeout=5.0)
        for pipeline in self._pipelines:
            pipeline.close()
        return super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    use_large_data_profile()
    try:
        rclpy.init(args=argv)
    except Exception as exc:  # rcl's own error for malformed --ros-args, with a C backtrace
        print(f"{NODE_NAME}: error: cannot parse the --ros-args: {str(exc).split(', at ')[0]}", file=sys.stderr)
        return 1
    try:
        node = InstanceRegistrationNode()
    except InputError as exc:
        print(f"{NODE_NAME}: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
