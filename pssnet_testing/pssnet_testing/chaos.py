"""Chaos scenarios against the completion node over real DDS: a node, a client or a subscriber that dies or
stalls, and what that does to everyone else. Shared by ``benchmarks/chaos_bench.py`` (prints the numbers) and
``test/test_node_chaos.py`` (asserts them); each scenario does one unkind thing and returns what happened.

- :func:`kill_node_mid_call`: kill -9 of the node while it works on a request; the client's wait ends at
  its timeout, a restarted node removes the dead one's Fast DDS shared memory and serves again.
- :func:`kill_client_mid_call`: kill -9 of a client process while the node works on its request; the node
  answers into the void and serves the next client.
- :func:`run_with_subscribers`: completions and service calls while other subscribers of
  ``/pssnet/completions`` never spin, sleep in their callback, or are frozen (SIGSTOP).
- :func:`transition_mid_work`: deactivate, cleanup or shutdown sent while a call or a topic set is in
  flight; the call is answered, the node lives (or stops cleanly after shutdown) and serves again.

The processes the scenarios start run this module: ``python -m pssnet_testing.chaos client|subscriber ...``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_ros.shm import SHM_GRACE_S
from pssnet_testing.client import SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.processes import (
    LOCK_SUFFIX,
    RosProcess,
    cpu_seconds,
    machine_cpu,
    rss_mb,
    shm_files,
    stale_shm_files,
)

COMPLETIONS_TOPIC = "/pssnet/completions"
#: samples in a request that keeps the node busy long enough to kill something mid-way (500 with grasps:
#: 2.4 s on a 2-core AVX-512 BF16 CPU); the node must allow them (``max_num_samples``).
HEAVY_SAMPLES = 500
NODE_PARAMS: dict[str, Any] = {"max_num_samples": 1000}
LIGHT_SAMPLES = 20
SUBSCRIBER_MODES = ("never_spins", "slow_callback", "frozen")
#: the node's log line when its start removed stale shared memory (completion_node.main)
REMOVED_LOG = r"removed \d+ stale Fast DDS shared-memory files of dead processes \([\d.]+ MiB\): (.*)$"


def scene_request(num_samples: int, grasps: bool = True) -> Any:
    """A SampleCompletions request carrying the synthetic camera's scene (640x480 depth, mask, camera_info)."""
    from pssnet_interfaces.srv import SampleCompletions

    from pssnet_ros.conversions import intrinsics_to_camera_info, numpy_to_image
    from pssnet_testing.synthetic_camera import FRAME_ID, SceneOptions, render_scene

    view = render_scene(SceneOptions())
    messages = (numpy_to_image(view.depth, "32FC1"), numpy_to_image(view.mask, "mono8"),
                intrinsics_to_camera_info(view.intrinsics))
    for msg in messages:
        msg.header.frame_id = FRAME_ID
    return SampleCompletions.Request(depth=messages[0], mask=messages[1], camera_info=messages[2],
                                     num_samples=num_samples, compute_grasps=grasps)


def scene_up_vector() -> list[float]:
    """The node's ``up_vector`` for the synthetic camera's scene."""
    from pssnet_testing.synthetic_camera import SceneOptions, render_scene

    return [float(v) for v in render_scene(SceneOptions()).up]


class BackgroundCall:
    """A call in a thread, so that the caller can kill something while the request is in flight.

    ``call`` returns the response (e.g. ``lambda: RosClient.call(client, request, timeout)``); what it raises is
    kept in ``error`` for the caller to judge.
    """

    def __init__(self, call: Callable[[], Any]) -> None:
        self.sent_at = time.monotonic()
        self.finished_at: float | None = None
        self.response: Any = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(call,), daemon=True)
        self._thread.start()

    def _run(self, call: Callable[[], Any]) -> None:
        try:
            self.response = call()
        except BaseException as error:  # reported to the caller, who judges it
            self.error = error
        self.finished_at = time.monotonic()

    def wait(self, timeout: float) -> bool:
        """True when the call has finished (answered or given up) within ``timeout`` s."""
        self._thread.join(timeout)
        return not self._thread.is_alive()


