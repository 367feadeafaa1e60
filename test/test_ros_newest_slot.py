"""The continuous mode's newest-item slot and rate limit, exactly, on a fake clock: no DDS, no sleeps."""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest

from pssnet_ros.newest_slot import NewestSlot, SlotStats


class FakeClock:
    """Time moves only when told to, or when the slot waits with a timeout (it then "sleeps" exactly that long).

    A wait without a timeout (nothing to do) runs ``on_idle``, which stands in for another thread: it may
    put an item or close the slot. Waits are recorded.
    """

    def __init__(self, on_idle: Callable[[], None] | None = None) -> None:
        self.t = 100.0
        self.waits: list[float | None] = []
        self.on_idle = on_idle

    def now(self) -> float:
        return self.t

    def wait(self, condition: threading.Condition, timeout: float | None) -> None:
        self.waits.append(timeout)
        if timeout is None:
            assert self.on_idle is not None, "the slot waited forever"
            on_idle, self.on_idle = self.on_idle, None
            condition.release()  # as Condition.wait does: the other "thread" needs the lock
            try:
                on_idle()
            finally:
                condition.acquire()
        else:
            self.t += timeout


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


def test_take_waits_exactly_the_rest_of_the_period():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(4.0, clock=clock)
    slot.put("a")
    assert slot.take() == "a" and clock.waits == []
    slot.done()
    clock.t += 0.1
    slot.put("b")
    start = clock.t
    assert slot.take() == "b"
    assert clock.waits == [pytest.approx(0.15)] and clock.t == pytest.approx(start + 0.15)


def test_take_sleeps_until_an_item_arrives_and_returns_none_once_closed():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(10.0, clock=clock)
    clock.on_idle = lambda: slot.put("late")
    assert slot.take() == "late"
    assert clock.waits == [None]
    slot.done()
    clock.on_idle = slot.close
    assert slot.take() is None
    assert slot.take() is None  # stays closed, without waiting
    assert clock.waits == [None, None]


def test_paused_slot_keeps_the_newest_item_until_resumed():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(1.0, paused=True, clock=clock)
    slot.put("a")
    slot.put("b")
    assert slot.wait_time() is None and slot.try_take() is None
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
    assert slot.wait_time() == pytest.approx(1.0)
    slot.max_rate_hz = 10.0
    assert slot.wait_time() == pytest.approx(0.1)
    with pytest.raises(ValueError, match="max_rate_hz must be positive"):
        slot.max_rate_hz = 0.0


def test_one_item_at_a_time():
    clock = FakeClock()
    slot: NewestSlot[str] = NewestSlot(100.0, clock=clock)
    slot.put("a")
    slot.try_take()
    clock.t += 1.0
    slot.put("b")
    with pytest.raises(RuntimeError, match="take\\(\\) before done\\(\\)"):
        slot.try_take()
    slot.done()
    assert slot.try_take() == "b"


def test_real_clock_worker_thread_gets_the_newest_item():
    """The real clock and a real thread: the blocking path wakes on put and on close."""
    slot: NewestSlot[int] = NewestSlot(1000.0)
    taken: list[int] = []
    ready = threading.Event()

    def worker() -> None:
        while (item := slot.take()) is not None:
            taken.append(item)
            slot.done()
            ready.set()

    thread = threading.Thread(target=worker)
    thread.start()
    slot.put(1)
    assert ready.wait(10.0)
    slot.close()
    thread.join(10.0)
    assert not thread.is_alive() and taken == [1]
