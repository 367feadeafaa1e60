"""Chaos over real DDS: kill -9 of the node and of a client in the middle of a call, stale Fast DDS
shared memory, stalled subscribers of /pssnet/completions.

The scenarios live in :mod:`pssnet_testing.chaos`; ``benchmarks/chaos_bench.py`` runs them longer and prints the
numbers (RELIABILITY.md). These are the short versions, each asserting what must hold. Nothing waits a guessed
time: every wait is on a condition (a log line, a counter of the node, a file's state) with a deadline.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import fcntl
import os
import secrets
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_node_helpers import domain_for, node_checkpoint

from pssnet_ros.shm import SHM_DIR, SHM_GRACE_S, clean_stale_shm
from pssnet_testing import chaos
from pssnet_testing.client import RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import (
    LOCK_SUFFIX,
    RosProcess,
    ros_env,
    shm_files,
    stale_shm_files,
)

pytestmark = pytest.mark.ros
DOMAIN = domain_for(11)
TIMEOUT = 60.0  # for anything a process must do: generous, the machine may be loaded
CALL_TIMEOUT = 3.0  # the client's patience in the kill -9 scenario


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return node_checkpoint(tmp_path_factory.mktemp("chaos"))[0]


def node_under_test(checkpoint: Path, domain: int) -> NodeUnderTest:
    """A completion node that allows heavy requests (:data:`chaos.NODE_PARAMS`), not started yet."""
    return NodeUnderTest(domain, model_path=checkpoint, **chaos.NODE_PARAMS, up_vector=chaos.scene_up_vector(),
                         threads=1, num_samples=chaos.LIGHT_SAMPLES, max_rate_hz=5.0)


@pytest.fixture(scope="module")
def dead_files() -> Iterator[dict[str, int]]:
    """Fast DDS files of the processes these tests kill: removed at the end, once no live process maps them."""
    files: dict[str, int] = {}
    yield files
    chaos.remove_dead_files(files)


@pytest.fixture(scope="module")
def node(checkpoint, dead_files) -> Iterator[RosProcess]:
    node = node_under_test(checkpoint, DOMAIN)
    process = node.start()
    yield process
    assert node.close() == 0, process.output[-4000:]


@pytest.fixture(scope="module")
def ros(node) -> Iterator[RosClient]:
    with RosClient(DOMAIN, "chaos_test_client") as client:
        yield client


# ----------------------------------------------------------------------------- (c) stale shared memory
class PosixSemaphore:
    """A named POSIX semaphore like Fast DDS' port mutex (created here with value 0: "held by someone")."""

    def __init__(self, name: str) -> None:
        self._libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        self._libc.sem_open.restype = ctypes.c_void_p
        self.name = name
        self._sem = self._libc.sem_open(f"/{name}".encode(), os.O_CREAT | os.O_EXCL, 0o644, 0)
        assert self._sem, f"sem_open failed: {os.strerror(ctypes.get_errno())}"

    def release(self) -> None:
        self._libc.sem_post(ctypes.c_void_p(self._sem))

    def close(self) -> None:
        self._libc.sem_close(ctypes.c_void_p(self._sem))
        self._libc.sem_unlink(f"/{self.name}".encode())


def fake_segment(name: str, age_s: float = 0.0) -> list[Path]:
    """A segment file and its lock file as Fast DDS creates them, ``age_s`` old."""
    paths = [SHM_DIR / name, SHM_DIR / (name + LOCK_SUFFIX)]
    for path in paths:
        path.write_bytes(b"")
    backdate(paths, age_s)
    return paths


def backdate(paths, age_s: float) -> None:
    then = time.time() - age_s
    for path in paths:
        if os.path.exists(path):
            os.utime(path, (then, then))


def with_locks(files: dict[str, int]) -> list[str]:
    return [p for path in files for p in (path, path + LOCK_SUFFIX)]


