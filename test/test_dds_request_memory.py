"""A service request's payload is freed once taken (issue 29, item 4, RELIABILITY.md "Memory after a burst of
bad requests").

rmw_fastrtps gives a service's request reader PREALLOCATED_WITH_REALLOC history memory: Fast DDS keeps each
payload buffer of the reader's pool at the largest request it ever held, so one refused 4000x3000 float request
held 46 MiB of the node's heap for the rest of its life. The shipped Fast DDS profile, read with
RMW_FASTRTPS_USE_QOS_FROM_XML=1 (set with it by ``ros_env``), gives request readers DYNAMIC memory instead.
A bare server (no model) receives one such request; its anonymous memory is compared before and after. And the
node's threads allocate from glibc's main arena, whose unused top ``malloc_trim`` returns (``use_one_arena``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from test_node_helpers import domain_for

from pssnet_testing.processes import USE_QOS_FROM_XML, RosProcess, resident_mib_by_kind, ros_env, spinning_node_script

SERVICE = "/request_memory_probe"
SERVER = spinning_node_script("request_memory_probe", f"""
from pssnet_interfaces.srv import SampleCompletions
from pssnet_ros.heap import trim_heap
node.create_service(SampleCompletions, "{SERVICE}", lambda request, response: response)
node.create_timer(0.2, trim_heap)  # so that what the process freed does not count""", "server up")
HUGE = (3000, 4000)  # rows, columns: 46 MiB of float32, more than the 8 MiB shared-memory segment
MIB = 1 << 20


def settled_rss_mib(pid: int, seconds: float = 1.5) -> float:
    time.sleep(seconds)  # the server's trim timer runs meanwhile
    return resident_mib_by_kind(pid)["heap and anonymous"]


@pytest.mark.ros
@pytest.mark.parametrize("profile_policy", [True, pytest.param(False, marks=pytest.mark.slow)],
                         ids=["shipped profile", "rmw_fastrtps default"])
def test_a_large_request_payload_is_freed_once_taken(profile_policy: bool):
    """With the shipped profile the server's anonymous memory comes back after a 46 MiB request; with
    rmw_fastrtps' default history memory (the slow case, which shows what the profile fixes) it stays."""
    from pssnet_interfaces.srv import SampleCompletions

    from pssnet_ros.conversions import numpy_to_image
    from pssnet_testing.client import RosClient

    domain = domain_for(8)
    env = ros_env(domain, extra=None if profile_policy else {USE_QOS_FROM_XML: "0"})
    assert profile_policy == (env.get(USE_QOS_FROM_XML) == "1")
    request = SampleCompletions.Request()
    request.depth = numpy_to_image(np.full(HUGE, 0.6, np.float32), "32FC1")
    small = SampleCompletions.Request()
    small.depth = numpy_to_image(np.full((480, 640), 0.6, np.float32), "32FC1")
    with RosProcess([sys.executable, "-c", SERVER], env, name="request_memory_probe") as server:
        server.wait_for("server up", timeout=60)
        ros = RosClient(domain, name="request_memory_client")
        try:
            client = ros.service(SampleCompletions, SERVICE)
            for _ in range(3):  # pools, arenas and the shared-memory segment of ordinary requests
                ros.call(client, small, 30.0)
            before = settled_rss_mib(server.pid)
            ros.call(client, request, 60.0)
            after_huge = settled_rss_mib(server.pid)
            ros.call(client, small, 30.0)
            after = settled_rss_mib(server.pid)
        finally:
            ros.close()
        assert server.stop() == 0, server.output
    growth = after - before
    held = HUGE[0] * HUGE[1] * 4 / MIB
    if profile_policy:
        assert growth < held / 3, (f"{growth:.1f} MiB of the server's heap stayed after one {held:.0f} MiB request "
                                   f"({before:.1f} -> {after_huge:.1f} -> {after:.1f} MiB)")
    else:
        assert growth > held * 0.8, (f"rmw_fastrtps' default kept only {growth:.1f} MiB of a {held:.0f} MiB request "
                                     f"({before:.1f} -> {after_huge:.1f} -> {after:.1f} MiB)")


ARENA_PROBE = """
import ctypes, sys, threading
from pssnet_ros.heap import use_one_arena
pinned = use_one_arena() if sys.argv[1] == "one" else False
kept = []
threads = [threading.Thread(target=lambda: kept.append(bytearray(100_000))) for _ in range(4)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
print(pinned, flush=True)
ctypes.CDLL(None).malloc_stats()  # one "Arena N:" block per arena, on stderr
"""


@pytest.mark.parametrize("one", [True, False], ids=["use_one_arena", "glibc default"])
def test_the_nodes_threads_allocate_from_the_one_arena_malloc_trim_returns_whole(one: bool):
    """pssnet_ros.heap.use_one_arena (called by the node at start): threads started afterwards allocate from the main
    arena, whose unused top malloc_trim returns; by default a thread gets an arena of its own, whose top it does not."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    done = subprocess.run([sys.executable, "-c", ARENA_PROBE, "one" if one else "default"], env=env,
                          capture_output=True, text=True, timeout=60, check=True)
    arenas = sum(line.startswith("Arena ") for line in done.stderr.splitlines())
    assert done.stdout.split() == [str(one)]
    assert (arenas == 1) if one else (arenas > 1), done.stderr
