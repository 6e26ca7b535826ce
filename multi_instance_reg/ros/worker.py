"""The per-frame pipeline in a process of its own, so that it never holds the node's GIL.

In one process the pipeline's Python stretches starved the executor thread: image callbacks
ran late and a reliable reader's queue overflowed (about 2 % of 30 Hz frames lost, measured).
Here the node's process only converts messages and publishes; frames go to the child over a
pipe (about 2 MB, a few ms) and the FrameResult comes back. No ROS import: the child needs
none. The child runs ``MultiModelRegistration`` over every model (one SIFT pass per frame);
a new set of models is a new child (``PipelineProcess.start_many``), started while the old
one still serves.
"""
from __future__ import annotations

import multiprocessing
import os
import threading

from ..errors import InputError


class PipelineClosed(RuntimeError):
    """The process was closed (its models were replaced) before it took this frame."""


def _serve(conn, models, config, niceness: int = 0) -> None:
    """The child: build the pipeline, then answer frames until told to stop (None)."""
    from ..rgbd.multi_model import MultiModelRegistration

    try:
        if niceness:
            os.nice(niceness)  # behind the node's per-frame work (tracking) on a busy CPU
        pipeline = MultiModelRegistration(models, config)
        pipeline.warm_up()  # one-off compilation now, not in the first frame's latency
    except Exception as exc:  # reported to the parent, which stops with one clear line
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", None))
    while True:
        try:
            job = conn.recv()
        except (EOFError, KeyboardInterrupt):
            return
        if job is None:
            return
        rgb, depth, intrinsics, new_config, gravity = job
        try:
            if new_config != pipeline.config:
                pipeline = MultiModelRegistration(models, new_config)
                pipeline.warm_up()
            conn.send(("ok", pipeline.register_frame(rgb, depth, intrinsics, gravity)))
        except InputError as exc:
            conn.send(("input_error", str(exc)))
        except Exception as exc:  # a bug on one frame must not end the stream
            conn.send(("failed", f"{type(exc).__name__}: {exc}"))


class PipelineProcess:
    """``register(rgb, depth_m, intrinsics, config, gravity=None) -> FrameResult`` of every model, run in a child
    process. Raises InputError for a frame the pipeline refuses, RuntimeError when the pipeline
    failed (the child is restarted if it died) and PipelineClosed once ``close`` was called."""

    def __init__(self, models, config, start_timeout: float = 300.0, wait: bool = True, niceness: int = 0):
        self._models = list(models)
        self._niceness = niceness
        self._start_timeout = start_timeout
        self._lock = threading.RLock()  # one frame at a time; close() waits for it
        self._closed = False
        self._launch(config)
        if wait:
            self.wait_ready()

    @classmethod
    def start_many(cls, models, config, count: int, niceness: int = 0) -> list["PipelineProcess"]:
        """``count`` pipeline processes, started together (each spends seconds warming up)."""
        started = [cls(models, config, wait=False, niceness=niceness) for _ in range(count)]
        try:
            for p in started:
                p.wait_ready()
        except InputError:
            for p in started:
                p.close()
            raise
        return started

    def _start(self, config) -> None:
        self._launch(config)
        self.wait_ready()

    def _launch(self, config) -> None:
        # spawn, not fork: the parent runs DDS threads, which a fork would copy half-way.
        ctx = multiprocessing.get_context("spawn")
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child_conn, self._models, config, self._niceness),
                                 name="instance_registration_pipeline", daemon=True)
        self._proc.start()
        child_conn.close()

    def wait_ready(self) -> None:
        if not self._conn.poll(self._start_timeout):
            self.close()
            raise InputError(f"the pipeline process did not start within {self._start_timeout:g} s")
        try:
            status, payload = self._conn.recv()
        except EOFError:
            status, payload = "error", f"the pipeline process exited with code {self._proc.exitcode}"
        if status != "ready":
            self.close()
            raise InputError(f"cannot start the pipeline: {payload}")

    @property
    def pid(self) -> int:
        return self._proc.pid

    def register(self, rgb, depth_m, intrinsics, config, gravity=None):
        with self._lock:
            if self._closed:
                raise PipelineClosed("the pipeline process was closed")
            try:
                self._conn.send((rgb, depth_m, intrinsics, config, gravity))
                status, payload = self._conn.recv()
            except (EOFError, BrokenPipeError, ConnectionResetError):
                code = self._proc.exitcode
                self._stop()
                self._start(config)
                raise RuntimeError(f"the pipeline process died (exit code {code}); restarted it") from None
        if status == "ok":
            return payload
        if status == "input_error":
            raise InputError(payload)
        raise RuntimeError(payload)

    def close(self) -> None:
        """Stop the child, after the frame it is working on (if any)."""
        with self._lock:
            self._closed = True
            self._stop()

    def _stop(self) -> None:
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._proc.join(timeout=5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=5.0)
        self._conn.close()
