"""Work-arounds for rclpy behaviour this node cannot accept, each behind one function.

Each has a canary test (``test/test_ros_rclpy_fixes.py``) that checks the plain rclpy behaviour it works
around: the day rclpy changes, that test fails, and the work-around can go.
"""

from __future__ import annotations

from typing import Any

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode


def refuse_unknown_transitions(node: LifecycleNode) -> None:
    """Makes ``node``'s ``change_state`` service answer success=False to a transition its current state does
    not have, instead of dying.

    rclpy (7.1) raises RCLError out of the change_state service callback for such a request, which ends the
    executor's spin: any client could stop the node with one bad request. The state is left unchanged.
    """
    service = node._service_change_state  # rclpy offers no public hook for this service
    change_state = service.callback

    def change_state_or_refuse(request: Any, response: Any) -> Any:
        try:
            return change_state(request, response)
        except _rclpy.RCLError as error:
            node.get_logger().warning(f"refused lifecycle transition id {request.transition.id} "
                                      f"{request.transition.label!r}: {error}")
            response.success = False
            return response

    service.callback = change_state_or_refuse
