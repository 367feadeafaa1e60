"""The completion node's action over real DDS: the service's call with feedback, cancellable by its client.

One node process serves the module; the client is this test process.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from pssnet_interfaces.action import SampleCompletions as SampleCompletionsAction
from pssnet_interfaces.srv import SampleCompletions
from test_node_helpers import domain_for, make_request, node_checkpoint, render_mug_scene, stamped_header

from pssnet_ros.completion_node import CANCELLED_MESSAGE, CLIENT_CANCELLED_MESSAGE
from pssnet_ros.conversions import pointcloud2_to_numpy
from pssnet_testing import chaos
from pssnet_testing.client import SAMPLE_SERVICE
from pssnet_testing.node_under_test import NodeUnderTest

pytestmark = pytest.mark.ros
DOMAIN = domain_for(22)
Feedback = SampleCompletionsAction.Feedback
Result = SampleCompletionsAction.Result


def test_status_constants_are_the_services():
    names = [n for n in dir(SampleCompletions.Response) if n.startswith("STATUS_")]
    assert len(names) >= 7
    for name in names:
        assert getattr(Result, name) == getattr(SampleCompletions.Response, name), name


@pytest.fixture(scope="module")
def scene():
    return render_mug_scene(seed=3)


@pytest.fixture(scope="module")
def node(tmp_path_factory, scene):
    path, _ = node_checkpoint(tmp_path_factory.mktemp("node"))
    with NodeUnderTest(DOMAIN, model_path=path, up_vector=scene.up, num_samples=8, threads=1,
                       **chaos.NODE_PARAMS) as node:
        yield node


@pytest.fixture(scope="module")
def action(node):
    return node.ros.action(SampleCompletionsAction, SAMPLE_SERVICE, timeout=30)


def goal_of(request: SampleCompletions.Request) -> SampleCompletionsAction.Goal:
    """The service request as the action's goal (the same fields)."""
    return SampleCompletionsAction.Goal(depth=request.depth, mask=request.mask, camera_info=request.camera_info,
                                        num_samples=request.num_samples, compute_grasps=request.compute_grasps)


class FeedbackLog:
    """The feedback messages of one goal, and an event set when a given stage is reported."""

    def __init__(self, signal_stage: str = "") -> None:
        self.messages: list[Feedback] = []
        self.signal_stage = signal_stage
        self.reached = threading.Event()

    def __call__(self, feedback: Feedback) -> None:
        self.messages.append(feedback)
        if feedback.stage == self.signal_stage:
            self.reached.set()


def run_goal(node: NodeUnderTest, action, goal, feedback=None, timeout: float = 120.0) -> tuple[int, Result]:
    handle = node.ros.send_goal(action, goal, feedback)
    assert handle.accepted
    return node.ros.goal_result(handle, timeout)


def test_goal_reports_each_step_and_returns_the_services_answer(node, action, scene):
    request = make_request(scene, stamped_header(77, 88), num_samples=5, compute_grasps=True)
    log = FeedbackLog()
    status, result = run_goal(node, action, goal_of(request), log)
    assert status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert result.success and result.status == Result.STATUS_OK
    assert [f.stage for f in log.messages] == [Feedback.STAGE_OBSERVATION, Feedback.STAGE_NETWORK,
                                               Feedback.STAGE_GRASPS]
    elapsed = [f.elapsed_s for f in log.messages]
    assert elapsed == sorted(elapsed) and elapsed[0] >= 0
    # The node's seed parameter is fixed (0), so the service answers the same request with the same samples.
    response = node.ros.call(node.ros.service(SampleCompletions, SAMPLE_SERVICE), request, 120)
    assert response.success, response.message
    assert (result.header.stamp.sec, result.header.stamp.nanosec) == (77, 88)
    assert result.voxel_size == response.voxel_size and len(result.completions) == len(response.completions) == 5
    for ours, theirs in zip(result.completions, response.completions, strict=True):
        np.testing.assert_array_equal(pointcloud2_to_numpy(ours)[0], pointcloud2_to_numpy(theirs)[0])
    assert list(result.sample_weights) == list(response.sample_weights)
    assert len(result.grasps.poses) > 0 and list(result.grasp_scores) == list(response.grasp_scores)
    assert list(result.grasp_weight_shares) == list(response.grasp_weight_shares)
    assert result.message.split(", seed")[0] == response.message.split(", seed")[0]


def test_invalid_goal_is_aborted_with_the_reason(node, action, scene):
    request = make_request(scene, stamped_header(1, 0), num_samples=3)
    request.mask.data = bytes(len(request.mask.data))  # nothing masked
    before = node.ros.stats()
    status, result = run_goal(node, action, goal_of(request))
    assert status == GoalStatus.STATUS_ABORTED
    assert result.status == Result.STATUS_INVALID_INPUT and not result.success and "mask" in result.message
    after = node.ros.stats()
    assert after["action_goals"] == before["action_goals"] + 1
    assert after["action_failures"] == before["action_failures"] + 1
    assert after["service_calls"] == before["service_calls"]  # goals are counted apart from service calls


