"""``instance_registration_node``: every instance's pose from a live RGB-D stream.

Subscribes to colour, aligned depth and camera_info (realsense-ros names by default; remap
to change), or to depth recorded unaligned with its camera_info and the depth to colour
extrinsics, registered to colour here (``depth_registration``; ``rgbd.registration``), pairs
colour and depth by header stamp, takes the direction of gravity per frame
from the camera's accelerometer when it is published (``camera/camera/accel/sample``,
``gravity_source``), and publishes:

- ``instances/poses`` (geometry_msgs/PoseArray): model frame in the camera optical frame,
  every object's instances, by object (the models' order), then by track_id (tracking off: by
  id, the rank by inliers);
- ``instances/<name>/poses`` (PoseArray): one object's instances (one topic per loaded model);
- ``instances/detections`` (vision_msgs/Detection3DArray, when vision_msgs is installed) and
  ``instances/label_info`` (vision_msgs/LabelInfo, transient local): ``detections.py``;
- ``instances/markers`` (visualization_msgs/MarkerArray): box + label per instance, namespace =
  object name, marker id and colour = track id; deleted when the track ends;
- ``instances/details`` (std_msgs/String, JSON): object, id, inliers, score, track_id, state,
  source, age per instance, latency;
- ``instances/debug_image`` (sensor_msgs/Image rgb8): only drawn when subscribed or asked;
- ``~/stats`` (std_msgs/String, JSON): frame counts and latency, also logged.
Names are relative to the node's namespace (root: ``/instances/poses``; with
``-r __ns:=/left``: ``/left/instances/poses`` and ``/left/camera/camera/...`` in).

With tracking (``tracking.enabled``, the default) a tracking thread takes every synchronised
pair, brings the tracks up to date on it (``tracking.LiveTracker``: ICP against the depth, a
few ms) and publishes at once; then it hands the frame to the detector, the per-frame
pipeline (``multi_instance_reg.rgbd.pipeline``) in a child process (``worker.py``, niced so
that tracking wins the CPU), which always takes the newest frame and feeds what it found back
to the tracker for the frame it was found on. Without tracking the detector's results are
published as they are, for the frames it processed.

Models: ``model_paths`` (and/or the older ``model_path``), all found in one SIFT pass
(``rgbd.multi_model``), one tracker per object (``tracking.LiveObjectTrackers``). Setting
``model_paths`` at run time loads the files first (a bad one, or two models with one name,
is refused with the reason and nothing changes), then starts a detector process for the new
set while the old one goes on, and switches when it is ready (``_swap_models``).

Callbacks never wait for either: a synchronised pair goes into a one-frame mailbox and the
thread behind it always takes the newest one (the pipeline runs in a child process, so it
never holds this process's GIL); pairs replaced before they were taken are counted as
dropped, so latency cannot queue up when the camera outruns the node.

Run: ``instance_registration_node --ros-args --params-file config/params.yaml
-p "model_paths:=[snack_bar.npz, can.npz]"`` (or ``python -m multi_instance_reg.ros.node ...``).
"""
from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass

# Ctrl-C in the second or two these imports take ends the start quietly, like one later on.
try:
    import numpy as np
    import rclpy
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, Imu
    from geometry_msgs.msg import PoseArray
    from std_msgs.msg import String
    from visualization_msgs.msg import MarkerArray

    from ..errors import InputError
    from ..gravity import AccelWindow, imu_accel
    from ..messages import array_to_image_fields, camera_info_to_intrinsics, colour_to_rgb, depth_to_metres
    from ..params import param_specs, with_overrides
    from . import conversions
    from .conversions import ObjectClass
    from .detections import DetectionPublisher
    from .parameters import (READ_ONLY, NodeSettings, all_specs, check_parameters, declare, node_settings, node_specs,
                             tracking_specs)
    from .sync import ApproximateTimeSync, LatestSlot, stamp_to_ns
    from .transport import use_large_data_profile
except KeyboardInterrupt:
    print("instance_registration: interrupted while starting", file=sys.stderr)
    raise SystemExit(130) from None

NODE_NAME = "instance_registration"
# Relative names: `--ros-args -r __ns:=/left` moves inputs and outputs together (one node per
# camera); in the root namespace they resolve to /camera/camera/... and /instances/...
COLOUR_TOPIC = "camera/camera/color/image_raw"
DEPTH_TOPIC = "camera/camera/aligned_depth_to_color/image_raw"
CAMERA_INFO_TOPIC = "camera/camera/color/camera_info"
ACCEL_TOPIC = "camera/camera/accel/sample"   # realsense-ros' accelerometer (best effort: sensor data QoS)
# realsense-ros without align_depth.enable: the depth imager's own stream, its intrinsics and the
# extrinsics from depth to colour (published once, transient local).
UNALIGNED_DEPTH_TOPIC = "camera/camera/depth/image_rect_raw"
DEPTH_INFO_TOPIC = "camera/camera/depth/camera_info"
EXTRINSICS_TOPIC = "camera/camera/extrinsics/depth_to_color"
LATENCY_WINDOW = 300  # frames kept for the latency percentiles


