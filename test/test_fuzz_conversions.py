"""Property-based fuzzing of every message <-> numpy conversion in pssnet_ros.conversions (Hypothesis).

The property, for arbitrary messages (any encoding, size, step, data length, byte order; any K, D, R, P; any
PointCloud2 fields, offsets, steps and data; any pose): the conversion either returns a correct result or raises
ConversionError, never another exception type. Images and point clouds convert exactly when they follow the
documented rules, to exactly what their bytes say; every CameraInfo accepted obeys README's rules for
calibrations that real cameras have. Where an inverse exists, the round trip is exact. The expectations are
computed independently of the code under test: pixel by pixel and point by point with ``struct``, and the camera
rules written out again here.

Profiles ("ci": derandomized and short, the default; "fuzz": many random examples) are in test/conftest.py:
    HYPOTHESIS_PROFILE=fuzz .venv/bin/pytest -q test/test_fuzz_conversions.py
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from geometry_msgs.msg import Pose
from hypothesis import event, given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

from pssnet_core.geometry import CameraIntrinsics, CameraLimits
from pssnet_ros.conversions import (
    DEPTH_ENCODINGS,
    IMAGE_ENCODINGS,
    MASK_ENCODINGS,
    UINT32_MAX,
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

#: encodings a camera driver might send that the node does not read, next to the ones it does
FOREIGN_ENCODINGS = ("", "rgb8", "bgr8", "32FC2", "16SC1", "64FC1", "mono8 ", "MONO8", "8uc1", "32fc1")
#: struct format letter of each numpy base type used by the encodings (the independent decoder)
STRUCT_CODES = {"f4": "f", "u2": "H", "u1": "B", "i1": "b", "i2": "h", "i4": "i", "u4": "I", "f8": "d"}
#: message bodies are capped so that every example decodes in microseconds; sizes above it are still drawn,
#: with data of the wrong length
MAX_DATA = 2048

uint32s = st.integers(0, UINT32_MAX)
#: mostly small sizes that can carry data, sometimes the extremes of the uint32 fields
dimensions = st.one_of(st.integers(0, 12), st.sampled_from([2**16, 2**31 - 1, UINT32_MAX]))
any_floats = st.floats(allow_nan=True, allow_infinity=True)


def outcome(convert: Callable[[], Any]) -> Any:
    """The conversion's result, or the ConversionError it raised; any other exception fails the test.

    Both outcomes are counted as Hypothesis events (``--hypothesis-show-statistics`` shows how often each is drawn).
    """
    try:
        result = convert()
    except ConversionError as error:
        assert str(error), "a ConversionError must say what is wrong"
        event("refused")
        return error
    event("converted")
    return result


def same_values(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal shapes, dtypes and values, NaN equal to NaN."""
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.all((a == b) | (np.isnan(a) & np.isnan(b))
                                                                      if a.dtype.kind == "f" else a == b))


# ------------------------------------------------------------------------------------------------ Image
@st.composite
def data_of_length_near(draw: st.DrawFn, expected: int) -> bytes:
    """Bytes of exactly ``expected`` length, a few bytes short or long, or of any small length."""
    if expected <= MAX_DATA:
        length = draw(st.one_of(st.just(expected), st.integers(max(expected - 8, 0), expected + 8),
                                st.integers(0, MAX_DATA)))
    else:
        length = draw(st.integers(0, MAX_DATA))
    return draw(st.binary(min_size=length, max_size=length))


def corruptions(draw: st.DrawFn, kinds: list[str]) -> list[str]:
    """Up to two of ``kinds``; as likely none at all, so that well-formed messages are drawn about as often."""
    return draw(st.lists(st.sampled_from(kinds + ["keep"] * len(kinds)), max_size=2))


