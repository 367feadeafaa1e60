"""completion_node: samples diverse plausible completions of a segmented object and ranks grasps across them.

A managed (lifecycle) node, as ROS 2 drivers are: ``configure`` reads and checks the parameters and loads the
model, ``activate`` opens the subscriptions, enables the publishers and starts serving, ``deactivate`` stops
the work in flight and closes them, ``cleanup`` drops the model; a failed ``configure`` (bad parameter,
missing model) leaves the node unconfigured, and it can be retried after fixing the parameter. With
``autostart`` (the default) the node configures and activates itself at start-up and exits with a one-line
error if it cannot: the plain node.

Interface (node name ``pssnet``; relative names are remappable):

- subscribes ``depth`` (sensor_msgs/Image 32FC1 m | 16UC1), ``mask`` (mono8 | 8UC1), ``camera_info``;
  synchronised by stamp within ``sync_tolerance``; best-effort QoS, so reliable and sensor-data publishers
  both connect.
- serves ``~/sample_completions`` (pssnet_interfaces/srv/SampleCompletions) -> /pssnet/sample_completions
  (answering STATUS_NOT_ACTIVE unless active) and ``~/get_stats`` (std_srvs/Trigger: counters as JSON, see
  :meth:`CompletionNode.stats`) in every state; the standard lifecycle services ``~/change_state``, ``~/get_state``, ...
- is the action server ``~/sample_completions`` (pssnet_interfaces/action/SampleCompletions): the same call as
  the service, with feedback at each step and cancellable by its client; a goal succeeds with STATUS_OK, is
  cancelled with STATUS_CANCELLED, and is aborted with any other status.
- publishes in continuous mode (and for every service result with ``publish_service_results``)
  ``~/completions`` (PointCloud2 x, y, z + ``sample``), ``~/known_occupied``, ``~/grasps`` (PoseArray, best
  first), ``~/grasp_candidates`` (pssnet_interfaces/msg/GraspCandidates), ``~/grasp_markers``
  (visualization_msgs/MarkerArray: gripper outlines coloured by score, for RViz); and ``/diagnostics``
  (diagnostic_msgs/DiagnosticArray) at 1 Hz in every state.

All outputs carry the input's header. The node only converts messages; the work is done by
:class:`pssnet_core.pipeline.CompletionPipeline`.
"""

from __future__ import annotations

import collections
import copy
import faulthandler
import json
import math
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Pose, PoseArray
from pssnet_interfaces.action import SampleCompletions as SampleCompletionsAction
from pssnet_interfaces.msg import GraspCandidates
from pssnet_interfaces.srv import SampleCompletions
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from pssnet_core.pipeline import CompletionPipeline, ModelOutputError, PipelineResult, RunCancelled, up_vector_warning
from pssnet_ros.completion_io import (
    OUTPUT_TOPICS,
    STREAMS,
    SYNC_QUEUE_SIZE,
    MoreViewMessages,
    complete_messages,
    fill_response,
    load_pipeline,
    more_views_of,
    output_messages,
    stamp_ns,
)
from pssnet_ros.diagnostics import CompletionHealth, diagnostic_status
from pssnet_ros.heap import trim_heap, use_one_arena
from pssnet_ros.newest_slot import NewestSlot
from pssnet_ros.params import (
    CONFIGURE_ONLY,
    PARAMETERS,
    SPECS,
    check_values,
    from_ros,
    markdown_table,
    pipeline_config,
)
from pssnet_ros.rclpy_fixes import refuse_unknown_transitions
from pssnet_ros.shm import clean_stale_shm
from pssnet_ros.spinning import shutdown_once, spin_until_shutdown
from pssnet_ros.sync import StampSynchronizer, SyncedSet

NODE_NAME = "pssnet"
WARN_THROTTLE_S = 2.0
DIAGNOSTICS_PERIOD_S = 1.0
#: Shortest delay the continuous-mode timer is armed for (it fires when the pending set may start, else sleeps).
CONTINUOUS_MIN_DELAY_NS = 1_000_000
#: Longest a transition waits for the work in flight (a network pass of max_num_samples x 10 proposals on a slow CPU).
TRANSITION_WAIT_LIMIT_S = 300.0
#: What a call stopped by a lifecycle transition answers.
CANCELLED_MESSAGE = ("cancelled: the node left the active state during the call (deactivate, cleanup or shutdown); "
                     "call again once it is active")
CLIENT_CANCELLED_MESSAGE = "cancelled at the client's request"
SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE

#: Best effort + volatile matches both best-effort (sensor data) and reliable publishers.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)
#: Reliable publishers match reliable and best-effort subscribers alike.
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: The inputs' and outputs' history, depth and reliability can be overridden at start-up, as ROS 2 drivers allow:
#: read-only parameters ``qos_overrides.<resolved topic>.subscription|publisher.<policy>`` (a params file, or
#: ``-p``), e.g. ``qos_overrides./camera/depth/image_rect.subscription.reliability: reliable``. rclpy applies
#: them to the profile it is given, in place: each entity gets a copy of the shared defaults.
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()
#: Requests wait in DDS while the node answers one at a time; the default services QoS keeps only the last 10,
#: so with more waiting clients the oldest requests were dropped unanswered (16 clients: 41 of 755 lost,
#: RELIABILITY.md). 64 waiting 640x480 requests hold about 100 MB at most.
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=64, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
#: Continuous-mode outputs: name -> type (topics: completion_io.OUTPUT_TOPICS, ``~/name`` of this node).
OUTPUT_TYPES: dict[str, type] = {"completions": PointCloud2, "known_occupied": PointCloud2, "grasps": PoseArray,
                                 "grasp_candidates": GraspCandidates, "grasp_markers": MarkerArray}


class StartupError(RuntimeError):
    """The node cannot start (bad parameters, missing or corrupt model); the message says why."""


Status = SampleCompletions.Response  # the status constants: Status.STATUS_OK, ... (the action's are the same)
#: A service response or an action result: the same fields, filled the same way.
Answer = SampleCompletions.Response | SampleCompletionsAction.Result


class InputError(ValueError):
    """A request or a topic set cannot be used (no data yet, stale, unsynchronised stamps, no model); ``status``
    is the service's code for it."""

    def __init__(self, message: str, status: int = Status.STATUS_INVALID_INPUT) -> None:
        super().__init__(message)
        self.status = status


