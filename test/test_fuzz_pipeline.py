"""Property-based fuzzing of the pipeline's input checks (pssnet_core.pipeline.CompletionPipeline, Hypothesis).

Starting from a real view (a rendered mug, cropped to 160x192 px so that an example takes milliseconds), every
input is mutated the way broken drivers and hostile callers do: depth scaled to the wrong unit, negative, NaN,
inf or 1e38 in patches, the wrong dtype or shape; masks empty, full, shifted, speckled, of another size;
intrinsics of any positive magnitude; num_samples out of range; an up vector along the optical axis. The
property: ``run`` either returns completions of the requested count, made of finite voxel centres, from an
input that meets every documented precondition, or raises PipelineInputError; never another exception. The
same holds one level up, for the messages the node receives (conversions, then the pipeline): the result, or
ConversionError or PipelineInputError, the two errors the node turns into ``success: false``.

Profiles ("ci": derandomized and short, the default; "fuzz": many random examples) are in test/conftest.py.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import CameraInfo, Image
from test_node_helpers import render_mug_scene, tiny_checkpoint

from pssnet_core.data.scenes import RenderedView
from pssnet_core.geometry import CameraIntrinsics, CameraLimits, GridPose, Observation, carve_free_space
from pssnet_core.inference import CompletionResult
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig, PipelineInputError, PipelineResult
from pssnet_ros.conversions import (
    ConversionError,
    camera_info_to_intrinsics,
    depth_to_metres,
    intrinsics_to_camera_info,
    mask_to_numpy,
    matrix_to_pose,
    numpy_to_image,
    points_to_pointcloud2,
)

#: the window of the 640x480 mug view that holds the mug with a margin: rows, columns
CROP = (slice(144, 336), slice(240, 400))
LIMITS = CameraLimits()


class KnownOccupiedCompleter:
    """Stand-in model, fast and exact: every sample is the observation's known-occupied grid."""

    def __init__(self) -> None:
        self.grid_size = 32
        self.model_name = "known_occupied"
        self.info: dict[str, object] = {}

    def complete(self, observation: Observation, num_samples: int, seed: int, box_temperature: float | None = None
                 ) -> CompletionResult:
        occupancy = np.repeat(observation.known_occupied[None], num_samples, axis=0)
        return CompletionResult(occupancy.astype(np.float32), occupancy, self.grid_size, seed, self.model_name, 0.0)


@cache
def cropped_view() -> tuple[RenderedView, np.ndarray, np.ndarray, CameraIntrinsics]:
    """The mug view, and its depth, mask and intrinsics cropped to :data:`CROP` (rendered once per session)."""
    view = render_mug_scene(seed=0)
    rows, cols = CROP
    k = view.intrinsics
    intrinsics = CameraIntrinsics(width=cols.stop - cols.start, height=rows.stop - rows.start, fx=k.fx, fy=k.fy,
                                  cx=k.cx - cols.start, cy=k.cy - rows.start)
    return view, view.depth[CROP].copy(), view.mask[CROP].copy(), intrinsics


def pipeline_for(up: tuple[float, float, float], estimate_up: bool) -> CompletionPipeline:
    return CompletionPipeline(KnownOccupiedCompleter(), PipelineConfig(num_samples=3, max_num_samples=8,
                                                                       up_vector=up, estimate_up=estimate_up))


# ---------------------------------------------------------------------------------------------- strategies
special_depths = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -1.0, 1e38, 1e-30, 0.05, 6.0])
#: wrong units (mm read as m, m read as mm), mirrored, slightly off
depth_factors = st.one_of(st.sampled_from([1000.0, 0.001, 10.0, 0.1, -1.0, 1.0]), st.floats(0.01, 100.0))


@st.composite
def rectangles(draw: st.DrawFn, shape: tuple[int, int]) -> tuple[slice, slice]:
    top, left = draw(st.integers(0, shape[0] - 1)), draw(st.integers(0, shape[1] - 1))
    return slice(top, draw(st.integers(top + 1, shape[0]))), slice(left, draw(st.integers(left + 1, shape[1])))