@st.composite
def image_messages(draw: st.DrawFn) -> Image:
    """Images of any encoding, size, step, byte order and data length: a well-formed one, maybe corrupted."""
    encoding = draw(st.sampled_from(tuple(IMAGE_ENCODINGS)))
    height, width = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    step = width * np.dtype(IMAGE_ENCODINGS[encoding][0]).itemsize + draw(st.integers(0, 9))
    msg = Image(height=height, width=width, encoding=encoding, is_bigendian=draw(st.integers(0, 255)), step=step,
                data=draw(st.binary(min_size=step * height, max_size=step * height)))
    for kind in corruptions(draw, ["encoding", "height", "width", "step", "data"]):
        if kind == "encoding":
            msg.encoding = draw(st.sampled_from(tuple(IMAGE_ENCODINGS) + FOREIGN_ENCODINGS))
        elif kind in ("height", "width", "step"):
            setattr(msg, kind, draw(st.one_of(dimensions, uint32s)))
        elif kind == "data":
            msg.data = draw(data_of_length_near(msg.step * msg.height))
    return msg


def image_is_well_formed(msg: Image, allowed: tuple[str, ...]) -> bool:
    """The documented rules of image_to_numpy."""
    if msg.encoding not in allowed or msg.height == 0 or msg.width == 0:
        return False
    row = msg.width * np.dtype(IMAGE_ENCODINGS[msg.encoding][0]).itemsize
    return msg.step >= row and len(msg.data) == msg.step * msg.height


def decode_pixel_by_pixel(msg: Image) -> np.ndarray:
    """The image's values read one pixel at a time with ``struct`` (the expected result)."""
    base, _ = IMAGE_ENCODINGS[msg.encoding]
    code = (">" if msg.is_bigendian else "<") + STRUCT_CODES[base]
    size = struct.calcsize(code)
    data = bytes(msg.data)
    return np.array([[struct.unpack_from(code, data, row * msg.step + col * size)[0] for col in range(msg.width)]
                     for row in range(msg.height)], dtype=np.dtype(base))


@given(msg=image_messages(), allowed=st.sampled_from([None, DEPTH_ENCODINGS, MASK_ENCODINGS]))
def test_any_image_decodes_to_its_bytes_or_raises_conversion_error(msg: Image, allowed: tuple[str, ...] | None):
    result = outcome(lambda: image_to_numpy(msg, allowed))
    if not image_is_well_formed(msg, allowed or tuple(IMAGE_ENCODINGS)):
        assert isinstance(result, ConversionError), f"accepted a malformed image: {msg.encoding} " \
            f"{msg.width}x{msg.height} step {msg.step} with {len(msg.data)} bytes"
        return
    assert not isinstance(result, ConversionError), f"refused a well-formed image: {result}"
    assert result.dtype.isnative and result.flags.c_contiguous
    assert same_values(result, decode_pixel_by_pixel(msg))


@given(msg=image_messages(), depth_scale=st.one_of(st.floats(1e-6, 10.0), any_floats))
def test_any_depth_image_gives_float32_metres_or_raises_conversion_error(msg: Image, depth_scale: float):
    result = outcome(lambda: depth_to_metres(msg, depth_scale))
    if not (0 < depth_scale < math.inf and image_is_well_formed(msg, DEPTH_ENCODINGS)):
        assert isinstance(result, ConversionError)
        return
    if isinstance(result, ConversionError) and "is_bigendian" in str(result):
        # The byte-order check may refuse bytes that read as depth only in the other order, never both orders.
        flipped = Image(height=msg.height, width=msg.width, encoding=msg.encoding, step=msg.step, data=msg.data,
                        is_bigendian=int(not msg.is_bigendian))
        assert not isinstance(outcome(lambda: depth_to_metres(flipped, depth_scale)), ConversionError), str(result)
        return
    assert not isinstance(result, ConversionError), f"refused a well-formed depth image: {result}"
    raw = decode_pixel_by_pixel(msg)
    expected = raw if raw.dtype == np.float32 else raw.astype(np.float32) * np.float32(depth_scale)
    assert same_values(result, expected)


