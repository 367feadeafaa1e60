"""Continuous mode over real DDS: best-effort and reliable camera publishers, rate limit, dropped sets, counters.

One node process (continuous: true, max_rate_hz 5) for the module; this process publishes a rendered mug
at 30 Hz and listens to the node's outputs.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray
from pssnet_interfaces.msg import GraspCandidates
from pssnet_interfaces.srv import SampleCompletions
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_srvs.srv import Trigger
from test_node_helpers import RosClient, domain_for, node_args, node_checkpoint, render_mug_scene, scene_messages

from pssnet_ros.conversions import numpy_to_image, pointcloud2_to_numpy
from pssnet_ros.processes import RosProcess, ros_env, stale_shm_files

pytestmark = pytest.mark.ros
DOMAIN = domain_for(2)
RATE_HZ = 5.0
SAMPLES = 3
RELIABLE = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture(scope="module")
def scene():
    return render_mug_scene(seed=5)


@pytest.fixture(scope="module")
def node(tmp_path_factory, scene):
    path, _ = node_checkpoint(tmp_path_factory.mktemp("node"))
    params = dict(up_vector=scene.up, num_samples=SAMPLES, threads=1, continuous=True, max_rate_hz=RATE_HZ,
                  max_input_age=1.0, sync_tolerance=0.005)
    process = RosProcess.python_module("pssnet_ros.completion_node", node_args(path, **params), ros_env(DOMAIN),
                                       name="completion_node")
    try:
        process.wait_for(r"ready: serving /pssnet/sample_completions, continuous on", timeout=120)
        yield process
    finally:
        process.stop()


class Listener:
    """Collects the node's outputs."""

    def __init__(self, ros: RosClient) -> None:
        self.lock = threading.Lock()
        self.messages: dict[str, list] = {"completions": [], "known_occupied": [], "grasps": [], "grasp_candidates": []}
        for name, msg_type in (("completions", PointCloud2), ("known_occupied", PointCloud2), ("grasps", PoseArray),
                               ("grasp_candidates", GraspCandidates)):
            ros.node.create_subscription(msg_type, f"/pssnet/{name}", lambda m, n=name: self._add(n, m), RELIABLE)

    def _add(self, name, msg):
        with self.lock:
            self.messages[name].append(msg)

    def take(self) -> dict[str, list]:
        with self.lock:
            taken = {k: list(v) for k, v in self.messages.items()}
            for v in self.messages.values():
                v.clear()
            return taken


@pytest.fixture(scope="module")
def ros(node):
    client = RosClient(DOMAIN)
    client.listener = Listener(client)
    yield client
    client.close()


