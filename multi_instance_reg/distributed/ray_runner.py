"""Tasks on Ray: actors that hold the models, retries, progress.

A run is a list of tasks (an image, a scene of a tracking run, a bag) and a worker class
whose ``__init__`` loads what every task needs (models, the pipeline) and whose
``run(task)`` returns the task's result. ``run_tasks`` starts one actor per worker, keeps
each one busy, hands every result to ``on_result`` as soon as it arrives (the caller writes
it to disk there, which is what makes a rerun resumable), retries a failed task and reports
one that fails again with its input and error. The serial path calls the same worker class
in this process, so both give the same results by construction.
"""
from __future__ import annotations

import tempfile
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import InputError
from ..progress import Progress

DEFAULT_RETRIES = 1


@dataclass
class TaskFailure:
    task: str       # the task's input, as the user would name it
    error: str      # the last attempt's error, one line

    def as_json(self) -> dict:
        return {"task": self.task, "error": self.error}


def add_ray_arguments(p, what: str) -> None:
    """``--ray``, ``--workers``, ``--address``, ``--retries`` on a command whose tasks are ``what``."""
    p.add_argument("--ray", action="store_true",
                   help=f"spread the {what} over Ray workers (a local Ray unless --address); results are written as "
                        f"they finish and a rerun with the same output folder skips what is done")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="Ray workers, each holding the models once (implies --ray; default: every CPU Ray has)")
    p.add_argument("--address", default=None,
                   help="join this Ray cluster (implies --ray): 'auto' for the one `ray start` runs on this machine, "
                        "or HEAD_IP:6379; every node must see the data and the output at the same paths")
    p.add_argument("--retries", type=int, default=DEFAULT_RETRIES, metavar="N",
                   help=f"times a failed task is tried again before it is reported (default {DEFAULT_RETRIES})")


def wants_ray(args) -> bool:
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    if args.retries < 0:
        raise InputError(f"--retries must be 0 or more, got {args.retries}")
    return bool(args.ray or args.workers is not None or args.address)


def connect(address: str | None = None, workers: int | None = None) -> int:
    """Join (``address``) or start a local Ray unless this process has one already; the
    number of workers to start: ``workers`` or every CPU the cluster has."""
    try:
        import ray
    except ImportError:
        raise InputError("Ray is not installed in this environment; run `make install` (requirements.txt pins it)") from None
    if not ray.is_initialized():
        kwargs = dict(include_dashboard=False, logging_level="ERROR", log_to_driver=False)
        try:
            if address:
                check_reachable(address)
                ray.init(address=address, **kwargs)
            else:
                ray.init(num_cpus=workers, **kwargs)
        except ConnectionError as exc:
            raise InputError(f"could not join the Ray cluster at {address}: {str(exc).splitlines()[0]}; "
                             f"start it with `ray start --head` or check --address") from None
    cpus = int(ray.cluster_resources().get("CPU", 1))
    return max(1, workers or cpus)


def check_reachable(address: str) -> None:
    """InputError at once when no Ray head answers at ``address`` ('auto': the one ``ray
    start`` recorded on this machine): ray.init would retry for minutes, logging each try."""
    import os
    import socket

    if address.startswith("ray://"):
        return                      # Ray Client: its own connection and errors
    target = address
    if address == "auto":
        target = os.environ.get("RAY_ADDRESS", "")
        record = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
        if not target and record.is_file():
            target = record.read_text().strip()
        if not target:
            raise InputError("--address auto: no Ray cluster runs on this machine (start one with `ray start --head`, "
                             "or give HEAD_IP:6379)")
    host, _, port = target.rpartition(":")
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=5).close()
    except (OSError, ValueError):
        raise InputError(f"--address {address}: no Ray head answers at {target} (start it with `ray start --head "
                         f"--port {port or 6379}` there, or check the address)") from None


def one_line(exc: BaseException) -> str:
    """The error a task raised, without Ray's wrapping and traceback."""
    cause = getattr(exc, "cause", None)     # RayTaskError: the worker's own exception
    if isinstance(cause, BaseException):
        exc = cause
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()


