"""The continuous mode's newest-item slot and rate limit, exactly, on a fake clock: no DDS, no sleeps."""

from __future__ import annotations

import pytest

from pssnet_ros.newest_slot import NewestSlot, SlotStats


class FakeClock:
    """Time moves only when told to."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_first_item_starts_at_once_and_starts_are_rate_limited_exactly():
    clock = FakeClock()  # times below are binary fractions: the arithmetic is exact
    slot: NewestSlot[str] = NewestSlot(4.0, clock=clock)
    assert slot.wait_time() is None and slot.try_take() is None  # nothing pending
    slot.put("a")
    assert slot.wait_time() == 0.0 and slot.try_take() == "a"
    slot.done()
    clock.t += 0.0625
    slot.put("b")
    assert slot.wait_time() == 0.1875 and slot.try_take() is None
    clock.t += 0.1875 - 2**-20
    assert slot.wait_time() == 2**-20 and slot.try_take() is None  # a microsecond early
    clock.t += 2**-20
    assert slot.try_take() == "b"
    slot.done()
    # A worker that was busy longer than the period starts the next item at once.
    clock.t += 1.0
    slot.put("c")
    assert slot.try_take() == "c"


def test_a_newer_item_replaces_the_pending_one_and_is_counted_as_superseded():
    clock = FakeClock()
    slot: NewestSlot[int] = NewestSlot(2.0, clock=clock)
    slot.put(0)
    assert slot.try_take() == 0
    for i in range(1, 31):  # 30 items arrive while the worker is busy and the rate limit holds
        assert slot.put(i) is (i > 1)
        clock.t += 1 / 30
    assert slot.stats() == SlotStats(offered=31, superseded=29, started=1, pending=1, in_progress=1)
    slot.done()
    assert slot.try_take() == 30  # the newest, never an older one
    slot.done()
    stats = slot.stats()
    assert stats.offered == stats.superseded + stats.started + stats.pending + stats.in_progress
    assert stats == SlotStats(offered=31, superseded=29, started=2, pending=0, in_progress=0)


def test_paused_slot_keeps_the_newest_item_until_resumed():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(1.0, paused=True, clock=clock)
    slot.put("a")
    slot.put("b")
    assert slot.try_take() is None
    assert slot.stats() == SlotStats(offered=2, superseded=1, started=0, pending=1, in_progress=0)
    slot.paused = False
    assert slot.try_take() == "b"


def test_rate_changes_apply_to_the_next_start():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(1.0, clock=clock)
    slot.put("a")
    assert slot.try_take() == "a"
    slot.done()
    slot.put("b")
    clock.t += 0.5
    assert slot.try_take() is None  # 1 Hz: half a period has passed
    slot.max_rate_hz = 10.0
    assert slot.try_take() == "b"  # 10 Hz: five periods have passed
    with pytest.raises(ValueError, match="max_rate_hz must be positive"):
        slot.max_rate_hz = 0.0


def test_one_item_at_a_time():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(100.0, clock=clock)
    slot.put("a")
    slot.try_take()
    clock.t += 1.0
    slot.put("b")
    with pytest.raises(RuntimeError, match="try_take\\(\\) before done\\(\\)"):
        slot.try_take()
    slot.done()
    assert slot.try_take() == "b"
