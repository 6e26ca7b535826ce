"""The per-frame pipeline in a process of its own, so that it never holds the node's GIL.

In one process the pipeline's Python stretches starved the executor thread: image callbacks
ran late and a reliable reader's queue overflowed (about 2 % of 30 Hz frames lost, measured).
Here the node's process only converts messages and publishes; frames go to the child over a
pipe (about 2 MB, a few ms) and the FrameResult comes back. No ROS import: the child needs
none. The child runs ``MultiModelRegistration`` over every model (one SIFT pass per frame);
a new set of models is a new child (``PipelineProcess.start_many``), started while the old
one still serves.

Stopping: the child never takes SIGINT (it is spawned with SIGINT blocked), so Ctrl-C in a
terminal, which reaches the whole process group, stops the node only, and the node stops the
child after its frame. A child whose node is gone (killed) exits by itself with one line.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import time
from multiprocessing import resource_tracker

from ..errors import InputError


_HELD_AT_SPAWN = {signal.SIGINT, signal.SIGTERM}   # see PipelineProcess._launch


class PipelineClosed(RuntimeError):
    """The process was closed (its models were replaced) before it took this frame."""


class _ParentGone(Exception):
    """The pipe to the node broke: the node process ended without closing the child."""


def _serve(conn, models, config, niceness: int = 0) -> None:
    """The child: build the pipeline, then answer frames until told to stop (None) or the node
    is gone (the pipe closed or broken: one line, then exit)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # blocked since the spawn; the node decides
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})   # close() may need to terminate us
    try:
        _answer_frames(conn, models, config, niceness)
    except _ParentGone:
        print(f"instance_registration detector (pid {os.getpid()}): the node process is gone; exiting",
              file=sys.stderr, flush=True)


def _send(conn, message) -> None:
    try:
        conn.send(message)
    except OSError:   # BrokenPipeError, ConnectionResetError
        raise _ParentGone from None


def _answer_frames(conn, models, config, niceness: int) -> None:
    from ..rgbd.multi_model import MultiModelRegistration

    try:
        if niceness:
            os.nice(niceness)  # behind the node's per-frame work (tracking) on a busy CPU
        pipeline = MultiModelRegistration(models, config)
        pipeline.warm_up()  # one-off compilation now, not in the first frame's latency
    except Exception as exc:  # reported to the parent, which stops with one clear line
        _send(conn, ("error", f"{type(exc).__name__}: {exc}"))
        return
    _send(conn, ("ready", None))
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):  # closed without the stop message: the node died
            raise _ParentGone from None
        if job is None:
            return
        rgb, depth, intrinsics, new_config, gravity = job
        try:
            if new_config != pipeline.config:
                pipeline = MultiModelRegistration(models, new_config)
                pipeline.warm_up()
            answer = ("ok", pipeline.register_frame(rgb, depth, intrinsics, gravity))
        except InputError as exc:
            answer = ("input_error", str(exc))
        except Exception as exc:  # a bug on one frame must not end the stream
            answer = ("failed", f"{type(exc).__name__}: {exc}")
        _send(conn, answer)


class PipelineProcess:
    """``register(rgb, depth_m, intrinsics, config, gravity=None) -> FrameResult`` of every model, run in a child
    process. Raises InputError for a frame the pipeline refuses, RuntimeError when the pipeline
    failed (the child is restarted if it died, unless ``keep_running()`` says the program is
    stopping) and PipelineClosed once ``close`` was called or the program is stopping."""

    def __init__(self, models, config, start_timeout: float = 300.0, wait: bool = True, niceness: int = 0,
                 keep_running=None):
        self._models = list(models)
        self._niceness = niceness
        self._start_timeout = start_timeout
        self._keep_running = keep_running or (lambda: True)
        self._lock = threading.RLock()  # one frame at a time; close() waits for it
        self._closed = False
        self._launch(config)
        if wait:
            self.wait_ready()

    @classmethod
    def start_many(cls, models, config, count: int, niceness: int = 0, keep_running=None) -> list["PipelineProcess"]:
        """``count`` pipeline processes, started together (each spends seconds warming up)."""
        started = []
        try:
            started += [cls(models, config, wait=False, niceness=niceness, keep_running=keep_running)
                        for _ in range(count)]
            for p in started:
                p.wait_ready()
        except BaseException:   # a bad model, or Ctrl-C while they start: none is left behind
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
        # The child inherits this thread's signal mask through fork and exec: with SIGINT blocked
        # it never sees a Ctrl-C, not even while it imports (before _serve could ignore it).
        # SIGTERM waits until _serve too: a child killed before it has read its arguments (the
        # models) leaves this process blocked for ever in Process.start, writing to a pipe whose
        # read end it holds itself (multiprocessing's spawn). Meanwhile this process takes the
        # signals on another thread, as Python does anyway. The resource tracker is started
        # first: starting it unblocks SIGINT and SIGTERM in this thread.
        resource_tracker.ensure_running()
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD_AT_SPAWN)
        try:
            self._proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
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
                self._proc.join(timeout=1.0)
                code = self._proc.exitcode
                self._stop()
                if self._stopping(code):
                    self._closed = True
                    raise PipelineClosed(f"the pipeline process ended (exit code {code}) as the program stops") from None
                self._start(config)
                raise RuntimeError(f"the pipeline process died (exit code {code}); restarted it") from None
        if status == "ok":
            return payload
        if status == "input_error":
            raise InputError(payload)
        raise RuntimeError(payload)

    def _stopping(self, exitcode) -> bool:
        """Whether a child that just died should stay dead: the program is stopping. A child
        killed by SIGTERM or SIGHUP was most likely signalled with its whole process group (a
        service manager, a terminal closed): give the program's own shutdown a moment to show."""
        if not self._keep_running():
            return True
        if exitcode is not None and -exitcode in (signal.SIGTERM, signal.SIGHUP):
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                if not self._keep_running():
                    return True
                time.sleep(0.05)
        return self._closed

    def close(self) -> None:
        """Stop the child, after the frame it is working on (if any)."""
        self._closed = True   # before the lock: a frame under way that finds the child gone must not restart it
        with self._lock:
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
