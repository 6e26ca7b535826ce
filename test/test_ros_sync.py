"""The node's approximate-time synchroniser and latest-frame mailbox (pure Python, no ROS)."""
import threading
import time
from types import SimpleNamespace

import pytest

from multi_instance_reg.ros.sync import ApproximateTimeSync, LatestSlot, stamp_to_ns

MS = 1_000_000


def test_stamp_to_ns():
    assert stamp_to_ns(SimpleNamespace(sec=3, nanosec=5)) == 3_000_000_005


def test_identical_stamps_pair_immediately_in_either_order():
    sync = ApproximateTimeSync(2, slop_ns=10 * MS)
    assert sync.add(0, 100 * MS, "c0") is None
    assert sync.add(1, 100 * MS, "d0") == ("c0", "d0")
    assert sync.add(1, 133 * MS, "d1") is None
    assert sync.add(0, 133 * MS, "c1") == ("c1", "d1")
    assert sync.counters.matched == 2 and sync.counters.unmatched == 0


def test_pairs_within_slop_and_not_beyond():
    sync = ApproximateTimeSync(2, slop_ns=5 * MS)
    sync.add(0, 100 * MS, "c0")
    assert sync.add(1, 106 * MS, "d0") is None          # 6 ms apart > 5 ms slop
    assert sync.add(0, 133 * MS, "c1") is None
    assert sync.add(1, 130 * MS, "d1") == ("c1", "d1")  # 3 ms apart
    # c0 and d0 were never matched and are gone now: both count as unmatched.
    assert sync.counters.unmatched == 2


def test_closest_partner_wins_and_older_ones_are_dropped():
    sync = ApproximateTimeSync(2, slop_ns=20 * MS)
    for k in range(3):
        sync.add(1, (100 + 33 * k) * MS, f"d{k}")
    assert sync.add(0, 167 * MS, "c") == ("c", "d2")
    assert sync.counters.unmatched == 2


def test_duplicate_stamp_is_stale_not_matched_again():
    sync = ApproximateTimeSync(2, slop_ns=5 * MS)
    sync.add(0, 200 * MS, "c1")
    assert sync.add(1, 200 * MS, "d1") == ("c1", "d1")
    assert sync.add(0, 200 * MS, "c1 again") is None
    assert sync.add(1, 200 * MS, "d1 again") is None
    assert sync.counters.stale == 2 and sync.counters.matched == 1


def test_queue_is_bounded():
    sync = ApproximateTimeSync(2, slop_ns=1 * MS, queue_size=3)
    for k in range(10):
        sync.add(0, k * 100 * MS, k)
    assert len(sync._queues[0]) == 3
    assert sync.counters.unmatched == 7
    assert sync.add(1, 900 * MS, "d") == (9, "d")


def test_three_streams():
    sync = ApproximateTimeSync(3, slop_ns=10 * MS)
    assert sync.add(0, 100 * MS, "a") is None
    assert sync.add(2, 104 * MS, "c") is None
    assert sync.add(1, 95 * MS, "b") == ("a", "b", "c")


def test_slop_change_applies_to_next_add():
    sync = ApproximateTimeSync(2, slop_ns=1 * MS)
    sync.add(0, 100 * MS, "c")
    assert sync.add(1, 110 * MS, "d") is None
    sync.set_slop(20 * MS)
    assert sync.add(0, 120 * MS, "c2") == ("c2", "d")


def test_rejects_bad_construction():
    with pytest.raises(ValueError):
        ApproximateTimeSync(1, slop_ns=0)
    with pytest.raises(ValueError):
        ApproximateTimeSync(2, slop_ns=0, queue_size=0)


def test_latest_slot_keeps_only_the_newest_and_counts_replaced():
    slot = LatestSlot()
    assert slot.put(1) is False
    assert slot.put(2) is True
    assert slot.put(3) is True
    assert slot.take(timeout=0) == 3
    assert slot.take(timeout=0) is None
    assert slot.replaced == 2


def test_latest_slot_wakes_a_waiting_worker_and_close_releases_it():
    slot = LatestSlot()
    got = []
    worker = threading.Thread(target=lambda: got.append(slot.take(timeout=5)))
    worker.start()
    time.sleep(0.05)
    slot.put("frame")
    worker.join(2)
    assert got == ["frame"]
    worker = threading.Thread(target=lambda: got.append(slot.take(timeout=5)))
    worker.start()
    slot.close()
    worker.join(2)
    assert not worker.is_alive() and got == ["frame", None]


def test_time_jumping_back_starts_afresh():
    """A looping bag repeats its stamps: pairs must keep coming, not be dropped as stale."""
    sync = ApproximateTimeSync(2, slop_ns=5 * MS)
    for lap in range(2):
        for k in range(3):
            sync.add(0, (5000 + 33 * k) * MS, (lap, k))
            assert sync.add(1, (5000 + 33 * k) * MS, "d") == ((lap, k), "d")
    assert sync.counters.resets == 2 and sync.counters.stale == 0  # one per stream


def test_looping_streams_that_drift_apart_lose_only_the_pairs_at_the_wrap():
    """Colour runs two frames ahead of depth when the bag wraps around."""
    sync = ApproximateTimeSync(2, slop_ns=5 * MS)
    stamps = [k * 33 * MS for k in range(6)] * 3
    out = []
    for k in range(len(stamps) + 2):
        if k < len(stamps):
            out.append(sync.add(0, stamps[k], ("c", k)))
        if k >= 2:
            out.append(sync.add(1, stamps[k - 2], ("d", k - 2)))
    pairs = [p for p in out if p is not None]
    assert all(c[1] == d[1] for c, d in pairs)  # never a pair from different laps
    assert len(pairs) >= 18 - 2 * 2


def _feed(slot, items, period):
    for item in items:
        slot.put(item)
        time.sleep(period)


def test_latest_slot_waits_for_the_next_item_when_the_waiting_one_is_old():
    slot = LatestSlot()
    period = 0.1
    _feed(slot, range(4), period)            # learns the interval; item 3 has waited ~1 period
    feeder = threading.Thread(target=lambda: (time.sleep(0.01), slot.put(4)))
    feeder.start()
    assert slot.take(timeout=1, fresher=True) == 4   # the next one, not the stale 3
    feeder.join()
    assert slot.replaced == 4
    # A fresh item is taken at once; without fresher, an old one too.
    slot.put(5)
    t0 = time.monotonic()
    assert slot.take(timeout=1, fresher=True) == 5 and time.monotonic() - t0 < period / 2
    slot.put(6)
    time.sleep(period)
    assert slot.take(timeout=1) == 6


def test_latest_slot_gives_up_waiting_when_no_newer_item_comes():
    slot = LatestSlot()
    period = 0.1
    _feed(slot, range(4), period)
    t0 = time.monotonic()
    assert slot.take(timeout=1, fresher=True) == 3        # waited until 1.25 intervals, then took it
    assert 0.1 * period < time.monotonic() - t0 < 0.5
