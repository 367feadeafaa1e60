"""One in-process rclpy client of the completion node, shared by the tests, the demo and the benchmark.

    with RosClient(domain_id) as ros:
        service = ros.service(SampleCompletions, SAMPLE_SERVICE)
        response = ros.call(service, SampleCompletions.Request(num_samples=5))
        action = ros.action(SampleCompletionsAction, SAMPLE_SERVICE)     # the same call as an action
        status, result = ros.goal_result(ros.send_goal(action, SampleCompletionsAction.Goal(num_samples=5)))
        counters = ros.stats()

Its own rclpy context (so several can live in one process next to a node under test), spun by a background
executor; calls wait on the response's future (an event, not a polling loop), and :func:`wait_until` waits
for a condition with a deadline instead of sleeping a guessed time.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from pssnet_testing.processes import configure_this_process

NODE = "/pssnet"
SAMPLE_SERVICE = f"{NODE}/sample_completions"
STATS_SERVICE = f"{NODE}/get_stats"

T = TypeVar("T")


def wait_until(condition: Callable[[], T], timeout: float, what: str, interval: float = 0.05) -> T:
    """Polls ``condition`` until it returns a truthy value, which is returned.

    Raises:
        TimeoutError: still false after ``timeout`` seconds; the message says what was awaited.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        time.sleep(interval)


def _result(future: Any, timeout: float, what: str) -> Any:
    """Waits for an rclpy future (an event, not a poll); its result, or TimeoutError("{what} within ...")."""
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    if not done.wait(timeout):
        raise TimeoutError(f"{what} within {timeout:g} s")
    if future.exception() is not None:
        raise future.exception()
    return future.result()