@st.composite
def mutated_depths(draw: st.DrawFn, depth: np.ndarray) -> np.ndarray:
    """The view's depth with zero or more corruptions of its values, then maybe of its dtype and shape."""
    depth = depth.copy()
    # "keep" weighs the draw towards inputs that still complete, so that both outcomes are exercised.
    kinds = ["keep", "keep", "keep", "scale", "patch", "noise", "all"]
    for kind in draw(st.lists(st.sampled_from(kinds), max_size=2)):
        if kind == "keep":
            continue
        if kind == "scale":
            with np.errstate(over="ignore"):
                depth = (depth * draw(depth_factors)).astype(depth.dtype)
        elif kind == "patch":
            depth[draw(rectangles(depth.shape[:2]))] = draw(special_depths)
        elif kind == "noise":
            rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
            sigma = draw(st.one_of(st.floats(1e-4, 3e-3), st.floats(1e-4, 1.0)))  # sensor noise, or garbage
            depth = (depth + rng.normal(0.0, sigma, depth.shape)).astype(depth.dtype)
        else:
            depth = np.full_like(depth, draw(special_depths))
    with np.errstate(invalid="ignore", over="ignore"):
        depth = depth.astype(draw(st.sampled_from([np.float32] * 6 + [np.float16, np.float64, np.int32, np.uint16,
                                                                      bool])))
    return draw(st.sampled_from([depth] * 8 + [depth[1:], depth[:, :-1], depth.T, depth[..., None], depth[0]]))


@st.composite
def mutated_masks(draw: st.DrawFn, mask: np.ndarray) -> np.ndarray:
    """The view's mask with zero or more corruptions of its values, then maybe of its dtype and shape."""
    mask = mask.copy()
    kinds = ["keep", "keep", "keep", "empty", "full", "shift", "speckle", "few"]
    for kind in draw(st.lists(st.sampled_from(kinds), max_size=2)):
        if kind == "keep":
            continue
        if kind == "empty":
            mask = np.zeros_like(mask)
        elif kind == "full":
            mask = np.ones_like(mask)
        elif kind == "shift":
            shift = st.one_of(st.integers(-3, 3), st.integers(-100, 100))
            mask = np.roll(mask, (draw(shift), draw(shift)), axis=(0, 1))
        elif kind == "speckle":
            rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
            mask = (rng.random(mask.shape) < draw(st.floats(0.0, 1.0))).astype(mask.dtype)
        elif kind == "few":
            keep = np.flatnonzero(mask)[:draw(st.integers(0, 80))]
            mask = np.zeros_like(mask)
            mask.flat[keep] = 1
    mask = mask.astype(draw(st.sampled_from([np.uint8, bool, np.float32, np.int64])))
    return draw(st.sampled_from([mask] * 8 + [mask[1:], mask[:, :-1], mask.T, mask[..., None]]))


#: positive finite values of any magnitude (zero, negative, NaN and inf cannot make a CameraIntrinsics at all)
positive_values = st.one_of(st.floats(1e-300, 1e300), st.floats(1.0, 2000.0), st.floats(-50.0, 300.0))


@st.composite
def mutated_intrinsics(draw: st.DrawFn, intrinsics: CameraIntrinsics) -> CameraIntrinsics:
    values = {"width": intrinsics.width, "height": intrinsics.height, "fx": intrinsics.fx, "fy": intrinsics.fy,
              "cx": intrinsics.cx, "cy": intrinsics.cy}
    for name in draw(st.lists(st.sampled_from(sorted(values) + ["keep"] * 6), max_size=2, unique=True)):
        if name == "keep":
            continue
        if name in ("width", "height"):
            values[name] = draw(st.integers(1, 400))
        elif name in ("fx", "fy"):
            values[name] = draw(positive_values.filter(lambda v: v > 0))
        else:
            values[name] = draw(positive_values)
    return CameraIntrinsics(**values)


def unit_vector(azimuth: float, elevation: float) -> tuple[float, float, float]:
    return (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))