def image_subscriptions(transport: str):
    """(message type, colour topic, depth topic) for ``image_transport``: image_transport's
    names, <topic>/compressed for colour and <topic>/compressedDepth for depth."""
    if transport == "compressed":
        from sensor_msgs.msg import CompressedImage

        return CompressedImage, COLOUR_TOPIC + "/compressed", DEPTH_TOPIC + "/compressedDepth"
    return Image, COLOUR_TOPIC, DEPTH_TOPIC


def unaligned_depth_topic(transport: str) -> str:
    return UNALIGNED_DEPTH_TOPIC + "/compressedDepth" if transport == "compressed" else UNALIGNED_DEPTH_TOPIC


@dataclass
class FrameCounters:
    colour_received: int = 0
    depth_received: int = 0
    synchronised: int = 0
    processed: int = 0
    dropped: int = 0          # synchronised pairs replaced by a newer one before processing
    bad: int = 0              # malformed images (encoding, step, sizes), skipped
    no_camera_info: int = 0   # pairs skipped because no camera_info had arrived yet
    no_extrinsics: int = 0    # pairs of unaligned depth skipped: no depth camera_info or extrinsics yet
    failed: int = 0           # pipeline raised on a frame, skipped
    detected: int = 0         # frames the detector (the full pipeline) ran on
    deadline_cut: int = 0     # of those, frames whose shape search frontend.shape_deadline_ms stopped
    model_swaps: int = 0      # run-time changes of the models, done
    accel_received: int = 0   # accelerometer samples
    with_gravity: int = 0     # frames given the direction of gravity (the rest go without)


@dataclass
class _Pair:
    colour: Image
    depth: Image
    received: float  # time.monotonic() when the pair was complete
    received_ns: int  # the same moment on the wall clock (comparable with header stamps)
    sequence: int
    unaligned: bool = False   # the depth is the depth imager's own, to be registered to colour


@dataclass
class _Frame:
    """A pair converted and tracked, waiting for the detector."""
    pair: _Pair
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: object
    gravity: np.ndarray | None = None


class InstanceRegistrationNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        from ..rgbd.pipeline import PipelineConfig
        from ..tracking import LiveConfig, LiveObjectTrackers, TrackerConfig
        from .worker import PipelineProcess

        node_values = declare(self, node_specs(), READ_ONLY)
        pipeline_values = declare(self, param_specs(PipelineConfig()))
        tracking_values = declare(self, tracking_specs(), READ_ONLY)
        self._specs = {s.name: s for s in all_specs()}
        self._warn_unknown_parameters()
        self.settings = node_settings(node_values)
        self.config = with_overrides(PipelineConfig(), pipeline_values)
        live = {k: v for k, v in _tracker_fields(tracking_values).items() if k in LiveConfig.__dataclass_fields__}
        self.live_config = LiveConfig(**live)
        tracking = self.live_config.enabled
        self.tracker_config = with_overrides(TrackerConfig(), {
            k: v for k, v in _tracker_fields(tracking_values).items() if k not in live})
        self._loaded: dict = {}   # model file -> (its mtime, the model): unchanged files keep their tracks
        self.model_files, self.models = self._load_models(model_files(self.settings.model_path,
                                                                      self.settings.model_paths))
        self._pending_models = None  # validated by _validate_parameters, applied by _apply_parameters
        self._swap_lock = threading.Lock()
        # The pipeline runs in child processes (see worker.py): it never holds our GIL. With
        # tracking it is the detector, behind the tracking of every frame (niced).
        self._niceness = self.settings.detector_niceness if tracking else 0
        self._pipelines = PipelineProcess.start_many(self.models, self.config, self.settings.pipeline_processes,
                                                     niceness=self._niceness, keep_running=self.context.ok)
        self._tracker = LiveObjectTrackers(self.models, self.tracker_config, self.live_config) if tracking else None
        if tracking:
            from ..tracking.icp import warm_up
            warm_up()   # the depth alignment compiled now, not in the first detection carried forward

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
        self._slot = LatestSlot()        # the detector's input: pairs, or frames already tracked
        self._track_slot = LatestSlot()  # the tracking thread's input (tracking on)
        self._intrinsics = None
        self._camera_info_refused: str | None = None   # why the last camera_info was not taken
        self._have_intrinsics = threading.Event()
        self._latest_stamps: list[int | None] = [None, None]   # colour, depth: for the pairing warning
        self._unpaired_since_pair = [0, 0]
        self._pairing_warned = False
        self._latencies = deque(maxlen=LATENCY_WINDOW)
        self._detection_latencies = deque(maxlen=LATENCY_WINDOW)  # pair complete -> detections fused
        self._last_detection: dict | None = None
        self._marker_ids: set = set()   # (namespace, id) of the markers shown
        self._publish_lock = threading.Lock()
        self._sequence = 0          # of synchronised pairs, to publish results in order
        self._last_published = -1
        self._last_stats = time.monotonic()

        self._pub_poses = self.create_publisher(PoseArray, "instances/poses", pub_qos)
        self._pub_markers = self.create_publisher(MarkerArray, "instances/markers", pub_qos)
        self._pub_details = self.create_publisher(String, "instances/details", pub_qos)
        self._pub_debug = self.create_publisher(Image, "instances/debug_image", pub_qos)
        self._pub_qos = pub_qos
        self._objects = {m.name: ObjectClass.of_model(m) for m in self.models}
        self._pub_object_poses = {name: self.create_publisher(PoseArray, object_poses_topic(name), pub_qos)
                                  for name in self._objects}
        self._pub_detections = DetectionPublisher.create(self, pub_qos, list(self._objects.values()))
        self._pub_stats = self.create_publisher(String, "~/stats", pub_qos)
        image_type, colour_topic, depth_topic = image_subscriptions(self.settings.image_transport)
        self.create_subscription(image_type, colour_topic, lambda m: self._on_image(0, m), sub_qos)
        self.create_subscription(CameraInfo, CAMERA_INFO_TOPIC, self._on_camera_info, sub_qos)
        mode = self.settings.depth_registration
        self._aligned_seen = False
        self._depth_intrinsics = None
        self._colour_from_depth = None
        self._have_depth_calibration = threading.Event()   # both of the above
        depth_topics = []
        if mode != "unaligned":
            self.create_subscription(image_type, depth_topic, self._on_aligned_depth, sub_qos)
            depth_topics.append(depth_topic)
        if mode != "aligned" and self._subscribe_unaligned(image_type, sub_qos):
            depth_topics.append(unaligned_depth_topic(self.settings.image_transport))
        self._accel = AccelWindow()
        self._accel_lock = threading.Lock()
        self._accel_subscription = None
        self._gravity_warned = False
        self._subscribe_accel()
        self.create_timer(0.25, self._maybe_report)

        self._workers = [threading.Thread(target=self._work, args=(k,), name=f"pipeline{k}", daemon=True)
                         for k in range(len(self._pipelines))]
        if self._tracker is not None:
            self._workers.append(threading.Thread(target=self._track_frames, name="tracking", daemon=True))
        for worker in self._workers:
            worker.start()
        self.get_logger().info(
            f"ready: models {', '.join(f'{m.name} ({f})' for m, f in zip(self.models, self.model_files))}, listening on "
            f"{self.resolve_topic_name(colour_topic)} + {' or '.join(map(self.resolve_topic_name, depth_topics))} "
            f"({self.settings.qos_reliability}); tracking {'on' if self._tracker else 'off'}")

    # ---- parameters -------------------------------------------------------------------
    def _warn_unknown_parameters(self) -> None:
        """Once per name: a value from -p or a parameter file for a parameter this node does not
        have (a typo, an older name) would otherwise be dropped without a word."""
        import difflib

        declared = set(self._parameters)
        for name in sorted(set(self._parameter_overrides) - declared):
            close = difflib.get_close_matches(name, sorted(declared), n=1, cutoff=0.75)
            hint = f"did you mean {close[0]}? " if close else ""
            self.get_logger().warn(f"unknown parameter {name} (ignored): {hint}config/params.yaml lists every "
                                   "parameter of this node")

    def _load_models(self, files: list[str]):
        """(files, models) with every file loaded and checked (InputError naming the problem);
        a file loaded before and unchanged since gives the same model object."""
        from pathlib import Path

        from ..rgbd.multi_model import check_model_names
        from ..models.model import load_model

        if not files:
            raise InputError("no model: pass -p \"model_paths:=[A.npz, B.npz]\" or -p model_path:=MODEL "
                             "(build one with `mireg build-model --name NAME`)")
        models = []
        for f in files:
            mtime = Path(f).stat().st_mtime_ns if Path(f).is_file() else None
            cached = self._loaded.get(f)
            models.append(cached[1] if cached is not None and cached[0] == mtime else load_model(f))
        check_model_names(models, files)
        self._loaded = {f: (Path(f).stat().st_mtime_ns, m) for f, m in zip(files, models)}
        return files, models

    def _validate_parameters(self, params) -> SetParametersResult:
        reason = check_parameters(self._specs, params)
        self._pending_models = None
        new_paths = [p.value for p in params if p.name == "model_paths"]
        if reason is None and new_paths:
            # Load before accepting: a bad file is refused here and the current models stay.
            try:
                self._pending_models = self._load_models(model_files(self.settings.model_path, new_paths[-1]))
            except InputError as exc:
                reason = f"model_paths refused, the node keeps {', '.join(m.name for m in self.models)}: {exc}"
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply_parameters(self, params) -> None:
        pipeline_changes, node_changes, tracking_changes = {}, {}, {}
        for p in params:
            group = (node_changes if p.name in NodeSettings.__dataclass_fields__ else
                     tracking_changes if p.name.startswith("tracking.") else pipeline_changes)
            group[p.name] = self._specs[p.name].check(p.value)
        if node_changes:
            self.settings = node_settings({**asdict(self.settings), **node_changes})
            self._sync.set_slop(int(self.settings.sync_slop_s * 1e9))
            self._subscribe_accel()
        if "model_paths" in node_changes and self._pending_models is not None:
            # The new detector process takes seconds to start: the old one serves meanwhile.
            pending, self._pending_models = self._pending_models, None
            threading.Thread(target=self._swap_models, args=pending, name="swap_models", daemon=True).start()
        if pipeline_changes:
            # Takes effect on the next frame: it goes to the pipeline process with the frame.
            self.config = with_overrides(self.config, pipeline_changes)
        if tracking_changes:
            # From the next frame on; the tracks and their ids stay.
            self.tracker_config = with_overrides(self.tracker_config, _tracker_fields(tracking_changes))
            if self._tracker is not None:
                self._tracker.set_config(self.tracker_config)
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{k}={v!r}" for k, v in {**node_changes, **pipeline_changes, **tracking_changes}.items()))

    def _swap_models(self, files: list[str], models: list) -> None:
        """A detector process for ``models`` is started beside the running one; once it is ready
        the detector threads take it for their next frame, the trackers of objects gone end,
        new objects get theirs and their topics, and the old process is closed after the frame
        it is working on. Swaps run one after the other (the newest set is the last one)."""
        from .worker import PipelineProcess

        with self._swap_lock:
            t0 = time.monotonic()
            try:
                pipelines = PipelineProcess.start_many(models, self.config, len(self._pipelines),
                                                       niceness=self._niceness, keep_running=self.context.ok)
            except InputError as exc:
                self.get_logger().error(f"cannot load the new models, keeping the current ones: {exc}")
                return
            with self._publish_lock:
                old, self._pipelines = self._pipelines, pipelines
                if self._tracker is not None:
                    self._tracker.set_models(models)
                self.models, self.model_files = models, files
                self._objects = {m.name: ObjectClass.of_model(m) for m in models}
                for name in set(self._pub_object_poses) - set(self._objects):
                    self.destroy_publisher(self._pub_object_poses.pop(name))
                for name in self._objects:
                    if name not in self._pub_object_poses:
                        self._pub_object_poses[name] = self.create_publisher(
                            PoseArray, object_poses_topic(name), self._pub_qos)
                if self._pub_detections is not None:
                    self._pub_detections.set_objects(list(self._objects.values()))
            for pipeline in old:
                pipeline.close()
            self._count("model_swaps")
            self.get_logger().info(f"models now: {', '.join(m.name for m in models)} "
                                   f"(the new detector was ready after {time.monotonic() - t0:.1f} s)")

    # ---- input ------------------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._intrinsics = camera_info_to_intrinsics(msg)
            self._camera_info_refused = None
            self._have_intrinsics.set()
        except InputError as exc:
            self._camera_info_refused = str(exc)
            self.get_logger().warn(f"ignoring camera_info: {exc}", throttle_duration_sec=5.0)

    def _subscribe_accel(self) -> None:
        """With ``gravity_source`` imu, listen to the accelerometer (once; "none" later only
        stops using it)."""
        if self.settings.gravity_source == "imu" and self._accel_subscription is None:
            # realsense-ros publishes its IMU topics best effort ("SENSOR_DATA"); a best-effort
            # reader also meets a reliable writer (a bag played back). Deeper than sensor data's
            # 5: at 200 Hz a callback held up by an image for 25 ms would lose samples.
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
            self._accel_subscription = self.create_subscription(Imu, ACCEL_TOPIC, self._on_accel, qos)

    def _on_accel(self, msg: Imu) -> None:
        with self._accel_lock:
            self._accel.add(stamp_to_ns(msg.header.stamp), imu_accel(msg))
        self._count("accel_received")

    def _gravity(self, stamp_ns: int):
        """The frame's "up" from the accelerometer samples of the 0.1 s before its stamp, or None
        (``gravity_source`` none, no samples, stale ones, or not about 1 g): the pipeline then
        goes without, never fails for it."""
        if self.settings.gravity_source != "imu":
            return None
        with self._accel_lock:
            up, received = self._accel.up_at(stamp_ns), self._accel.received
        if up is not None:
            self._count("with_gravity")
        elif received and not self._gravity_warned:
            self._gravity_warned = True
            self.get_logger().warn(
                f"accelerometer samples arrive on {self.resolve_topic_name(ACCEL_TOPIC)} but none within 0.1 s "
                "before a frame's stamp (another clock? stopped?) or not about 1 g: frames go without gravity "
                "until they do")
        return up

    def _subscribe_unaligned(self, image_type, sub_qos) -> bool:
        """Subscriptions for depth recorded unaligned; False when realsense2_camera_msgs (the
        extrinsics' type) is not installed (logged)."""
        from rclpy.qos import DurabilityPolicy

        try:
            from realsense2_camera_msgs.msg import Extrinsics
        except ImportError:
            log = self.get_logger().error if self.settings.depth_registration == "unaligned" else self.get_logger().info
            log("realsense2_camera_msgs is not installed, so the depth to colour extrinsics cannot be received: "
                "only aligned depth is read (run `make install`, or start realsense-ros with align_depth.enable:=true)")
            return False
        self.create_subscription(image_type, unaligned_depth_topic(self.settings.image_transport),
                                 self._on_unaligned_depth, sub_qos)
        self.create_subscription(CameraInfo, DEPTH_INFO_TOPIC, self._on_depth_camera_info, sub_qos)
        # realsense-ros publishes the extrinsics once, transient local: a late subscriber still gets them.
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(Extrinsics, EXTRINSICS_TOPIC, self._on_extrinsics, latched)
        return True

    def _on_aligned_depth(self, msg: Image) -> None:
        self._aligned_seen = True
        self._on_image(1, msg)

    def _on_unaligned_depth(self, msg: Image) -> None:
        # auto: realsense-ros publishes the raw depth also when it aligns; the aligned one wins.
        if not self._aligned_seen:
            self._on_image(1, msg, unaligned=True)

    def _on_depth_camera_info(self, msg: CameraInfo) -> None:
        try:
            self._depth_intrinsics = camera_info_to_intrinsics(msg)
            if self._colour_from_depth is not None:
                self._have_depth_calibration.set()
        except InputError as exc:
            self.get_logger().warn(f"ignoring the depth camera_info: {exc}", throttle_duration_sec=5.0)

    def _on_extrinsics(self, msg) -> None:
        # Imported on first use, not with the node's imports: importing numba swallows a Ctrl-C
        # that lands during it (a start-up cut short by a signal must still end).
        from ..rgbd.registration import extrinsics_matrix

        try:
            self._colour_from_depth = extrinsics_matrix(msg.rotation, msg.translation)
            if self._depth_intrinsics is not None:
                self._have_depth_calibration.set()
        except InputError as exc:
            self.get_logger().warn(f"ignoring the extrinsics on {self.resolve_topic_name(EXTRINSICS_TOPIC)}: {exc}",
                                   throttle_duration_sec=5.0)

    def _on_image(self, stream: int, msg: Image, unaligned: bool = False) -> None:
        now = time.monotonic()
        with self._counters_lock:
            if stream == 0:
                self.counters.colour_received += 1
            else:
                self.counters.depth_received += 1
        stamp = stamp_to_ns(msg.header.stamp)
        pair = self._sync.add(stream, stamp, msg if stream == 0 else (msg, unaligned))
        if pair is None:
            self._note_unpaired(stream, stamp)
            return
        self._unpaired_since_pair = [0, 0]
        slot = self._slot if self._tracker is None else self._track_slot
        (depth, depth_unaligned) = pair[1]
        with self._counters_lock:
            self.counters.synchronised += 1
            self._sequence += 1
            if slot.put(_Pair(pair[0], depth, now, time.time_ns(), self._sequence, depth_unaligned)):
                self.counters.dropped += 1

    UNPAIRED_BEFORE_WARNING = 15   # images of each stream without a pair

    def _note_unpaired(self, stream: int, stamp: int) -> None:
        """Warn once when both streams keep arriving and never pair (their stamps further apart
        than sync_slop_s: two clocks, a depth stream not aligned to colour, a bag with shifted
        stamps), with how far apart they are."""
        self._latest_stamps[stream] = stamp
        self._unpaired_since_pair[stream] += 1
        if self._pairing_warned or min(self._unpaired_since_pair) < self.UNPAIRED_BEFORE_WARNING:
            return
        self._pairing_warned = True
        colour, depth = self._latest_stamps
        self.get_logger().warn(
            f"colour and depth images arrive but never pair: the latest depth stamp is {(depth - colour) / 1e6:+.0f} ms "
            f"from the latest colour stamp, more than sync_slop_s ({self.settings.sync_slop_s * 1e3:g} ms) allows; "
            "stamp both from one clock (realsense-ros: align_depth.enable:=true gives depth the colour stamp), "
            "or raise sync_slop_s")

    # ---- the worker threads -----------------------------------------------------------
    def _work(self, index: int) -> None:
        """A detector thread (one per pipeline process; ``index``: which one)."""
        while not self._slot.closed:
            item = self._slot.take(timeout=0.5, fresher=self.settings.wait_for_fresher)
            if item is None:
                continue
            with self._ending_quietly():
                if isinstance(item, _Frame):
                    self._detect(item, index)
                else:
                    self._process(item, index)

    def _track_frames(self) -> None:
        while not self._track_slot.closed:
            pair = self._track_slot.take(timeout=0.5)
            if pair is not None:
                with self._ending_quietly():
                    self._track(pair)

    @contextlib.contextmanager
    def _ending_quietly(self):
        """A frame under way when a signal shut the context down fails to publish (RCLError,
        publisher's context invalid): the stop asked for, so the frame is dropped in silence."""
        try:
            yield
        except Exception:
            if self.context.ok():
                raise

    def _count(self, name: str) -> None:
        with self._counters_lock:
            setattr(self.counters, name, getattr(self.counters, name) + 1)

    def _convert(self, pair: _Pair):
        """(rgb, depth in metres, intrinsics) of a pair, or None when it is skipped (counted)."""
        from ..rgbd.pipeline import check_frame
        from ..rgbd.registration import register_to_colour

        if self._intrinsics is None and self._camera_info_refused is None:
            # At start-up the first camera_info can trail the first images: a reliable reader
            # holds later samples back until a lost one is repaired (Fast DDS heartbeats: 3 s).
            self._have_intrinsics.wait(timeout=3.5)
        intrinsics = self._intrinsics
        if intrinsics is None:
            self._count("no_camera_info")
            topic = self.resolve_topic_name(CAMERA_INFO_TOPIC)
            refused = self._camera_info_refused
            self.get_logger().warn(
                f"skipping frames: the camera_info on {topic} is refused ({refused})" if refused else
                f"no camera_info received on {topic} yet; skipping frames until it arrives", throttle_duration_sec=5.0)
            return None
        if pair.unaligned and not self._have_depth_calibration.is_set() and self.counters.no_extrinsics == 0:
            # As for camera_info: at start-up the depth's camera_info (published after its
            # image) or the extrinsics can trail the first depth image.
            self._have_depth_calibration.wait(timeout=3.5)
        depth_intrinsics, colour_from_depth = self._depth_intrinsics, self._colour_from_depth
        if pair.unaligned and (depth_intrinsics is None or colour_from_depth is None):
            self._count("no_extrinsics")
            missing = DEPTH_INFO_TOPIC if depth_intrinsics is None else EXTRINSICS_TOPIC
            self.get_logger().warn(
                f"depth arrives unaligned but nothing has come on {self.resolve_topic_name(missing)} yet; skipping "
                "frames until it does (realsense-ros publishes the extrinsics once at its start, transient local)",
                throttle_duration_sec=5.0)
            return None
        try:
            rgb = colour_to_rgb(pair.colour)
            depth = depth_to_metres(pair.depth, self.settings.depth_scale)
            if pair.unaligned:
                depth = register_to_colour(depth, depth_intrinsics, intrinsics, colour_from_depth)
            check_frame(rgb, depth, intrinsics)
        except InputError as exc:
            self._count("bad")
            self.get_logger().warn(f"skipping a malformed frame: {exc}", throttle_duration_sec=2.0)
            return None
        return rgb, depth, intrinsics

    def _register(self, index: int, rgb, depth, intrinsics, gravity=None):
        """The detector's FrameResult, or None when it failed on this frame (counted)."""
        from .worker import PipelineClosed

        try:
            while True:
                try:
                    result = self._pipelines[index].register(rgb, depth, intrinsics, self.config, gravity)
                    break
                except PipelineClosed:   # the models were swapped meanwhile: the new process takes it
                    if self._slot.closed or not self.context.ok():   # ... unless the node is shutting down
                        return None
        except InputError as exc:
            self._count("bad")
            self.get_logger().warn(f"skipping a malformed frame: {exc}", throttle_duration_sec=2.0)
            return None
        except RuntimeError as exc:  # a bug must not take the camera pipeline down with it
            self._count("failed")
            self.get_logger().error(f"the pipeline failed on a frame: {exc}", throttle_duration_sec=2.0)
            return None
        self._count("detected")
        if result.deadline_cut:
            self._count("deadline_cut")
        return result

    def _process(self, pair: _Pair, index: int) -> None:
        """Tracking off: detect on the pair and publish what was found."""
        frame = self._convert(pair)
        if frame is None:
            return
        rgb, depth, intrinsics = frame
        result = self._register(index, rgb, depth, intrinsics, self._gravity(stamp_to_ns(pair.colour.header.stamp)))
        if result is None:
            return
        timings = {k: round(float(v), 2) for k, v in result.timings_ms.items()}
        if self._publish(pair, result.instances, timings_ms=timings):
            self._publish_debug_image(rgb, result, intrinsics, pair.colour.header)

    def _track(self, pair: _Pair) -> None:
        """Tracking on: every live track brought to this frame and published, then the frame is
        offered to the detector (which takes the newest when it is free)."""
        frame = self._convert(pair)
        if frame is None:
            return
        rgb, depth, intrinsics = frame
        t0 = time.perf_counter()
        # (The tracker logs it when the stamps go back and it ends every track.)
        tracks = self._tracker.step(stamp_to_ns(pair.colour.header.stamp), depth, intrinsics, rgb)
        tracking_ms = round((time.perf_counter() - t0) * 1e3, 2)
        self._slot.put(_Frame(pair, rgb, depth, intrinsics, self._gravity(stamp_to_ns(pair.colour.header.stamp))))
        if self._publish(pair, tracks, timings_ms={"tracking": tracking_ms, "total": tracking_ms},
                         detection=self._last_detection, tracker=self._tracker.counts()):
            self._publish_debug_image(rgb, None, intrinsics, pair.colour.header, tracks)

    def _detect(self, frame: _Frame, index: int) -> None:
        """Tracking on: full detection on a tracked frame, fed back to the tracker for it."""
        result = self._register(index, frame.rgb, frame.depth, frame.intrinsics, frame.gravity)
        if result is None:
            return
        stamp = stamp_to_ns(frame.pair.colour.header.stamp)
        self._tracker.add_detections(stamp, result.instances)
        latency_ms = (time.monotonic() - frame.pair.received) * 1e3
        with self._counters_lock:
            self._detection_latencies.append(latency_ms)
        self._last_detection = {"stamp_ns": stamp, "instances": len(result.instances),
                                "latency_ms": round(latency_ms, 2),
                                "timings_ms": {k: round(float(v), 2) for k, v in result.timings_ms.items()}}

    def _publish(self, pair: _Pair, instances, **details) -> bool:
        """Poses, details and markers of one frame; False if a newer frame was published already."""
        header = pair.colour.header
        with self._publish_lock:
            if pair.sequence < self._last_published:
                # With several pipeline processes a newer frame can finish first: never go back.
                self._count("dropped")
                return False
            self._last_published = pair.sequence
            # A detector result of models just unloaded (tracking off) names objects gone.
            instances = [inst for inst in instances if inst.object in self._objects]
            self._pub_poses.publish(conversions.pose_array(instances, header))
            for name, pub in self._pub_object_poses.items():
                pub.publish(conversions.pose_array([i for i in instances if i.object == name], header))
            if self._pub_detections is not None:
                self._pub_detections.publish(instances, header)
            # Latency as a user sees it: pair complete -> poses out (waiting for a worker included).
            latency_ms = (time.monotonic() - pair.received) * 1e3
            with self._counters_lock:
                self.counters.processed += 1
                self._latencies.append(latency_ms)
            counters = self.frame_counts()
            self._pub_details.publish(conversions.details_message(
                stamp_to_ns(header.stamp), header.frame_id, latency_ms, instances,
                received_ns=pair.received_ns, published_ns=time.time_ns(), counters=counters, **details))
            markers, self._marker_ids = conversions.marker_array(instances, header, self._objects, self._marker_ids)
            self._pub_markers.publish(markers)
        return True

    def _publish_debug_image(self, rgb, result, intrinsics, header, tracks=None) -> None:
        from ..rgbd.overlay import draw_overlay

        if not (self.settings.publish_debug_image or self._pub_debug.get_subscription_count() > 0):
            return
        overlay = draw_overlay(rgb, result, intrinsics, {m.name: m.box_corners() for m in self.models},
                               conversions.instance_colour,
                               instances=tracks)
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
        stats["objects"] = list(self._objects)
        with self._counters_lock:
            lat = np.array(self._latencies) if self._latencies else None
        stats["latency_ms_p50"] = round(float(np.percentile(lat, 50)), 2) if lat is not None else None
        stats["latency_ms_p95"] = round(float(np.percentile(lat, 95)), 2) if lat is not None else None
        stats["latency_ms_mean"] = round(float(lat.mean()), 2) if lat is not None else None
        if self._tracker is not None:
            with self._counters_lock:
                det = np.array(self._detection_latencies) if self._detection_latencies else None
            # How far behind the camera the detections are when they reach the tracker.
            stats["detection_latency_ms_p50"] = round(float(np.percentile(det, 50)), 2) if det is not None else None
            stats.update(self._tracker.counts())
        return stats

    def _maybe_report(self) -> None:
        now = time.monotonic()
        if not rclpy.ok() or now - self._last_stats < self.settings.stats_log_period_s:
            return
        self._last_stats = now
        stats = self.stats()
        self._pub_stats.publish(String(data=json.dumps(stats)))
        self.get_logger().info(
            f"frames: {stats['processed']} processed, {stats['dropped']} dropped, {stats['bad']} bad, "
            f"{stats['unmatched']} unmatched, {stats['no_camera_info']} without camera_info; "
            f"latency p50 {stats['latency_ms_p50']} ms, p95 {stats['latency_ms_p95']} ms"
            + (f"; {stats['detected']} detected (p50 {stats['detection_latency_ms_p50']} ms behind), "
               f"{stats['tracks_live']} tracks live" if self._tracker is not None else ""))

    def destroy_node(self):
        self._track_slot.close()
        self._slot.close()
        for worker in self._workers:
            worker.join(timeout=5.0)
        for pipeline in self._pipelines:
            pipeline.close()
        return super().destroy_node()