def heavy_goal(scene) -> SampleCompletionsAction.Goal:
    """A goal that keeps the node busy for a while (see chaos.HEAVY_SAMPLES)."""
    return goal_of(make_request(scene, stamped_header(5, 0), num_samples=chaos.HEAVY_SAMPLES, compute_grasps=True))


def light_goal(scene) -> SampleCompletionsAction.Goal:
    return goal_of(make_request(scene, stamped_header(6, 0), num_samples=3, compute_grasps=True))


def test_client_cancels_a_heavy_goal_at_its_next_step(node, action, scene):
    log = FeedbackLog(signal_stage=Feedback.STAGE_NETWORK)
    handle = node.ros.send_goal(action, heavy_goal(scene), log)
    assert handle.accepted
    assert log.reached.wait(60), "the goal never reached the network"
    cancel = node.ros.cancel_goal(handle)
    assert len(cancel.goals_canceling) == 1
    status, result = node.ros.goal_result(handle, 120)
    assert status == GoalStatus.STATUS_CANCELED, result.message
    assert result.status == Result.STATUS_CANCELLED and result.message == CLIENT_CANCELLED_MESSAGE
    assert Feedback.STAGE_GRASPS not in [f.stage for f in log.messages]  # stopped before the grasps
    status, result = run_goal(node, action, light_goal(scene))  # and serves on
    assert status == GoalStatus.STATUS_SUCCEEDED, result.message


def test_goals_run_one_at_a_time_in_order_and_a_waiting_goal_can_be_cancelled(node, action, scene):
    """Three goals sent at once: the second starts only after the first has ended (its first feedback comes
    after the first's last), the third is cancelled while it waits and ends cancelled without work."""
    arrivals: list[tuple[int, str]] = []  # (goal, stage) in the order the client receives them
    lock = threading.Lock()

    def log_for(goal: int):
        def log(feedback: Feedback) -> None:
            with lock:
                arrivals.append((goal, feedback.stage))
        return log

    before = node.ros.stats()
    handles = [node.ros.send_goal(action, goal, log_for(k))
               for k, goal in enumerate([heavy_goal(scene), light_goal(scene), light_goal(scene)])]
    assert all(h.accepted for h in handles)
    assert node.ros.cancel_goal(handles[2]).goals_canceling  # still waiting behind the first two
    results = [node.ros.goal_result(h, 180) for h in handles]
    assert [status for status, _ in results] == [GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_SUCCEEDED,
                                                  GoalStatus.STATUS_CANCELED], [r.message for _, r in results]
    assert results[2][1].status == Result.STATUS_CANCELLED and results[2][1].message == CLIENT_CANCELLED_MESSAGE
    with lock:
        first_of_second = arrivals.index((1, Feedback.STAGE_OBSERVATION))
        assert arrivals.index((0, Feedback.STAGE_GRASPS)) < first_of_second, arrivals
        assert [stage for goal, stage in arrivals if goal == 2] == [], arrivals  # no step of the cancelled goal ran
    after = node.ros.stats()
    assert after["action_goals"] - before["action_goals"] == 3
    assert after["action_failures"] - before["action_failures"] == 1


def test_deactivation_stops_a_goal_and_inactive_node_aborts_goals(node, action, scene):
    log = FeedbackLog(signal_stage=Feedback.STAGE_NETWORK)
    handle = node.ros.send_goal(action, heavy_goal(scene), log)
    waiting = node.ros.send_goal(action, light_goal(scene))  # queued behind the heavy one
    assert log.reached.wait(60), "the goal never reached the network"
    assert node.ros.change_state("deactivate")  # returns once the goal in flight has stopped
    status, result = node.ros.goal_result(handle, 30)
    assert status == GoalStatus.STATUS_ABORTED
    assert result.status == Result.STATUS_CANCELLED and result.message == CANCELLED_MESSAGE
    status, result = node.ros.goal_result(waiting, 30)  # answered by the transition, not left waiting
    assert status == GoalStatus.STATUS_ABORTED and result.status == Result.STATUS_NOT_ACTIVE, result.message
    status, result = run_goal(node, action, light_goal(scene))
    assert status == GoalStatus.STATUS_ABORTED and result.status == Result.STATUS_NOT_ACTIVE, result.message
    assert "inactive" in result.message
    assert node.ros.change_state("activate")
    status, result = run_goal(node, action, light_goal(scene))
    assert status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert node.process.running()
