"""The managed node over real DDS: lifecycle transitions through the standard lifecycle_msgs services, a failed
configure that can be retried, and /diagnostics in each state.

One node process (autostart:=false, a missing model at first) is driven through the states in order, as a
lifecycle manager (Nav2's, launch_ros's) would drive it.
"""

from __future__ import annotations

import threading

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from pssnet_interfaces.srv import SampleCompletions
from test_node_helpers import (
    domain_for,
    make_request,
    render_mug_scene,
    stamped_header,
    tiny_checkpoint,
)

from pssnet_ros.completion_node import CANCELLED_MESSAGE, Status
from pssnet_ros.diagnostics import CompletionHealth, diagnostic_status
from pssnet_testing import chaos
from pssnet_testing.client import NODE, SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import RosProcess, ros_env

pytestmark = pytest.mark.ros
DOMAIN = domain_for(11)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("lifecycle") / "tiny32.pt")


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    missing = tmp_path_factory.mktemp("missing") / "absent.pt"
    with NodeUnderTest(DOMAIN, model_path=missing, autostart=False, threads=1, num_samples=4) as node:
        yield node.process


@pytest.fixture(scope="module")
def ros(node):
    client = RosClient(DOMAIN)
    yield client
    client.close()


class DiagnosticsListener:
    """Keeps the newest /diagnostics status of the node."""

    def __init__(self, ros: RosClient) -> None:
        self._lock = threading.Lock()
        self.latest: DiagnosticStatus | None = None
        ros.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_message, 10)

    def _on_message(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.hardware_id == NODE:
                with self._lock:
                    self.latest = status

    def wait_for_state(self, state: str, timeout: float = 30.0) -> dict[str, str]:
        def matching() -> dict[str, str] | None:
            with self._lock:
                status = self.latest
            if status is None:
                return None
            values = {kv.key: kv.value for kv in status.values}
            return {**values, "level": status.level, "message": status.message} if values["state"] == state else None

        return wait_until(matching, timeout, f"/diagnostics reporting state {state!r}")


def test_transitions_failed_configure_retry_and_diagnostics(ros, node, checkpoint):
    diagnostics = DiagnosticsListener(ros)
    # A client from the start, so that by the time it matters it has discovered the server.
    service = ros.node.create_client(SampleCompletions, SAMPLE_SERVICE)
    assert ros.lifecycle_state() == "unconfigured"
    seen = diagnostics.wait_for_state("unconfigured")
    assert seen["level"] == DiagnosticStatus.WARN

    # A missing model: configure fails, the node stays unconfigured and says why (log and /diagnostics).
    mark = len(node.lines())
    assert not ros.change_state("configure")
    assert ros.lifecycle_state() == "unconfigured"
    wait_until(lambda: any("configure failed" in line and "no checkpoint file" in line for line in node.lines(mark)),
               30, "the failed configure logged")
    failed = wait_until(lambda: (d := diagnostics.wait_for_state("unconfigured"))["level"]
                        == DiagnosticStatus.ERROR and d, 30, "an ERROR status")
    assert "no checkpoint file" in failed["message"]

    # Fix the parameter (allowed while unconfigured) and retry.
    assert ros.set_parameters(model_path=str(checkpoint))[0].successful
    assert ros.change_state("configure")
    assert ros.lifecycle_state() == "inactive"
    refused = ros.set_parameters(model_path="/elsewhere.pt")[0]
    assert not refused.successful and "only change while the node is unconfigured" in refused.reason
    assert ros.set_parameters(num_samples=3)[0].successful  # ordinary parameters change in any state
    # The planner's candidate options are parameters too; a list the planner refuses is refused with its reason.
    assert ros.set_parameters(grasp_tilted_pitches=[30.0, 45.0])[0].successful
    refused = ros.set_parameters(grasp_tilted_pitches=[95.0])[0]
    assert not refused.successful and "tilted_pitches must be degrees in (0, 90)" in refused.reason
    assert service.wait_for_service(timeout_sec=30)  # in every state; it serves only while active
    inactive = ros.call(service, SampleCompletions.Request())
    assert inactive.status == inactive.STATUS_NOT_ACTIVE and not inactive.success
    assert inactive.message.startswith("the node is inactive: it serves completions only while active"), inactive

    assert ros.change_state("activate")
    assert ros.lifecycle_state() == "active"
    scene = render_mug_scene(seed=3)  # a camera pitched 30 degrees: the true up_vector is not the default
    assert ros.set_parameters(up_vector=[float(v) for v in scene.up])[0].successful
    # Finite, but its length overflows: refused at set time, the node keeps the value above (checked below).
    overflowing = ros.set_parameters(up_vector=[1e200, 1e200, 0.0])[0]
    assert not overflowing.successful and "up_vector must be 3 finite numbers of length" in overflowing.reason
    assert service.wait_for_service(timeout_sec=30)
    response = ros.call(service, make_request(scene, stamped_header(5)), timeout=120)
    assert response.success, response.message
    assert len(response.completions) == 3
    # Two calls so far (the one refused while inactive counts). A call is counted when it starts and timed when it
    # ends: a status published in between shows the one but not the other (the checked sampler's call spans a
    # 1 Hz diagnostics tick on a busy machine).
    latency = "latency p50 (ms, last 10 s)"
    active = wait_until(lambda: (d := diagnostics.wait_for_state("active"))["service calls"] == "2"
                        and float(d[latency]) > 0 and d, 30, "diagnostics counting and timing the call")
    assert active["level"] == DiagnosticStatus.OK
    assert active["model"] == "pssnet 32^3" and active["device"] == "cpu"
    assert active["sampler"] == "checked" and float(active["up_vector vs support plane (deg)"]) < 1.0
    # The default (level-camera) up_vector on the same pitched view: answered, and flagged on every channel.
    assert ros.set_parameters(up_vector=[0.0, -1.0, 0.0])[0].successful
    mark = len(node.lines())
    response = ros.call(service, make_request(scene, stamped_header(6)), timeout=120)
    assert response.success and "tilted 30 deg from up_vector" in response.message, response.message
    warned = wait_until(lambda: (d := diagnostics.wait_for_state("active"))["service calls"] == "3"
                        and d["level"] == DiagnosticStatus.WARN and d, 30, "a WARN status for the wrong up_vector")
    assert "tilted 30 deg from up_vector" in warned["message"]
    assert float(warned["up_vector vs support plane (deg)"]) == pytest.approx(30.0, abs=1.0)
    wait_until(lambda: any("up_vector looks wrong" in line for line in node.lines(mark)), 30, "the warning logged")

    assert ros.change_state("deactivate")
    assert ros.lifecycle_state() == "inactive"
    assert ros.call(service, make_request(scene, stamped_header(7))).status == inactive.STATUS_NOT_ACTIVE
    assert ros.change_state("cleanup")
    assert ros.lifecycle_state() == "unconfigured"
    unconfigured = ros.call(service, SampleCompletions.Request())
    assert unconfigured.status == inactive.STATUS_NOT_ACTIVE and "the node is unconfigured" in unconfigured.message
    assert ros.set_parameters(model_path=str(checkpoint))[0].successful  # unconfigured again: allowed
    # A transition the state machine does not have from here is refused, the state unchanged, the node alive
    # (plain rclpy lets this request end the node's spin).
    assert not ros.change_state("activate")
    assert ros.lifecycle_state() == "unconfigured"
    assert not ros.change_state("deactivate")
    assert node.running() and ros.lifecycle_state() == "unconfigured"
    assert ros.change_state("unconfigured_shutdown")
    assert ros.lifecycle_state() == "finalized"
    assert node.running()  # finalized is a state, not an exit: the process waits for SIGINT
    assert node.stop() == 0


def test_transitions_while_the_node_works_answer_the_call_and_keep_the_node(checkpoint):
    """Deactivate, cleanup and shutdown sent while a heavy call computes or a topic set is completed: the call
    is answered (cancelled at its next step, or done), the node lives on (after shutdown: stops cleanly), and
    serves again. Each once here, at staggered moments; ``benchmarks/chaos_bench.py --only e`` runs them 50
    times each (RELIABILITY.md)."""
    node = NodeUnderTest(domain_for(15), model_path=checkpoint, **chaos.NODE_PARAMS, up_vector=chaos.scene_up_vector(),
                         threads=1, num_samples=chaos.HEAVY_SAMPLES, max_rate_hz=20.0)
    camera = None
    reports = []
    try:
        node.start()
        for work in chaos.WORK_KINDS:
            if work == "topics":
                camera = RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", "10"],
                                                  ros_env(node.domain), name="camera")
                camera.wait_for(r"publishing", 60)
                assert node.ros.set_parameters(continuous=True)[0].successful
                node.params["continuous"] = True  # for the node started again after "shutdown"
            for i, transition in enumerate(chaos.TRANSITION_SEQUENCES):
                report, _ = chaos.transition_mid_work(node.ros, node.process, transition, work, node.start,
                                                      delay_s=0.15 * i, timeout=120)
                reports.append(report)
    finally:
        if camera is not None:
            camera.stop()
        exit_code = node.close()
    assert exit_code == 0, node.process.output[-4000:]
    for report in reports:
        assert report.busy, report  # otherwise nothing was tested
        assert report.accepted and report.node_alive and report.restored, report
        assert report.clean_exit is not False, report
        if report.work == "call":
            assert report.answered, report
            assert report.status in (Status.STATUS_OK, Status.STATUS_CANCELLED), report
            assert report.success == (report.status == Status.STATUS_OK), report
            assert report.success or report.message == CANCELLED_MESSAGE, report
    assert any(r.work == "call" and not r.success for r in reports), "no call was cancelled: the test is too slow"


