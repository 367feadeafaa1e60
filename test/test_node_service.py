"""The completion node's service over real DDS: the node runs in its own process, this test is the client.

One node process serves the whole module (start-up costs seconds); the last test stops it with SIGINT and
checks the exit code and that no Fast DDS shared-memory file of it is left.
"""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import Pose
from pssnet_interfaces.srv import SampleCompletions
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial import cKDTree
from sensor_msgs.msg import PointField
from test_node_helpers import (
    domain_for,
    make_request,
    node_checkpoint,
    render_mug_scene,
    scene_messages,
    stamped_header,
)

from pssnet_core.data.scenes import render_view
from pssnet_core.geometry import CameraIntrinsics
from pssnet_core.shapes import make_shape
from pssnet_ros.conversions import (
    intrinsics_to_camera_info,
    matrix_to_pose,
    numpy_to_image,
    pointcloud2_to_numpy,
    pose_to_matrix,
)
from pssnet_testing.client import SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import stale_shm_files

pytestmark = pytest.mark.ros
DOMAIN = domain_for(1)


@pytest.fixture(scope="module")
def scene():
    return render_mug_scene(seed=3)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return node_checkpoint(tmp_path_factory.mktemp("node"))


@pytest.fixture(scope="module")
def node(checkpoint, scene):
    path, _ = checkpoint
    with NodeUnderTest(DOMAIN, model_path=path, up_vector=scene.up, num_samples=8, threads=1) as node:
        yield node.process


@pytest.fixture(scope="module")
def ros(node):
    client = RosClient(DOMAIN)
    yield client
    client.close()


@pytest.fixture(scope="module")
def service(ros):
    return ros.service(SampleCompletions, SAMPLE_SERVICE, timeout=30)


def call(ros, service, request, timeout=60.0):
    return ros.call(service, request, timeout)


def test_round_trip_returns_completions_in_the_request_frame(ros, service, scene, checkpoint):
    header = stamped_header(1234, 5678)
    response = call(ros, service, make_request(scene, header, num_samples=5))
    assert response.success and response.status == response.STATUS_OK, response.message
    assert re.fullmatch(r"5 samples, \d+ voxels, 0 grasps, seed 0, \d+ ms \(observation [\d.]+, network [\d.]+, "
                        r"grasps 0\.0 ms\)", response.message), response.message
    assert response.header.frame_id == "camera_depth_optical_frame"
    assert (response.header.stamp.sec, response.header.stamp.nanosec) == (1234, 5678)
    assert response.voxel_size > 0 and len(response.completions) == 5
    assert len(response.sample_weights) == 5 and sum(response.sample_weights) == pytest.approx(1.0)
    assert len(response.grasps.poses) == 0 and response.grasps.header.frame_id == "camera_depth_optical_frame"
    known, _ = pointcloud2_to_numpy(response.known_occupied)
    assert len(known) > 50 and response.known_occupied.header.stamp.sec == 1234
    for cloud in response.completions:
        assert [(f.name, f.datatype) for f in cloud.fields] == [(n, PointField.FLOAT32) for n in "xyz"]
        assert cloud.header.frame_id == "camera_depth_optical_frame"
    # The observed points, exactly as the node sees them.
    v, u = np.nonzero((scene.mask > 0) & (scene.depth > 0.1))
    observed = scene.intrinsics.backproject(u, v, scene.depth[v, u])
    distance, _ = cKDTree(known).query(observed)
    assert distance.max() <= 0.5 * np.sqrt(3) * response.voxel_size + 1e-4
    _, trained = checkpoint
    if not trained:
        pytest.skip("completions of a real shape need the shipped default model "
                    "(pssnet_core/checkpoints/default_pssnet_32.pt is missing); the plumbing above passed")
    for i, cloud in enumerate(response.completions):
        points, _ = pointcloud2_to_numpy(cloud)
        # A mug-sized solid around the observation, not somewhere else and not a speck ...
        assert len(points) > len(known), f"sample {i}: {len(points)} voxels for {len(known)} observed"
        assert np.linalg.norm(points.mean(axis=0) - observed.mean(axis=0)) < 0.1, i
        assert np.ptp(points, axis=0).max() > 0.06, i
        # ... that reproduces the observation: every observed point within ~1 voxel of the sample's voxels
        # (half diagonal + one voxel).
        distance, _ = cKDTree(points).query(observed)
        assert np.quantile(distance, 0.99) <= (0.5 * np.sqrt(3) + 1.0) * response.voxel_size, i


