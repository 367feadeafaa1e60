"""The stamp synchroniser: matching within tolerance, ordering, bounded queues, counters, clock jumps."""

from __future__ import annotations

import pytest

from pssnet_ros.sync import StampSynchronizer

MS = 1_000_000
STREAMS = ("depth", "mask", "camera_info")


def test_matches_equal_stamps_in_any_arrival_order():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.0)
    assert sync.add("mask", 100 * MS, "m1") is None
    assert sync.add("camera_info", 100 * MS, "c1") is None
    synced = sync.add("depth", 100 * MS, "d1")
    assert synced is not None and synced.messages == {"depth": "d1", "mask": "m1", "camera_info": "c1"}
    assert synced.stamp_ns == 100 * MS and synced.spread_ns == 0
    assert sync.stats.matched == 1 and sync.stats.dropped_unmatched == 0


def test_tolerance_is_the_largest_allowed_spread():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.010)
    sync.add("depth", 100 * MS, "d")
    sync.add("mask", 108 * MS, "m")
    assert sync.add("camera_info", 111 * MS, "c") is None  # spread 11 ms > 10 ms
    synced = sync.add("camera_info", 105 * MS, "c2")
    assert synced is not None and synced.messages["camera_info"] == "c2" and synced.spread_ns == 8 * MS


def test_delayed_mask_matches_the_right_depth_and_older_ones_are_dropped():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.001)
    for t in (100, 133, 166):
        sync.add("depth", t * MS, f"d{t}")
        sync.add("camera_info", t * MS, f"c{t}")
    synced = sync.add("mask", 133 * MS, "m133")  # segmentation is slow: its mask arrives late
    assert synced.messages == {"depth": "d133", "mask": "m133", "camera_info": "c133"}
    assert sync.stats.dropped_unmatched == 2  # depth and camera_info of t=100 can never match now
    assert sync.add("mask", 100 * MS, "m100") is None  # older than the emitted set
    assert sync.stats.dropped_unmatched == 3
    assert sync.add("mask", 166 * MS, "m166").messages["depth"] == "d166"


def test_queues_are_bounded():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.0, queue_size=3)
    for t in range(10):
        sync.add("depth", t * MS, t)
    assert sync.stats.dropped_unmatched == 7 and sync.stats.received == 10
    sync.add("mask", 9 * MS, "m")
    assert sync.add("camera_info", 9 * MS, "c").messages["depth"] == 9


def test_out_of_order_arrivals_and_clock_jump_back():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.0)
    sync.add("depth", 9000 * MS, "d9000")
    sync.add("depth", 8000 * MS, "d8000")
    sync.add("mask", 8000 * MS, "m8000")
    assert sync.add("camera_info", 8000 * MS, "c8000").messages["depth"] == "d8000"
    sync.add("mask", 9000 * MS, "m9000")
    assert sync.add("camera_info", 9000 * MS, "c9000").messages["depth"] == "d9000"
    assert sync.add("depth", 8500 * MS, "late") is None  # a little older: dropped, counted
    assert sync.stats.dropped_unmatched == 1
    # A bag that loops starts again from an old time: the synchroniser resets instead of dropping forever.
    for name in STREAMS:
        result = sync.add(name, 1 * MS, name)
    assert result is not None and result.stamp_ns == 1 * MS


def test_tolerance_update_and_argument_errors():
    sync = StampSynchronizer(STREAMS, tolerance_s=0.0)
    sync.tolerance_s = 0.05
    assert sync.tolerance_s == pytest.approx(0.05)
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        sync.tolerance_s = -1.0
    with pytest.raises(ValueError, match="unknown stream 'rgb'"):
        sync.add("rgb", 0, None)
    with pytest.raises(ValueError, match="unique stream names"):
        StampSynchronizer(("a", "a"), 0.0)
    with pytest.raises(ValueError, match="queue_size"):
        StampSynchronizer(STREAMS, 0.0, queue_size=0)
