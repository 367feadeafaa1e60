"""An rclpy action client that can be called from a thread other than the one spinning its executor.

rclpy 7.1 (ROS 2 Jazzy's, the version the PyPI wheels carry) sends a goal, cancel or result request first and
records the request's sequence number after. When the executor spins in another thread, as
:class:`~pssnet_testing.client.RosClient`'s does, and the server answers inside that gap, the executor takes the
response, finds no record of it, logs "Ignoring unexpected goal response" and drops it: the caller's future never
completes (rclpy issue 1123; fixed upstream after the 7.1 wheels). It happens when the calling thread is
descheduled at the wrong moment, so on a loaded machine. Holding one lock while a request is sent and recorded,
and while the executor takes responses, closes the gap. The client is otherwise rclpy's own.
"""

from __future__ import annotations

import threading
from typing import Any

from rclpy.action import ActionClient


class SerialisedActionClient(ActionClient):
    """:class:`rclpy.action.ActionClient` whose requests are recorded before any response to them can be taken."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._requests_lock = threading.RLock()
        super().__init__(*args, **kwargs)

    def take_data(self) -> dict:
        with self._requests_lock:
            return super().take_data()

    def send_goal_async(self, goal: Any, feedback_callback: Any = None, goal_uuid: Any = None) -> Any:
        with self._requests_lock:
            return super().send_goal_async(goal, feedback_callback, goal_uuid)

    def _cancel_goal_async(self, goal_handle: Any) -> Any:
        with self._requests_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle: Any) -> Any:
        with self._requests_lock:
            return super()._get_result_async(goal_handle)
