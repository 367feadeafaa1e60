"""sensor_msgs <-> numpy without cv_bridge or sensor_msgs_py (neither exists as a wheel).

Images: 32FC1 (metres), 16UC1 (millimetres, or any unit through ``depth_scale``), mono8 and 8UC1, in either
byte order (``is_bigendian``) and with row padding (``step`` larger than ``width * bytes_per_pixel``). A depth
image whose data contradict its byte-order flag is refused (:func:`byte_order_mismatch`).
Point clouds: (M, 3) points plus an optional per-point ``sample`` index, as x, y, z float32 (+ uint32
``sample``), and back from any PointCloud2 that has float32/float64 x, y, z fields.

Every malformed message raises :class:`ConversionError` with a message that says what is wrong (the property
that test/test_fuzz_conversions.py checks on arbitrary messages).
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Pose
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from pssnet_core.geometry import CameraIntrinsics, ObservationError, check_camera_model


class ConversionError(ValueError):
    """A ROS message cannot be converted: wrong encoding, size, data length or fields."""


#: encoding -> (numpy dtype without byte order, channels)
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    "32FC1": ("f4", 1),
    "16UC1": ("u2", 1),
    "mono16": ("u2", 1),
    "mono8": ("u1", 1),
    "8UC1": ("u1", 1),
}
DEPTH_ENCODINGS: tuple[str, ...] = ("32FC1", "16UC1", "mono16")
MASK_ENCODINGS: tuple[str, ...] = ("mono8", "8UC1")
#: largest value of the uint32 size fields of Image and PointCloud2 (height, width, step, row_step, ...)
UINT32_MAX = 2**32 - 1
#: numpy cannot build a record type larger than this, so no PointCloud2 point may be
MAX_POINT_STEP = 2**31 - 1
#: how far R R^T of a pose may differ from the identity (float32 poses from other nodes pass)
ROTATION_TOLERANCE = 1e-5
#: depths (metres) a 32FC1 reading can have: what the byte-order check counts as readable
PLAUSIBLE_METRES = (1e-3, 1e3)
#: fewest readings (or neighbouring pairs) on which the byte-order check decides
MIN_BYTE_ORDER_EVIDENCE = 16

_POINTFIELD_DTYPES: dict[int, str] = {
    PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2", PointField.UINT16: "u2",
    PointField.INT32: "i4", PointField.UINT32: "u4", PointField.FLOAT32: "f4", PointField.FLOAT64: "f8",
}
_INTEGER_POINTFIELDS = (PointField.INT8, PointField.UINT8, PointField.INT16, PointField.UINT16, PointField.INT32,
                        PointField.UINT32)


def image_to_numpy(msg: Image, allowed: tuple[str, ...] | None = None, name: str = "image") -> np.ndarray:
    """Decodes a single-channel Image into an (H, W) array in native byte order (a copy, never a view).

    Args:
        msg: the image.
        allowed: encodings accepted here (default: every encoding in :data:`IMAGE_ENCODINGS`).
        name: what the image is, for error messages ("depth", "mask").

    Raises:
        ConversionError: unknown or disallowed encoding, zero size, step too small, or wrong data length.
    """
    allowed = allowed or tuple(IMAGE_ENCODINGS)
    encoding = msg.encoding
    if encoding not in allowed or encoding not in IMAGE_ENCODINGS:
        raise ConversionError(f"{name} has encoding {encoding!r}; supported: {', '.join(allowed)}")
    height, width = int(msg.height), int(msg.width)
    if height == 0 or width == 0:
        raise ConversionError(f"{name} is empty ({width}x{height})")
    base, channels = IMAGE_ENCODINGS[encoding]
    dtype = np.dtype(base).newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = width * channels * dtype.itemsize
    step = int(msg.step)
    if step < row_bytes:
        raise ConversionError(f"{name} step {step} is smaller than width * bytes per pixel = {row_bytes} "
                              f"({width} x {encoding})")
    data = msg.data
    expected = step * height
    if len(data) != expected:
        raise ConversionError(f"{name} data has {len(data)} bytes; {width}x{height} {encoding} with step "
                              f"{step} needs {expected}")
    raw = np.frombuffer(memoryview(data), dtype=np.uint8).reshape(height, step)[:, :row_bytes]
    # ascontiguousarray drops the row padding; astype to the native order copies and swaps bytes if needed.
    return np.ascontiguousarray(raw).view(dtype).reshape(height, width).astype(dtype.newbyteorder("="))


def byte_order_mismatch(depth: np.ndarray) -> str:
    """Why ``depth`` (decoded in the byte order its message claims) reads right only in the other order, or "".

    A real camera's depth is plausible in its own byte order and garbage in the other, so a wrong
    ``is_bigendian`` flag shows without knowing the scene:

    - 32FC1: of the readings (non-zero, not NaN in either order), fewer than half are metres in
      [``PLAUSIBLE_METRES``] while at least 90 % are in the other order;
    - 16-bit: depth is smooth, so neighbouring readings differ in their low byte; read in the wrong order that
      difference lands in the high byte. Refused when the median difference of neighbouring unequal readings is
      more than 16x smaller in the other order.

    The rule never refuses both orders of the same bytes, and decides nothing on fewer than
    ``MIN_BYTE_ORDER_EVIDENCE`` readings (or pairs).
    """
    swapped = depth.byteswap()  # what the same bytes read in the other order
    if depth.dtype.kind == "f":
        with np.errstate(invalid="ignore"):
            readings = (depth != 0) & ~np.isnan(depth) & ~np.isnan(swapped)
            if readings.sum() < MIN_BYTE_ORDER_EVIDENCE:
                return ""
            low, high = PLAUSIBLE_METRES
            share = float(((depth[readings] >= low) & (depth[readings] <= high)).mean())
            other = float(((swapped[readings] >= low) & (swapped[readings] <= high)).mean())
        if share < 0.5 and other >= 0.9:
            return (f"{share:.0%} of its readings are depths in [{low:g}, {high:g}] m as flagged, {other:.0%} in the "
                    "other byte order")
        return ""
    left, right = depth[:, :-1].astype(np.int64), depth[:, 1:].astype(np.int64)
    pairs = (left != 0) & (right != 0) & (left != right)
    if pairs.sum() < MIN_BYTE_ORDER_EVIDENCE:
        return ""
    step = float(np.median(np.abs(left - right)[pairs]))
    other = float(np.median(np.abs(swapped[:, :-1].astype(np.int64) - swapped[:, 1:].astype(np.int64))[pairs]))
    if other * 16 < step:
        return (f"neighbouring readings differ by {step:g} units (median) as flagged, by {other:g} in the other "
                "byte order")
    return ""


def depth_to_metres(msg: Image, depth_scale: float = 0.001) -> np.ndarray:
    """Depth image -> (H, W) float32 metres; 0 or NaN stays "no reading".

    Args:
        msg: 32FC1 (metres) or 16UC1/mono16 (integer units).
        depth_scale: metres per unit of a 16-bit image (0.001 for millimetres).

    Raises:
        ConversionError: besides the malformed images of :func:`image_to_numpy`, a byte-order flag that
            contradicts the data (:func:`byte_order_mismatch`): such depth would be garbage.
    """
    if not 0 < depth_scale < float("inf"):
        raise ConversionError(f"depth_scale must be positive and finite, got {depth_scale}")
    depth = image_to_numpy(msg, DEPTH_ENCODINGS, "depth")
    if reason := byte_order_mismatch(depth):
        order = "big" if msg.is_bigendian else "little"
        raise ConversionError(f"depth is flagged {order}-endian (is_bigendian={int(bool(msg.is_bigendian))}) but "
                              f"reads as the other byte order: {reason}; fix the publisher's is_bigendian")
    if depth.dtype == np.float32:
        return depth
    return depth.astype(np.float32) * np.float32(depth_scale)


def mask_to_numpy(msg: Image) -> np.ndarray:
    """Mask image (mono8/8UC1) -> (H, W) bool, non-zero = target object."""
    return image_to_numpy(msg, MASK_ENCODINGS, "mask") != 0


def numpy_to_image(array: np.ndarray, encoding: str, header: Header | None = None, *,
                   is_bigendian: bool = False, step: int | None = None) -> Image:
    """Encodes an (H, W) array as an Image.

    Args:
        array: values; cast to the encoding's type (bool masks become 0/255 for mono8/8UC1).
        encoding: one of :data:`IMAGE_ENCODINGS`.
        header: stamp and frame (default: empty).
        is_bigendian: byte order of the data written.
        step: row length in bytes (default: no padding); larger values pad each row with zeros.

    Raises:
        ConversionError: unknown encoding, an array that is not 2-D, or a step below the row size or beyond
            what the message's uint32 field holds.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(f"cannot encode {encoding!r}; supported: {', '.join(IMAGE_ENCODINGS)}")
    array = np.asarray(array)
    if array.ndim != 2:
        raise ConversionError(f"image array must be 2-D, got shape {array.shape}")
    base, _ = IMAGE_ENCODINGS[encoding]
    if array.dtype == bool:
        array = array.astype(np.uint8) * 255
    dtype = np.dtype(base).newbyteorder(">" if is_bigendian else "<")
    height, width = array.shape
    row_bytes = width * dtype.itemsize
    step = row_bytes if step is None else int(step)
    if step < row_bytes:
        raise ConversionError(f"step {step} is smaller than the row size {row_bytes}")
    # Checked before allocating: an absurd step would otherwise allocate step * height bytes first.
    if max(step, height, width) > UINT32_MAX:
        raise ConversionError(f"image of {width}x{height} with step {step} does not fit the uint32 fields of "
                              "sensor_msgs/Image")
    buffer = np.zeros((height, step), dtype=np.uint8)
    buffer[:, :row_bytes] = np.ascontiguousarray(array.astype(dtype)).view(np.uint8).reshape(height, row_bytes)
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width, msg.encoding = height, width, encoding
    msg.is_bigendian = int(is_bigendian)
    msg.step = step
    msg.data = buffer.tobytes()
    return msg