def allocated_bytes(files: dict[str, int]) -> int:
    """Memory held by those of ``files`` (path -> inode) that still exist as the same file."""
    total = 0
    for path, inode in files.items():
        try:
            stat = os.stat(path)
        except OSError:
            continue
        total += stat.st_blocks * 512 if stat.st_ino == inode else 0
    return total


def remove_dead_files(files: dict[str, int]) -> list[str]:
    """Removes those of ``files`` (a dead process's Fast DDS segments) that no live process uses, with their lock
    files, without :func:`~pssnet_ros.shm.clean_stale_shm`'s grace period: for a caller that killed the
    process itself. Returns the segments removed."""
    removed = sorted(stale_shm_files(files))
    for path in removed:
        for leftover in (path, path + LOCK_SUFFIX):
            Path(leftover).unlink(missing_ok=True)
    return removed


# ------------------------------------------------------------------------------------ (a) node killed
@dataclass
class NodeKill:
    """What kill -9 of the node in the middle of a request did.

    Attributes:
        in_flight_s: request sent -> kill (the node had counted the call, so it was working on it).
        call_timeout_s: the client's timeout for that request.
        answered: an answer arrived after all (it must not: the node is dead).
        gave_up_after_kill_s: kill -> the client's TimeoutError; None = still waiting after its timeout (a hang).
        error: what the client's call raised.
        server_gone_s: kill -> the client's ``service_is_ready()`` turned false (DDS noticed the dead
            participant); None = not within ``watch_server_s`` (or not watched).
        shm_files: Fast DDS segments and ports the killed node had created; shm_bytes: the memory they held
            right after the kill.
        stale_before_restart: those no live process locked or mapped when the new node started.
        removed_by_node: the files the new node's start removed (its log), the killed node's and any other.
        fates: what became of each of ``shm_files`` once the new node was ready: "removed by the new node",
            "removed by Fast DDS" (a live peer's Fast DDS removes a dead participant's segments it maps, and
            the rest when the participant's lease expires), "replaced" (Fast DDS re-created a port of that
            name) or "left" (still mapped by a live peer).
        restart_ready_s: the new node's start -> "ready".
        resent_answered: a request sent by :meth:`RosClient.call_until_answered` right after the kill, while
            no node ran, was answered with success by the restarted node; attempts: the attempts it took;
            served_ms: its first attempt -> the answer (includes the restart).
    """

    in_flight_s: float
    call_timeout_s: float
    answered: bool
    gave_up_after_kill_s: float | None
    error: str
    server_gone_s: float | None
    shm_files: dict[str, int]
    shm_bytes: int
    stale_before_restart: list[str]
    removed_by_node: list[str]
    fates: dict[str, str]
    restart_ready_s: float
    resent_answered: bool
    attempts: int
    served_ms: float


def _kill(process: RosProcess) -> float:
    """kill -9; returns the moment (monotonic)."""
    process.record_shm_files()
    process.proc.send_signal(signal.SIGKILL)
    killed_at = time.monotonic()
    process.stop()  # reaps it and its output reader
    return killed_at


