"""Image / CameraInfo / PointCloud2 / Pose <-> numpy: round trips, byte order, row padding, malformed input."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header
from test_node_helpers import render_mug_scene

from pssnet_core.geometry import CameraIntrinsics, masked_points
from pssnet_ros.conversions import (
    ConversionError,
    camera_info_to_intrinsics,
    depth_to_metres,
    image_to_numpy,
    intrinsics_to_camera_info,
    mask_to_numpy,
    matrix_to_pose,
    numpy_to_image,
    pointcloud2_to_numpy,
    points_to_pointcloud2,
    pose_to_matrix,
)

RNG = np.random.default_rng(0)
ARRAYS = {
    "32FC1": RNG.uniform(0.2, 3.0, (5, 7)).astype(np.float32),
    "16UC1": RNG.integers(0, 65535, (5, 7)).astype(np.uint16),
    "mono16": RNG.integers(0, 65535, (5, 7)).astype(np.uint16),
    "mono8": RNG.integers(0, 255, (5, 7)).astype(np.uint8),
    "8UC1": RNG.integers(0, 255, (5, 7)).astype(np.uint8),
}


@pytest.mark.parametrize("encoding", sorted(ARRAYS))
@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("padding", [0, 3, 16])
def test_image_round_trip(encoding, bigendian, padding):
    array = ARRAYS[encoding]
    row = array.shape[1] * array.dtype.itemsize
    msg = numpy_to_image(array, encoding, is_bigendian=bigendian, step=row + padding)
    assert msg.step == row + padding and len(msg.data) == msg.step * msg.height
    back = image_to_numpy(msg)
    assert back.dtype == array.dtype and back.dtype.isnative
    np.testing.assert_array_equal(back, array)


def test_big_endian_bytes_are_decoded_as_big_endian():
    msg = Image(height=1, width=2, encoding="16UC1", is_bigendian=1, step=4, data=bytes([0x01, 0x02, 0x00, 0x0A]))
    np.testing.assert_array_equal(image_to_numpy(msg), [[0x0102, 0x000A]])
    msg.is_bigendian = 0
    np.testing.assert_array_equal(image_to_numpy(msg), [[0x0201, 0x0A00]])


@pytest.mark.parametrize("encoding", ["32FC1", "16UC1"])
@pytest.mark.parametrize("bigendian", [False, True])
def test_a_camera_depth_image_decodes_right_in_its_byte_order_and_is_refused_with_the_wrong_flag(encoding, bigendian):
    from test_node_helpers import render_mug_scene

    depth = render_mug_scene().depth.astype(np.float32)
    if encoding == "16UC1":
        depth = np.rint(depth * 1000).astype(np.uint16)
    msg = numpy_to_image(depth, encoding, is_bigendian=bigendian)
    expected = depth if encoding == "32FC1" else depth.astype(np.float32) * np.float32(0.001)
    np.testing.assert_array_equal(depth_to_metres(msg), expected)
    msg.is_bigendian = int(not bigendian)
    order = "little" if bigendian else "big"
    with pytest.raises(ConversionError, match=rf"depth is flagged {order}-endian \(is_bigendian={int(not bigendian)}\) "
                                              r"but reads as the other byte order: .*fix the publisher's is_bigendian"):
        depth_to_metres(msg)


def test_depth_scale_and_float_passthrough():
    mm = np.array([[0, 500, 1234]], dtype=np.uint16)
    np.testing.assert_allclose(depth_to_metres(numpy_to_image(mm, "16UC1")), [[0.0, 0.5, 1.234]], rtol=1e-6)
    np.testing.assert_allclose(depth_to_metres(numpy_to_image(mm, "16UC1"), depth_scale=1e-4), [[0, 0.05, 0.1234]],
                               rtol=1e-6)
    metres = np.array([[np.nan, 0.0, 1.5]], dtype=np.float32)
    out = depth_to_metres(numpy_to_image(metres, "32FC1", is_bigendian=True))
    assert out.dtype == np.float32 and np.isnan(out[0, 0]) and out[0, 2] == np.float32(1.5)
    with pytest.raises(ConversionError, match="depth_scale"):
        depth_to_metres(numpy_to_image(mm, "16UC1"), depth_scale=0.0)


def test_mask_accepts_mono8_and_8uc1_only():
    mask = np.array([[0, 1, 255]], dtype=np.uint8)
    for encoding in ("mono8", "8UC1"):
        np.testing.assert_array_equal(mask_to_numpy(numpy_to_image(mask, encoding)), [[False, True, True]])
    with pytest.raises(ConversionError, match=r"mask has encoding '16UC1'; supported: mono8, 8UC1"):
        mask_to_numpy(numpy_to_image(mask.astype(np.uint16), "16UC1"))
    bool_mask = numpy_to_image(np.array([[True, False]]), "mono8")
    assert bytes(bool_mask.data) == bytes([255, 0])


@pytest.mark.parametrize("mutate, message", [
    (lambda m: setattr(m, "encoding", "rgb8"), r"depth has encoding 'rgb8'; supported: 32FC1, 16UC1, mono16"),
    (lambda m: setattr(m, "encoding", ""), r"depth has encoding ''"),
    (lambda m: setattr(m, "data", bytes(m.data)[:-1]), r"depth data has 139 bytes; 7x5 32FC1 with step 28 needs 140"),
    (lambda m: setattr(m, "data", bytes(m.data) + b"\0"), r"depth data has 141 bytes"),
    (lambda m: setattr(m, "step", 20), r"depth step 20 is smaller than width \* bytes per pixel = 28"),
    (lambda m: setattr(m, "height", 0), r"depth is empty \(7x0\)"),
])
def test_malformed_depth_raises_clear_error(mutate, message):
    msg = numpy_to_image(ARRAYS["32FC1"], "32FC1")
    mutate(msg)
    with pytest.raises(ConversionError, match=message):
        depth_to_metres(msg)


def test_numpy_to_image_rejects_bad_arguments():
    with pytest.raises(ConversionError, match="cannot encode 'bgr8'"):
        numpy_to_image(np.zeros((2, 2)), "bgr8")
    with pytest.raises(ConversionError, match="must be 2-D"):
        numpy_to_image(np.zeros((2, 2, 3)), "mono8")
    with pytest.raises(ConversionError, match="step 1 is smaller"):
        numpy_to_image(np.zeros((2, 2)), "mono8", step=1)


def test_camera_info_round_trip_and_errors():
    intrinsics = CameraIntrinsics(width=640, height=480, fx=525.0, fy=520.0, cx=319.5, cy=239.5)
    header = Header(frame_id="camera_depth_optical_frame")
    msg = intrinsics_to_camera_info(intrinsics, header)
    assert msg.header.frame_id == "camera_depth_optical_frame" and len(msg.p) == 12
    assert camera_info_to_intrinsics(msg) == intrinsics
    zero = CameraInfo(width=640, height=480)
    with pytest.raises(ConversionError, match="K matrix is all zeros"):
        camera_info_to_intrinsics(zero)
    with pytest.raises(ConversionError, match="image size 0x0"):
        camera_info_to_intrinsics(CameraInfo(k=msg.k))
    bad = intrinsics_to_camera_info(intrinsics)
    bad.k[0] = 0.0
    with pytest.raises(ConversionError, match="focal lengths must be positive"):
        camera_info_to_intrinsics(bad)
    bad.k[0] = float("nan")
    with pytest.raises(ConversionError, match="finite"):
        camera_info_to_intrinsics(bad)


def test_camera_info_no_camera_has_is_refused_naming_the_field():
    """The checks are the core's (check_camera_model): K, D, R and P all come from the message."""
    intrinsics = CameraIntrinsics.kinect_like()
    for field, index, value, message in [
        ("k", 0, 1e30, r"^camera_info: K fx = 1e\+30 px gives a horizontal field of view of 3.67e-26 deg"),
        ("k", 1, 1e30, r"^camera_info: K skew K\[0,1\] = 1e\+30 shifts pixels"),
        ("k", 2, -5000.0, r"^camera_info: K principal point cx = -5000 px lies outside the 640 px wide image$"),
        ("k", 0, 5.0, r"^camera_info: K fx = 5 px gives a horizontal field of view of 178 deg"),
        ("r", 1, 0.5, r"^camera_info: R is not a rotation matrix"),
        ("p", 5, 600.0, r"^camera_info: P fy = 600 but K fy = 525"),
    ]:
        msg = intrinsics_to_camera_info(intrinsics)
        getattr(msg, field)[index] = value
        with pytest.raises(ConversionError, match=message):
            camera_info_to_intrinsics(msg)
    msg = intrinsics_to_camera_info(intrinsics)
    msg.d = [0.05, -0.1, 0.0, 0.0, 0.0]  # distorted: P is the rectified camera, free to differ from K
    msg.p[0] = msg.p[5] = 500.0
    assert camera_info_to_intrinsics(msg) == replace(intrinsics, fx=500.0, fy=500.0)
    msg.p[1] = 100.0  # P's skew, dropped like K's, is checked like K's
    with pytest.raises(ConversionError, match=r"^camera_info: P skew P\[0,1\] = 100 shifts pixels"):
        camera_info_to_intrinsics(msg)