#: the view's true up, a level camera's, along the optical axis (no horizontal viewing direction), any direction
up_vectors = st.one_of(st.just("view"), st.sampled_from([(0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.1, 1.0)]),
                       st.builds(unit_vector, st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2)))
num_samples = st.one_of(st.none(), st.integers(-3, 12))
#: grasp planning takes ~25x the rest of a run: one example in four plans grasps
compute_grasps = st.sampled_from([False, False, False, True])


# ---------------------------------------------------------------------------------------------- properties
def refusal_kind(error: Exception) -> str:
    """The first words of a refusal, so that Hypothesis' statistics show which checks the examples reach."""
    return " ".join(str(error).split()[:3])


def assert_meets_the_documented_preconditions(depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
                                              config: PipelineConfig) -> None:
    """What the pipeline's docstrings promise about any input it accepts (computed here, not by its checks)."""
    assert np.issubdtype(depth.dtype, np.floating), f"accepted depth of dtype {depth.dtype}"
    assert depth.shape == mask.shape == (intrinsics.height, intrinsics.width)
    assert np.count_nonzero(mask) >= config.min_mask_pixels
    usable = np.isfinite(depth) & (depth >= config.min_depth) & (depth <= config.max_depth) & (mask != 0)
    assert np.count_nonzero(usable) >= config.min_valid_points
    for focal, size in ((intrinsics.fx, intrinsics.width), (intrinsics.fy, intrinsics.height)):
        fov = math.degrees(2.0 * math.atan(size / (2.0 * focal)))
        assert LIMITS.min_fov_deg <= fov <= LIMITS.max_fov_deg, f"accepted a field of view of {fov} deg"
    assert max(intrinsics.fx / intrinsics.fy, intrinsics.fy / intrinsics.fx) <= LIMITS.max_pixel_aspect
    assert 0 <= intrinsics.cx <= intrinsics.width and 0 <= intrinsics.cy <= intrinsics.height


def assert_a_sound_result(result: PipelineResult, requested: int | None, config: PipelineConfig,
                          compute_grasps: bool) -> None:
    assert result.num_samples == (requested or config.num_samples)
    assert len(result.known_occupied) > 0 and np.all(np.isfinite(result.known_occupied))
    for completion in result.completions:
        assert completion.dtype == np.float32 and completion.ndim == 2 and completion.shape[1] == 3
        assert np.all(np.isfinite(completion))
    assert (result.grasps is not None) == compute_grasps


def run_or_refuse(pipeline: CompletionPipeline, depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
                  requested: int | None, grasps: bool) -> PipelineResult | PipelineInputError:
    """The result, or the PipelineInputError raised; any other exception fails the test."""
    try:
        result = pipeline.run(depth, mask, intrinsics, requested, grasps)
    except PipelineInputError as error:
        assert str(error), "a refusal must say what is wrong"
        event(f"refused: {refusal_kind(error)}")
        return error
    event("completed")
    return result


@given(data=st.data(), up=up_vectors, estimate_up=st.booleans(), requested=num_samples, grasps=compute_grasps)
def test_any_input_completes_or_raises_pipeline_input_error(data: st.DataObject,
                                                            up: str | tuple[float, float, float], estimate_up: bool,
                                                            requested: int | None, grasps: bool):
    view, depth, mask, intrinsics = cropped_view()
    pipeline = pipeline_for(tuple(view.up) if up == "view" else up, estimate_up)
    depth = data.draw(mutated_depths(depth), label="depth")
    mask = data.draw(mutated_masks(mask), label="mask")
    intrinsics = data.draw(mutated_intrinsics(intrinsics), label="intrinsics")
    result = run_or_refuse(pipeline, depth, mask, intrinsics, requested, grasps)
    if isinstance(result, PipelineInputError):
        return
    assert_meets_the_documented_preconditions(depth, mask, intrinsics, pipeline.config)
    assert requested is None or 0 <= requested <= pipeline.config.max_num_samples
    assert_a_sound_result(result, requested, pipeline.config, grasps)


