"""The continuous mode's input slot: the newest pending item, handed out at most ``max_rate_hz``.

ROS-free (no rclpy) and with an injectable clock, so that its rules are tested exactly, without DDS or sleeps:

- one slot: a newer item replaces an unprocessed one, which is counted as superseded (bounded memory, no
  queue, and the taker always gets the newest input);
- starts are at least ``1 / max_rate_hz`` apart (start to start);
- paused: an item is kept but not handed out.

Nothing here blocks: the node's continuous-mode timer is armed for :meth:`NewestSlot.wait_time` and then
asks :meth:`NewestSlot.try_take`, so the work runs as an executor callback that a lifecycle transition can wait
for, and an idle node polls nothing.

The counters (:class:`SlotStats`) are read atomically, so a caller can account for every item put: it was
superseded, is pending, is in progress, or was started and finished (``started - in_progress``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class SlotStats:
    """Counters of a :class:`NewestSlot`, read in one piece.

    Attributes:
        offered: items put.
        superseded: items replaced by a newer one before the taker got them.
        started: items handed out.
        pending: 1 while an item waits in the slot.
        in_progress: 1 between :meth:`NewestSlot.try_take` handing one out and :meth:`NewestSlot.done`.
    """

    offered: int
    superseded: int
    started: int
    pending: int
    in_progress: int


class NewestSlot(Generic[T]):
    """Holds the newest item for one taker, which gets it no more often than ``max_rate_hz``.

    Args:
        max_rate_hz: largest start rate (> 0).
        paused: start paused (items are kept, not handed out).
        clock: seconds now (default ``time.monotonic``).
    """

    def __init__(self, max_rate_hz: float, paused: bool = False, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._item: T | None = None
        self._has_item = False  # an item may itself be None
        self._period = 0.0
        self.max_rate_hz = max_rate_hz
        self._paused = paused
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
        with self._lock:
            self._period = 1.0 / float(value)

    @property
    def paused(self) -> bool:
        return self._paused

    @paused.setter
    def paused(self, value: bool) -> None:
        with self._lock:
            self._paused = bool(value)

    def put(self, item: T) -> bool:
        """Offers the newest item; returns True when it replaced one not yet handed out."""
        with self._lock:
            replaced = self._has_item
            self._item, self._has_item = item, True
            self._offered += 1
            self._superseded += int(replaced)
            return replaced

    def wait_time(self) -> float | None:
        """Seconds until :meth:`try_take` would hand out the pending item (0 = now); None when nothing is
        pending, or the slot is paused."""
        with self._lock:
            return self._wait_time()

    def _wait_time(self) -> float | None:
        if self._paused or not self._has_item:
            return None
        if self._last_start is None:
            return 0.0
        return max(0.0, self._last_start + self._period - self._clock())

    def try_take(self) -> T | None:
        """Hands out the pending item if the rate limit allows it now, else returns None (never blocks).

        Raises:
            RuntimeError: the previous item is still in progress (:meth:`done` not called).
        """
        with self._lock:
            if self._wait_time() != 0.0:
                return None
            if self._busy:
                raise RuntimeError("try_take() before done(): one item is completed at a time")
            item, self._item, self._has_item = self._item, None, False
            self._last_start = self._clock()
            self._started += 1
            self._busy = True
            return item

    def done(self) -> None:
        """The taker finished the item it took last."""
        with self._lock:
            self._busy = False

    def stats(self) -> SlotStats:
        with self._lock:
            return SlotStats(offered=self._offered, superseded=self._superseded, started=self._started,
                             pending=int(self._has_item), in_progress=int(self._busy))