class CompletionNode(LifecycleNode):
    """The thin ROS layer over :class:`CompletionPipeline` (see the module docstring for the interface)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        refuse_unknown_transitions(self)
        # Guards the counters, the latest set and the slot's put/done, so that stats() is one consistent snapshot.
        self._lock = threading.Lock()
        self._counters = {"sets_synchronised": 0, "sets_processed": 0, "sets_dropped_stale": 0,
                          "sets_dropped_invalid": 0, "sets_cancelled": 0, "service_calls": 0,
                          "service_failures": 0, "action_goals": 0, "action_failures": 0}
        self._latest: SyncedSet | None = None  # newest synchronised set (the service's default input)
        self.pipeline: CompletionPipeline | None = None  # loaded on configure, dropped on cleanup
        self._configure_error = ""
        self._up_disagreement_deg = math.nan  # of the last input the pipeline checked (NaN: not checked)
        self._worked_since_trim = False  # a call or a topic set ended since the heap was last trimmed
        self._active = False
        # Set when the node leaves the active state: calls and topic sets in flight stop at their next step.
        self._stopping = threading.Event()
        # Action goals run as executor tasks, outside any callback group, so the node runs them one at a time
        # itself: the next accepted goal waits here (holding no executor thread) until the current one ends.
        # A transition stops the executing goal and waits for it as for the service's call in flight.
        self._goal_turn_taken = False  # a goal executes, or its successor is about to
        self._goals_waiting: collections.deque[ServerGoalHandle] = collections.deque()
        self._goals_running = 0  # goals whose execution has started and not ended
        self._goals_done = threading.Condition(self._lock)
        self._subscriptions: list[Subscription] = []  # the inputs, while active
        self._continuous_timer: Timer | None = None  # while active with continuous on
        try:
            self._values = self._declare()
        except StartupError:
            self.destroy_node()
            raise
        # Continuous mode: a timer completes the newest pending set at most max_rate_hz; a newer set replaces
        # an unprocessed one (one slot: bounded memory, no queue). Paused unless active.
        self._slot: NewestSlot[SyncedSet] = NewestSlot(self._values["max_rate_hz"], paused=True)
        self._sync = StampSynchronizer(STREAMS, self._values["sync_tolerance"], queue_size=SYNC_QUEUE_SIZE)
        self._health = CompletionHealth()
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._topics_group = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/get_stats", self._on_get_stats, callback_group=self._topics_group)
        # The sample service lives as long as the node and answers STATUS_NOT_ACTIVE unless active, as Nav2's
        # servers reject goals while inactive: a client is told instead of timing out, and no transition
        # destroys it while an answer may still be in transit (which lost 1 answer in 50 deactivations).
        # Inference has its own group so that topic callbacks keep flowing while a request runs.
        self._sample_service = self.create_service(
            SampleCompletions, "~/sample_completions", self._on_sample_completions, qos_profile=SERVICE_QOS,
            callback_group=MutuallyExclusiveCallbackGroup())
        # The same call as an action, for progress and cancelling; like the service it lives as long as the node.
        self._action_server = ActionServer(
            self, SampleCompletionsAction, "~/sample_completions", execute_callback=self._execute_goal,
            handle_accepted_callback=self._on_goal_accepted, cancel_callback=lambda goal_handle: CancelResponse.ACCEPT,
            callback_group=MutuallyExclusiveCallbackGroup())
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # Entities with QoS event handlers (publishers, subscriptions with rclpy's default handlers) must not be
        # destroyed while the executor runs: rclpy 7.1's MultiThreadedExecutor adds event handlers to its wait set
        # without holding them, and one destroyed meanwhile raised InvalidHandle out of spin() (1 cleanup in 55).
        # So the lifecycle publishers live as long as the node (enabled only while active), and the inputs,
        # created on activate and destroyed on deactivate, go without event handlers (below).
        self._outputs = {name: self.create_lifecycle_publisher(msg_type, f"~/{name}", copy.copy(OUTPUT_QOS),
                                                               qos_overriding_options=QOS_OVERRIDES)
                         for name, msg_type in OUTPUT_TYPES.items()}
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, callback_group=self._topics_group)
        if self._values["autostart"]:
            self._start()

    def _start(self) -> None:
        """configure + activate, as the plain node does; raises :class:`StartupError` with the reason."""
        if self.trigger_configure() != SUCCESS:
            reason = self._configure_error or "configure failed"
            self.destroy_node()
            raise StartupError(reason)
        if self.trigger_activate() != SUCCESS:
            self.destroy_node()
            raise StartupError("activation failed (see the log)")

    # ------------------------------------------------------------------------------------------ set-up
    def _declare(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for spec in PARAMETERS:
            default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
            try:
                values[spec.name] = from_ros(spec.name, self.declare_parameter(spec.name, default,
                                                                               spec.descriptor()).value)
            except (InvalidParameterValueException, InvalidParameterTypeException) as error:
                raise StartupError(f"invalid parameter {spec.name}: {error}") from None
        return values

    def _load_pipeline(self, values: dict[str, Any]) -> CompletionPipeline:
        reason = check_values(values)
        if reason:
            raise StartupError(f"invalid parameters: {reason}")
        try:
            pipeline = load_pipeline(values)
        except ValueError as error:  # missing or corrupt model, unavailable device, parameters the model refuses
            raise StartupError(str(error)) from None
        completer = pipeline.completer
        self.get_logger().info(
            f"model {completer.model_name} {completer.grid_size}^3 from {completer.info.get('path')} on "
            f"{values['device']} ({completer.precision}); voxel {pipeline.grid_config().voxel_size * 1000:.2f} mm")
        return pipeline

    # ------------------------------------------------------------------------------------- lifecycle
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.pipeline = self._load_pipeline(self._values)
        except StartupError as error:
            self._configure_error = str(error)
            self.get_logger().error(f"configure failed, still unconfigured: {error}")
            return FAILURE
        self._configure_error = ""
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stopping.clear()
        # No event handlers (see __init__): rclpy's defaults only warn of incompatible QoS, which a best-effort
        # volatile subscription cannot meet, and of a publisher of another type on the topic.
        no_handlers = SubscriptionEventCallbacks(use_default_callbacks=False)
        self._subscriptions = [self.create_subscription(
            msg_type, stream, lambda m, stream=stream: self._on_input(stream, m), copy.copy(INPUT_QOS),
            callback_group=self._topics_group, event_callbacks=no_handlers, qos_overriding_options=QOS_OVERRIDES)
            for stream, msg_type in (("depth", Image), ("mask", Image), ("camera_info", CameraInfo))]
        with self._lock:
            self._active = True
            self._slot.paused = not self._values["continuous"]
        self._update_continuous_timer()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_work()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_work()
        self._release()
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error(f"error in a transition from {state.label}; releasing everything, unconfigured")
        self._stop_work()
        self._release()
        return SUCCESS

    def _stop_work(self) -> None:
        """Leaves the active state: closes the inputs, stops the call or topic set in flight at its next step
        and waits until it has been answered (a call) or dropped (a set), and removes the continuous timer.

        Only then may the transition go on to release the model and the publishers: the work in flight uses
        them, and an answer sent through a destroyed handle raised InvalidHandle out of the executor and ended
        the process.
        """
        self._stopping.set()
        with self._lock:
            self._active = False
            self._slot.paused = True
        for subscription in self._subscriptions:
            self.destroy_subscription(subscription)
        self._subscriptions = []
        self._when_idle(self._sample_service, lambda service: None)
        with self._lock:  # waiting goals are answered now, without work, not after the executing one
            waiting, self._goals_waiting = list(self._goals_waiting), collections.deque()
        for goal_handle in waiting:
            goal_handle.execute(self._end_waiting_goal)
        self._wait_for_goals()
        self._update_continuous_timer()

    def _wait_for_goals(self) -> None:
        """Waits until no started action goal executes (each stops at its next step, as ``_stopping`` is set)."""
        with self._goals_done:
            if not self._goals_done.wait_for(lambda: self._goals_running == 0, TRANSITION_WAIT_LIMIT_S):
                self.get_logger().error(f"an action goal did not stop within {TRANSITION_WAIT_LIMIT_S:.0f} s; "
                                        f"going on without it")

    def _when_idle(self, entity: Service | Timer, action: Any) -> None:
        """Runs ``action(entity)`` once no callback of ``entity`` runs (or sends its answer), holding its
        (mutually exclusive) callback group so that none starts meanwhile."""
        group = entity.callback_group
        waiting_since = time.monotonic()
        told = False
        while not group.beginning_execution(entity):  # a call or a topic set is running or sending its answer
            waited = time.monotonic() - waiting_since
            if not told and waited > 1.0:
                told = True
                self.get_logger().info("waiting for the work in flight to stop at its next step (a network pass "
                                       "cannot be interrupted)")
            if waited > TRANSITION_WAIT_LIMIT_S:  # a stuck callback must not hold the transition for ever
                self.get_logger().error(f"the work in flight did not stop within {TRANSITION_WAIT_LIMIT_S:.0f} s; "
                                        f"going on without it")
                action(entity)
                return
            time.sleep(0.005)
        try:
            action(entity)
        finally:
            group.ending_execution(entity)

    def _update_continuous_timer(self) -> None:
        """The continuous mode's timer exists exactly while the node is active with ``continuous`` on."""
        wanted = self._active and self._values["continuous"]
        if wanted and self._continuous_timer is None:
            timer = self.create_timer(1.0, self._continuous_tick, callback_group=MutuallyExclusiveCallbackGroup(),
                                      autostart=False)
            with self._lock:
                self._continuous_timer = timer
                self._arm_continuous()
        elif not wanted and self._continuous_timer is not None:
            with self._lock:
                timer, self._continuous_timer = self._continuous_timer, None
            self._when_idle(timer, self.destroy_timer)

    def _arm_continuous(self) -> None:
        """Sets the continuous-mode timer to fire when the pending set may start (now, or once max_rate_hz
        allows), or stops it when nothing is pending or a set is in progress (its end re-arms it): an idle node
        polls nothing, and a ready timer whose callback group is busy would keep the executor spinning. Call
        with ``_lock`` held, so that a set put meanwhile re-arms it."""
        timer = self._continuous_timer
        if timer is None:
            return
        wait = self._slot.wait_time()
        if wait is None or self._slot.stats().in_progress:
            timer.cancel()
        else:
            timer.timer_period_ns = max(int(wait * 1e9), CONTINUOUS_MIN_DELAY_NS)
            timer.reset()

    def _release(self) -> None:
        with self._lock:
            self._latest = None
        self.pipeline = None

    # -------------------------------------------------------------------------------------- parameters
    # Only the node's own parameters (SPECS) are checked and applied here; rclpy's (use_sim_time, the read-only
    # qos_overrides.*) pass these callbacks too, and rclpy has its own rules for them.
    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        params = [p for p in params if p.name in SPECS]
        if not params:  # not checked against the node's values, which may be invalid until a configure refuses them
            return SetParametersResult(successful=True)
        values = dict(self._values)
        for param in params:
            values[param.name] = from_ros(param.name, param.value)
        pipeline = self.pipeline
        fixed = [p.name for p in params if p.name in CONFIGURE_ONLY and p.value != self._values[p.name]]
        if fixed and pipeline is not None:
            return SetParametersResult(successful=False, reason=f"{', '.join(fixed)} can only change while the "
                                                                f"node is unconfigured (cleanup first)")
        reason = check_values(values)
        if reason is None and pipeline is not None:
            try:
                pipeline.check_config(pipeline_config(values))
            except ValueError as error:
                reason = str(error)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply_parameters(self, params: list[Parameter]) -> None:
        params = [p for p in params if p.name in SPECS]
        if not params:
            return
        for param in params:
            self._values[param.name] = from_ros(param.name, param.value)
        pipeline = self.pipeline
        if pipeline is not None:
            pipeline.config = pipeline_config(self._values)
        if any(p.name == "sync_tolerance" for p in params):
            self._sync.tolerance_s = self._values["sync_tolerance"]
        with self._lock:
            self._slot.max_rate_hz = self._values["max_rate_hz"]
            self._slot.paused = not (self._active and self._values["continuous"])
            self._arm_continuous()
        self._update_continuous_timer()

    # ------------------------------------------------------------------------------------------ topics
    def _count(self, key: str, n: int = 1) -> int:
        with self._lock:
            self._counters[key] += n
            return self._counters[key]

    def _on_input(self, stream: str, msg: Image | CameraInfo) -> None:
        synced = self._sync.add(stream, stamp_ns(msg.header), msg)
        if synced is None:
            return
        with self._lock:
            self._counters["sets_synchronised"] += 1
            self._latest = synced
            if self._active and self._values["continuous"]:
                self._slot.put(synced)
                self._arm_continuous()

    def _age_s(self, synced: SyncedSet) -> float:
        return (self.get_clock().now().nanoseconds - synced.stamp_ns) * 1e-9

    def _continuous_tick(self) -> None:
        with self._lock:
            synced = self._slot.try_take()
            self._arm_continuous()  # stopped unless a newer set is already waiting
        if synced is not None:
            self._complete_topic_set(synced)

    def _finish(self, outcome: str) -> int:
        """Counts the outcome of the set in progress and frees the slot in one step (stats stay consistent)."""
        self._worked_since_trim = True
        with self._lock:
            self._counters[outcome] += 1
            self._slot.done()
            self._arm_continuous()
            return self._counters[outcome]

    def _complete_topic_set(self, synced: SyncedSet) -> None:
        max_age = self._values["max_input_age"]
        age = self._age_s(synced)
        if max_age > 0 and age > max_age:
            count = self._finish("sets_dropped_stale")
            self.get_logger().warning(f"dropped a stale input set ({count} so far): {age:.2f} s old, "
                                      f"max_input_age {max_age} s", throttle_duration_sec=WARN_THROTTLE_S)
            return
        t0 = time.perf_counter()
        try:
            result, header = self._run(synced.messages["depth"], synced.messages["mask"],
                                       synced.messages["camera_info"], 0, self._values["continuous_grasps"])
            self._publish(result, header)
        except RunCancelled:
            self._finish("sets_cancelled")
            return
        except ValueError as error:
            count = self._finish("sets_dropped_invalid")
            self.get_logger().warning(f"dropped an input set ({count} so far): {error}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        except Exception as error:  # never let one bad set end continuous mode
            count = self._finish("sets_dropped_invalid")
            self.get_logger().error(f"completion failed ({count} dropped so far): {type(error).__name__}: {error}\n"
                                    f"{traceback.format_exc()}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        self._health.completed(time.perf_counter() - t0)
        self._finish("sets_processed")

    def _publish(self, result: PipelineResult, header: Header) -> None:
        messages = output_messages(result, header, self.pipeline.config.grasps.gripper)
        for name in OUTPUT_TOPICS:
            self._outputs[name].publish(getattr(messages, name))

    # ----------------------------------------------------------------------------------------- service
    def _run(self, depth_msg: Image, mask_msg: Image, info_msg: CameraInfo, num_samples: int,
             compute_grasps: bool, should_stop: Callable[[str], bool] | None = None,
             more_views: Sequence[MoreViewMessages] = (),
             candidate_views: Sequence[Pose] = ()) -> tuple[PipelineResult, Header]:
        """Completes one set (with any further looks at the object, scoring any candidate views); stops at the
        pipeline's next step when the node leaves the active state or ``should_stop`` (told the step) says so."""
        pipeline = self.pipeline
        if pipeline is None:
            raise InputError("the node is not configured (no model loaded)", Status.STATUS_NOT_ACTIVE)

        def stop(step: str) -> bool:
            return self._stopping.is_set() or bool(should_stop and should_stop(step))

        result, header = complete_messages(pipeline, depth_msg, mask_msg, info_msg, self._values["depth_scale"],
                                           num_samples, compute_grasps, stop, more_views, candidate_views)
        self._up_disagreement_deg = result.up_disagreement_deg
        if warning := self.up_warning():
            self.get_logger().warning(f"up_vector looks wrong: {warning}", throttle_duration_sec=WARN_THROTTLE_S)
        return result, header

    def up_warning(self) -> str:
        """What the last checked input said about ``up_vector`` ("" when it agreed or was not checked)."""
        return up_vector_warning(self._up_disagreement_deg, self._values["up_check_deg"])

    def _request_input(self, request: SampleCompletions.Request) -> tuple[Image, Image, CameraInfo]:
        if request.depth.height == 0:
            with self._lock:
                synced = self._latest
            if synced is None:
                names = ", ".join(self.resolve_topic_name(s) for s in STREAMS)
                raise InputError(f"request has no depth image and no synchronised set has arrived on {names} "
                                 f"yet (sync_tolerance {self._values['sync_tolerance']} s)", Status.STATUS_NO_INPUT)
            max_age = self._values["max_input_age"]
            age = self._age_s(synced)
            if max_age > 0 and age > max_age:
                raise InputError(f"the latest synchronised input is stale: {age:.2f} s old, "
                                 f"max_input_age {max_age} s", Status.STATUS_NO_INPUT)
            return synced.messages["depth"], synced.messages["mask"], synced.messages["camera_info"]
        tolerance = self._values["sync_tolerance"]
        depth_stamp = stamp_ns(request.depth.header)
        for name, header in (("mask", request.mask.header), ("camera_info", request.camera_info.header)):
            other = stamp_ns(header)
            # An unset stamp (0) means the caller does not claim a time for that part: nothing to compare.
            if other and depth_stamp and abs(other - depth_stamp) > tolerance * 1e9:
                raise InputError(f"unsynchronised request: depth stamp {depth_stamp * 1e-9:.6f} s and {name} stamp "
                                 f"{other * 1e-9:.6f} s differ by {abs(other - depth_stamp) * 1e-9:.6f} s "
                                 f"(sync_tolerance {tolerance} s)")
        return request.depth, request.mask, request.camera_info

    def _on_sample_completions(self, request: SampleCompletions.Request,
                               response: SampleCompletions.Response) -> SampleCompletions.Response:
        try:
            return self._answer(request, response, "service")
        finally:
            self._worked_since_trim = True

    def _on_goal_accepted(self, goal_handle: ServerGoalHandle) -> None:
        """Executes the goal now when none executes, else queues it behind the executing one."""
        with self._lock:
            if self._goal_turn_taken:
                self._goals_waiting.append(goal_handle)
                return
            self._goal_turn_taken = True
        goal_handle.execute()

    def _execute_goal(self, goal_handle: ServerGoalHandle) -> SampleCompletionsAction.Result:
        """The action's goal: the service's answer as its result, feedback before each step, and the goal
        stopped at its next step when the client cancels it (or the node leaves the active state); then the
        next waiting goal's turn."""
        with self._lock:
            self._goals_running += 1
        try:
            t0 = time.perf_counter()

            def progress(stage: str) -> bool:
                if goal_handle.is_cancel_requested:
                    return True
                goal_handle.publish_feedback(SampleCompletionsAction.Feedback(
                    stage=stage, elapsed_s=time.perf_counter() - t0))
                return False

            if progress(SampleCompletionsAction.Feedback.STAGE_OBSERVATION):  # cancelled while it waited
                return self._end_waiting_goal(goal_handle)
            return self._end_goal(goal_handle, self._answer(goal_handle.request, SampleCompletionsAction.Result(),
                                                            "action", progress))
        finally:
            self._worked_since_trim = True
            with self._lock:
                self._goals_running -= 1
                next_goal = self._goals_waiting.popleft() if self._goals_waiting else None
                self._goal_turn_taken = next_goal is not None
                self._goals_done.notify_all()
            if next_goal is not None:
                next_goal.execute()

    def _end_waiting_goal(self, goal_handle: ServerGoalHandle) -> SampleCompletionsAction.Result:
        """Ends a goal that never got its turn, without work: cancelled by its client, or the node stopped
        serving before its turn (a lifecycle transition)."""
        self._count("action_goals")
        cancelled = goal_handle.is_cancel_requested
        result = self._refuse(SampleCompletionsAction.Result(), "action_failures",
                              Status.STATUS_CANCELLED if cancelled else Status.STATUS_NOT_ACTIVE,
                              CLIENT_CANCELLED_MESSAGE if cancelled else
                              "the node left the active state before this goal's turn: send it again once it is active")
        return self._end_goal(goal_handle, result)

    @staticmethod
    def _end_goal(goal_handle: ServerGoalHandle,
                  result: SampleCompletionsAction.Result) -> SampleCompletionsAction.Result:
        """Sets the goal's final state from its result's status: succeeded, canceled (its client asked), aborted."""
        if result.status == Status.STATUS_OK:
            goal_handle.succeed()
        elif result.status == Status.STATUS_CANCELLED and goal_handle.is_cancel_requested:
            result.message = CLIENT_CANCELLED_MESSAGE
            goal_handle.canceled()
        else:
            goal_handle.abort()
        return result

    def _answer(self, request: SampleCompletions.Request | SampleCompletionsAction.Goal, response: Answer,
                kind: str, should_stop: Callable[[str], bool] | None = None) -> Answer:
        """Answers a service request or an action goal (``kind``: "service" | "action", which counters count it)."""
        calls, failures = ("service_calls", "service_failures") if kind == "service" else ("action_goals",
                                                                                            "action_failures")
        self._count(calls)
        t0 = time.perf_counter()
        if not self._active:
            state = "inactive" if self.pipeline is not None else "unconfigured"
            return self._refuse(response, failures, Status.STATUS_NOT_ACTIVE,
                                f"the node is {state}: it serves completions only while active (lifecycle "
                                f"configure, then activate)")
        try:
            depth_msg, mask_msg, info_msg = self._request_input(request)
            response.header = depth_msg.header
            result, header = self._run(depth_msg, mask_msg, info_msg, int(request.num_samples),
                                       bool(request.compute_grasps), should_stop, more_views_of(request),
                                       list(request.candidate_views))
        except RunCancelled:
            return self._refuse(response, failures, Status.STATUS_CANCELLED, CANCELLED_MESSAGE)
        except ValueError as error:
            status = (error.status if isinstance(error, InputError) else Status.STATUS_MODEL_FAILURE
                      if isinstance(error, ModelOutputError) else Status.STATUS_INVALID_INPUT)
            count = self._count(failures)
            self.get_logger().warning(f"sample_completions ({kind}) refused ({count} so far): {error}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return self._refuse(response, failures, status, str(error), counted=True)
        except Exception as error:  # an answer even for a bug: the caller must not hang
            self.get_logger().error(f"sample_completions ({kind}) failed: {traceback.format_exc()}")
            return self._refuse(response, failures, Status.STATUS_INTERNAL_ERROR,
                                f"internal error: {type(error).__name__}: {error}")
        fill_response(response, result, header)
        response.status = Status.STATUS_OK
        if self._values["publish_service_results"]:  # so that RViz shows what a planner asked for
            self._publish(result, header)
        self._health.completed(time.perf_counter() - t0)
        points = sum(len(c) for c in result.completions)
        ms = {name: seconds * 1000 for name, seconds in result.timings.items()}
        response.message = (f"{result.num_samples} samples, {points} voxels, {len(response.grasps.poses)} grasps, seed "
                            f"{result.seed}, {(time.perf_counter() - t0) * 1000:.0f} ms (observation "
                            f"{ms['observe']:.1f}, network {ms['network']:.1f}, grasps {ms['grasps']:.1f} ms)"
                            + (f"; {result.note}" if result.note else ""))
        return response

    def _refuse(self, response: Answer, failures: str, status: int, message: str, counted: bool = False) -> Answer:
        if not counted:
            self._count(failures)
        response.status, response.success, response.message = status, False, message
        return response

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        del request
        stats = self.stats()
        response.success, response.message = True, json.dumps(stats, sort_keys=True)
        return response

    def _publish_diagnostics(self) -> None:
        if self._worked_since_trim:  # here, at most once a second and never on a call's critical path
            self._worked_since_trim = False
            trim_heap()
        pipeline = self.pipeline
        model = {} if pipeline is None else {
            "model": f"{pipeline.completer.model_name} {pipeline.completer.grid_size}^3",
            "device": self._values["device"], "precision": pipeline.completer.precision,
            "sampler": self._values["sampler"],
            "up_vector vs support plane (deg)": f"{self._up_disagreement_deg:.1f}"}
        state = "active" if self._active else ("inactive" if pipeline is not None else "unconfigured")
        status = diagnostic_status(f"{NODE_NAME}: completion", self.get_fully_qualified_name(), state,
                                   self._health.snapshot(), self.stats(), model, self._configure_error,
                                   self.up_warning())
        self._pub_diagnostics.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now().to_msg()),
                                                      status=[status]))

    def stats(self) -> dict[str, int]:
        """Counters, one consistent snapshot.

        ``sets_synchronised`` (all synchronised sets), ``sets_processed`` (completed and published in continuous
        mode), ``sets_dropped_superseded`` / ``_stale`` / ``_invalid``, ``sets_pending`` and ``sets_in_progress``
        (0 or 1 each), ``sets_cancelled`` (stopped by a lifecycle transition), ``service_calls``,
        ``service_failures``, ``action_goals``, ``action_failures`` (not succeeded: refused, aborted or cancelled),
        ``messages_received``, ``messages_unmatched``, and ``latest_set_stamp_ns`` (stamp
        of the newest synchronised set, 0 before the first). While continuous mode is on, every synchronised set
        is accounted for: synchronised = processed + superseded + stale + invalid + cancelled + pending +
        in_progress.
        """
        with self._lock:
            stats = dict(self._counters)
            slot = self._slot.stats()
            stats.update(sets_dropped_superseded=slot.superseded, sets_pending=slot.pending,
                         sets_in_progress=slot.in_progress,
                         latest_set_stamp_ns=self._latest.stamp_ns if self._latest is not None else 0)
        sync = self._sync.stats
        stats.update(messages_received=sync.received, messages_unmatched=sync.dropped_unmatched)
        return stats

    def destroy_node(self) -> None:
        if getattr(self, "_active", False):
            self._stop_work()
        super().destroy_node()