@given(msg=image_messages())
def test_any_mask_image_gives_the_non_zero_pixels_or_raises_conversion_error(msg: Image):
    result = outcome(lambda: mask_to_numpy(msg))
    if not image_is_well_formed(msg, MASK_ENCODINGS):
        assert isinstance(result, ConversionError)
        return
    assert not isinstance(result, ConversionError), f"refused a well-formed mask: {result}"
    np.testing.assert_array_equal(result, decode_pixel_by_pixel(msg) != 0)
    assert result.dtype == bool


image_shapes = hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=16)


@given(data=st.data(), encoding=st.sampled_from(tuple(IMAGE_ENCODINGS)), bigendian=st.booleans(),
       padding=st.integers(0, 9))
def test_numpy_to_image_round_trips_bit_for_bit(data: st.DataObject, encoding: str, bigendian: bool, padding: int):
    """Arrays of the encoding's own type (NaN payloads, infinities, subnormals included) come back unchanged."""
    dtype = np.dtype(IMAGE_ENCODINGS[encoding][0])
    array = data.draw(hnp.arrays(dtype, image_shapes), label="array")
    msg = numpy_to_image(array, encoding, is_bigendian=bigendian, step=array.shape[1] * dtype.itemsize + padding)
    back = image_to_numpy(msg)
    assert back.dtype == dtype and back.shape == array.shape
    assert back.tobytes() == array.tobytes()


@given(mask=hnp.arrays(bool, image_shapes), encoding=st.sampled_from(MASK_ENCODINGS), bigendian=st.booleans())
def test_bool_masks_round_trip(mask: np.ndarray, encoding: str, bigendian: bool):
    np.testing.assert_array_equal(mask_to_numpy(numpy_to_image(mask, encoding, is_bigendian=bigendian)), mask)


# Values cast to a narrower encoding type (NaN or 1e300 to uint8) are documented casts: numpy warns.
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@given(array=hnp.arrays(st.sampled_from([np.uint8, np.uint16, np.float32, np.float64, bool]),
                        hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5)),
       encoding=st.sampled_from(tuple(IMAGE_ENCODINGS) + FOREIGN_ENCODINGS),
       step=st.one_of(st.none(), st.integers(-4, 40), st.integers(UINT32_MAX + 1, 2**64)))
def test_numpy_to_image_encodes_or_raises_conversion_error(array: np.ndarray, encoding: str, step: int | None):
    """Wrong encodings, shapes and steps are refused; everything else encodes to a message that decodes."""
    result = outcome(lambda: numpy_to_image(array, encoding, step=step))
    itemsize = np.dtype(IMAGE_ENCODINGS[encoding][0]).itemsize if encoding in IMAGE_ENCODINGS else 0
    row = array.shape[1] * itemsize if array.ndim == 2 else 0
    encodable = (encoding in IMAGE_ENCODINGS and array.ndim == 2
                 and (step is None or row <= step <= UINT32_MAX))
    assert isinstance(result, ConversionError) != encodable
    if encodable:
        assert len(result.data) == result.step * result.height
        assert result.step == (row if step is None else step)


def test_absurd_step_is_refused_before_anything_is_allocated():
    """Regression (found by the fuzz suite): step 2**32 used to allocate 4 GiB per row, then fail on the field."""
    with pytest.raises(ConversionError, match=r"does not fit the uint32 fields of sensor_msgs/Image"):
        numpy_to_image(np.zeros((1, 1), np.uint8), "mono8", step=2**32)


def test_infinite_depth_scale_is_refused():
    """Regression: an infinite depth_scale turned every 0 of a 16-bit image into NaN instead of an error."""
    with pytest.raises(ConversionError, match=r"depth_scale must be positive and finite, got inf"):
        depth_to_metres(numpy_to_image(np.zeros((2, 2), np.uint16), "16UC1"), math.inf)