def test_health_window_rate_and_percentiles():
    now = [100.0]
    health = CompletionHealth(window_s=10.0, clock=lambda: now[0])
    empty = health.snapshot()
    assert empty.completions == 0 and empty.rate_hz == 0.0 and empty.latency_p50_ms != empty.latency_p50_ms  # NaN
    for latency in (0.010, 0.020, 0.030, 0.040):
        health.completed(latency)
        now[0] += 1.0
    snap = health.snapshot()
    assert snap.completions == 4 and snap.rate_hz == pytest.approx(0.4)
    assert snap.latency_p50_ms == pytest.approx(25.0) and snap.latency_p95_ms == pytest.approx(38.5)
    now[0] += 6.5  # 110.5 s: the first completion (at 100 s) is now more than 10 s old
    assert health.snapshot().completions == 3
    with pytest.raises(ValueError, match="window_s"):
        CompletionHealth(window_s=0.0)


def test_diagnostic_status_levels():
    snap = CompletionHealth().snapshot()
    counters = {"service_calls": 2, "sets_dropped_stale": 1, "latest_set_stamp_ns": 5}
    ok = diagnostic_status("pssnet: completion", "/pssnet", "active", snap, counters, {"model": "pssnet 32^3"})
    assert ok.level == DiagnosticStatus.OK
    values = {kv.key: kv.value for kv in ok.values}
    assert values["sets dropped stale"] == "1" and values["model"] == "pssnet 32^3"
    assert "latest set stamp ns" not in values
    assert diagnostic_status("n", "/pssnet", "inactive", snap, counters, {}).level == DiagnosticStatus.WARN
    error = diagnostic_status("n", "/pssnet", "unconfigured", snap, counters, {}, "cannot load the model")
    assert error.level == DiagnosticStatus.ERROR and "cannot load the model" in error.message