def usage() -> str:
    return ("usage: completion_node [--help] [--ros-args -p NAME:=VALUE ... --params-file FILE -r FROM:=TO]\n\n"
            "PSSNet completion node: diverse plausible shape completions of a segmented object from one depth\n"
            "image, and parallel-jaw grasps ranked across them.\n\n"
            "A lifecycle node: with autostart (default) it configures and activates itself; with\n"
            "autostart:=false it waits for configure/activate on /pssnet/change_state.\n\n"
            "Node name: pssnet. Subscribes: depth, mask, camera_info (remappable). Serves:\n"
            "/pssnet/sample_completions (pssnet_interfaces/srv/SampleCompletions, and the action of the same\n"
            "name and type: feedback, cancellable), /pssnet/get_stats.\n"
            "Publishes (continuous mode): /pssnet/completions, /pssnet/known_occupied, /pssnet/grasps,\n"
            "/pssnet/grasp_candidates, /pssnet/grasp_markers, /diagnostics (1 Hz).\n\nParameters:\n"
            + markdown_table() + "\n")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point (console script and ``ros2 run pssnet_ros completion_node``); returns the exit code."""
    argv = list(sys.argv if args is None else args)
    try:
        plain_args = remove_ros_args(argv)[1:]
    except RuntimeError as error:  # rclpy's RCLInvalidROSArgsError: a malformed --ros-args section
        print(f"[completion_node] error: invalid ROS arguments: {error}", file=sys.stderr)
        return 2
    if any(a in ("-h", "--help") for a in plain_args):
        print(usage())
        return 0
    # A predecessor killed with -9 leaves its Fast DDS shared memory (8 MiB per participant): remove what
    # belongs to dead processes only, before this process's own participant exists.
    shm = clean_stale_shm()
    use_one_arena()  # before DDS, the executor and torch start threads: see pssnet_ros.heap
    faulthandler.register(signal.SIGUSR1)  # `kill -USR1 PID` prints every thread's stack: a hung node explains itself
    rclpy.init(args=argv)
    node: CompletionNode | None = None
    code = 0
    try:
        node = CompletionNode()
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        if shm.removed:
            node.get_logger().info(f"removed {len(shm.removed)} stale Fast DDS shared-memory files of dead "
                                   f"processes ({shm.freed_bytes / 2**20:.1f} MiB): {' '.join(shm.removed)}")
        if node.get_parameter("autostart").value:
            node.get_logger().info(f"ready: serving {node.resolve_service_name('~/sample_completions')}, "
                                   f"continuous {'on' if node.get_parameter('continuous').value else 'off'}")
        else:
            node.get_logger().info("unconfigured: waiting for a lifecycle manager (configure, then activate)")
        spin_until_shutdown(executor)
    except StartupError as error:
        print(f"[completion_node] error: {error}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        shutdown_once()
    return code


if __name__ == "__main__":
    sys.exit(main())