def kill_node_mid_call(ros: RosClient, node: RosProcess, restart: Callable[[], RosProcess], call_timeout: float,
                       timeout: float = 60.0, watch_server_s: float = 0.0, backdate: bool = False,
                       resend_timeout: float = 10.0) -> tuple[NodeKill, RosProcess]:
    """kill -9 of ``node`` while it works on a heavy request; a re-sending client sends a light request while no
    node runs (attempts ``resend_timeout`` s apart); then ``restart()`` (a ready node), which must answer it.

    The new node removes only files older than its grace period (:data:`SHM_GRACE_S`): this waits for the
    killed node's files to be that old before restarting, or with ``backdate`` (a test's shortcut) sets their
    modification time back by that much, as they are the killed node's and nobody else's. Returns the report
    and the new node (yours to stop).
    """
    from pssnet_interfaces.srv import SampleCompletions

    service = ros.service(SampleCompletions, SAMPLE_SERVICE, timeout)
    calls = ros.stats(timeout)["service_calls"]
    call = BackgroundCall(lambda: RosClient.call(service, scene_request(HEAVY_SAMPLES), call_timeout))
    wait_until(lambda: ros.stats(timeout)["service_calls"] > calls, timeout, "the node working on the request")
    killed_at = _kill(node)
    light = scene_request(LIGHT_SAMPLES)
    attempts = max(3, int((SHM_GRACE_S + 3 * timeout) / resend_timeout))  # outlasts the wait and the restart
    resent = BackgroundCall(lambda: ros.call_until_answered(SampleCompletions, SAMPLE_SERVICE, light,
                                                            resend_timeout, attempts))
    server_gone_s = None
    if watch_server_s > 0:
        try:
            wait_until(lambda: not service.service_is_ready(), watch_server_s, "the server gone", interval=0.1)
            server_gone_s = time.monotonic() - killed_at
        except TimeoutError:
            pass
    finished = call.wait(max(0.0, call.sent_at + call_timeout + 5.0 - time.monotonic()))
    owned = dict(node.shm_files)
    owned_bytes = allocated_bytes(owned)

    def old_enough() -> bool:
        try:
            return all(time.time() - os.stat(p).st_mtime >= SHM_GRACE_S for p in owned if os.path.exists(p))
        except OSError:  # removed meanwhile: old enough for nobody
            return False

    if backdate:
        then = time.time() - SHM_GRACE_S
        for path in [*owned, *(p + LOCK_SUFFIX for p in owned)]:
            with contextlib.suppress(FileNotFoundError):  # removed meanwhile by a live peer's Fast DDS
                os.utime(path, (then, then))
    wait_until(old_enough, SHM_GRACE_S + timeout, "the killed node's files older than the grace period")
    stale = sorted(stale_shm_files(owned))
    start = time.monotonic()
    new_node = restart()
    ready_s = time.monotonic() - start
    current = shm_files()
    logged = [m.group(1).split() for line in new_node.lines() if (m := re.search(REMOVED_LOG, line))]
    removed_by_node = sorted(path for paths in logged for path in paths)
    fates = {path: ("left" if current.get(path) == inode else "removed by the new node" if path in removed_by_node
                    else "replaced" if path in current else "removed by Fast DDS") for path, inode in owned.items()}
    resent.wait(attempts * resend_timeout + timeout)
    response, used = resent.response if resent.response is not None else (None, attempts)
    served_ms = (resent.finished_at - resent.sent_at) * 1000 if resent.finished_at else float("nan")
    report = NodeKill(
        in_flight_s=killed_at - call.sent_at, call_timeout_s=call_timeout,
        answered=call.response is not None,
        gave_up_after_kill_s=call.finished_at - killed_at if finished and call.finished_at else None,
        error=f"{type(call.error).__name__}: {call.error}" if call.error else "", server_gone_s=server_gone_s,
        shm_files=owned, shm_bytes=owned_bytes, stale_before_restart=stale, removed_by_node=removed_by_node,
        fates=fates,
        restart_ready_s=ready_s, resent_answered=response is not None and bool(response.success), attempts=used,
        served_ms=served_ms)
    return report, new_node


# ---------------------------------------------------------------------------------- (b) client killed
@dataclass
class ClientKill:
    """What kill -9 of a client process in the middle of its request did.

    Attributes:
        in_flight_s: the client's "sending" -> kill (the node had counted the call).
        answered_before_kill: the killed client had its answer already (then it was not killed mid-call).
        node_alive: the node process still runs.
        next_served: the next client (a new process) got a successful answer; next_ms: its call's latency,
            which includes the rest of the dead client's request (the node serves one call at a time);
            next_message: the node's message.
        failures: the node's ``service_failures`` counter, change over the scenario.
        killed_files: the killed client's Fast DDS files (see :func:`remove_dead_files`).
    """

    in_flight_s: float
    answered_before_kill: bool
    node_alive: bool
    next_served: bool
    next_ms: float
    next_message: str
    failures: int
    killed_files: dict[str, int] = field(default_factory=dict)


