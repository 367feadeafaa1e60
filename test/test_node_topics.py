"""Continuous mode over real DDS: best-effort and reliable camera publishers, rate limit, dropped sets, counters.

One node process (continuous: true, max_rate_hz 5) for the module; this process publishes a rendered mug
at 30 Hz and listens to the node's outputs.

Nothing here waits a guessed time. A burst of frames ends when the node reports (``/pssnet/get_stats``,
``latest_set_stamp_ns``) that it synchronised the burst's last frame: DDS delivers each topic in order, so
nothing of the burst is still on its way. Then the node is idle when it has no set pending or in progress,
and its counters account for every synchronised set exactly; outputs are matched to a burst by their stamps.
The exact rules of the newest-set slot and the rate limit are tested without DDS in test_ros_newest_slot.py.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray
from pssnet_interfaces.msg import GraspCandidates
from pssnet_interfaces.srv import SampleCompletions
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from test_node_helpers import domain_for, node_checkpoint, render_mug_scene, scene_messages
from visualization_msgs.msg import Marker, MarkerArray

from pssnet_ros.completion_node import WARN_THROTTLE_S
from pssnet_ros.conversions import numpy_to_image, pointcloud2_to_numpy
from pssnet_testing.client import SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import stale_shm_files

pytestmark = pytest.mark.ros
DOMAIN = domain_for(2)
RATE_HZ = 5.0
SAMPLES = 3
MAX_INPUT_AGE = 1.0
RELIABLE = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
#: the listener keeps everything: a late executor must not turn into lost outputs
LISTEN = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
OUTPUTS = {"completions": PointCloud2, "known_occupied": PointCloud2, "grasps": PoseArray,
           "grasp_candidates": GraspCandidates, "grasp_markers": MarkerArray}
TIMEOUT = 60.0  # for anything the node must do: generous, since the machine may be loaded


@pytest.fixture(scope="module")
def scene():
    return render_mug_scene(seed=5)


@pytest.fixture(scope="module")
def node(tmp_path_factory, scene):
    path, _ = node_checkpoint(tmp_path_factory.mktemp("node"))
    params = dict(up_vector=scene.up, num_samples=SAMPLES, threads=1, continuous=True, max_rate_hz=RATE_HZ,
                  max_input_age=MAX_INPUT_AGE, sync_tolerance=0.005)
    with NodeUnderTest(DOMAIN, model_path=path, **params) as node:
        yield node.process


def stamp_of(msg) -> int:
    header = msg.markers[0].header if isinstance(msg, MarkerArray) else msg.header  # a DELETEALL marker comes first
    return header.stamp.sec * 10**9 + header.stamp.nanosec


class Listener:
    """Collects the node's outputs."""

    def __init__(self, ros: RosClient) -> None:
        self.lock = threading.Lock()
        self.messages: dict[str, list] = {name: [] for name in OUTPUTS}
        self.subscriptions = [
            ros.node.create_subscription(msg_type, f"/pssnet/{name}", lambda m, n=name: self._add(n, m), LISTEN)
            for name, msg_type in OUTPUTS.items()]

    def _add(self, name: str, msg) -> None:
        with self.lock:
            self.messages[name].append(msg)

    def of(self, stamps: list[int]) -> dict[str, list]:
        """The outputs whose stamps are among ``stamps``, per topic, in arrival order."""
        wanted = set(stamps)
        with self.lock:
            return {name: [m for m in msgs if stamp_of(m) in wanted] for name, msgs in self.messages.items()}


