"""A small stamp synchroniser for depth, mask and camera_info (message_filters is not available as a wheel).

Each stream keeps a short queue. When a message arrives it is matched against the message of every other
stream whose stamp is nearest to its own; if the spread of the stamps is within the tolerance, the set is
emitted and everything up to the matched messages is removed. Memory is bounded by ``queue_size`` per
stream; messages that fall out of a queue unmatched, or arrive older than the last emitted set, are counted.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

#: a message older than the last emitted set by more than this means the clock jumped back (nanoseconds)
CLOCK_JUMP_NS = 5_000_000_000


@dataclass(frozen=True)
class SyncedSet:
    """One message per stream with stamps within the tolerance.

    Attributes:
        stamp_ns: stamp of the newest message of the set (nanoseconds).
        spread_ns: newest minus oldest stamp of the set.
        messages: stream name -> message.
    """

    stamp_ns: int
    spread_ns: int
    messages: dict[str, Any]


@dataclass
class SyncStats:
    """Counters of a :class:`StampSynchronizer`."""

    received: int = 0
    matched: int = 0
    dropped_unmatched: int = 0  # fell out of a full queue, or was older than a set already emitted


class StampSynchronizer:
    """Matches messages of several streams by stamp (approximate time within a tolerance). Thread-safe."""

    def __init__(self, streams: Sequence[str], tolerance_s: float, queue_size: int = 10) -> None:
        """Args:
            streams: stream names, e.g. ("depth", "mask", "camera_info"); at least two, unique.
            tolerance_s: largest allowed spread of stamps in one set (seconds, >= 0).
            queue_size: messages kept per stream while waiting for partners (>= 1).
        """
        if len(streams) < 2 or len(set(streams)) != len(streams):
            raise ValueError(f"need at least two unique stream names, got {list(streams)}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self._streams = tuple(streams)
        self._queues: dict[str, deque[tuple[int, Any]]] = {s: deque() for s in streams}
        self._queue_size = int(queue_size)
        self._tolerance_ns = 0
        self.tolerance_s = tolerance_s
        self._last_emitted_ns: int | None = None
        self._lock = threading.Lock()
        self._stats = SyncStats()

    @property
    def tolerance_s(self) -> float:
        return self._tolerance_ns * 1e-9

    @tolerance_s.setter
    def tolerance_s(self, value: float) -> None:
        if not value >= 0:
            raise ValueError(f"tolerance must be >= 0 seconds, got {value}")
        self._tolerance_ns = round(float(value) * 1e9)

    @property
    def stats(self) -> SyncStats:
        """A copy of the counters."""
        with self._lock:
            return SyncStats(**vars(self._stats))

    def add(self, stream: str, stamp_ns: int, message: Any) -> SyncedSet | None:
        """Adds one message; returns the set it completes, if any."""
        if stream not in self._queues:
            raise ValueError(f"unknown stream {stream!r}; known: {list(self._streams)}")
        stamp_ns = int(stamp_ns)
        with self._lock:
            self._stats.received += 1
            if self._last_emitted_ns is not None and stamp_ns <= self._last_emitted_ns - self._tolerance_ns:
                if self._last_emitted_ns - stamp_ns > CLOCK_JUMP_NS:
                    # Far older than anything seen: the clock went back (a looping bag); start afresh.
                    for old in self._queues.values():
                        self._stats.dropped_unmatched += len(old)
                        old.clear()
                    self._last_emitted_ns = None
                else:
                    self._stats.dropped_unmatched += 1  # older than a set already emitted: can never match
                    return None
            queue = self._queues[stream]
            queue.append((stamp_ns, message))
            if len(queue) > 1 and queue[-2][0] > stamp_ns:  # out of order: keep the queue sorted
                ordered = sorted(queue, key=lambda item: item[0])
                queue.clear()
                queue.extend(ordered)
            while len(queue) > self._queue_size:
                queue.popleft()
                self._stats.dropped_unmatched += 1
            return self._match(stream, stamp_ns, message)

    def _match(self, pivot_stream: str, pivot_ns: int, pivot_msg: Any) -> SyncedSet | None:
        chosen: dict[str, tuple[int, Any]] = {pivot_stream: (pivot_ns, pivot_msg)}
        for stream in self._streams:
            if stream == pivot_stream:
                continue
            queue = self._queues[stream]
            if not queue:
                return None
            chosen[stream] = min(queue, key=lambda item: abs(item[0] - pivot_ns))
        stamps = [stamp for stamp, _ in chosen.values()]
        spread = max(stamps) - min(stamps)
        if spread > self._tolerance_ns:
            return None
        for stream, (stamp, message) in chosen.items():
            queue = self._queues[stream]
            while queue and queue[0][0] <= stamp:
                old_stamp, old_message = queue.popleft()
                if old_message is not message:
                    self._stats.dropped_unmatched += 1
        self._stats.matched += 1
        self._last_emitted_ns = max(stamps)
        return SyncedSet(stamp_ns=max(stamps), spread_ns=spread,
                         messages={stream: message for stream, (_, message) in chosen.items()})

    def clear(self) -> None:
        """Forgets every queued message (e.g. after the tolerance changed or the clock jumped back)."""
        with self._lock:
            for queue in self._queues.values():
                queue.clear()
            self._last_emitted_ns = None