def raw_camera_info(rectified: CameraIntrinsics, rotation: np.ndarray | None = None) -> CameraInfo:
    """What a driver publishes for a distorted camera whose rectified image (image_proc's image_rect) has the
    intrinsics ``rectified``: K of the raw image (longer focal length, off-centre), D non-zero, P of the
    rectified image."""
    msg = intrinsics_to_camera_info(rectified)
    raw = replace(rectified, fx=rectified.fx * 1.08, fy=rectified.fy * 1.08, cx=rectified.cx + 12.0,
                  cy=rectified.cy - 9.0)
    msg.k = raw.matrix().reshape(-1).tolist()
    msg.d = [-0.28, 0.07, 0.0005, -0.0003, 0.0]
    if rotation is not None:
        msg.r = rotation.reshape(-1).tolist()
    return msg


def test_a_rectified_image_is_back_projected_with_p_as_image_geometry_does():
    """image_geometry's PinholeCameraModel maps pixels of the rectified image with P (fx = P[0,0], cx = P[0,2]):
    a depth image rendered with the rectified camera gives its true points only with P's intrinsics."""
    scene = render_mug_scene(seed=0)
    msg = raw_camera_info(scene.intrinsics)
    assert camera_info_to_intrinsics(msg) == scene.intrinsics
    truth = masked_points(scene.depth, scene.mask, scene.intrinsics)
    np.testing.assert_array_equal(masked_points(scene.depth, scene.mask, camera_info_to_intrinsics(msg)), truth)
    with_k = masked_points(scene.depth, scene.mask, CameraIntrinsics.from_k(msg.k, msg.width, msg.height))
    assert np.linalg.norm(with_k - truth, axis=1).mean() > 0.005  # K would move the object by centimetres
    # A stereo camera's rectification rotation (R not the identity) without distortion: P as well.
    msg = raw_camera_info(scene.intrinsics, Rotation.from_euler("y", 1.5, degrees=True).as_matrix())
    msg.d = [0.0] * 5
    assert camera_info_to_intrinsics(msg) == scene.intrinsics
    # P all zero (not given): K is all there is.
    msg.p = [0.0] * 12
    assert camera_info_to_intrinsics(msg) == CameraIntrinsics.from_k(msg.k, msg.width, msg.height)