class Camera:
    """Publishes the scene on /depth, /mask, /camera_info with fresh stamps, as a camera driver does."""

    def __init__(self, ros: RosClient, scene) -> None:
        self.ros = ros
        self.messages = scene_messages(scene, None)
        self._publishers: dict[int, list] = {}

    def publishers(self, qos: QoSProfile) -> list:
        key = int(qos.reliability)
        if key not in self._publishers:
            pubs = [self.ros.node.create_publisher(t, name, qos) for t, name in
                    ((Image, "/depth"), (Image, "/mask"), (CameraInfo, "/camera_info"))]
            self.ros.wait_for_subscribers(pubs)
            self._publishers[key] = pubs
        return self._publishers[key]

    def stream(self, qos: QoSProfile, seconds: float = 0.0, rate: float = 30.0, mask: np.ndarray | None = None,
               age_s: float = 0.0, masks: bool = True, until: Callable[[list[int]], bool] | None = None,
               confirm: bool = True) -> list[int]:
        """Publishes frames at ``rate`` Hz for ``seconds`` (or, with ``until``, until it returns True for the
        stamps sent so far); returns the depth stamps sent (ns).

        ``masks=False`` leaves the mask out (segmentation down). With ``confirm``, keeps publishing (a fresh
        frame each second) until the node has synchronised the last frame sent: everything sent before has then
        been delivered or lost for good.
        """
        pubs = self.publishers(qos)
        depth, mask_msg, info = self.messages
        if mask is not None:
            mask_msg = numpy_to_image(mask, "mono8")
        stamps: list[int] = []

        def send() -> None:
            now = self.ros.node.get_clock().now().nanoseconds - int(age_s * 1e9)
            for pub, msg in zip(pubs, (depth, mask_msg, info), strict=True):
                if msg is mask_msg and not masks:
                    continue
                msg.header.stamp.sec, msg.header.stamp.nanosec = now // 10**9, now % 10**9
                msg.header.frame_id = "camera_depth_optical_frame"
                pub.publish(msg)
            stamps.append(now)

        start, n = time.monotonic(), 0
        while True:
            send()
            n += 1
            if until is None and time.monotonic() - start >= seconds:
                break
            if until is not None and n % 8 == 0:  # every ~0.25 s: each check is a call to the node
                if until(stamps):
                    break
                assert time.monotonic() - start < TIMEOUT, f"the node did not react within {TIMEOUT} s"
            time.sleep(max(0.0, start + n / rate - time.monotonic()))
        if confirm:
            deadline = time.monotonic() + TIMEOUT
            while True:
                try:
                    wait_until(lambda: self.ros.stats()["latest_set_stamp_ns"] == stamps[-1], 1.0,
                               "the last frame synchronised")
                    break
                except TimeoutError:  # the last frame was lost (best effort): a camera sends the next one
                    assert time.monotonic() < deadline, f"no frame synchronised within {TIMEOUT} s"
                    send()
        return stamps


@pytest.fixture(scope="module")
def ros(node):
    client = RosClient(DOMAIN)
    client.listener = Listener(client)
    yield client
    client.close()


@pytest.fixture(scope="module")
def camera(ros, scene):
    """The camera, once the node's outputs reach the listener: an output published before the node's writer
    matched our reader would be missed, so stream until one arrives, then let the node go idle."""
    camera = Camera(ros, scene)
    wait_until(lambda: all(s.get_publisher_count() > 0 for s in ros.listener.subscriptions), TIMEOUT,
               "the node's output publishers")
    camera.stream(RELIABLE, until=lambda stamps: bool(ros.listener.of(stamps)["completions"]))
    ros.wait_idle(TIMEOUT)
    return camera


def delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {k: after[k] - before[k] for k in after}


def outputs_of(ros, stamps: list[int], count: int) -> dict[str, list]:
    """Waits until ``count`` outputs of the frames ``stamps`` have arrived on every output topic; returns them."""

    def arrived() -> dict[str, list] | None:
        out = ros.listener.of(stamps)
        return out if all(len(v) >= count for v in out.values()) else None

    return wait_until(arrived, TIMEOUT, f"{count} outputs on each of {', '.join(OUTPUTS)}")


def check_outputs(out: dict[str, list], stamps: list[int], count: int) -> None:
    clouds = out["completions"]
    assert len(clouds) == count, f"{len(clouds)} completions for {count} processed sets"
    assert [stamp_of(c) for c in clouds] == sorted({stamp_of(c) for c in clouds}), "not newest-first in time order"
    for cloud in clouds:
        assert cloud.header.frame_id == "camera_depth_optical_frame"
        expected = [(n, PointField.FLOAT32) for n in "xyz"] + [("sample", PointField.UINT32)]
        assert [(f.name, f.datatype) for f in cloud.fields] == expected
        points, sample = pointcloud2_to_numpy(cloud)
        assert len(points) > 0 and set(np.unique(sample).tolist()) <= set(range(SAMPLES))
    cloud_stamps = [stamp_of(c) for c in clouds]
    for name in ("known_occupied", "grasps", "grasp_candidates", "grasp_markers"):
        assert [stamp_of(m) for m in out[name]] == cloud_stamps, name
    for candidates, markers in zip(out["grasp_candidates"], out["grasp_markers"], strict=True):
        # one gripper outline per published grasp, after the DELETEALL that clears the previous set's
        assert [m.action for m in markers.markers] == [Marker.DELETEALL] + [Marker.ADD] * len(candidates.poses)
        assert all(m.header.frame_id == "camera_depth_optical_frame" for m in markers.markers)
        assert len(candidates.weight_shares) == len(candidates.scores) == len(candidates.poses)