@st.composite
def transforms(draw: st.DrawFn) -> np.ndarray:
    """A camera pose as a client might send it: rigid (any rotation, near or far), or broken (NaN, scaled,
    mirrored, of the wrong shape)."""
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_rotvec(draw(st.tuples(*[st.floats(-3.2, 3.2)] * 3))).as_matrix()
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = draw(st.tuples(*[st.one_of(st.floats(-1.0, 1.0), st.sampled_from([0.0, 1e6, -1e6]))] * 3))
    kind = draw(st.sampled_from(["rigid"] * 4 + ["nan", "scaled", "mirrored", "shape"]))
    if kind == "nan":
        matrix[draw(st.integers(0, 3)), draw(st.integers(0, 3))] = math.nan
    elif kind == "scaled":
        matrix[:3, :3] *= draw(st.floats(0.1, 10.0).filter(lambda f: abs(f - 1.0) > 1e-3))
    elif kind == "mirrored":
        matrix[:3, 2] *= -1.0
    elif kind == "shape":
        matrix = matrix[:3]
    return matrix


@given(data=st.data(), grasps=compute_grasps)
def test_any_further_view_or_candidate_place_completes_or_raises_pipeline_input_error(data: st.DataObject,
                                                                                      grasps: bool):
    """A second look as a client may send it: the view from behind (or a mutated one), at any pose, and candidate
    places anywhere (behind the object, at the camera, far away, broken)."""
    from pssnet_core.pipeline import MoreView

    view, depth, mask, intrinsics = cropped_view()
    pipeline = pipeline_for(tuple(view.up), False)
    more = MoreView(data.draw(mutated_depths(depth), label="second depth"),
                    data.draw(mutated_masks(mask), label="second mask"),
                    data.draw(mutated_intrinsics(intrinsics), label="second intrinsics"),
                    data.draw(transforms(), label="second pose"))
    candidates = data.draw(st.lists(transforms(), max_size=3), label="candidate views")
    try:
        result = pipeline.run(depth, mask, intrinsics, None, grasps, more_views=(more,), candidate_views=candidates)
    except PipelineInputError as error:
        assert str(error)
        event(f"refused: {refusal_kind(error)}")
        return
    event("completed")
    assert_a_sound_result(result, None, pipeline.config, grasps)
    assert len(result.observation.views) == 2 and len(result.view_scores) == len(candidates)
    assert np.all((result.view_scores >= 0.0) & (result.view_scores <= 1.0))


@pytest.fixture(scope="module")
def tiny_model_pipeline(tmp_path_factory: pytest.TempPathFactory) -> CompletionPipeline:
    view, *_ = cropped_view()
    path = tiny_checkpoint(tmp_path_factory.mktemp("fuzz") / "tiny.pt")
    return CompletionPipeline.from_checkpoint(path, PipelineConfig(num_samples=2, max_num_samples=4,
                                                                   up_vector=tuple(view.up)), threads=1)