def model_files(model_path: str, model_paths) -> list[str]:
    """The model files to load: ``model_path`` (the older, single-model parameter) first, then
    ``model_paths``; a file named twice is loaded once."""
    return list(dict.fromkeys([*([model_path] if model_path else []), *model_paths]))


def object_poses_topic(name: str) -> str:
    return f"instances/{name}/poses"


def _tracker_fields(values: dict) -> dict:
    """{"tracking.coast_s": v} -> {"coast_s": v}: TrackerConfig's own names."""
    return {name.split(".", 1)[1]: value for name, value in values.items()}


def main(argv: list[str] | None = None) -> int:
    sys.unraisablehook = _quiet_half_built_executor(sys.unraisablehook)
    try:
        return _main(argv)
    except KeyboardInterrupt:   # before rclpy took over the signals, or between its steps
        return _stopped_while_starting()


def _quiet_half_built_executor(hook):
    """The unraisable-exception hook, less one case: a signal that lands inside rclpy's
    Executor() (rclpy.spin makes one) leaves it without the attributes its __del__ reads, and
    Python would print that AttributeError as a traceback while the node stops as asked."""
    def quiet(unraisable):
        obj = getattr(unraisable, "object", None)
        if (isinstance(unraisable.exc_value, AttributeError) and getattr(obj, "__qualname__", "") == "Executor.__del__"):
            return
        hook(unraisable)
    return quiet


