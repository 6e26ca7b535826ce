"""Approximate-time synchronisation of several streams on their header stamps.

message_filters is not available as a wheel, so this is the project's own, small and
pure Python (no ROS import): messages go in with a stream index and a stamp in
nanoseconds; a tuple with one message per stream comes out when the stamps all lie
within ``slop_ns`` of each other. Matching is greedy and immediate (a set is emitted as
soon as the last of its members arrives), which adds no latency for a camera whose colour
and aligned depth carry the same stamp.
"""
from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time (rclpy or rosbags) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class SyncCounters:
    matched: int = 0        # sets emitted
    unmatched: int = 0      # messages dropped without a partner (evicted or superseded)
    stale: int = 0          # duplicates of an emitted stamp
    resets: int = 0         # time jumped back (a looping bag, a restarted camera)


class ApproximateTimeSync:
    """Pair (or n-tuple) messages from ``n_streams`` streams whose stamps differ by at most
    ``slop_ns``.

    ``add(stream, stamp_ns, msg)`` returns the matched tuple (ordered by stream) or None.
    Each stream keeps at most ``queue_size`` unmatched messages; once a set is emitted,
    everything at or before its stamps is discarded, so a set never repeats a message and
    time never goes backwards. Each stream arrives in order (DDS keeps a writer's order),
    so a stamp older than that stream's last emitted one means time jumped back (a bag
    starting again, a camera restarted): that stream starts afresh rather than discarding
    everything from then on. A repeated stamp is a duplicate and counts as stale.
    Thread-safe.
    """

    def __init__(self, n_streams: int, slop_ns: int, queue_size: int = 10):
        if n_streams < 2:
            raise ValueError("synchronising needs at least two streams")
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        self.n_streams = n_streams
        self.slop_ns = int(slop_ns)
        self.queue_size = queue_size
        self._queues: list[deque] = [deque() for _ in range(n_streams)]
        self._last_emitted: list[int | None] = [None] * n_streams
        self._lock = threading.Lock()
        self.counters = SyncCounters()

    def set_slop(self, slop_ns: int) -> None:
        with self._lock:
            self.slop_ns = int(slop_ns)

    def add(self, stream: int, stamp_ns: int, msg: Any) -> tuple | None:
        with self._lock:
            last = self._last_emitted[stream]
            if last is not None and stamp_ns < last:
                # This stream's time went back: forget its own past (other streams reset
                # themselves when their own time goes back, so every queue stays sorted).
                self.counters.resets += 1
                self.counters.unmatched += len(self._queues[stream])
                self._queues[stream].clear()
                self._last_emitted[stream] = None
            elif last is not None and stamp_ns == last:
                self.counters.stale += 1
                return None
            queue = self._queues[stream]
            queue.append((stamp_ns, msg))
            if len(queue) > self.queue_size:
                queue.popleft()
                self.counters.unmatched += 1
            match = self._match(stream, stamp_ns)
            if match is None:
                return None
            self._emit(match)
            return tuple(msg for _, msg in match)

    def _match(self, stream: int, stamp_ns: int):
        """The set built around the newest arrival: the closest-stamped message of every
        other stream, if all lie within the slop of each other."""
        chosen = []
        for s, queue in enumerate(self._queues):
            if s == stream:
                chosen.append(queue[-1])
                continue
            if not queue:
                return None
            chosen.append(min(queue, key=lambda item: abs(item[0] - stamp_ns)))
        stamps = [stamp for stamp, _ in chosen]
        if max(stamps) - min(stamps) > self.slop_ns:
            return None
        return chosen

    def _emit(self, match) -> None:
        self.counters.matched += 1
        for s, (stamp, _) in enumerate(match):
            queue = self._queues[s]
            while queue and queue[0][0] <= stamp:
                item = queue.popleft()
                if item[0] != stamp:
                    self.counters.unmatched += 1
            self._last_emitted[s] = stamp


class LatestSlot:
    """A one-item mailbox: ``put`` replaces whatever is waiting, ``take`` blocks for the next.

    This is what keeps latency from queueing up: when frames arrive faster than they are
    processed, the worker always gets the newest one and the replaced ones are counted.

    ``take(fresher=True)`` also avoids starting on a frame that has already waited more than
    half the interval between frames: the next one is then due sooner than this one is old,
    so it waits for that one (up to 1.25 intervals after the last arrival, then takes what
    is there). With the pipeline slower than the camera the worker frees up at a random
    moment, so this cuts the mean wait from half an interval to an eighth (30 Hz: ~17 -> ~4
    ms) for about 1/8 interval of idle time per frame processed.
    """

    PERIOD_SAMPLES = 15  # arrival intervals whose median is the frame interval

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._has_item = False
        self._closed = False
        self._put_at = None                                  # time.monotonic() of the last put
        self._intervals = deque(maxlen=self.PERIOD_SAMPLES)
        self.replaced = 0

    def put(self, item) -> bool:
        """Store ``item``; True if it replaced one that was never taken."""
        with self._cond:
            now = time.monotonic()
            if self._put_at is not None:
                self._intervals.append(now - self._put_at)
            self._put_at = now
            replaced = self._has_item
            if replaced:
                self.replaced += 1
            self._item, self._has_item = item, True
            self._cond.notify_all()
            return replaced

    def take(self, timeout: float | None = None, fresher: bool = False):
        """The waiting item (and empties the slot), or None on timeout or close; with
        ``fresher``, the next item instead when it is due sooner than this one is old."""
        with self._cond:
            if not self._has_item and not self._closed:
                self._cond.wait(timeout)
            if not self._has_item:
                return None
            if fresher and len(self._intervals) >= 3:
                period = statistics.median(self._intervals)
                waited_for = self._put_at
                deadline = waited_for + 1.25 * period
                if time.monotonic() - waited_for > 0.5 * period:
                    while self._put_at == waited_for and not self._closed:
                        left = deadline - time.monotonic()
                        if left <= 0 or not self._cond.wait(left):
                            break
                if not self._has_item:  # another worker took it meanwhile
                    return None
            item, self._item, self._has_item = self._item, None, False
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