def kill_client_mid_call(ros: RosClient, node: RosProcess, env: dict[str, str], timeout: float = 60.0) -> ClientKill:
    """kill -9 of a client process while the node works on its heavy request; then a new client calls."""
    before = ros.stats(timeout)
    client = RosProcess.python_module("pssnet_testing.chaos", ["client", "--samples", str(HEAVY_SAMPLES)], env,
                                      name="doomed_client")
    try:
        client.wait_for(r"^sending", timeout)
        sent_at = time.monotonic()
        wait_until(lambda: ros.stats(timeout)["service_calls"] > before["service_calls"], timeout,
                   "the node working on the doomed client's request")
    finally:
        killed_at = _kill(client)
    with RosProcess.python_module("pssnet_testing.chaos", ["client", "--samples", str(LIGHT_SAMPLES)], env,
                                  name="next_client") as next_client:
        match = next_client.wait_for(r"^answered success=(\w+) in ([\d.]+) ms: (.*)", timeout)
    after = ros.stats(timeout)
    return ClientKill(in_flight_s=killed_at - sent_at, answered_before_kill="answered" in client.output,
                      node_alive=node.running(), next_served=match.group(1) == "True",
                      next_ms=float(match.group(2)), next_message=match.group(3),
                      failures=after["service_failures"] - before["service_failures"],
                      killed_files=dict(client.shm_files))


# ------------------------------------------------------------------------------ (d) stalled subscribers
class CompletionsListener:
    """A well-behaved subscriber of /pssnet/completions (reliable, keep all) in the caller's process: records
    (arrival time, input stamp) of every completion."""

    def __init__(self, ros: RosClient) -> None:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self._lock = threading.Lock()
        self._arrivals: list[tuple[float, int]] = []
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        self.subscription = ros.node.create_subscription(PointCloud2, COMPLETIONS_TOPIC, self._add, qos)

    def _add(self, msg: Any) -> None:
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        with self._lock:
            self._arrivals.append((time.time(), stamp))

    def arrivals(self, start: int = 0) -> list[tuple[float, int]]:
        with self._lock:
            return self._arrivals[start:]

    def __len__(self) -> int:
        with self._lock:
            return len(self._arrivals)


@dataclass
class OutputWindow:
    """Completions and service calls over a window of continuous mode.

    Attributes:
        label: what else was subscribed.
        seconds: window length.
        sets_processed: sets the node completed and published (its counter).
        delivered: of those, completions the well-behaved listener received (waited for after the window).
        latency_ms: input stamp -> arrival at the listener, per completion of the window.
        service_ms: latency of the service calls made during the window (all answered, or TimeoutError).
        node_rss_mb: the node's resident memory at the end.
        node_cpu_pct: the node's CPU time over the window, % of one core.
        others_cpu_pct: CPU time every other process on the machine took, % of one core (the subscribers,
            this process, and whatever else runs: a loaded machine slows the node, not the subscribers).
        spare_cpu_pct: CPU time nobody used (idle), % of one core: a node that waits with work pending while
            this is high is stalled; with none spare it is starved.
    """

    label: str
    seconds: float
    sets_processed: int
    delivered: int
    latency_ms: list[float]
    service_ms: list[float]
    node_rss_mb: float
    node_cpu_pct: float
    others_cpu_pct: float
    spare_cpu_pct: float

    @property
    def rate_hz(self) -> float:
        return self.sets_processed / self.seconds

    def summary(self) -> str:
        lat = np.asarray(self.latency_ms) if self.latency_ms else np.asarray([np.nan])
        svc = np.asarray(self.service_ms) if self.service_ms else np.asarray([np.nan])
        return (f"{self.label}: {self.sets_processed} sets in {self.seconds:g} s ({self.rate_hz:.2f}/s), "
                f"{self.delivered} delivered to the normal subscriber; stamp -> received p50 "
                f"{np.percentile(lat, 50):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms; {len(self.service_ms)} "
                f"service calls p50 {np.percentile(svc, 50):.0f} ms, max {svc.max():.0f} ms; node RSS "
                f"{self.node_rss_mb:.0f} MB, node CPU {self.node_cpu_pct:.0f} %, others {self.others_cpu_pct:.0f} %, "
                f"idle {self.spare_cpu_pct:.0f} % (of one core)")


