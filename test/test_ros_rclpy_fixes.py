"""The rclpy work-arounds of pssnet_ros.rclpy_fixes, and canaries that fail the day rclpy no longer needs them."""

from __future__ import annotations

import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode

from pssnet_ros.rclpy_fixes import refuse_unknown_transitions

pytestmark = pytest.mark.ros


@pytest.fixture
def lifecycle_node():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = LifecycleNode("rclpy_fixes_probe", context=context)
    yield node
    node.destroy_node()
    context.try_shutdown()


def activate_request() -> ChangeState.Request:
    return ChangeState.Request(transition=Transition(id=Transition.TRANSITION_ACTIVATE))


def test_canary_plain_rclpy_raises_out_of_change_state_for_an_unknown_transition(lifecycle_node):
    """If this fails, rclpy answers such requests itself now: delete refuse_unknown_transitions."""
    with pytest.raises(_rclpy.RCLError, match="Transition is not registered"):
        lifecycle_node._service_change_state.callback(activate_request(), ChangeState.Response())


def test_unknown_transitions_are_refused_and_the_state_kept(lifecycle_node):
    refuse_unknown_transitions(lifecycle_node)
    response = lifecycle_node._service_change_state.callback(activate_request(), ChangeState.Response())
    assert response.success is False
    assert lifecycle_node._state_machine.current_state[1] == "unconfigured"
    configure = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE))
    assert lifecycle_node._service_change_state.callback(configure, ChangeState.Response()).success
