"""What the node reports on /diagnostics: completion rate and latency, dropped sets, model, state.

:class:`CompletionHealth` is ROS-free (a clock can be injected, so it is tested exactly); :func:`diagnostic_status`
turns its snapshot and the node's counters into one ``diagnostic_msgs/DiagnosticStatus``, as ROS 2 drivers
publish theirs at 1 Hz for ``rqt_robot_monitor`` and the diagnostic aggregator.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue


@dataclass(frozen=True)
class HealthSnapshot:
    """Completions over the last ``window_s`` seconds.

    Attributes:
        window_s: the window.
        completions: completions (service answers and continuous-mode sets) finished in the window.
        rate_hz: completions / window_s.
        latency_p50_ms: median time from input to published output or response, ms (NaN when none).
        latency_p95_ms: 95th percentile of the same, ms (NaN when none).
    """

    window_s: float
    completions: int
    rate_hz: float
    latency_p50_ms: float
    latency_p95_ms: float


class CompletionHealth:
    """Thread-safe record of recent completions: (finish time, latency) pairs within a sliding window.

    Args:
        window_s: how far back the rate and percentiles look.
        clock: monotonic seconds (injectable for tests).
    """

    def __init__(self, window_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s = window_s
        self._clock = clock
        self._lock = threading.Lock()
        self._events: deque[tuple[float, float]] = deque()

    def completed(self, latency_s: float) -> None:
        """Records one finished completion that took ``latency_s`` seconds."""
        with self._lock:
            self._events.append((self._clock(), float(latency_s)))
            self._trim()

    def _trim(self) -> None:
        oldest = self._clock() - self.window_s
        while self._events and self._events[0][0] < oldest:
            self._events.popleft()

    def snapshot(self) -> HealthSnapshot:
        with self._lock:
            self._trim()
            latencies = np.array([latency for _, latency in self._events]) * 1000.0
        if len(latencies) == 0:
            return HealthSnapshot(self.window_s, 0, 0.0, float("nan"), float("nan"))
        p50, p95 = np.percentile(latencies, [50, 95])
        return HealthSnapshot(self.window_s, len(latencies), len(latencies) / self.window_s, float(p50), float(p95))


def diagnostic_status(name: str, hardware_id: str, state: str, health: HealthSnapshot, counters: dict[str, int],
                      model: dict[str, str], error: str = "", warning: str = "") -> DiagnosticStatus:
    """One status: OK when active, WARN when inactive or unconfigured, ERROR after a failed configure.

    Args:
        name: status name (e.g. "pssnet: completion").
        hardware_id: the node's fully qualified name.
        state: lifecycle state label ("active", "inactive", "unconfigured").
        health: recent completions.
        counters: the node's counters (``CompletionNode.stats``); the dropped sets are reported by reason.
        model: "model", "device", "precision" when a model is loaded, else empty.
        error: the last configure error, if any.
        warning: a problem with the input that does not stop the node (e.g. an up vector the support plane
            disagrees with): an active node reports WARN with it.
    """
    if error:
        level, message = DiagnosticStatus.ERROR, f"{state}: {error}"
    elif state != "active":
        level, message = DiagnosticStatus.WARN, f"{state}: not serving"
    elif warning:
        level, message = DiagnosticStatus.WARN, f"active, {health.rate_hz:.2f} completions/s; {warning}"
    else:
        level, message = DiagnosticStatus.OK, f"active, {health.rate_hz:.2f} completions/s"
    values = {
        "state": state,
        "completion rate (Hz)": f"{health.rate_hz:.3f}",
        f"latency p50 (ms, last {health.window_s:g} s)": f"{health.latency_p50_ms:.1f}",
        f"latency p95 (ms, last {health.window_s:g} s)": f"{health.latency_p95_ms:.1f}",
        **{key.replace("_", " "): str(value) for key, value in sorted(counters.items())
           if key != "latest_set_stamp_ns"},
        **model,
    }
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in values.items()])