def measure_window(ros: RosClient, listener: CompletionsListener, node: RosProcess, seconds: float, label: str,
                   request: Any, call_every_s: float = 1.0, timeout: float = 60.0) -> OutputWindow:
    """Continuous mode for ``seconds`` with a service call every ``call_every_s``; then waits until every
    completion published in the window has reached ``listener`` (TimeoutError if not within ``timeout``)."""
    from pssnet_interfaces.srv import SampleCompletions

    service = ros.service(SampleCompletions, SAMPLE_SERVICE, timeout)
    before, first = ros.stats(timeout), len(listener)
    cpu, machine, start = cpu_seconds(node.pid), machine_cpu(), time.monotonic()
    service_ms: list[float] = []
    while time.monotonic() - start < seconds:
        t0 = time.perf_counter()
        response = ros.call(service, request, timeout)
        service_ms.append((time.perf_counter() - t0) * 1000)
        if not response.success:
            raise RuntimeError(f"the service refused a valid request: {response.message}")
        time.sleep(max(0.0, min(call_every_s - (time.perf_counter() - t0), start + seconds - time.monotonic())))
    elapsed = time.monotonic() - start
    node_cpu, (busy, total) = cpu_seconds(node.pid) - cpu, machine_cpu()
    processed = ros.stats(timeout)["sets_processed"] - before["sets_processed"]
    wait_until(lambda: len(listener) - first >= processed, timeout,
               f"the {processed} completions of the window at the normal subscriber")
    arrivals = listener.arrivals(first)
    return OutputWindow(label=label, seconds=elapsed, sets_processed=processed, delivered=len(arrivals),
                        latency_ms=[(t - s * 1e-9) * 1000 for t, s in arrivals], service_ms=service_ms,
                        node_rss_mb=rss_mb(node.pid), node_cpu_pct=node_cpu / elapsed * 100,
                        others_cpu_pct=(busy - machine[0] - node_cpu) / elapsed * 100,
                        spare_cpu_pct=((total - machine[1]) - (busy - machine[0])) / elapsed * 100)