def check_accounting(d: dict[str, int], elapsed_s: float) -> None:
    """Every synchronised set was completed, superseded by a newer one, or dropped (stale or invalid); none
    is queued or cancelled (no transition here).
    Every start obeys the rate limit: starts are 1 / RATE_HZ apart, so within ``elapsed_s``."""
    assert d["sets_synchronised"] == (d["sets_processed"] + d["sets_dropped_superseded"] + d["sets_dropped_stale"]
                                      + d["sets_dropped_invalid"]), d
    assert d["sets_cancelled"] == 0, d
    started = d["sets_processed"] + d["sets_dropped_stale"] + d["sets_dropped_invalid"]
    assert started <= np.floor(RATE_HZ * elapsed_s) + 1, f"{started} starts in {elapsed_s:.2f} s: rate limit broken"


@pytest.mark.parametrize("qos_name", ["best_effort", "reliable"])
def test_continuous_mode_with_either_publisher_qos(ros, camera, qos_name):
    qos = qos_profile_sensor_data if qos_name == "best_effort" else RELIABLE
    before = ros.wait_idle(TIMEOUT)
    t0 = time.monotonic()
    stamps = camera.stream(qos, seconds=2.0)
    after = ros.wait_idle(TIMEOUT)
    elapsed = time.monotonic() - t0
    d = delta(after, before)
    check_accounting(d, elapsed)
    assert d["sets_dropped_invalid"] == 0 and d["sets_processed"] >= 1, d
    out = outputs_of(ros, stamps, d["sets_processed"])
    check_outputs(out, stamps, d["sets_processed"])
    # The newest set is never lost: the last frame was completed, unless it had gone stale meanwhile.
    assert stamp_of(out["completions"][-1]) == stamps[-1] or d["sets_dropped_stale"] > 0, d


def test_service_uses_the_latest_synchronised_set(ros, camera):
    service = ros.service(SampleCompletions, SAMPLE_SERVICE)
    # Fresh enough whatever the load: this part checks which set is used; staleness is checked below.
    assert all(r.successful for r in ros.set_parameters(max_input_age=3600.0))
    try:
        stamps = camera.stream(RELIABLE, seconds=0.5)
        response = ros.call(service, SampleCompletions.Request(num_samples=2))  # depth empty: the topics' latest
    finally:
        assert all(r.successful for r in ros.set_parameters(max_input_age=MAX_INPUT_AGE))
    assert response.success, response.message
    assert stamp_of(response) == stamps[-1] and len(response.completions) == 2
    # No newer frame comes: once the clock passes the last stamp + max_input_age, the set is stale.
    wait_until(lambda: ros.node.get_clock().now().nanoseconds > stamps[-1] + MAX_INPUT_AGE * 1e9, TIMEOUT,
               "the latest set older than max_input_age")
    response = ros.call(service, SampleCompletions.Request(num_samples=2))
    assert not response.success and response.message.startswith("the latest synchronised input is stale: ")
    assert response.message.endswith(f"s old, max_input_age {MAX_INPUT_AGE} s")