def run_serial(worker_cls, worker_args: tuple, tasks, describe: Callable, on_result: Callable,
               bar: Progress | None = None, done_before: int = 0) -> list[TaskFailure]:
    """The tasks one after the other in this process, through the same worker class. An
    error stops the run, as before Ray, but with several tasks a bad input (InputError, one
    bag that cannot be read) is reported with its task and the others go on."""
    tasks = list(tasks)
    worker = worker_cls(*worker_args)
    failures = []
    for n, task in enumerate(tasks):
        try:
            result = worker.run(task)
        except InputError as exc:
            if len(tasks) == 1:
                raise
            failures.append(TaskFailure(describe(task), one_line(exc)))
        else:
            on_result(task, result)
        if bar is not None:
            bar.update(done_before + n + 1, f"({len(failures)} failed)" if failures else "", counted_from=done_before)
    return failures


def run_tasks(worker_cls, worker_args: tuple, tasks, describe: Callable, on_result: Callable,
              workers: int, retries: int = DEFAULT_RETRIES, bar: Progress | None = None,
              done_before: int = 0) -> list[TaskFailure]:
    """The tasks on ``workers`` Ray actors of ``worker_cls(*worker_args)`` (connect() first),
    each actor built once and given task after task. ``tasks``: a list, or an iterable drawn
    from only when an actor is free (``mireg tune`` asks its study for the next trial then,
    after the results so far are in). Returns the tasks that failed ``retries`` + 1 times (a
    bad input, InputError, is not tried again). A worker process that dies is replaced by a
    new actor and its task counts as a failed attempt."""
    import ray
    from ray.exceptions import RayActorError, RayError

    source = iter(tasks)
    retry: deque[int] = deque()
    pulled: list = []                        # every task drawn so far, by index
    attempts: list[int] = []

    def next_task() -> int | None:
        if retry:
            return retry.popleft()
        task = next(source, _END)
        if task is _END:
            return None
        pulled.append(task)
        attempts.append(0)
        return len(pulled) - 1

    n_actors = max(1, min(workers, len(tasks))) if hasattr(tasks, "__len__") else max(1, workers)
    if hasattr(tasks, "__len__") and not len(tasks):
        return []
    remote_cls = ray.remote(num_cpus=1, max_restarts=0)(worker_cls)
    # Large arguments (the models) go into the object store once, not once per actor.
    shared_args = tuple(ray.put(a) for a in worker_args)
    actors = [remote_cls.remote(*shared_args) for _ in range(n_actors)]
    in_flight: dict = {}                     # object ref -> (actor index, task index)
    idle = list(range(n_actors))
    failures: list[TaskFailure] = []
    finished = 0
    exhausted = False
    try:
        while True:
            while idle and not exhausted:
                i = next_task()
                if i is None:
                    exhausted = not retry
                    break
                a = idle.pop()
                in_flight[actors[a].run.remote(pulled[i])] = (a, i)
            if not in_flight:
                if retry:                    # a retry queued after the source ran dry
                    exhausted = False
                    continue
                break
            (ref,), _ = ray.wait(list(in_flight), num_returns=1)
            a, i = in_flight.pop(ref)
            try:
                result = ray.get(ref)
            except RayError as exc:
                if isinstance(exc, RayActorError):
                    actors[a] = remote_cls.remote(*shared_args)    # a dead worker: a fresh one loads the models again
                idle.append(a)
                attempts[i] += 1
                if attempts[i] <= retries and not isinstance(getattr(exc, "cause", None), InputError):
                    retry.append(i)
                    exhausted = False
                    continue
                failures.append(TaskFailure(describe(pulled[i]), one_line(exc)))
            else:
                idle.append(a)
                on_result(pulled[i], result)
            finished += 1
            if bar is not None:
                bar.update(done_before + finished, f"({len(failures)} failed)" if failures else "",
                           counted_from=done_before)
    finally:
        for actor in actors:
            ray.kill(actor)
    return failures


_END = object()