# ------------------------------------------------------------------------------------------- CameraInfo
LIMITS = CameraLimits()


@st.composite
def real_intrinsics(draw: st.DrawFn) -> CameraIntrinsics:
    """Intrinsics of cameras that exist: any focal length, fields of view of 2-150 degrees (the image size
    follows from them), near-square pixels, the principal point anywhere in the image."""
    fx = draw(st.floats(10.0, 20_000.0))
    fy = fx * draw(st.floats(0.6, 1.6))

    def size_for(focal: float) -> int:  # whole pixels keep the field of view well inside 1-160 degrees
        return max(1, round(2.0 * focal * math.tan(math.radians(draw(st.floats(2.0, 150.0))) / 2.0)))

    width, height = size_for(fx), size_for(fy)
    return CameraIntrinsics(width=width, height=height, fx=fx, fy=fy, cx=draw(st.floats(0.0, width)),
                            cy=draw(st.floats(0.0, height)))


#: a value that replaces a calibration entry: anything (NaN, inf, 1e308, subnormals), or a plausible number
replacement_values = st.one_of(any_floats, st.floats(-1e4, 1e4))


@st.composite
def camera_info_messages(draw: st.DrawFn) -> CameraInfo:
    """A real calibration (K, maybe a rectifying R, P = [K | 0], P of another focal length or none, no or some
    distortion), maybe corrupted: other image sizes, entries of K, R, P or D replaced by any float, whole
    matrices of noise or zeros."""
    camera = draw(real_intrinsics())
    k = camera.matrix().reshape(-1)
    r = draw(st.sampled_from([np.eye(3), np.zeros((3, 3)), "rotation"]))  # zeros: R not given
    if isinstance(r, str):
        r = Rotation.from_rotvec(draw(st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3))).as_matrix()
    p = draw(st.sampled_from(["k", "none", "rectified"]))
    if p == "rectified":  # the rectified image's camera, another focal length (refused without D and R)
        rectified = replace(camera, fx=camera.fx * draw(st.floats(0.8, 1.25)),
                            fy=camera.fy * draw(st.floats(0.8, 1.25)))
        p = np.hstack([rectified.matrix(), np.zeros((3, 1))])
    else:
        p = np.hstack([camera.matrix(), np.zeros((3, 1))]) if p == "k" else np.zeros((3, 4))
    d = draw(st.sampled_from([[], [0.0] * 5, [0.05, -0.1, 0.0, 0.0, 0.01]]))
    msg = CameraInfo(width=camera.width, height=camera.height, distortion_model="plumb_bob", d=d, k=k.tolist(),
                     r=r.reshape(-1).tolist(), p=p.reshape(-1).tolist())
    for kind in corruptions(draw, ["size", "k", "r", "p", "d", "noise", "zeros"]):
        if kind == "size":
            msg.width, msg.height = draw(dimensions), draw(dimensions)
        elif kind in ("k", "r", "p"):
            values = getattr(msg, kind)
            for index in draw(st.lists(st.integers(0, len(values) - 1), min_size=1, max_size=3)):
                values[index] = draw(replacement_values)
        elif kind == "d":
            msg.d = draw(st.lists(replacement_values, max_size=8))
        else:
            matrix = draw(st.sampled_from(["k", "r", "p"]))
            size = len(getattr(msg, matrix))
            setattr(msg, matrix, [0.0] * size if kind == "zeros" else draw(st.lists(any_floats, min_size=size,
                                                                                      max_size=size)))
    return msg