# A real network is ~10x slower per example than the stand-in: a quarter of the profile's examples.
@settings(max_examples=max(10, settings.default.max_examples // 4))
@given(data=st.data(), requested=st.one_of(st.none(), st.integers(-1, 6)))
def test_real_model_completes_or_raises_pipeline_input_error(tiny_model_pipeline: CompletionPipeline,
                                                             data: st.DataObject, requested: int | None):
    _, depth, mask, intrinsics = cropped_view()
    depth = data.draw(mutated_depths(depth), label="depth")
    mask = data.draw(mutated_masks(mask), label="mask")
    result = run_or_refuse(tiny_model_pipeline, depth, mask, intrinsics, requested, False)
    if not isinstance(result, PipelineInputError):
        assert_meets_the_documented_preconditions(depth, mask, intrinsics, tiny_model_pipeline.config)
        assert_a_sound_result(result, requested, tiny_model_pipeline.config, False)


# ------------------------------------------------------------------------------------ the node's messages
@st.composite
def depth_messages(draw: st.DrawFn, depth: np.ndarray) -> Image:
    """A corrupted depth array as the node receives it: 32FC1 metres, or 16UC1/mono16 at some scale."""
    encoding = draw(st.sampled_from(["32FC1", "16UC1", "mono16"]))
    depth = draw(mutated_depths(depth))
    if depth.ndim != 2:
        depth = depth.reshape(depth.shape[0], -1)
    if encoding != "32FC1":  # a driver's integer units, saturated like one
        with np.errstate(invalid="ignore", over="ignore"):
            depth = np.nan_to_num(depth.astype(np.float64) * 1000.0, nan=0.0, posinf=0.0, neginf=0.0)
        depth = np.clip(np.rint(depth), 0, 65535)
    return numpy_to_image(depth, encoding, is_bigendian=draw(st.booleans()))


@st.composite
def mask_messages(draw: st.DrawFn, mask: np.ndarray) -> Image:
    mask = draw(mutated_masks(mask))
    if mask.ndim != 2:
        mask = mask.reshape(mask.shape[0], -1)
    return numpy_to_image(mask.astype(bool), draw(st.sampled_from(["mono8", "8UC1"] * 3 + ["16UC1"])))


@st.composite
def camera_info_messages(draw: st.DrawFn, intrinsics: CameraIntrinsics) -> CameraInfo:
    """The view's CameraInfo with up to three K/P entries set to any float (zero, NaN, inf, huge included)."""
    msg = intrinsics_to_camera_info(intrinsics)
    changes = st.lists(st.tuples(st.sampled_from(["k", "p"]), st.integers(0, 8)), max_size=3)
    for matrix, index in draw(st.one_of(st.just([]), changes)):
        getattr(msg, matrix)[index] = draw(st.one_of(st.floats(), st.floats(-1e3, 1e3)))
    return msg


@given(data=st.data(), depth_scale=st.sampled_from([0.001] * 4 + [0.0001, 1.0]), requested=num_samples,
       grasps=compute_grasps)
def test_any_message_set_completes_or_is_refused_with_a_reason(data: st.DataObject, depth_scale: float,
                                                               requested: int | None, grasps: bool):
    """The node's path, without the node: conversions, then the pipeline, then the output conversions."""
    view, depth, mask, intrinsics = cropped_view()
    pipeline = pipeline_for(tuple(view.up), False)
    depth_msg = data.draw(depth_messages(depth), label="depth")
    mask_msg = data.draw(mask_messages(mask), label="mask")
    info_msg = data.draw(camera_info_messages(intrinsics), label="camera_info")
    try:
        result = pipeline.run(depth_to_metres(depth_msg, depth_scale), mask_to_numpy(mask_msg),
                              camera_info_to_intrinsics(info_msg), requested, grasps)
    except (ConversionError, PipelineInputError) as error:
        assert str(error)
        event(f"refused: {type(error).__name__}: {refusal_kind(error)}")
        return
    event("completed")
    assert_a_sound_result(result, requested, pipeline.config, grasps)
    points, index = result.merged()
    assert points_to_pointcloud2(points, sample=index).width == len(points)
    for pose in result.grasps.poses if result.grasps is not None else ():
        matrix_to_pose(pose)  # every grasp pose is a rigid transform the node can publish


def test_free_space_lookup_is_exact_on_images_beyond_2_24_pixels():
    """Regression: the pixel index v * width + u was computed in float32, which above 2**24 pixels (e.g. 4200 x 4200)
    rounds to a neighbouring pixel, and for the last pixel to one past the image: an IndexError, not an answer."""
    width = height = 4200
    intrinsics = CameraIntrinsics(width=width, height=height, fx=3500.0, fy=3500.0, cx=2099.5, cy=2099.5)
    voxel = 0.00625
    # A grid aligned with the camera whose first voxel centre lies 1 m out on the ray of the last pixel.
    corner = intrinsics.backproject(np.array([width - 1.0]), np.array([height - 1.0]), np.array([1.0]))[0]
    pose = GridPose(rotation=np.eye(3), origin=corner - 0.5 * voxel, voxel_size=voxel, size=4)
    depth = np.full((height, width), 2.0, dtype=np.float32)
    free = carve_free_space(depth, np.ones(depth.shape, dtype=bool), intrinsics, pose)
    assert free[0, 0, 0], "the voxel in front of the last pixel's reading is free"