class RosClient:
    """An rclpy context + node in this process, spun by a background single-threaded executor.

    Args:
        domain_id: ROS_DOMAIN_ID of the node to talk to.
        name: node name of this client.
    """

    def __init__(self, domain_id: int, name: str = "pssnet_client") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        configure_this_process(domain_id)
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._clients: dict[tuple[type, str], Any] = {}
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"{name}-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok() and not self._closing.is_set():
                self._executor.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:
            pass
        except RuntimeError:  # rclpy's shutdown race (see pssnet_ros.spinning), unless the context is still valid
            if self.context.ok():
                raise

    def service(self, srv_type: type, name: str, timeout: float = 30.0, new: bool = False) -> Any:
        """A client of service ``name`` whose server has been discovered (waits up to ``timeout`` s).

        Clients are cached by (type, name) unless ``new`` (several clients of one service, e.g. for concurrency).
        """
        client = self.node.create_client(srv_type, name) if new else self._client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            if new:
                self.node.destroy_client(client)
            raise TimeoutError(f"service {name} not discovered within {timeout:g} s")
        return client

    def _client(self, srv_type: type, name: str) -> Any:
        """The cached client of service ``name``, created (without waiting for discovery) on first use."""
        key = (srv_type, name)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(srv_type, name)
        return self._clients[key]

    def call_until_answered(self, srv_type: type, name: str, request: Any, attempt_timeout: float = 30.0,
                            attempts: int = 5) -> tuple[Any, int]:
        """Sends ``request`` to service ``name`` until an attempt is answered; returns (response, attempts used).

        A request sent while the server is down, or after a restart before this client has matched the new
        server, is lost without an error (DDS keeps a dead server "available" until its lease expires, ~20 s),
        so an attempt that is not answered within ``attempt_timeout`` is sent again. Choose ``attempt_timeout``
        above the call's own latency: a slow call re-sent is computed twice. Safe for the completion service,
        which has no side effects: a repeated request is simply computed again.

        Raises:
            TimeoutError: ``attempts`` attempts went unanswered.
        """
        client = self._client(srv_type, name)  # no discovery wait here: the server may be down right now
        for attempt in range(1, attempts + 1):
            try:
                return self.call(client, request, attempt_timeout), attempt
            except TimeoutError:
                continue
        raise TimeoutError(f"{name}: no answer to {attempts} attempts of {attempt_timeout:g} s")

    @staticmethod
    def call(client: Any, request: Any, timeout: float = 60.0) -> Any:
        """Sends ``request`` and waits for the response (TimeoutError after ``timeout`` s)."""
        future = client.call_async(request)
        try:
            return _result(future, timeout, f"no response from {client.srv_name}")
        except TimeoutError:
            client.remove_pending_request(future)
            raise

    def action(self, action_type: type, name: str, timeout: float = 30.0) -> Any:
        """An action client of ``name`` whose server has been discovered (waits up to ``timeout`` s)."""
        from pssnet_testing.action_client import SerialisedActionClient

        client = SerialisedActionClient(self.node, action_type, name)
        if not client.wait_for_server(timeout_sec=timeout):
            client.destroy()
            raise TimeoutError(f"action server {name} not discovered within {timeout:g} s")
        return client

    @staticmethod
    def send_goal(client: Any, goal: Any, feedback: Callable[[Any], None] | None = None,
                  timeout: float = 30.0) -> Any:
        """Sends ``goal``; returns its (accepted or rejected) goal handle. ``feedback`` gets each feedback message."""
        on_feedback = None if feedback is None else (lambda message: feedback(message.feedback))
        return _result(client.send_goal_async(goal, feedback_callback=on_feedback), timeout,
                       "no goal response from the action server")

    @staticmethod
    def goal_result(goal_handle: Any, timeout: float = 60.0) -> tuple[int, Any]:
        """Waits for an accepted goal's end: (its action_msgs/GoalStatus code, its result)."""
        response = _result(goal_handle.get_result_async(), timeout, "no result of the goal")
        return response.status, response.result

    @staticmethod
    def cancel_goal(goal_handle: Any, timeout: float = 30.0) -> Any:
        """Asks the server to cancel the goal; returns its action_msgs/CancelGoal response."""
        return _result(goal_handle.cancel_goal_async(), timeout, "no answer to the cancel request")

    def stats(self, timeout: float = 30.0) -> dict[str, int]:
        """The node's counters (``/pssnet/get_stats``)."""
        from std_srvs.srv import Trigger

        return json.loads(self.call(self.service(Trigger, STATS_SERVICE, timeout), Trigger.Request(), timeout).message)

    def wait_idle(self, timeout: float = 60.0) -> dict[str, int]:
        """Waits until the node has no topic set pending or in progress; returns its counters at that moment."""

        def idle() -> dict[str, int] | None:
            stats = self.stats(timeout)
            return stats if stats["sets_pending"] == 0 and stats["sets_in_progress"] == 0 else None

        return wait_until(idle, timeout, "the node idle (no set pending or in progress)")

    def set_parameters(self, node: str = NODE, timeout: float = 30.0, **values: bool | int | float | str) -> list:
        """Sets parameters of ``node`` in one request; returns the SetParametersResult of each (in order)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        parameters = [Parameter(name, value=value).to_parameter_msg() for name, value in values.items()]
        request = SetParameters.Request(parameters=parameters)
        return self.call(self.service(SetParameters, f"{node}/set_parameters", timeout), request, timeout).results

    def change_state(self, transition: str, node: str = NODE, timeout: float = 60.0) -> bool:
        """Sends lifecycle ``transition`` ("configure", "activate", "deactivate", "cleanup", "shutdown" from
        the node's current state, ...) to ``node``; True when the node made it."""
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        ids = {"configure": Transition.TRANSITION_CONFIGURE, "cleanup": Transition.TRANSITION_CLEANUP,
               "activate": Transition.TRANSITION_ACTIVATE, "deactivate": Transition.TRANSITION_DEACTIVATE,
               "unconfigured_shutdown": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
               "inactive_shutdown": Transition.TRANSITION_INACTIVE_SHUTDOWN,
               "active_shutdown": Transition.TRANSITION_ACTIVE_SHUTDOWN}
        if transition == "shutdown":
            transition = f"{self.lifecycle_state(node, timeout)}_shutdown"
        request = ChangeState.Request(transition=Transition(id=ids[transition]))
        return bool(self.call(self.service(ChangeState, f"{node}/change_state", timeout), request, timeout).success)

    def lifecycle_state(self, node: str = NODE, timeout: float = 30.0) -> str:
        """The lifecycle state of ``node``: "unconfigured", "inactive", "active", "finalized", ..."""
        from lifecycle_msgs.srv import GetState

        return self.call(self.service(GetState, f"{node}/get_state", timeout), GetState.Request(),
                         timeout).current_state.label

    @staticmethod
    def wait_for_subscribers(publishers: list, timeout: float = 30.0) -> None:
        """Waits until every publisher has matched at least one subscription (discovery)."""
        wait_until(lambda: all(p.get_subscription_count() > 0 for p in publishers), timeout,
                   f"subscribers of {', '.join(p.topic_name for p in publishers)}")

    def close(self) -> None:
        self._closing.set()
        self._thread.join(timeout=5)  # the spinner leaves within one spin_once timeout, before anything is torn down
        self._executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()

    def __enter__(self) -> RosClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