def assert_a_real_camera(msg: CameraInfo, intrinsics: CameraIntrinsics) -> None:
    """Every rule of README's "calibrations no real camera has", checked on an accepted CameraInfo."""
    k, r, p, d = (np.asarray(v, dtype=np.float64) for v in (msg.k, msg.r, msg.p, msg.d))
    assert (intrinsics.width, intrinsics.height) == (msg.width, msg.height) and msg.width > 0 and msg.height > 0
    # P's intrinsics (the rectified image's, as image_geometry) where P is given, else K's.
    used = p.reshape(3, 4)[:, :3].reshape(-1) if np.any(p) else k
    assert (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy) == (used[0], used[4], used[2], used[5])
    assert np.all(np.isfinite(k)) and intrinsics.fx > 0 and intrinsics.fy > 0
    for matrix in (k.reshape(3, 3), p.reshape(3, 4)[:, :3]) if np.any(p) else (k.reshape(3, 3),):
        fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
        for focal, size in ((fx, msg.width), (fy, msg.height)):
            fov = math.degrees(2.0 * math.atan(size / (2.0 * focal)))
            assert LIMITS.min_fov_deg <= fov <= LIMITS.max_fov_deg, f"field of view {fov} deg accepted"
        assert max(fx / fy, fy / fx) <= LIMITS.max_pixel_aspect
        assert 0.0 <= cx <= msg.width and 0.0 <= cy <= msg.height, "principal point outside the image accepted"
        assert np.abs(matrix[1:] - [[0.0, fy, cy], [0.0, 0.0, 1.0]]).max() <= LIMITS.matrix_tolerance
    for matrix in (k, used):
        rows = max(matrix[5], msg.height - matrix[5])
        assert abs(matrix[1]) * rows / matrix[4] <= LIMITS.max_skew_shift_px + 1e-9, "a shearing skew accepted"
    rotated = False
    if np.any(r):
        rotation = r.reshape(3, 3)
        assert np.all(np.isfinite(rotation)) and np.linalg.det(rotation) > 0
        assert np.abs(rotation @ rotation.T - np.eye(3)).max() <= LIMITS.matrix_tolerance, "R not a rotation"
        rotated = np.abs(rotation - np.eye(3)).max() > LIMITS.matrix_tolerance
    if np.any(p):
        assert np.all(np.isfinite(p)) and abs(p[11]) <= LIMITS.matrix_tolerance
        if not rotated and not np.any(d):  # unrectified image: P describes the same camera as K
            rel = LIMITS.projection_tolerance
            for of_p, of_k, scale in ((p[0], k[0], k[0]), (p[5], k[4], k[4]), (p[2], k[2], msg.width),
                                      (p[6], k[5], msg.height)):
                assert abs(of_p - of_k) <= rel * scale, "P that disagrees with K accepted"


# R or P of 1e308 overflows while it is checked (and is refused): numpy's warning is expected, not a finding.
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@given(msg=camera_info_messages())
def test_any_camera_info_gives_a_real_camera_or_raises_conversion_error(msg: CameraInfo):
    result = outcome(lambda: camera_info_to_intrinsics(msg))
    if not isinstance(result, ConversionError):
        assert_a_real_camera(msg, result)


@given(camera=real_intrinsics())
def test_real_cameras_round_trip_through_camera_info(camera: CameraIntrinsics):
    assert camera_info_to_intrinsics(intrinsics_to_camera_info(camera)) == camera


# ------------------------------------------------------------------------------------------- PointCloud2
POINTFIELD_TYPES = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2", PointField.UINT16: "u2",
                    PointField.INT32: "i4", PointField.UINT32: "u4", PointField.FLOAT32: "f4",
                    PointField.FLOAT64: "f8"}
FLOAT_FIELDS = (PointField.FLOAT32, PointField.FLOAT64)
INTEGER_FIELDS = (PointField.INT8, PointField.UINT8, PointField.INT16, PointField.UINT16, PointField.INT32,
                  PointField.UINT32)
#: datatype 0 and 9..255 are not PointField types
datatypes = st.one_of(st.sampled_from(sorted(POINTFIELD_TYPES)), st.integers(0, 255))