def test_grasps_are_returned_best_first_in_the_request_frame(ros, service, scene, checkpoint):
    response = call(ros, service, make_request(scene, stamped_header(77), num_samples=6, compute_grasps=True))
    assert response.success, response.message
    n = len(response.grasps.poses)
    assert len(response.grasp_scores) == n == len(response.grasp_widths) == len(response.grasp_weight_shares)
    assert n <= 10  # grasp_top_k
    assert response.grasps.header.stamp.sec == 77 and response.grasps.header.frame_id == "camera_depth_optical_frame"
    # Best first by the expected grip (GraspConfig.rank_by), which the response does not carry: the scores need not
    # be sorted, but a grasp that holds for no sample never precedes one that holds for some.
    held = [s > 0.0 for s in response.grasp_scores]
    assert held == sorted(held, reverse=True)
    assert all(0.0 <= s <= 1.0 for s in response.grasp_scores) and all(0 < w <= 0.08 for w in response.grasp_widths)
    # A share of the weight in [0, 1]; a grasp holding for no sample holds none of it.
    assert all(0.0 <= share <= 1.0 and (h or share == 0.0)
               for share, h in zip(response.grasp_weight_shares, held, strict=True))
    for pose in response.grasps.poses:
        q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
        assert abs(np.linalg.norm(q) - 1.0) < 1e-6
    if checkpoint[1]:  # a trained model completes a mug a parallel-jaw gripper can hold
        assert n > 0 and response.grasp_scores[0] >= 0.5, response.message


