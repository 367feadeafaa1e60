"""The test client's action client keeps a goal response that arrives before rclpy has recorded the request.

A bare action server in a child process rejects every goal at once; in this process the client's rcl handle is
wrapped so that each send returns only after a pause, as when the calling thread is descheduled on a loaded
machine (CI once lost ``test_node_action``'s goal response so, with "Ignoring unexpected goal response").
"""

from __future__ import annotations

import sys
import time
from typing import Any

import pytest
from test_node_helpers import domain_for

from pssnet_testing.processes import RosProcess, ros_env, spinning_node_script

pytestmark = pytest.mark.ros
ACTION = "/action_race_probe"
SERVER = spinning_node_script("action_race_probe", f"""
from rclpy.action import ActionServer, GoalResponse
from pssnet_interfaces.action import SampleCompletions
server = ActionServer(node, SampleCompletions, "{ACTION}", execute_callback=lambda handle: SampleCompletions.Result(),
                      goal_callback=lambda goal: GoalResponse.REJECT)""", "server up")
PAUSE_S = 1.0  # between sending a goal and returning to the caller: far longer than the server takes to answer


class PausingSender:
    """Forwards everything to an rcl action client handle; returns from each goal send ``PAUSE_S`` late."""

    def __init__(self, handle: Any) -> None:
        self._handle = handle

    def __getattr__(self, name: str) -> Any:
        return getattr(self._handle, name)

    def __enter__(self) -> Any:
        return self._handle.__enter__()

    def __exit__(self, *exc: Any) -> Any:
        return self._handle.__exit__(*exc)

    def send_goal_request(self, request: Any) -> int:
        sequence_number = self._handle.send_goal_request(request)
        time.sleep(PAUSE_S)
        return sequence_number


@pytest.fixture(scope="module")
def ros():
    from pssnet_testing.client import RosClient

    domain = domain_for(24)
    with RosProcess([sys.executable, "-c", SERVER], ros_env(domain), name="action_race_probe") as server:
        server.wait_for("server up", timeout=60)
        client = RosClient(domain, name="action_race_client")
        try:
            yield client
        finally:
            client.close()
        assert server.stop() == 0, server.output


def paused_client(ros, client_type: type) -> Any:
    from pssnet_interfaces.action import SampleCompletions

    client = client_type(ros.node, SampleCompletions, ACTION)
    assert client.wait_for_server(timeout_sec=30), "the probe's action server was not discovered"
    client._client_handle = PausingSender(client._client_handle)
    return client


def goal() -> Any:
    from pssnet_interfaces.action import SampleCompletions

    return SampleCompletions.Goal(num_samples=1)


def test_a_response_that_outruns_the_send_is_kept(ros):
    from pssnet_testing.action_client import SerialisedActionClient

    client = paused_client(ros, SerialisedActionClient)
    for _ in range(3):
        handle = ros.send_goal(client, goal(), timeout=PAUSE_S + 10)
        assert not handle.accepted  # the probe rejects every goal


def test_rclpys_own_client_still_loses_it(ros):
    """The race the serialised client closes is real with the installed rclpy: if this fails, rclpy has fixed
    it (its issue 1123) and ``SerialisedActionClient`` can go."""
    from rclpy.action import ActionClient

    client = paused_client(ros, ActionClient)
    with pytest.raises(TimeoutError, match="no goal response"):
        ros.send_goal(client, goal(), timeout=PAUSE_S + 4)