def camera_info_to_intrinsics(msg: CameraInfo) -> CameraIntrinsics:
    """CameraInfo -> pinhole intrinsics of the rectified image, refusing calibrations no real camera has.

    As image_geometry's PinholeCameraModel: P's fx, fy, cx, cy when P is given (the camera matrix of the
    rectified image, image_rect), K's when P is all zero. The checks (field of view, principal point, skew,
    R a rotation, P equal to K where D is zero and R the identity) and the rule are the ROS-free
    :func:`pssnet_core.geometry.check_camera_model`. Binning and ROI are not applied: an image whose size
    differs from the CameraInfo's is refused where the two meet (:func:`pssnet_core.geometry.validate_depth_and_mask`).

    Raises:
        ConversionError: zero image size, an all-zero K, or an implausible calibration (the message names the
            value).
    """
    if int(msg.width) == 0 or int(msg.height) == 0:
        raise ConversionError(f"camera_info has image size {msg.width}x{msg.height} (uncalibrated camera?)")
    k = np.asarray(msg.k, dtype=np.float64)
    if k.shape != (9,) or not np.any(k):
        raise ConversionError("camera_info K matrix is all zeros (uncalibrated camera?)")
    try:
        return check_camera_model(int(msg.width), int(msg.height), k, msg.d, msg.r, msg.p)
    except ObservationError as error:
        raise ConversionError(f"camera_info: {error}") from error