def wait_until_idle(ros, quiet_s: float = 1.0, timeout_s: float = 20.0) -> None:
    """Lets completions of earlier inputs arrive and discards them: the node may still be finishing the last
    set of the previous test, and its output must not be counted (or checked) as this test's."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(quiet_s)
        if not ros.listener.take()["completions"]:
            return
    raise AssertionError(f"the node kept publishing completions for {timeout_s} s without input")


def stats(ros) -> dict[str, int]:
    return json.loads(ros.call(ros.client(Trigger, "/pssnet/get_stats"), Trigger.Request()).message)


def publish(ros, scene, qos, seconds=2.0, rate=30.0, mask=None, age_s=0.0, mask_offset_s=0.0, settle=1.0
            ) -> list[int]:
    """Publishes depth/mask/camera_info at ``rate`` Hz for ``seconds``; returns the stamps (ns) sent."""
    pubs = [ros.node.create_publisher(t, name, qos) for t, name in
            ((Image, "/depth"), (Image, "/mask"), (CameraInfo, "/camera_info"))]
    deadline = time.monotonic() + 15.0
    while any(p.get_subscription_count() == 0 for p in pubs):  # discovery
        assert time.monotonic() < deadline, "the node's subscriptions were not discovered within 15 s"
        time.sleep(0.05)
    depth, mask_msg, info = scene_messages(scene, None)
    if mask is not None:
        mask_msg = numpy_to_image(mask, "mono8")
    stamps = []
    start = time.monotonic()
    n = 0
    while time.monotonic() - start < seconds:
        now = ros.node.get_clock().now().nanoseconds - int(age_s * 1e9)
        for msg, offset in ((depth, 0.0), (mask_msg, mask_offset_s), (info, 0.0)):
            t = now + int(offset * 1e9)
            msg.header.stamp.sec, msg.header.stamp.nanosec = t // 10**9, t % 10**9
            msg.header.frame_id = "camera_depth_optical_frame"
        for pub, msg in zip(pubs, (depth, mask_msg, info), strict=True):
            pub.publish(msg)
        stamps.append(now)
        n += 1
        time.sleep(max(0.0, start + n / rate - time.monotonic()))
    time.sleep(settle)  # let the last completion arrive
    for pub in pubs:
        ros.node.destroy_publisher(pub)
    return stamps


def stamp_of(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def check_outputs(out, stamps, seconds):
    clouds = out["completions"]
    assert clouds, "no completions published"
    assert len(clouds) <= RATE_HZ * (seconds + 1.0) + 1, f"{len(clouds)} completions: the rate limit did not hold"
    for cloud in clouds:
        assert stamp_of(cloud) in stamps and cloud.header.frame_id == "camera_depth_optical_frame"
        expected = [(n, PointField.FLOAT32) for n in "xyz"] + [("sample", PointField.UINT32)]
        assert [(f.name, f.datatype) for f in cloud.fields] == expected
        points, sample = pointcloud2_to_numpy(cloud)
        assert len(points) > 0 and set(np.unique(sample).tolist()) <= set(range(SAMPLES))
    cloud_stamps = {stamp_of(c) for c in clouds}
    for name in ("known_occupied", "grasps", "grasp_candidates"):
        assert {stamp_of(m) for m in out[name]} == cloud_stamps, name


@pytest.mark.parametrize("qos_name", ["best_effort", "reliable"])
def test_continuous_mode_with_either_publisher_qos(ros, scene, qos_name):
    qos = qos_profile_sensor_data if qos_name == "best_effort" else RELIABLE
    wait_until_idle(ros)
    before = stats(ros)
    stamps = publish(ros, scene, qos, seconds=2.0)
    out = ros.listener.take()
    check_outputs(out, stamps, 2.0)
    after = stats(ros)
    processed = after["sets_processed"] - before["sets_processed"]
    assert processed == len(out["completions"])
    # 30 Hz in, at most 5 Hz out: every synchronised set was either completed or superseded by a newer one
    # (dropped, never queued; at most one may still be pending).
    synchronised = after["sets_synchronised"] - before["sets_synchronised"]
    superseded = after["sets_dropped_superseded"] - before["sets_dropped_superseded"]
    assert synchronised > processed and processed + superseded >= synchronised - 1


def test_service_uses_the_latest_synchronised_set(ros, scene):
    stamps = publish(ros, scene, RELIABLE, seconds=0.5, settle=0.3)
    client = ros.client(SampleCompletions, "/pssnet/sample_completions")
    response = ros.call(client, SampleCompletions.Request(num_samples=2))  # depth empty: the topics' latest
    assert response.success, response.message
    # The newest set the node had synchronised when the call arrived (the very last frame may still be in flight
    # while the node's worker holds the CPU).
    assert stamp_of(response) in stamps[-3:] and len(response.completions) == 2
    time.sleep(1.0)  # older than max_input_age now
    response = ros.call(client, SampleCompletions.Request(num_samples=2))
    assert not response.success and response.message.startswith("the latest synchronised input is stale: ")
    assert response.message.endswith("s old, max_input_age 1.0 s")


def test_bad_topic_input_is_dropped_counted_and_warned(ros, scene, node):
    before = stats(ros)
    ros.listener.take()
    publish(ros, scene, RELIABLE, seconds=1.0, mask=np.zeros_like(scene.mask))  # empty masks
    publish(ros, scene, RELIABLE, seconds=0.6, age_s=30.0)  # stale stamps (a camera clock 30 s behind)
    publish(ros, scene, RELIABLE, seconds=0.6, mask_offset_s=0.5)  # masks never match their depth
    after = stats(ros)
    assert after["sets_dropped_invalid"] > before["sets_dropped_invalid"]
    assert after["sets_dropped_stale"] > before["sets_dropped_stale"]
    assert after["messages_unmatched"] > before["messages_unmatched"]
    assert after["sets_processed"] == before["sets_processed"]
    assert not ros.listener.take()["completions"]
    node.wait_for(r"dropped an input set \(\d+ so far\): mask is empty: 0 pixels marked", timeout=5)
    node.wait_for(r"dropped a stale input set \(\d+ so far\): \d+\.\d+ s old, max_input_age 1.0 s", timeout=5)
    # Warnings are throttled: far fewer warning lines than dropped sets.
    warnings = node.output.count("dropped an input set")
    assert warnings < after["sets_dropped_invalid"]
    # ... and the node still works.
    stamps = publish(ros, scene, RELIABLE, seconds=1.0)
    check_outputs(ros.listener.take(), stamps, 1.0)


def test_sigint_shutdown_is_clean(node):
    files = set(node.shm_files)
    assert node.stop() == 0, node.output[-3000:]
    assert "Traceback" not in node.output
    assert stale_shm_files(files) == set()