@st.composite
def pointcloud_messages(draw: st.DrawFn) -> PointCloud2:
    """A well-formed cloud of any layout (x, y, z, maybe sample and other fields, in any order, with padding inside
    points and rows, either byte order), maybe corrupted: fields moved, retyped, dropped or duplicated, steps,
    sizes or data length changed."""
    names = draw(st.permutations(["x", "y", "z", "sample", "intensity"]))
    fields, offset = [], 0
    for name in names[:draw(st.integers(3, 5))]:
        datatype = draw(st.sampled_from(FLOAT_FIELDS if name in ("x", "y", "z") else INTEGER_FIELDS + FLOAT_FIELDS))
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=1))
        offset += np.dtype(POINTFIELD_TYPES[datatype]).itemsize + draw(st.integers(0, 3))
    point_step = offset + draw(st.integers(0, 8))
    height, width = draw(st.integers(0, 6)), draw(st.integers(0, 6))
    row_step = point_step * width + draw(st.integers(0, 8))
    msg = PointCloud2(height=height, width=width, fields=fields, is_bigendian=draw(st.booleans()),
                      point_step=point_step, row_step=row_step, is_dense=draw(st.booleans()),
                      data=draw(st.binary(min_size=row_step * height, max_size=row_step * height)))
    for kind in corruptions(draw, ["move", "retype", "drop", "add", "point_step", "row_step", "size", "data"]):
        if kind in ("move", "retype"):
            field = msg.fields[draw(st.integers(0, len(msg.fields) - 1))]
            if kind == "move":
                field.offset = draw(st.one_of(st.integers(0, offset + 8), uint32s))
            else:
                field.datatype = draw(datatypes)
        elif kind == "drop" and msg.fields:
            msg.fields = [f for i, f in enumerate(msg.fields) if i != draw(st.integers(0, len(msg.fields) - 1))]
        elif kind == "add":  # duplicate and empty names included
            msg.fields = list(msg.fields) + [PointField(name=draw(st.sampled_from(["", "x", "sample", "rgb"])),
                                                        offset=draw(st.integers(0, 64)), datatype=draw(datatypes),
                                                        count=draw(st.integers(0, 3)))]
        elif kind in ("point_step", "row_step"):
            setattr(msg, kind, draw(st.one_of(st.integers(0, 64), uint32s)))
        elif kind == "size":
            msg.height, msg.width = draw(dimensions), draw(dimensions)
        elif kind == "data":
            msg.data = draw(data_of_length_near(msg.row_step * msg.height))
    return msg


def pointcloud_is_well_formed(msg: PointCloud2) -> bool:
    """The documented rules of pointcloud2_to_numpy (the last of several fields with one name is the one read)."""
    by_name = {field.name: field for field in msg.fields}
    if any(axis not in by_name or by_name[axis].datatype not in FLOAT_FIELDS for axis in "xyz"):
        return False
    if "sample" in by_name and by_name["sample"].datatype not in INTEGER_FIELDS:
        return False
    for name in ("x", "y", "z", "sample"):
        if name in by_name:
            field = by_name[name]
            if field.offset + np.dtype(POINTFIELD_TYPES[field.datatype]).itemsize > msg.point_step:
                return False
    return msg.row_step >= msg.point_step * msg.width and len(msg.data) == msg.row_step * msg.height


def read_point_by_point(msg: PointCloud2, name: str) -> list[float | int]:
    """Field ``name`` of every point, read one at a time with ``struct`` (the expected result)."""
    field = {f.name: f for f in msg.fields}[name]
    code = (">" if msg.is_bigendian else "<") + STRUCT_CODES[POINTFIELD_TYPES[field.datatype]]
    data = bytes(msg.data)
    return [struct.unpack_from(code, data, row * msg.row_step + col * msg.point_step + field.offset)[0]
            for row in range(msg.height) for col in range(msg.width)]