def test_bad_topic_input_is_dropped_counted_and_warned(ros, camera, scene, node):
    start = ros.wait_idle(TIMEOUT)
    # Empty masks: every started set is invalid. Warnings are throttled: at most one per WARN_THROTTLE_S.
    first_line = len(node.lines())
    t0 = time.monotonic()
    camera.stream(RELIABLE, mask=np.zeros_like(scene.mask),
                  until=lambda _: ros.stats()["sets_dropped_invalid"] >= start["sets_dropped_invalid"] + 5)
    invalid = ros.wait_idle(TIMEOUT)
    span = time.monotonic() - t0
    d = delta(invalid, start)
    check_accounting(d, span)
    assert d["sets_dropped_invalid"] >= 5 and d["sets_processed"] == 0, d
    node.wait_for(r"dropped an input set \(\d+ so far\): mask is empty: 0 pixels marked", timeout=TIMEOUT)
    warnings = sum("dropped an input set" in line for line in node.lines(first_line))
    assert 1 <= warnings <= np.floor(span / WARN_THROTTLE_S) + 1, (warnings, span)

    # Stale stamps (a camera clock 30 s behind).
    camera.stream(RELIABLE, seconds=0.6, age_s=30.0)
    stale = ros.wait_idle(TIMEOUT)
    d = delta(stale, invalid)
    assert d["sets_dropped_stale"] >= 1 and d["sets_processed"] == 0, d
    node.wait_for(r"dropped a stale input set \(\d+ so far\): \d+\.\d+ s old, max_input_age 1.0 s", timeout=TIMEOUT)

    # No masks (the segmentation is down): depth and camera_info are queued, then dropped unmatched; no set.
    stamps = camera.stream(RELIABLE, masks=False, confirm=False,
                           until=lambda _: ros.stats()["messages_unmatched"] > stale["messages_unmatched"])
    unmatched = ros.wait_idle(TIMEOUT)
    d = delta(unmatched, stale)
    assert d["messages_unmatched"] > 0 and d["sets_synchronised"] == 0 and d["sets_processed"] == 0, d
    assert not any(ros.listener.of(stamps).values())

    # ... and the node still works.
    t0 = time.monotonic()
    stamps = camera.stream(RELIABLE, seconds=1.0)
    after = ros.wait_idle(TIMEOUT)
    d = delta(after, unmatched)
    check_accounting(d, time.monotonic() - t0)
    assert d["sets_processed"] >= 1, d
    check_outputs(outputs_of(ros, stamps, d["sets_processed"]), stamps, d["sets_processed"])


@pytest.mark.slow
def test_continuous_mode_accounts_for_every_set_over_a_minute(ros, camera):
    """A long run at 30 Hz: the same exact accounting and rate limit, and the node still answers after."""
    before = ros.wait_idle(TIMEOUT)
    t0 = time.monotonic()
    stamps = camera.stream(qos_profile_sensor_data, seconds=60.0)
    after = ros.wait_idle(TIMEOUT)
    d = delta(after, before)
    check_accounting(d, time.monotonic() - t0)
    assert d["sets_processed"] >= 1 and d["sets_dropped_invalid"] == 0, d
    check_outputs(outputs_of(ros, stamps, d["sets_processed"]), stamps, d["sets_processed"])


def test_qos_overrides_and_rclpy_parameters(tmp_path):
    """The inputs' and outputs' QoS follow ``qos_overrides.*`` at start-up (read-only afterwards), and rclpy's own
    parameters (use_sim_time) can be set like on any node."""
    path, _ = node_checkpoint(tmp_path)
    overrides = {"qos_overrides./depth.subscription.reliability": "reliable",
                 "qos_overrides./pssnet/grasps.publisher.reliability": "best_effort"}
    with NodeUnderTest(domain_for(23), model_path=path, threads=1, **overrides) as node:
        graph = node.ros.node

        def endpoints(info_by_topic: Callable, topic: str) -> dict:
            return {i.node_name: i.qos_profile.reliability for i in info_by_topic(topic) if i.node_name == "pssnet"}

        def reliability(info_by_topic: Callable, topic: str) -> ReliabilityPolicy:
            found = wait_until(lambda: endpoints(info_by_topic, topic), TIMEOUT, f"the node's endpoint on {topic}")
            return found["pssnet"]

        assert reliability(graph.get_subscriptions_info_by_topic, "/depth") == ReliabilityPolicy.RELIABLE
        assert reliability(graph.get_subscriptions_info_by_topic, "/mask") == ReliabilityPolicy.BEST_EFFORT
        assert reliability(graph.get_publishers_info_by_topic, "/pssnet/grasps") == ReliabilityPolicy.BEST_EFFORT
        assert reliability(graph.get_publishers_info_by_topic, "/pssnet/completions") == ReliabilityPolicy.RELIABLE
        assert node.ros.set_parameters(use_sim_time=True)[0].successful
        refused = node.ros.set_parameters(**{"qos_overrides./depth.subscription.reliability": "best_effort"})[0]
        assert not refused.successful and "read-only" in refused.reason
        assert node.ros.change_state("deactivate") and node.ros.change_state("activate")  # inputs made again
        assert reliability(graph.get_subscriptions_info_by_topic, "/depth") == ReliabilityPolicy.RELIABLE


def test_sigint_shutdown_is_clean(node):
    files = dict(node.shm_files)
    assert node.stop() == 0, node.output[-3000:]
    assert "Traceback" not in node.output
    assert stale_shm_files(files) == set()