def process_state(pid: int) -> str:
    """The kernel's one-letter state of a process (R, S, T = stopped, ...)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat[stat.rindex(")") + 2]


def run_with_subscribers(ros: RosClient, listener: CompletionsListener, node: RosProcess, env: dict[str, str],
                         modes: Sequence[str], seconds: float, request: Any, timeout: float = 60.0
                         ) -> tuple[OutputWindow, dict[str, str]]:
    """:func:`measure_window` while subscriber processes of ``modes`` (:data:`SUBSCRIBER_MODES`) are on
    /pssnet/completions: ``never_spins`` creates its subscription and never spins, ``slow_callback`` sleeps 2 s
    in every callback, ``frozen`` spins until its first message and is then stopped with SIGSTOP (its DDS
    threads too: it acknowledges nothing). All reliable, keep all. Returns the window and each subscriber's
    last line (messages it handled)."""
    processes: dict[str, RosProcess] = {}
    try:
        for mode in modes:
            processes[mode] = RosProcess.python_module(
                "pssnet_testing.chaos", ["subscriber", "--mode", "spinning" if mode == "frozen" else mode], env,
                name=f"subscriber_{mode}")
        for process in processes.values():
            process.wait_for(r"^subscribed", timeout)
        # All discovered here before one is frozen: a frozen participant answers no discovery either.
        wait_until(lambda: ros.node.count_subscribers(COMPLETIONS_TOPIC) >= 1 + len(modes), timeout,
                   "every subscriber of /pssnet/completions in the graph")
        if "frozen" in processes:
            frozen = processes["frozen"]
            frozen.wait_for(r"^received 1$", timeout)
            frozen.proc.send_signal(signal.SIGSTOP)
            wait_until(lambda: process_state(frozen.pid) == "T", timeout, "the subscriber stopped")
        label = f"with {', '.join(modes)} subscriber{'s' if len(modes) > 1 else ''}" if modes else "alone"
        window = measure_window(ros, listener, node, seconds, label, request, timeout=timeout)
    finally:
        for mode, process in processes.items():
            if mode == "frozen" and process.running():
                process.proc.send_signal(signal.SIGCONT)
            process.stop()
    return window, {mode: (process.lines()[-1:] or [""])[0] for mode, process in processes.items()}


# ------------------------------------------------------------------ (e) lifecycle transitions mid-work
#: Each scenario's transitions from active, and the way back to active ("shutdown" finalizes the node: its
#: process is stopped with SIGINT and a new one started instead).
TRANSITION_SEQUENCES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "deactivate": (("deactivate",), ("activate",)),
    "cleanup": (("deactivate", "cleanup"), ("configure", "activate")),
    "shutdown": (("shutdown",), ()),
}
WORK_KINDS = ("call", "topics")


@dataclass
class TransitionMidWork:
    """What a lifecycle transition sent while the node worked did.

    Attributes:
        transition: a key of :data:`TRANSITION_SEQUENCES`; work: "call" (a heavy service call in flight) or
            "topics" (a continuous-mode set in progress: the caller runs a camera and turned continuous on).
        delay_s: the wait between the work starting and the transition being sent.
        busy: the work was still in flight when the transition was sent.
        accepted: every transition of the sequence succeeded; transition_s: first sent -> last answered.
        answered: (call) a response arrived; status, success, message: its fields.
        cancelled_sets: (topics) change of the node's ``sets_cancelled``.
        node_alive: the process ran on after the transitions (a finalized node waits for SIGINT).
        clean_exit: (shutdown) the finalized node's exit code after SIGINT was 0.
        restored: active again (shutdown: a new process) and a light call answered with success.
    """

    transition: str
    work: str
    delay_s: float
    busy: bool
    accepted: bool
    transition_s: float
    answered: bool | None
    status: int | None
    success: bool | None
    message: str
    cancelled_sets: int
    node_alive: bool
    clean_exit: bool | None
    restored: bool


def transition_mid_work(ros: RosClient, node: RosProcess, transition: str, work: str,
                        restart: Callable[[], RosProcess], delay_s: float = 0.0, timeout: float = 60.0
                        ) -> tuple[TransitionMidWork, RosProcess]:
    """Sends ``transition`` while ``node`` works on a heavy call or a topic set, then brings it back to active
    (after "shutdown": stops it and calls ``restart()``). Returns the report and the node now serving."""
    from pssnet_interfaces.srv import SampleCompletions

    forward, back = TRANSITION_SEQUENCES[transition]
    before = ros.stats(timeout)
    call = None
    if work == "call":
        service = ros.service(SampleCompletions, SAMPLE_SERVICE, timeout)
        call = BackgroundCall(lambda: RosClient.call(service, scene_request(HEAVY_SAMPLES), timeout))
        wait_until(lambda: ros.stats(timeout)["service_calls"] > before["service_calls"], timeout,
                   "the node working on the heavy call")
    else:
        wait_until(lambda: ros.stats(timeout)["sets_in_progress"] == 1, timeout, "a topic set in progress")
    time.sleep(delay_s)
    busy = call.finished_at is None if call is not None else ros.stats(timeout)["sets_in_progress"] == 1
    started = time.monotonic()
    accepted = all([ros.change_state(name, timeout=timeout) for name in forward])
    transition_s = time.monotonic() - started
    if call is not None:
        call.wait(timeout)
    alive = node.running()
    cancelled = ros.stats(timeout)["sets_cancelled"] - before["sets_cancelled"] if alive else 0
    clean_exit = None
    if transition == "shutdown":
        clean_exit = alive and node.stop() == 0
        node = restart()
    elif alive:
        for name in back:  # a refused one shows as restored=False: the light call below finds no service
            ros.change_state(name, timeout=timeout)
    try:
        response, _ = ros.call_until_answered(SampleCompletions, SAMPLE_SERVICE,
                                              scene_request(LIGHT_SAMPLES, grasps=False), timeout / 3, 3)
        restored = bool(response.success)
    except TimeoutError:
        restored = False
    response = call.response if call is not None else None
    report = TransitionMidWork(
        transition=transition, work=work, delay_s=delay_s, busy=busy, accepted=accepted,
        transition_s=transition_s, answered=None if call is None else response is not None,
        status=None if response is None else int(response.status),
        success=None if response is None else bool(response.success),
        message="" if response is None else response.message, cancelled_sets=cancelled, node_alive=alive,
        clean_exit=clean_exit, restored=restored)
    return report, node


# ---------------------------------------------------------------------------- the scenarios' processes
def _client_main(args: argparse.Namespace, domain: int) -> int:
    """Sends one request, prints "sending", then "answered success=... in ... ms: message" or "no answer"."""
    request = scene_request(args.samples)
    with RosClient(domain, "chaos_client") as ros:
        from pssnet_interfaces.srv import SampleCompletions

        service = ros.service(SampleCompletions, SAMPLE_SERVICE, args.timeout)
        print(f"sending {args.samples} samples", flush=True)
        t0 = time.perf_counter()
        try:
            response = ros.call(service, request, args.timeout)
        except TimeoutError as error:
            print(f"no answer: {error}", flush=True)
            return 1
        print(f"answered success={response.success} in {(time.perf_counter() - t0) * 1000:.0f} ms: "
              f"{response.message}", flush=True)
    return 0


def _subscriber_main(args: argparse.Namespace, domain: int) -> int:
    """A reliable, keep-all subscriber of /pssnet/completions that never spins, or sleeps in its callback."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from pssnet_ros.spinning import shutdown_once, spin_until_shutdown

    received = 0

    def on_message(_: PointCloud2) -> None:
        nonlocal received
        received += 1
        print(f"received {received}", flush=True)
        if args.mode == "slow_callback":
            time.sleep(args.sleep)

    rclpy.init(domain_id=domain)
    node = rclpy.create_node(f"chaos_{args.mode}")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(PointCloud2, COMPLETIONS_TOPIC, on_message, qos)
    print("subscribed", flush=True)
    try:
        if args.mode == "never_spins":
            while rclpy.ok():  # SIGINT shuts the context down (rclpy's handler)
                time.sleep(0.1)
        else:
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            spin_until_shutdown(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        shutdown_once()
    print(f"handled {received} messages", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pssnet_testing.chaos", description=__doc__.split("\n\n")[0])
    roles = parser.add_subparsers(dest="role", required=True)
    client = roles.add_parser("client", help="send one sample_completions request and print the outcome")
    client.add_argument("--samples", type=int, default=LIGHT_SAMPLES)
    client.add_argument("--timeout", type=float, default=60.0)
    subscriber = roles.add_parser("subscriber", help="subscribe to /pssnet/completions and misbehave")
    subscriber.add_argument("--mode", choices=("never_spins", "slow_callback", "spinning"), required=True)
    subscriber.add_argument("--sleep", type=float, default=2.0, help="slow_callback: seconds per callback")
    args = parser.parse_args(argv)
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0"))  # ros_env sets it for every child
    return _client_main(args, domain) if args.role == "client" else _subscriber_main(args, domain)


if __name__ == "__main__":
    sys.exit(main())