def test_start_up_cleanup_removes_a_dead_participants_files_and_keeps_a_live_ones(dead_files):
    """What clean_stale_shm (run by every node start) removes: files of a participant killed with -9, once
    older than the grace period; never a live participant's, a young file, a segment whose lock someone holds,
    or a port whose mutex someone holds."""
    dead = RosProcess.python_module("pssnet_testing.chaos", ["subscriber", "--mode", "spinning"],
                                    ros_env(domain_for(13)), name="doomed_participant")
    live = RosProcess.python_module("pssnet_testing.chaos", ["subscriber", "--mode", "spinning"],
                                    ros_env(domain_for(14)), name="live_participant")
    token = secrets.token_hex(8)
    young = fake_segment(f"fastrtps_{token}")
    held = fake_segment(f"fastrtps_{secrets.token_hex(8)}", age_s=10 * SHM_GRACE_S)
    port = fake_segment(f"fastrtps_port{90000 + int(token[:4], 16)}", age_s=10 * SHM_GRACE_S)
    mutex = PosixSemaphore(f"{port[0].name}_mutex")
    try:
        with open(held[1], "rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # as the segment's owner holds it while it lives
            dead.wait_for(r"^subscribed", TIMEOUT)
            live.wait_for(r"^subscribed", TIMEOUT)
            assert dead.shm_files and live.shm_files, "a participant owns its segments"
            dead.proc.send_signal(signal.SIGKILL)
            dead.stop()
            dead_files.update(dead.shm_files)
            stale = wait_until(lambda: stale_shm_files(dead.shm_files), TIMEOUT, "the killed participant's files")
            # Both participants' files are ours to age: past the grace period, only locks and maps protect them.
            backdate(with_locks(dead.shm_files) + with_locks(live.shm_files), 10 * SHM_GRACE_S)
            first = clean_stale_shm()
            current = shm_files()
            for path in stale:
                assert current.get(path) != dead.shm_files[path], f"{path} of the killed participant left"
                # Port files are shared by name by every participant: another DDS user on the machine (a second
                # test run, a benchmark) may have re-created this one in the meantime, so ours had nothing left
                # to remove (run 12 of a 20-run loop failed so on fastrtps_port7000). Segments are per participant.
                assert path in first.removed or "fastrtps_port" in path, f"{path} not removed: {first.removed}"
            assert all(current.get(p) == inode for p, inode in live.shm_files.items()), "a live participant's file"
            assert live.running()
            assert all(p.exists() for p in young + held + port), "a young, a locked or a port opening"
        mutex.release()
        backdate(young, 10 * SHM_GRACE_S)
        second = clean_stale_shm()
        assert {str(p) for p in young + held + port} <= set(second.removed), "once old, unlocked, free"
    finally:
        mutex.close()
        for path in young + held + port:
            path.unlink(missing_ok=True)
        live.stop()


# -------------------------------------------------------------------------------- (b) client killed
def test_client_killed_mid_call_does_not_hurt_the_node(node, ros, dead_files):
    report = chaos.kill_client_mid_call(ros, node, ros_env(DOMAIN), TIMEOUT)
    dead_files.update(report.killed_files)
    assert not report.answered_before_kill, "the client had its answer: not killed mid-call"
    assert report.node_alive, node.output[-4000:]
    assert report.next_served, report.next_message
    assert report.failures == 0


# ---------------------------------------------------------------------------- (d) stalled subscribers
def test_stalled_subscribers_stall_neither_completions_nor_the_service(node, ros):
    """Subscribers that never spin, sleep 2 s in their callback, or are frozen (SIGSTOP, no acknowledgements
    at all) while the node publishes ~0.5 MB completions at up to 5 Hz: every completion still reaches a
    normal subscriber, the node keeps its pace, and the service keeps answering."""
    env = ros_env(DOMAIN)
    assert all(r.successful for r in ros.set_parameters(continuous=True))
    listener = chaos.CompletionsListener(ros)
    camera = RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", "10"], env, name="camera")
    try:
        camera.wait_for(r"publishing", TIMEOUT)
        wait_until(lambda: len(listener) > 0, TIMEOUT, "a first completion at the normal subscriber")
        request = chaos.scene_request(chaos.LIGHT_SAMPLES, grasps=False)
        alone, _ = chaos.run_with_subscribers(ros, listener, node, env, (), 4.0, request, TIMEOUT)
        stalled, lines = chaos.run_with_subscribers(ros, listener, node, env, chaos.SUBSCRIBER_MODES, 6.0, request,
                                                    TIMEOUT)
    finally:
        camera.stop()
        ros.set_parameters(continuous=False)
    assert alone.sets_processed >= 3, alone.summary()
    assert stalled.delivered >= stalled.sets_processed, stalled.summary()
    assert stalled.sets_processed >= 3, stalled.summary()
    # A stall is the node waiting, idle, with inputs pending while the machine has CPU to spare. Half the pace
    # alone is the bar; below it the window must show why the machine, not the subscribers, slowed the node:
    # no core left to spare (other processes took them), or the node burnt as much CPU as alone (the virtual
    # CPU itself ran slower). Pace alone varied 0.6-2x between 20 s windows on a shared machine (RELIABILITY.md).
    paced = stalled.rate_hz >= 0.5 * alone.rate_hz
    starved = stalled.spare_cpu_pct < 25.0
    working = stalled.node_cpu_pct >= 0.8 * alone.node_cpu_pct
    assert paced or starved or working, f"stalled:\n{alone.summary()}\n{stalled.summary()}"
    assert max(stalled.service_ms) < 10_000, stalled.summary()
    assert lines["never_spins"] == "handled 0 messages", lines
    assert lines["slow_callback"].startswith("handled"), lines


# ---------------------------------------------------------------------------------- (a) node killed
def test_node_killed_mid_call_client_gives_up_and_a_restarted_node_serves(checkpoint, dead_files):
    node = node_under_test(checkpoint, domain_for(12))
    try:
        first = node.start()
        report, _ = chaos.kill_node_mid_call(node.ros, first, node.start, CALL_TIMEOUT, TIMEOUT, backdate=True)
    finally:
        node.close()
    dead_files.update(report.shm_files)
    assert not report.answered, "an answer from a killed node"
    assert report.gave_up_after_kill_s is not None, f"the client still waited {CALL_TIMEOUT} s + 5 s after the call"
    assert report.gave_up_after_kill_s <= CALL_TIMEOUT + 1.0
    assert report.error.startswith("TimeoutError"), report.error
    assert report.resent_answered, f"a request sent while the node was down was lost ({report.attempts} attempts)"
    assert report.stale_before_restart, "kill -9 leaves shared memory nobody uses"
    # None of the killed node's stale files may be left. A port file can also be "replaced": port files are
    # shared by name by every participant, so a live one (the new node, or any other DDS user on the machine)
    # may have removed the stale inode and created a fresh one of the same name.
    for path in report.stale_before_restart:
        assert report.fates[path] in ("removed by the new node", "removed by Fast DDS", "replaced"), report.fates
        assert report.fates[path] != "replaced" or "fastrtps_port" in path, report.fates
