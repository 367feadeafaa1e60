"""Child ROS processes: free domains, blaming only the shared memory a process created itself, clean SIGINT."""

from __future__ import annotations

import os
import signal
import socket
import sys
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from test_node_helpers import domain_for

from pssnet_ros.spinning import shutdown_once, spin_until_shutdown
from pssnet_testing.processes import (
    DOMAIN_GAIN,
    LOCK_SUFFIX,
    PORT_BASE,
    RosProcess,
    claim_domain_id,
    free_domain_id,
    ros_env,
    shm_files,
    spinning_node_script,
    stale_shm_files,
)

PARTICIPANT = spinning_node_script("shm_probe", """
from std_msgs.msg import String
node.create_publisher(String, "probe", 10)
node.create_subscription(String, "probe", lambda m: None, 10)""", "participant up")


def test_a_domain_with_a_bound_rtps_port_is_skipped():
    domain = free_domain_id(40)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", PORT_BASE + DOMAIN_GAIN * domain + 17))  # as a participant of that domain does
        assert free_domain_id(domain) != domain
        with pytest.raises(RuntimeError, match=f"every ROS domain in \\[{domain}, {domain}\\] is in use"):
            free_domain_id(domain, low=domain, high=domain)
        with pytest.raises(RuntimeError, match=f"every ROS domain in \\[{domain}, {domain}\\] is in use"):
            claim_domain_id(domain, low=domain, high=domain)


CLAIMER = """
import sys, time
from pssnet_testing.processes import claim_domain_id
print(claim_domain_id(int(sys.argv[1])), flush=True)
time.sleep(300)
"""


def test_a_domain_claimed_by_a_live_process_is_neither_free_nor_claimable_until_it_ends():
    """Two test sessions on one machine pick their domains long before their nodes bind a port: the claim is
    what keeps them apart (and this process's own claims are not handed out twice)."""
    domain = free_domain_id(60)
    claimer = RosProcess([sys.executable, "-c", CLAIMER, str(domain)], ros_env(0), name="claimer")
    try:
        assert int(claimer.wait_for(r"^\d+$", 60).group(0)) == domain
        assert free_domain_id(domain) != domain
        with pytest.raises(RuntimeError, match="in use"):
            free_domain_id(domain, low=domain, high=domain)
        with pytest.raises(RuntimeError, match="in use or claimed"):
            claim_domain_id(domain, low=domain, high=domain)
    finally:
        claimer.proc.send_signal(signal.SIGKILL)  # a killed claimer's claim ends with it
        claimer.stop()
    mine = claim_domain_id(domain, low=domain, high=domain)
    assert mine == domain and free_domain_id(domain) != domain
    assert claim_domain_id(domain) != domain, "this process's own claim handed out again"


@pytest.mark.ros
def test_segments_left_by_a_killed_process_are_not_blamed_on_the_next_one():
    """Fast DDS port segments are shared: a participant killed with -9 leaves its files behind, and the next
    participant opens them, takes them over, or replaces them by new files of the same name. Only the killed
    one is blamed for its files; the next one only for files it created (compared by inode)."""
    env = ros_env(domain_for(7))
    killed = RosProcess([sys.executable, "-c", PARTICIPANT], env, name="killed")
    killed.wait_for("participant up", timeout=60)
    assert killed.shm_files, "a participant owns its segments"
    killed.proc.send_signal(signal.SIGKILL)
    killed.stop()
    left = stale_shm_files(killed.shm_files)
    try:
        assert left, "kill -9 leaves the segments a participant created"
        with RosProcess([sys.executable, "-c", PARTICIPANT], env, name="clean") as clean:
            clean.wait_for("participant up", timeout=60)
            before = {path: inode for path, inode in killed.shm_files.items() if path in left}
            assert not set(clean.shm_files.items()) & set(before.items()), "files that existed before it started"
            assert clean.stop() == 0, clean.output
        assert stale_shm_files(clean.shm_files) == set()
    finally:
        for path in stale_shm_files(killed.shm_files):  # ours to clean: the killed participant's leftovers
            name = Path(path).name
            for leftover in (path, path + LOCK_SUFFIX, f"{Path(path).parent}/sem.{name}_mutex"):
                if os.path.exists(leftover):
                    os.unlink(leftover)
    current = shm_files()  # by inode: another participant may have created a file of the same name meanwhile
    assert not any(current.get(path) == killed.shm_files[path] for path in left)


class RacingExecutor:
    """spin() fails as rclpy's does when the signal handler shuts the context down under it (or for real)."""

    def __init__(self, context_ok: bool) -> None:
        self.context = type("Context", (), {"ok": lambda _: context_ok})()

    def spin(self) -> None:
        raise RuntimeError("failed to initialize wait set: the given context is not valid")


def test_spin_until_shutdown_absorbs_only_the_shutdown_race():
    spin_until_shutdown(RacingExecutor(context_ok=False))  # shut down: a clean exit
    with pytest.raises(RuntimeError, match="wait set"):
        spin_until_shutdown(RacingExecutor(context_ok=True))  # still running: a real error


class ShutDownMeanwhile(Context):
    """A context that rclpy's signal-handler thread shuts down between ``try_shutdown``'s validity check and its
    own shutdown (ros2/rclpy#1352): the race's end state, made deterministic; rcl's own error follows."""

    def try_shutdown(self) -> None:
        self.shutdown()  # the signal handler's thread
        super().shutdown()  # try_shutdown's own call, after its check passed: "rcl_shutdown already called"


class FailsWhileValid(Context):
    def try_shutdown(self) -> None:
        raise RuntimeError("failed to shutdown: something else")


def test_shutdown_once_absorbs_only_a_shutdown_by_another_thread():
    domain = domain_for(25)
    raced = ShutDownMeanwhile()
    rclpy.init(context=raced, domain_id=domain)
    with pytest.raises(RuntimeError, match="already called"):
        raced.try_shutdown()  # what the node's exit hit in CI
    assert not raced.ok()

    raced = ShutDownMeanwhile()
    rclpy.init(context=raced, domain_id=domain)
    shutdown_once(raced)  # a clean exit
    assert not raced.ok()

    failing = FailsWhileValid()
    rclpy.init(context=failing, domain_id=domain)
    try:
        with pytest.raises(RuntimeError, match="something else"):
            shutdown_once(failing)  # still valid: a real error
    finally:
        failing.shutdown()
