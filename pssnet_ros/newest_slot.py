"""The continuous mode's input slot: the newest pending item, handed to one worker at most ``max_rate_hz``.

ROS-free (no rclpy) and with an injectable clock, so that its rules are tested exactly, without DDS or sleeps:

- one slot: a newer item replaces an unprocessed one, which is counted as superseded (bounded memory, no
  queue, and the worker always gets the newest input);
- starts are at least ``1 / max_rate_hz`` apart (start to start);
- paused: an item is kept but not handed out; closed: :meth:`NewestSlot.take` returns None at once.

The counters (:class:`SlotStats`) are read atomically, so a caller can account for every item put: it was
superseded, is pending, is in progress, or was started and finished (``started - in_progress``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

T = TypeVar("T")


class Clock(Protocol):
    """Time source of a :class:`NewestSlot`: ``now`` in seconds, ``wait`` on its condition for up to ``timeout``."""

    def now(self) -> float: ...

    def wait(self, condition: threading.Condition, timeout: float | None) -> None: ...


class MonotonicClock:
    """The real clock: ``time.monotonic`` and a plain condition wait."""

    def now(self) -> float:
        return time.monotonic()

    def wait(self, condition: threading.Condition, timeout: float | None) -> None:
        condition.wait(timeout)


@dataclass(frozen=True)
class SlotStats:
    """Counters of a :class:`NewestSlot`, read in one piece.

    Attributes:
        offered: items put.
        superseded: items replaced by a newer one before a worker took them.
        started: items handed to the worker.
        pending: 1 while an item waits in the slot.
        in_progress: 1 between :meth:`NewestSlot.take` and :meth:`NewestSlot.done`.
    """

    offered: int
    superseded: int
    started: int
    pending: int
    in_progress: int


class NewestSlot(Generic[T]):
    """Holds the newest item for one worker thread, which takes it no more often than ``max_rate_hz``.

    Args:
        max_rate_hz: largest start rate (> 0).
        paused: start paused (items are kept, not handed out).
        clock: time source (default :class:`MonotonicClock`).
    """

    def __init__(self, max_rate_hz: float, paused: bool = False, clock: Clock | None = None) -> None:
        self._clock = clock or MonotonicClock()
        self._cond = threading.Condition()
        self._item: T | None = None
        self._has_item = False  # an item may itself be None
        self._period = 0.0
        self.max_rate_hz = max_rate_hz
        self._paused = paused
        self._closed = False
        self._busy = False
        self._last_start: float | None = None
        self._offered = self._superseded = self._started = 0

    @property
    def max_rate_hz(self) -> float:
        return 1.0 / self._period

    @max_rate_hz.setter
    def max_rate_hz(self, value: float) -> None:
        if not value > 0:
            raise ValueError(f"max_rate_hz must be positive, got {value}")
        with self._cond:
            self._period = 1.0 / float(value)
            self._cond.notify_all()  # a waiting worker recomputes its wait

    @property
    def paused(self) -> bool:
        return self._paused

    @paused.setter
    def paused(self, value: bool) -> None:
        with self._cond:
            self._paused = bool(value)
            self._cond.notify_all()

    def put(self, item: T) -> bool:
        """Offers the newest item; returns True when it replaced one that no worker had taken."""
        with self._cond:
            replaced = self._has_item
            self._item, self._has_item = item, True
            self._offered += 1
            self._superseded += int(replaced)
            self._cond.notify_all()
            return replaced

    def wait_time(self) -> float | None:
        """Seconds until :meth:`try_take` would hand out the pending item (0 = now); None when nothing is
        pending, or the slot is paused or closed."""
        with self._cond:
            return self._wait_time()

    def _wait_time(self) -> float | None:
        if self._closed or self._paused or not self._has_item:
            return None
        if self._last_start is None:
            return 0.0
        return max(0.0, self._last_start + self._period - self._clock.now())

    def try_take(self) -> T | None:
        """Hands out the pending item if the rate limit allows it now, else returns None (never blocks).

        Raises:
            RuntimeError: the previous item is still in progress (:meth:`done` not called).
        """
        with self._cond:
            return self._try_take()

    def _try_take(self) -> T | None:
        if self._wait_time() != 0.0:
            return None
        if self._busy:
            raise RuntimeError("take() before done(): one worker completes one item at a time")
        item, self._item, self._has_item = self._item, None, False
        self._last_start = self._clock.now()
        self._started += 1
        self._busy = True
        return item

    def take(self) -> T | None:
        """Blocks until an item may start, and hands it out; returns None once the slot is closed."""
        with self._cond:
            while not self._closed:
                wait = self._wait_time()
                if wait == 0.0:
                    return self._try_take()
                # Woken early by put/pause/rate/close: the loop recomputes what to wait for.
                self._clock.wait(self._cond, wait)
            return None

    def done(self) -> None:
        """The worker finished the item it took last."""
        with self._cond:
            self._busy = False

    def close(self) -> None:
        """Wakes the worker; :meth:`take` returns None from now on (a pending item is left unprocessed)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def stats(self) -> SlotStats:
        with self._cond:
            return SlotStats(offered=self._offered, superseded=self._superseded, started=self._started,
                             pending=int(self._has_item), in_progress=int(self._busy))