@given(msg=pointcloud_messages())
def test_any_pointcloud_reads_its_points_or_raises_conversion_error(msg: PointCloud2):
    result = outcome(lambda: pointcloud2_to_numpy(msg))
    if not pointcloud_is_well_formed(msg):
        assert isinstance(result, ConversionError), "accepted a malformed point cloud"
        return
    assert not isinstance(result, ConversionError), f"refused a well-formed point cloud: {result}"
    points, sample = result
    assert points.shape == (msg.height * msg.width, 3) and points.dtype == np.float64
    expected = np.array([read_point_by_point(msg, axis) for axis in "xyz"], dtype=np.float64).T.reshape(-1, 3)
    assert same_values(points, expected)
    if not any(f.name == "sample" for f in msg.fields):
        assert sample is None
    else:
        assert sample.dtype == np.int64 and sample.tolist() == read_point_by_point(msg, "sample")


@given(points=hnp.arrays(np.float32, st.tuples(st.integers(0, 40), st.just(3))),
       sample=st.one_of(st.none(), st.lists(st.integers(0, UINT32_MAX), min_size=40, max_size=40)))
def test_points_round_trip_through_pointcloud2(points: np.ndarray, sample: list[int] | None):
    """float32 points (any value) and uint32 sample indices come back unchanged."""
    index = None if sample is None else np.array(sample[:len(points)], dtype=np.int64)
    back, back_index = pointcloud2_to_numpy(points_to_pointcloud2(points, sample=index))
    assert same_values(back, points.astype(np.float64))
    if index is None:
        assert back_index is None
    else:
        np.testing.assert_array_equal(back_index, index)


#: (M, 3) as often as any other shape
point_shapes = st.one_of(st.tuples(st.integers(0, 4), st.just(3)),
                         hnp.array_shapes(min_dims=1, max_dims=3, min_side=0, max_side=4))
sample_shapes = st.one_of(st.tuples(st.integers(0, 4)),
                          hnp.array_shapes(min_dims=1, max_dims=2, min_side=0, max_side=4))


# float64 points beyond float32's range become inf in the message's float32 fields: numpy warns.
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
@given(points=hnp.arrays(st.sampled_from([np.float32, np.float64, np.int64, np.complex64, "U2", bool]), point_shapes),
       sample=st.one_of(st.none(), hnp.arrays(st.sampled_from([np.int64, np.float64, np.uint64]), sample_shapes)))
def test_points_to_pointcloud2_encodes_or_raises_conversion_error(points: np.ndarray, sample: np.ndarray | None):
    result = outcome(lambda: points_to_pointcloud2(points, sample=sample))
    if isinstance(result, ConversionError):
        return
    assert points.ndim == 2 and points.shape[1] == 3 and points.dtype.kind in "iuf"
    assert result.width == len(points) and len(result.data) == result.row_step
    if sample is not None:  # an empty index of any dtype (np.array([]) is float64) has nothing to check
        assert sample.shape == (len(points),)
        assert not len(sample) or (sample.dtype.kind in "iu" and 0 <= sample.min() <= sample.max() <= UINT32_MAX)


def test_pointcloud_with_a_point_numpy_cannot_describe_is_refused():
    """Regression (found by the fuzz suite): point_step >= 2**31 raised numpy's "won't fit into a C int"."""
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    empty = PointCloud2(height=3, width=0, fields=fields, point_step=2**31, row_step=0, data=b"")
    points, sample = pointcloud2_to_numpy(empty)
    assert points.shape == (0, 3) and sample is None
    huge = PointCloud2(height=0, width=1, fields=fields, point_step=2**31, row_step=2**31, data=b"")
    assert pointcloud2_to_numpy(huge)[0].shape == (0, 3)