def test_p_that_disagrees_with_k_of_a_camera_without_distortion_is_refused():
    """D zero and R the identity: the raw image is its own rectified image, so K and P describe one camera."""
    scene = render_mug_scene(seed=0)
    msg = raw_camera_info(scene.intrinsics)
    for d in ([0.0] * 5, []):
        msg.d = d
        with pytest.raises(ConversionError, match=r"^camera_info: P fx = 525 but K fx = 567: without distortion "
                                                  r"and rectification \(D zero, R identity\) the two must agree"):
            camera_info_to_intrinsics(msg)
    msg.r = [0.0] * 9  # R not given counts as the identity
    with pytest.raises(ConversionError, match="P fx = 525 but K fx = 567"):
        camera_info_to_intrinsics(msg)


def test_pointcloud_round_trip_with_and_without_sample():
    points = RNG.normal(size=(50, 3)).astype(np.float32)
    sample = RNG.integers(0, 20, 50)
    header = Header(frame_id="cam")
    msg = points_to_pointcloud2(points, header, sample)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "sample"]
    assert [f.datatype for f in msg.fields] == [PointField.FLOAT32] * 3 + [PointField.UINT32]
    assert msg.point_step == 16 and msg.width == 50 and msg.height == 1 and msg.header.frame_id == "cam"
    back, back_sample = pointcloud2_to_numpy(msg)
    np.testing.assert_array_equal(back, points)
    np.testing.assert_array_equal(back_sample, sample)
    plain = points_to_pointcloud2(points)
    assert plain.point_step == 12 and pointcloud2_to_numpy(plain)[1] is None
    empty_points, empty_sample = pointcloud2_to_numpy(points_to_pointcloud2(np.zeros((0, 3)), sample=np.zeros(0, int)))
    assert empty_points.shape == (0, 3) and empty_sample.shape == (0,)