def test_service_results_are_published_for_rviz_only_when_asked(ros, service, scene):
    from visualization_msgs.msg import Marker, MarkerArray

    received: list[MarkerArray] = []
    listener = ros.node.create_subscription(MarkerArray, "/pssnet/grasp_markers", received.append,
                                            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    try:
        wait_until(lambda: ros.node.count_publishers("/pssnet/grasp_markers") > 0, 30, "the node's marker publisher")
        response = call(ros, service, make_request(scene, stamped_header(91), num_samples=4, compute_grasps=True))
        assert response.success, response.message
        time.sleep(1.0)
        assert not received, "published although publish_service_results is false (the default)"
        assert ros.set_parameters(publish_service_results=True)[0].successful
        try:
            response = call(ros, service, make_request(scene, stamped_header(92), num_samples=4,
                                                       compute_grasps=True))
        finally:
            assert ros.set_parameters(publish_service_results=False)[0].successful
        assert response.success, response.message
        markers = wait_until(lambda: received[0].markers if received else None, 30, "the call's grasp markers")
    finally:
        ros.node.destroy_subscription(listener)
    assert markers[0].action == Marker.DELETEALL and all(m.header.stamp.sec == 92 for m in markers)
    assert [m.id for m in markers[1:]] == list(range(len(response.grasps.poses)))
    for marker, pose, width, score in zip(markers[1:], response.grasps.poses, response.grasp_widths,
                                          response.grasp_scores, strict=True):
        # the first finger runs from the fingertip at -width/2 on the closing axis (y) back along the approach
        tip = pose_to_matrix(pose) @ np.array([0.0, -width / 2, 0.0, 1.0])
        first = marker.points[0]
        np.testing.assert_allclose([first.x, first.y, first.z], tip[:3], atol=1e-6)
        assert marker.type == Marker.LINE_LIST and len(marker.points) == 8
        assert abs(marker.color.g - min(1.0, 2 * score)) < 1e-6


def test_seeded_samples_are_reproducible_and_16uc1_works(ros, service, scene):
    header = stamped_header(10)
    a = call(ros, service, make_request(scene, header, num_samples=2))
    b = call(ros, service, make_request(scene, header, num_samples=2, depth_encoding="16UC1"))
    assert a.success and b.success, (a.message, b.message)
    assert a.completions[0].data == call(ros, service, make_request(scene, header, num_samples=2)).completions[0].data
    known_a, _ = pointcloud2_to_numpy(a.known_occupied)
    known_b, _ = pointcloud2_to_numpy(b.known_occupied)
    # Millimetre rounding moves the grid by < 1 mm: the same surface, give or take one voxel layer.
    distance, _ = cKDTree(known_a).query(known_b)
    assert distance.max() <= np.sqrt(3) * a.voxel_size + 1e-4


def bad_requests(scene):
    """(name, request, exact message pattern) for every bad input the issue lists."""
    header = stamped_header(50)

    def request(**changes):
        req = make_request(scene, header)
        for key, value in changes.items():
            target, field = key.split("__") if "__" in key else (key, None)
            if field is None:
                setattr(req, target, value)
            else:
                setattr(getattr(req, target), field, value)
        return req

    nan_depth = scene.depth.copy()
    nan_depth[scene.mask > 0] = np.nan
    inf_depth = scene.depth.copy()
    inf_depth[:] = np.inf
    zero_depth = np.zeros_like(scene.depth)
    tiny = np.zeros_like(scene.mask)
    tiny[100:104, 100:104] = 255
    zero_info = intrinsics_to_camera_info(scene.intrinsics, header)
    zero_info.k = [0.0] * 9
    nan_info = intrinsics_to_camera_info(scene.intrinsics, header)
    nan_info.k[0] = float("nan")
    small_info = intrinsics_to_camera_info(CameraIntrinsics.kinect_like(320, 240), header)

    def info_with(field, index, value):
        info = intrinsics_to_camera_info(scene.intrinsics, header)
        getattr(info, field)[index] = value
        return info

    plain = make_request(scene, header)
    depth_msg, info_msg = plain.depth, plain.camera_info
    zero_quaternion = Pose()
    zero_quaternion.orientation.w = 0.0
    quarter_mm = numpy_to_image(np.rint(scene.depth * 4000.0).astype(np.uint16), "16UC1", header)
    return [
        ("unknown depth encoding", request(depth__encoding="rgb8"),
         r"^depth has encoding 'rgb8'; supported: 32FC1, 16UC1, mono16$"),
        ("wrong mask encoding", request(mask=numpy_to_image(scene.mask.astype(np.float32), "32FC1", header)),
         r"^mask has encoding '32FC1'; supported: mono8, 8UC1$"),
        ("truncated depth", request(depth__data=bytes(make_request(scene, header).depth.data)[:-4]),
         r"^depth data has 1228796 bytes; 640x480 32FC1 with step 2560 needs 1228800$"),
        ("size mismatch", request(mask=numpy_to_image(scene.mask[:240], "mono8", header)),
         r"^mask is 640x240 but depth is 640x480: they must be the same size$"),
        ("empty mask", request(mask=numpy_to_image(np.zeros_like(scene.mask), "mono8", header)),
         r"^mask is empty: 0 pixels marked, need at least 50 \(min_mask_pixels\)$"),
        ("tiny mask", request(mask=numpy_to_image(tiny, "mono8", header)),
         r"^mask is too small: 16 pixels marked, need at least 50 \(min_mask_pixels\)$"),
        ("all-NaN depth", request(depth=numpy_to_image(nan_depth, "32FC1", header)),
         r"^depth has no finite reading inside the mask \(all NaN/Inf\)$"),
        ("all-Inf depth", request(depth=numpy_to_image(inf_depth, "32FC1", header)),
         r"^depth has no finite reading inside the mask \(all NaN/Inf\)$"),
        ("all-zero depth", request(depth=numpy_to_image(zero_depth, "32FC1", header)),
         r"^only 0 of \d+ masked pixels have a valid depth in \[0.1, 5.0\] m \(need at least 20\)$"),
        ("zero intrinsics", request(camera_info=zero_info),
         r"^camera_info K matrix is all zeros \(uncalibrated camera\?\)$"),
        ("NaN intrinsics", request(camera_info=nan_info), r"^camera_info: intrinsics must be finite"),
        ("camera_info size", request(camera_info=small_info), r"^depth is 640x480 but camera_info says 320x240$"),
        ("fx 1e30", request(camera_info=info_with("k", 0, 1e30)),
         r"^camera_info: K fx = 1e\+30 px gives a horizontal field of view of 3.67e-26 deg over 640 px; real cameras "
         r"have 1 to 160 deg \(corrupt calibration\?\)$"),
        ("fx 5 px", request(camera_info=info_with("k", 0, 5.0)),
         r"^camera_info: K fx = 5 px gives a horizontal field of view of 178 deg over 640 px"),
        ("skew 1e30", request(camera_info=info_with("k", 1, 1e30)),
         r"^camera_info: K skew K\[0,1\] = 1e\+30 shifts pixels by up to 4.58e\+29 px, which a pinhole model without "
         r"skew ignores; \|skew\| must be at most 1.09 \(0.5 px\)$"),
        ("cx outside", request(camera_info=info_with("k", 2, -5000.0)),
         r"^camera_info: K principal point cx = -5000 px lies outside the 640 px wide image$"),
        ("P disagrees with K", request(camera_info=info_with("p", 0, 600.0)),
         r"^camera_info: P fx = 600 but K fx = 525: without distortion and rectification \(D zero, R identity\) "
         r"the two must agree$"),
        ("R not a rotation", request(camera_info=info_with("r", 0, 2.0)),
         r"^camera_info: R is not a rotation matrix \(R R\^T differs from I by 3, det 2\)"),
        ("depth in 0.25 mm read as mm", request(depth=quarter_mm),
         r"^the observed object spans 0.\d+ m upwards, more than the 0.194 m the 32\^3 grid of 6.25 mm voxels holds: "
         r"too large for this model, or the depth units \(depth_scale of 16-bit images\) or the intrinsics are wrong$"),
        ("absurd num_samples", request(num_samples=4_000_000_000),
         r"^num_samples 4000000000 is out of range: ask for 1..100 \(max_num_samples\), or 0 for the node's"),
        ("more views of unequal length", request(more_depths=[make_request(scene, header).depth]),
         r"^more_depths, more_masks, more_camera_infos and more_camera_poses must be the same length, got 1, 0, 0, 0$"),
        ("an empty second mask", request(more_depths=[depth_msg], more_masks=[numpy_to_image(np.zeros_like(scene.mask),
                                                                                                "mono8", header)],
                                         more_camera_infos=[info_msg], more_camera_poses=[Pose()]),
         r"^view 2: mask is empty: 0 pixels marked, need at least 50 \(min_mask_pixels\)$"),
        ("a zero quaternion as a candidate view", request(candidate_views=[Pose(), zero_quaternion]),
         r"^candidate view 1: pose orientation is not a valid quaternion: \[0.0, 0.0, 0.0, 0.0\]$"),
        ("unsynchronised stamps", request(mask__header=stamped_header(51)),
         r"^unsynchronised request: depth stamp 50.000000 s and mask stamp 51.000000 s differ by 1.000000 s "
         r"\(sync_tolerance 0.01 s\)$"),
    ]


def test_every_bad_input_gets_an_exact_answer_and_the_node_keeps_serving(ros, service, scene, node):
    cases = bad_requests(scene)
    for name, request, pattern in cases:
        response = call(ros, service, request)
        assert not response.success and response.status == response.STATUS_INVALID_INPUT, name
        assert re.search(pattern, response.message), f"{name}: {response.message!r}"
        assert len(response.completions) == 0
    assert node.running()
    assert call(ros, service, make_request(scene, stamped_header(60), num_samples=1)).success
    assert ros.stats()["service_failures"] >= len(cases)


def test_a_second_look_adds_what_it_saw_and_candidate_views_are_scored(ros, service, scene, checkpoint):
    """The mug seen again from behind (its handle in view), and two places asked about: behind and the first
    camera's own. All poses are optical frames in the first depth image's frame."""
    back = render_view(make_shape("mug", 2_000_003), yaw_deg=0.0, distance=0.6, tilt_deg=30.0, azimuth_deg=0.0)
    first_from_back = np.linalg.inv(scene.camera_pose) @ back.camera_pose
    header = stamped_header(90)
    one = call(ros, service, make_request(scene, header, num_samples=4))
    request = make_request(scene, header, num_samples=4)
    depth, mask, info = scene_messages(back, stamped_header(91))
    request.more_depths, request.more_masks, request.more_camera_infos = [depth], [mask], [info]
    request.more_camera_poses = [matrix_to_pose(first_from_back)]
    request.candidate_views = [matrix_to_pose(first_from_back), matrix_to_pose(np.eye(4))]
    two = call(ros, service, request)
    assert one.success and two.success, (one.message, two.message)
    assert len(one.candidate_view_scores) == 0 and len(two.candidate_view_scores) == 2
    known_one, _ = pointcloud2_to_numpy(one.known_occupied)
    known_two, _ = pointcloud2_to_numpy(two.known_occupied)
    assert len(known_two) > 1.3 * len(known_one)  # the back of the mug and its handle
    # The points the back camera saw, in the first camera's frame, are in the known-occupied cloud.
    v, u = np.nonzero((back.mask > 0) & (back.depth > 0.1))
    seen = back.intrinsics.backproject(u, v, back.depth[v, u]) @ first_from_back[:3, :3].T + first_from_back[:3, 3]
    distance, _ = cKDTree(known_two).query(seen)
    assert np.quantile(distance, 0.99) <= 0.5 * np.sqrt(3) * two.voxel_size + 1e-4
    assert all(0.0 <= s <= 1.0 for s in two.candidate_view_scores)
    if checkpoint[1]:  # a trained model's samples differ where the first view did not look, not where it did
        asked = make_request(scene, header, num_samples=8)
        asked.candidate_views = list(request.candidate_views)
        behind, itself = call(ros, service, asked).candidate_view_scores
        assert itself <= 0.1 < behind


def test_empty_depth_without_topic_input_is_explained(ros, service):
    response = call(ros, service, SampleCompletions.Request())
    assert not response.success and response.status == response.STATUS_NO_INPUT
    assert re.search(r"^request has no depth image and no synchronised set has arrived on /depth, /mask, "
                     r"/camera_info yet", response.message), response.message


def test_concurrent_calls_are_all_answered(ros, service, scene):
    results: list = [None] * 4
    clients = [service] + [ros.service(SampleCompletions, SAMPLE_SERVICE, new=True) for _ in range(3)]

    def worker(i):
        results[i] = call(ros, clients[i], make_request(scene, stamped_header(100 + i), num_samples=3))

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert all(r is not None and r.success for r in results), [r and r.message for r in results]
    assert sorted(r.header.stamp.sec for r in results) == [100, 101, 102, 103]


def set_parameter(ros, name, value):
    return ros.set_parameters(**{name: value})[0]


def test_invalid_parameters_are_rejected_with_a_reason(ros, service, scene):
    result = set_parameter(ros, "num_samples", 500)
    assert not result.successful and result.reason == "num_samples must be in [1, max_num_samples=100], got 500"
    result = set_parameter(ros, "min_depth", 9.0)
    assert not result.successful and "need 0 <= min_depth < max_depth, got 9.0 and 5.0" in result.reason
    result = set_parameter(ros, "max_rate_hz", 0.0)
    assert not result.successful and "out of range" in result.reason
    assert set_parameter(ros, "num_samples", 2).successful
    response = call(ros, service, make_request(scene, stamped_header(7)))
    assert response.success and len(response.completions) == 2  # num_samples 0 in the request = the parameter
    assert set_parameter(ros, "num_samples", 8).successful


def test_sigint_shutdown_is_clean(ros, node):
    assert node.running()
    files = dict(node.shm_files)
    assert files, "expected the node to own Fast DDS shared-memory segments"
    code = node.stop()
    assert code == 0, node.output[-3000:]
    assert "Traceback" not in node.output
    assert stale_shm_files(files) == set()