def intrinsics_to_camera_info(intrinsics: CameraIntrinsics, header: Header | None = None) -> CameraInfo:
    """Pinhole intrinsics -> CameraInfo (no distortion, P = [K | 0])."""
    msg = CameraInfo()
    if header is not None:
        msg.header = header
    msg.width, msg.height = intrinsics.width, intrinsics.height
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    k = intrinsics.matrix()
    msg.k = k.reshape(-1).tolist()
    msg.r = np.eye(3).reshape(-1).tolist()
    msg.p = np.hstack([k, np.zeros((3, 1))]).reshape(-1).tolist()
    return msg


def points_to_pointcloud2(points: np.ndarray, header: Header | None = None,
                          sample: np.ndarray | None = None) -> PointCloud2:
    """(M, 3) points (+ optional (M,) per-point sample index) -> unorganised PointCloud2.

    Fields: x, y, z float32 at offsets 0, 4, 8 and, when ``sample`` is given, ``sample`` uint32 at 12.

    Raises:
        ConversionError: points that are not an (M, 3) array of real numbers, or sample indices that are not
            integers in the uint32 range.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ConversionError(f"points must have shape (M, 3), got {points.shape}")
    # Complex numbers would lose their imaginary part without a word, strings fail inside numpy.
    if not (np.issubdtype(points.dtype, np.integer) or np.issubdtype(points.dtype, np.floating)):
        raise ConversionError(f"points must be real numbers, got dtype {points.dtype}")
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    names, formats = ["x", "y", "z"], ["<f4", "<f4", "<f4"]
    if sample is not None:
        sample = np.asarray(sample)
        if sample.shape != (len(points),):
            raise ConversionError(f"sample must have shape ({len(points)},), got {sample.shape}")
        # Beyond the uint32 range an index would wrap around silently when written.
        if len(sample) and (not np.issubdtype(sample.dtype, np.integer) or sample.min() < 0
                            or sample.max() > UINT32_MAX):
            raise ConversionError(f"sample indices must be integers in [0, {UINT32_MAX}]")
        fields.append(PointField(name="sample", offset=12, datatype=PointField.UINT32, count=1))
        names.append("sample")
        formats.append("<u4")
    record = np.dtype({"names": names, "formats": formats})
    data = np.empty(len(points), dtype=record)
    for i, n in enumerate("xyz"):
        data[n] = points[:, i]
    if sample is not None:
        data["sample"] = sample
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = 1, len(points)
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = record.itemsize
    msg.row_step = record.itemsize * len(points)
    msg.is_dense = bool(np.all(np.isfinite(points))) if len(points) else True
    msg.data = data.tobytes()
    return msg


def pointcloud2_to_numpy(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray | None]:
    """PointCloud2 -> ((M, 3) float64 points, (M,) int64 ``sample`` index or None when the field is absent).

    Reads any layout (field offsets, padding in ``point_step``/``row_step``, either byte order) as long as
    x, y, z are float32 or float64 and ``sample``, when present, is an integer type. When several fields share a
    name, the last one is read.

    Raises:
        ConversionError: missing x/y/z, unsupported field type, or a data length that does not match.
    """
    order = ">" if msg.is_bigendian else "<"
    by_name = {f.name: f for f in msg.fields}
    for axis in "xyz":
        if axis not in by_name:
            raise ConversionError(f"point cloud has no {axis!r} field (fields: {sorted(by_name)})")
        if by_name[axis].datatype not in (PointField.FLOAT32, PointField.FLOAT64):
            raise ConversionError(f"point cloud field {axis!r} must be float32 or float64")
    wanted = [n for n in ("x", "y", "z", "sample") if n in by_name]
    # A float index would turn NaN or 1e30 into an arbitrary integer.
    if "sample" in by_name and by_name["sample"].datatype not in _INTEGER_POINTFIELDS:
        raise ConversionError(f"point cloud field 'sample' must be an integer type, got datatype "
                              f"{by_name['sample'].datatype}")
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    height, width = int(msg.height), int(msg.width)
    for n in wanted:
        end = by_name[n].offset + np.dtype(_POINTFIELD_DTYPES[by_name[n].datatype]).itemsize
        if end > point_step:
            raise ConversionError(f"point cloud field {n!r} ends at byte {end}, beyond point_step {point_step}")
    if row_step < point_step * width:
        raise ConversionError(f"point cloud row_step {row_step} < point_step {point_step} x width {width}")
    if len(msg.data) != row_step * height:
        raise ConversionError(f"point cloud data has {len(msg.data)} bytes; expected row_step {row_step} x "
                              f"height {height} = {row_step * height}")
    if height * width == 0:
        return np.zeros((0, 3)), (np.zeros(0, dtype=np.int64) if "sample" in by_name else None)
    if point_step > MAX_POINT_STEP:
        raise ConversionError(f"point cloud point_step {point_step} is beyond the {MAX_POINT_STEP} bytes a point can "
                              "have here")
    record = np.dtype({"names": wanted,
                       "formats": [order + _POINTFIELD_DTYPES[by_name[n].datatype] for n in wanted],
                       "offsets": [by_name[n].offset for n in wanted], "itemsize": point_step})
    raw = np.frombuffer(memoryview(msg.data), dtype=np.uint8).reshape(height, row_step)[:, :point_step * width]
    cloud = np.ascontiguousarray(raw).view(record).reshape(-1)
    points = np.stack([cloud[a].astype(np.float64) for a in "xyz"], axis=1)
    sample = cloud["sample"].astype(np.int64) if "sample" in by_name else None
    return points, sample


def matrix_to_pose(matrix: np.ndarray) -> Pose:
    """4x4 rigid transform -> geometry_msgs/Pose (position + unit quaternion).

    Raises:
        ConversionError: not a finite 4x4 matrix, its bottom row is not [0, 0, 0, 1], or its upper-left 3x3 block
            is not a rotation.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ConversionError(f"pose must be a finite 4x4 matrix, got shape {matrix.shape}")
    if np.abs(matrix[3] - [0.0, 0.0, 0.0, 1.0]).max() > ROTATION_TOLERANCE:
        raise ConversionError(f"pose bottom row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    # scipy would raise its own error on a reflection and quietly orthonormalise a scaled or sheared block.
    rotation = matrix[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
        determinant = float(np.linalg.det(rotation))
    if not (error <= ROTATION_TOLERANCE and determinant > 0):
        raise ConversionError(f"pose rotation is not a rotation matrix (R R^T differs from I by {error:.3g}, det "
                              f"{determinant:.3g})")
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in matrix[:3, 3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in (x, y, z, w))
    return pose


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 rigid transform.

    Raises:
        ConversionError: a position that is not finite, or a quaternion that is not finite or (almost) zero.
    """
    position = np.array([pose.position.x, pose.position.y, pose.position.z])
    if not np.all(np.isfinite(position)):
        raise ConversionError(f"pose position must be finite, got {position.tolist()}")
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
    if not np.all(np.isfinite(q)):
        raise ConversionError(f"pose orientation is not a valid quaternion: {q.tolist()}")
    # Scaled to a largest entry of 1 first: scipy's own normalisation overflows from about 1e154 and then
    # returns an all-zero "rotation".
    largest = float(np.abs(q).max())
    if largest == 0.0 or np.linalg.norm(q / largest) < 1e-9 / largest:
        raise ConversionError(f"pose orientation is not a valid quaternion: {q.tolist()}")
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(q / largest).as_matrix()
    matrix[:3, 3] = position
    return matrix