def test_pointcloud_reads_foreign_layouts():
    """Big-endian float64 fields at odd offsets with padded points and rows (as other drivers send)."""
    points = RNG.normal(size=(2, 3, 3))
    record = np.dtype({"names": ["z", "x", "y"], "formats": [">f8"] * 3, "offsets": [0, 8, 16], "itemsize": 32})
    rows = np.zeros((2, 3), dtype=record)
    rows["x"], rows["y"], rows["z"] = points[..., 0], points[..., 1], points[..., 2]
    data = b"".join(rows[r].tobytes() + b"\xff" * 8 for r in range(2))  # 8 bytes of row padding
    fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT64, count=1) for n, o in (("z", 0), ("x", 8),
                                                                                               ("y", 16))]
    msg = PointCloud2(height=2, width=3, fields=fields, is_bigendian=True, point_step=32, row_step=104, data=data)
    back, sample = pointcloud2_to_numpy(msg)
    np.testing.assert_array_equal(back, points.reshape(-1, 3))
    assert sample is None


def test_pointcloud_malformed():
    msg = points_to_pointcloud2(np.zeros((4, 3)))
    msg.data = bytes(msg.data)[:-1]
    with pytest.raises(ConversionError, match="data has 47 bytes; expected row_step 48"):
        pointcloud2_to_numpy(msg)
    no_z = points_to_pointcloud2(np.zeros((4, 3)))
    no_z.fields = no_z.fields[:2]
    with pytest.raises(ConversionError, match="no 'z' field"):
        pointcloud2_to_numpy(no_z)
    with pytest.raises(ConversionError, match=r"points must have shape \(M, 3\)"):
        points_to_pointcloud2(np.zeros((4, 2)))
    with pytest.raises(ConversionError, match=r"sample must have shape \(4,\)"):
        points_to_pointcloud2(np.zeros((4, 3)), sample=np.zeros(3, int))


def test_pose_round_trip():
    angle = 0.7
    matrix = np.eye(4)
    matrix[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    matrix[:3, 3] = [0.1, -0.2, 0.8]
    pose = matrix_to_pose(matrix)
    assert np.isclose(pose.orientation.w, np.cos(angle / 2)) and np.isclose(pose.orientation.z, np.sin(angle / 2))
    np.testing.assert_allclose(pose_to_matrix(pose), matrix, atol=1e-12)
    with pytest.raises(ConversionError, match="finite 4x4"):
        matrix_to_pose(np.eye(3))


def test_grasp_markers_draw_each_gripper_in_its_pose_coloured_by_score():
    from visualization_msgs.msg import Marker

    from pssnet_core.grasps import GripperConfig
    from pssnet_ros.completion_io import grasp_markers, score_colour

    header = Header(frame_id="camera_depth_optical_frame")
    assert [m.action for m in grasp_markers([], [], [], header, GripperConfig()).markers] == [Marker.DELETEALL]
    gripper = GripperConfig(finger_length=0.04)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # approach (+z) turned onto -y
    pose[:3, 3] = [0.1, 0.2, 0.6]
    markers = grasp_markers([matrix_to_pose(pose)], [0.25], [0.06], header, gripper).markers
    assert [m.action for m in markers] == [Marker.DELETEALL, Marker.ADD] and markers[1].header == header
    points = np.array([[p.x, p.y, p.z] for p in markers[1].points])
    # first finger: from the fingertip at y = -0.03 (closing axis, turned onto z) back 4 cm against the approach
    np.testing.assert_allclose(points[0], [0.1, 0.2, 0.6 - 0.03], atol=1e-9)
    np.testing.assert_allclose(points[1], [0.1, 0.2 + 0.04, 0.6 - 0.03], atol=1e-9)
    assert (score_colour(0.0).r, score_colour(0.0).g) == (1.0, 0.0)
    assert (score_colour(1.0).r, score_colour(1.0).g) == (0.0, 1.0)
    assert markers[1].color == score_colour(0.25) and score_colour(0.25).r == 1.0 and score_colour(0.25).g == 0.5