def _main(argv: list[str] | None) -> int:
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
        if not rclpy.ok():   # e.g. a parameter's declaration refused by the context a signal shut down
            return _stopped_while_starting()
        print(f"{NODE_NAME}: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return _stopped_while_starting()
    except Exception:
        # A signal shuts the context down under the constructor: its next publisher or
        # subscription fails (RCLError). That is the stop asked for, not an error.
        if rclpy.ok():
            raise
        return _stopped_while_starting()
    interrupted = False
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        interrupted = True   # (KeyboardInterrupt may come before rclpy's handler shut the context down)
    except Exception:
        # A timer's publish racing a Ctrl-C finds its context invalid: that is the shutdown
        # itself, not an error. Anything raised while the context is still up is.
        if rclpy.ok():
            raise
        interrupted = True
    finally:
        if interrupted or not rclpy.ok():   # printed: the node's logger would try rosout, going down too
            print(f"{NODE_NAME}: interrupted, stopping", file=sys.stderr, flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _stopped_while_starting() -> int:
    """Ctrl-C or SIGTERM before the node was up: one line, the detector processes already closed
    (PipelineProcess.start_many) or ended with this process (daemons)."""
    print(f"{NODE_NAME}: interrupted while starting", file=sys.stderr, flush=True)
    rclpy.try_shutdown()
    return 130


if __name__ == "__main__":
    sys.exit(main())