def test_float_sample_field_and_out_of_range_indices_are_refused():
    """Regression (found by the fuzz suite): a float `sample` field gave NaN -> arbitrary integers, and indices
    beyond uint32 wrapped around silently when written."""
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in
              enumerate(["x", "y", "z", "sample"])]
    data = np.array([0.0, 0.0, 0.0, np.nan], dtype="<f4").tobytes()
    msg = PointCloud2(height=1, width=1, fields=fields, point_step=16, row_step=16, data=data)
    with pytest.raises(ConversionError, match=r"field 'sample' must be an integer type, got datatype 7"):
        pointcloud2_to_numpy(msg)
    with pytest.raises(ConversionError, match=r"sample indices must be integers in \[0, 4294967295\]"):
        points_to_pointcloud2(np.zeros((1, 3)), sample=np.array([2**32 + 5]))
    with pytest.raises(ConversionError, match=r"points must be real numbers, got dtype complex128"):
        points_to_pointcloud2(np.ones((2, 3), complex))


# -------------------------------------------------------------------------------------------------- Pose
@st.composite
def rigid_transforms(draw: st.DrawFn) -> np.ndarray:
    """4x4 rigid transforms: any rotation, translations up to a kilometre."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_rotvec(draw(st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3))).as_matrix()
    matrix[:3, 3] = draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
    return matrix


@st.composite
def nearly_rigid_transforms(draw: st.DrawFn) -> np.ndarray:
    """A rigid transform with one entry nudged by anything from 1e-9 (still rigid) to a reflection's worth."""
    matrix = draw(rigid_transforms())
    row, col = draw(st.integers(0, 3)), draw(st.integers(0, 3))
    matrix[row, col] += draw(st.sampled_from([1e-9, 1e-7, 1e-5, 1e-3, 0.1, -2.0]))
    return matrix


@given(matrix=st.one_of(rigid_transforms(), nearly_rigid_transforms(),
                        hnp.arrays(np.float64, (4, 4), elements=any_floats),
                        hnp.arrays(np.float64, hnp.array_shapes(max_dims=3, max_side=5), elements=st.floats(-2, 2))))
def test_any_matrix_gives_a_unit_quaternion_pose_or_raises_conversion_error(matrix: np.ndarray):
    result = outcome(lambda: matrix_to_pose(matrix))
    if isinstance(result, ConversionError):
        return
    rotation = matrix[:3, :3]
    assert np.abs(rotation @ rotation.T - np.eye(3)).max() <= 1e-5 and np.linalg.det(rotation) > 0
    q = np.array([result.orientation.x, result.orientation.y, result.orientation.z, result.orientation.w])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-9
    np.testing.assert_allclose(pose_to_matrix(result), matrix, atol=1e-4)


@given(values=st.lists(any_floats, min_size=7, max_size=7))
def test_any_pose_gives_a_rigid_transform_or_raises_conversion_error(values: list[float]):
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = values[:3]
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = values[3:]
    result = outcome(lambda: pose_to_matrix(pose))
    if isinstance(result, ConversionError):
        return
    rotation = result[:3, :3]
    assert np.all(np.isfinite(result)) and np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(rotation), 1.0) and result[:3, 3].tolist() == values[:3]


@given(rotvec=st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3),
       translation=st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))
def test_rigid_transforms_round_trip_through_pose(rotvec: list[float], translation: list[float]):
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    matrix[:3, 3] = translation
    np.testing.assert_allclose(pose_to_matrix(matrix_to_pose(matrix)), matrix, atol=1e-9)


def test_reflections_and_overflowing_quaternions_are_refused():
    """Regression (found by the fuzz suite): a reflection raised scipy's ValueError, and a quaternion of 1e200
    gave an all-zero rotation."""
    with pytest.raises(ConversionError, match=r"pose rotation is not a rotation matrix .* det -1"):
        matrix_to_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ConversionError, match=r"pose rotation is not a rotation matrix"):
        matrix_to_pose(np.diag([2.0, 2.0, 2.0, 1.0]))
    pose = Pose()
    pose.orientation.x, pose.orientation.w = 1e200, 0.0
    np.testing.assert_allclose(pose_to_matrix(pose)[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
