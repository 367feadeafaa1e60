"""The ROS-free pipeline the node calls: geometry of the outputs, input errors, seeds, support-plane up vector."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from test_node_helpers import render_mug_scene, tiny_checkpoint

from pssnet_core.geometry import (
    CameraIntrinsics,
    CameraLimits,
    GridConfig,
    ObservationError,
    check_camera_model,
    check_intrinsics,
)
from pssnet_core.inference import CompletionResult
from pssnet_core.pipeline import (
    STEP_GRASPS,
    STEP_NETWORK,
    CompletionPipeline,
    PipelineConfig,
    PipelineInputError,
    RunCancelled,
)
from pssnet_core.support_plane import fit_support_plane


class EchoCompleter:
    """Stand-in model: every sample is the known-occupied grid (to check the coordinate plumbing exactly)."""

    def __init__(self, grid_size: int = 32, voxel_size: float | None = None) -> None:
        self.grid_size = grid_size
        self.model_name = "echo"
        self.info = {"voxel_size": voxel_size} if voxel_size else {}
        self.calls: list[tuple[int, int]] = []
        self.box_temperatures: list[float | None] = []

    def complete(self, observation, num_samples: int, seed: int, box_temperature: float | None = None
                 ) -> CompletionResult:
        self.calls.append((num_samples, seed))
        self.box_temperatures.append(box_temperature)
        occupancy = np.repeat(observation.known_occupied[None], num_samples, axis=0)
        return CompletionResult(occupancy.astype(np.float32), occupancy, self.grid_size, seed, "echo", 0.0)


@pytest.fixture(scope="module")
def scene():
    return render_mug_scene(seed=0)


@pytest.fixture(scope="module")
def tiny_pipeline(tmp_path_factory):
    path = tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")
    return CompletionPipeline.from_checkpoint(path, PipelineConfig(num_samples=4), threads=1)


def test_outputs_are_voxel_centres_around_the_observed_points(scene):
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(num_samples=3, up_vector=tuple(scene.up)))
    result = pipeline.run(scene.depth, scene.mask, scene.intrinsics)
    assert result.num_samples == 3 and result.voxel_size == GridConfig().voxel_size
    observed = result.observation.points
    half_diagonal = 0.5 * np.sqrt(3) * result.voxel_size
    for centres in [result.known_occupied, *result.completions]:
        assert centres.dtype == np.float32 and centres.shape[1] == 3
        distance, _ = cKDTree(centres).query(observed)
        assert distance.max() <= half_diagonal + 1e-6  # every observed point lies in one of the voxels
    points, index = result.merged()
    assert len(points) == 3 * len(result.known_occupied) and set(index.tolist()) == {0, 1, 2}
    assert set(result.timings) == {"observe", "network", "views", "centres", "grasps", "total"}


def test_should_stop_is_told_each_step_and_ends_the_run_there(scene):
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(num_samples=3, up_vector=tuple(scene.up)))
    for step in (STEP_NETWORK, STEP_GRASPS):
        told: list[str] = []

        def should_stop(next_step: str, stop_at: str = step, told: list[str] = told) -> bool:
            told.append(next_step)
            return next_step == stop_at

        with pytest.raises(RunCancelled, match=f"stopped before the {step}"):
            pipeline.run(scene.depth, scene.mask, scene.intrinsics, should_stop=should_stop)
        assert told == [STEP_NETWORK, STEP_GRASPS][:len(told)] and told[-1] == step
    told = []
    result = pipeline.run(scene.depth, scene.mask, scene.intrinsics, should_stop=lambda s: told.append(s) or False)
    assert result.num_samples == 3 and result.grasps is not None and told == [STEP_NETWORK, STEP_GRASPS]
    told = []
    pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False,
                 should_stop=lambda s: told.append(s) or False)
    assert told == [STEP_NETWORK]


def test_real_model_seeds_and_sample_counts(tiny_pipeline, scene):
    # The posterior sampler's samples of one seed are a prefix of each other; the checked sampler's are not (its
    # proposals and selection depend on the number asked for) but repeat exactly for the same request.
    tiny_pipeline.config = tiny_pipeline.with_config(up_vector=tuple(scene.up), sampler="checked")
    checked = [tiny_pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False) for _ in range(2)]
    np.testing.assert_array_equal(checked[0].occupancy, checked[1].occupancy)
    np.testing.assert_array_equal(checked[0].weights, checked[1].weights)
    tiny_pipeline.config = tiny_pipeline.with_config(sampler="posterior")
    a = tiny_pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False)
    assert a.num_samples == 4 and a.occupancy.shape == (4, 32, 32, 32) and a.seed == 0
    b = tiny_pipeline.run(scene.depth, scene.mask, scene.intrinsics, num_samples=2, compute_grasps=False)
    assert b.num_samples == 2
    np.testing.assert_array_equal(a.occupancy[:2], b.occupancy)  # same seed, same first samples
    tiny_pipeline.config = tiny_pipeline.with_config(seed=-1)
    c = tiny_pipeline.run(scene.depth, scene.mask, scene.intrinsics, num_samples=2, compute_grasps=False)
    d = tiny_pipeline.run(scene.depth, scene.mask, scene.intrinsics, num_samples=2, compute_grasps=False)
    assert c.seed != d.seed
    tiny_pipeline.config = tiny_pipeline.with_config(seed=0, sampler=PipelineConfig().sampler)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_precision_setting_reaches_the_completer(tmp_path, precision):
    path = tiny_checkpoint(tmp_path / "tiny.pt")
    pipeline = CompletionPipeline.from_checkpoint(path, threads=1, precision=precision)
    assert pipeline.completer.precision == precision
    with pytest.raises(ValueError, match="precision must be one of"):
        CompletionPipeline.from_checkpoint(path, threads=1, precision="fast")


def bad_inputs(scene):
    depth, mask, intr = scene.depth, scene.mask, scene.intrinsics
    tiny_mask = np.zeros_like(mask)
    tiny_mask[200:203, 300:303] = 255
    nan_depth = depth.copy()
    nan_depth[mask > 0] = np.nan
    zero_depth = np.where(mask > 0, 0.0, depth).astype(np.float32)
    holes = np.flatnonzero(mask > 0)[np.arange((mask > 0).sum()) % 5 != 0]  # 4 in 5 masked pixels without a reading
    sparse_depth = depth.copy()
    sparse_depth.reshape(-1)[holes] = 0.0
    return [
        ("empty mask", (depth, np.zeros_like(mask), intr, None),
         r"mask is empty: 0 pixels marked, need at least 50 \(min_mask_pixels\)"),
        ("tiny mask", (depth, tiny_mask, intr, None), "mask is too small: 9 pixels marked, need at least 50"),
        ("size mismatch", (depth, mask[:, :320], intr, None), "mask is 320x480 but depth is 640x480"),
        ("camera size", (depth, mask, CameraIntrinsics.kinect_like(320, 240), None),
         "depth is 640x480 but camera_info says 320x240"),
        ("nan depth", (nan_depth, mask, intr, None), r"depth has no finite reading inside the mask \(all NaN/Inf\)"),
        ("no valid depth", (zero_depth, mask, intr, None),
         r"only 0 of \d+ masked pixels have a valid depth in \[0.1, 5.0\] m \(need at least 20\)"),
        ("few valid depths", (sparse_depth, mask, intr, None),
         r"only \d+ of the \d+ masked pixels \(20%\) have a depth in \[0.1, 5.0\] m; need 25% \(min_valid_fraction\)"),
        ("absurd samples", (depth, mask, intr, 4_000_000_000),
         r"num_samples 4000000000 is out of range: ask for 1..100 \(max_num_samples\)"),
        ("integer depth", (depth.astype(np.uint16), mask, intr, None), "depth must be float metres, got dtype uint16"),
    ]


def test_bad_input_raises_exact_messages(scene):
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(up_vector=tuple(scene.up)))
    for name, (depth, mask, intr, n), message in bad_inputs(scene):
        with pytest.raises(PipelineInputError) as info:
            pipeline.run(depth, mask, intr, num_samples=n)
        assert re.search(message, str(info.value)), f"{name}: {info.value}"
    looking_down = PipelineConfig(up_vector=(0.0, 0.0, -1.0))
    pipeline.config = looking_down
    with pytest.raises(ValueError, match=r"up_vector must be 3 finite numbers of length 1e-06 to 1e\+06, got \[1e"):
        PipelineConfig(up_vector=(1e200, 1e200, 0.0))  # finite, but its length overflows: it would normalise to 0
    with pytest.raises(PipelineInputError, match="camera looks .almost. straight along the up vector"):
        pipeline.run(scene.depth, scene.mask, scene.intrinsics)


KINECT = CameraIntrinsics.kinect_like()


@pytest.mark.parametrize("changes, message", [
    ({"fx": 1e30}, r"^intrinsics: K fx = 1e\+30 px gives a horizontal field of view of 3.67e-26 deg over 640 px; "
                   r"real cameras have 1 to 160 deg \(corrupt calibration\?\)$"),
    ({"fy": 1e30}, r"^intrinsics: K fy = 1e\+30 px gives a vertical field of view of 2.75e-26 deg over 480 px"),
    ({"fx": 5.0, "fy": 5.0}, r"^intrinsics: K fx = 5 px gives a horizontal field of view of 178 deg over 640 px"),
    ({"fy": 250.0}, r"^intrinsics: K fx = 525 px and fy = 250 px differ by a factor of 2.1; real pixels are square "
                    r"to within 2x$"),
    ({"cx": -5000.0}, r"^intrinsics: K principal point cx = -5000 px lies outside the 640 px wide image$"),
    ({"cy": 480.5}, r"^intrinsics: K principal point cy = 480.5 px lies outside the 480 px high image$"),
])
def test_intrinsics_no_camera_has_are_refused_naming_the_value(scene, changes, message):
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(up_vector=tuple(scene.up)))
    with pytest.raises(PipelineInputError, match=message):
        pipeline.run(scene.depth, scene.mask, replace(scene.intrinsics, **changes))


@pytest.mark.parametrize("intrinsics", [
    KINECT,
    CameraIntrinsics(640, 480, 383.0, 383.0, 320.8, 238.4),  # RealSense D435 depth, 640x480
    CameraIntrinsics(1024, 1024, 504.0, 504.0, 511.5, 511.5),  # Azure Kinect WFOV unbinned
    CameraIntrinsics(64, 64, 525.0, 525.0, 0.0, 64.0),  # a 64 px corner crop: 7 degrees, centre on the edge
    CameraIntrinsics(640, 240, 525.0, 262.5, 319.5, 119.5),  # 2:1 vertical binning
])
def test_real_cameras_pass(intrinsics):
    check_intrinsics(intrinsics)


def test_field_of_view_limits():
    limits = CameraLimits()

    def camera(fov_deg: float) -> CameraIntrinsics:
        focal = 320.0 / np.tan(np.radians(fov_deg / 2))
        return CameraIntrinsics(640, 640, focal, focal, 320.0, 320.0)

    for fov in (limits.min_fov_deg * 1.01, limits.max_fov_deg * 0.99):
        check_intrinsics(camera(fov))
    for fov in (limits.min_fov_deg * 0.99, limits.max_fov_deg * 1.01):
        with pytest.raises(ObservationError, match="field of view"):
            check_intrinsics(camera(fov))


def k_of(intrinsics: CameraIntrinsics, skew: float = 0.0) -> list[float]:
    k = intrinsics.matrix()
    k[0, 1] = skew
    return k.reshape(-1).tolist()


def p_of(intrinsics: CameraIntrinsics, tx: float = 0.0) -> list[float]:
    return np.hstack([intrinsics.matrix(), [[tx], [0.0], [0.0]]]).reshape(-1).tolist()


def test_camera_model_skew_r_and_p_are_checked():
    eye = np.eye(3).reshape(-1).tolist()
    assert check_camera_model(640, 480, k_of(KINECT), (), eye, p_of(KINECT)) == KINECT
    # A negligible skew (at most half a pixel of shear over the image) is accepted and dropped.
    assert check_camera_model(640, 480, k_of(KINECT, skew=1.0)) == KINECT
    with pytest.raises(ObservationError, match=r"^K skew K\[0,1\] = 1e\+30 shifts pixels by up to 4.58e\+29 px"):
        check_camera_model(640, 480, k_of(KINECT, skew=1e30))
    with pytest.raises(ObservationError, match=r"^K skew K\[0,1\] = nan"):
        check_camera_model(640, 480, k_of(KINECT, skew=float("nan")))
    bad_k = k_of(KINECT)
    bad_k[8] = 1000.0  # a K scaled by its last entry, not normalised
    with pytest.raises(ObservationError, match=r"^K must have the form \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"):
        check_camera_model(640, 480, bad_k)
    # R: all zeros means "not given"; otherwise a rotation (not a reflection, not a shear).
    assert check_camera_model(640, 480, k_of(KINECT), r=[0.0] * 9) == KINECT
    for r, what in ((np.diag([1.0, 1.0, -1.0]), "det -1"), (np.array([[1.0, 0.2, 0], [0, 1, 0], [0, 0, 1]]), "0.2")):
        with pytest.raises(ObservationError, match=f"^R is not a rotation matrix .*{what}"):
            check_camera_model(640, 480, k_of(KINECT), r=r.reshape(-1))
    # P must equal K for an image that is its own rectified image (no distortion, R identity) ...
    with pytest.raises(ObservationError, match=r"^P fx = 600 but K fx = 525: without distortion and rectification"):
        check_camera_model(640, 480, k_of(KINECT), [0.0] * 5, eye, p_of(replace(KINECT, fx=600.0)))
    with pytest.raises(ObservationError, match=r"^P cy = 300 but K cy = 239.5"):
        check_camera_model(640, 480, k_of(KINECT), [], eye, p_of(replace(KINECT, cy=300.0)))
    # ... may differ after rectification (distortion or a rotation), and are then the intrinsics (of the
    # rectified image), but must still be a camera,
    rotated = Rotation.from_euler("y", 2.0, degrees=True).as_matrix().reshape(-1)
    wider = p_of(replace(KINECT, fx=500.0, fy=500.0), tx=-26.0)  # a stereo pair's right camera: Tx = -fx * B
    assert check_camera_model(640, 480, k_of(KINECT), [0.1, -0.2, 0, 0, 0], eye, wider) == replace(KINECT, fx=500.0,
                                                                                                   fy=500.0)
    assert check_camera_model(640, 480, k_of(KINECT), [], rotated, wider) == replace(KINECT, fx=500.0, fy=500.0)
    with pytest.raises(ObservationError, match=r"^P fx = 1e\+30 px gives a horizontal field of view"):
        check_camera_model(640, 480, k_of(KINECT), [0.1], eye, p_of(replace(KINECT, fx=1e30)))
    # ... with the form of a projection matrix.
    bad_p = p_of(KINECT)
    bad_p[11] = 1.0
    with pytest.raises(ObservationError, match=r"^P must have the form"):
        check_camera_model(640, 480, k_of(KINECT), [], eye, bad_p)
    with pytest.raises(ObservationError, match=r"^P must be 12 finite numbers"):
        check_camera_model(640, 480, k_of(KINECT), [], eye, [float("inf")] + p_of(KINECT)[1:])


@pytest.mark.parametrize("factor, message", [
    (4.0, r"^the observed object spans 0.\d+ m upwards, more than the 0.194 m the 32\^3 grid of 6.25 mm voxels "
          r"holds: too large for this model, or the depth units \(depth_scale of 16-bit images\) or the intrinsics "
          r"are wrong$"),
    (0.05, r"^the observed object spans only \d+.?\d* mm, less than 2 voxels \(12.5 mm\) of the grid: too small for "
           r"this model, or the depth units \(depth_scale of 16-bit images\) or the intrinsics are wrong$"),
])
def test_depth_units_that_make_the_object_absurd_are_refused(scene, factor, message):
    """Wrong depth units scale the object: a 16-bit image in 0.25 mm read as mm makes a mug 40 cm tall."""
    config = PipelineConfig(up_vector=tuple(scene.up), min_depth=0.0, max_depth=100.0)
    pipeline = CompletionPipeline(EchoCompleter(), config)
    pipeline.run(scene.depth, scene.mask, scene.intrinsics)  # the right units pass
    with pytest.raises(PipelineInputError, match=message):
        pipeline.run(scene.depth * np.float32(factor), scene.mask, scene.intrinsics)


def test_config_must_fit_the_model():
    pipeline = CompletionPipeline(EchoCompleter(voxel_size=0.005))
    assert pipeline.grid_config().voxel_size == 0.005  # voxel_size 0 = the model's
    with pytest.raises(ValueError, match="voxel_size 0.01 m differs from the 0.005 m the model was trained with"):
        pipeline.config = PipelineConfig(voxel_size=0.01)
    with pytest.raises(ValueError, match=r"grid margins must be in \[0, size/2\)"):
        CompletionPipeline(EchoCompleter(grid_size=16), PipelineConfig(front_margin=8.0))
    with pytest.raises(ValueError, match="num_samples must be in"):
        PipelineConfig(num_samples=200)


def test_support_plane_gives_the_true_up_vector(scene):
    level_prior = np.array([0.0, -1.0, 0.0])  # the camera is really tilted down by 30 degrees
    plane = fit_support_plane(scene.depth, scene.mask, scene.intrinsics, level_prior)
    angle = np.degrees(np.arccos(np.clip(plane.up @ scene.up, -1, 1)))
    assert angle < 1.0 and 29.0 < plane.tilt_deg < 31.0
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(estimate_up=True))
    result = pipeline.run(scene.depth, scene.mask, scene.intrinsics)
    assert np.degrees(np.arccos(np.clip(result.up @ scene.up, -1, 1))) < 1.0


def test_support_plane_failure_is_explained():
    scene = render_mug_scene(seed=0)
    floating = np.where(scene.mask > 0, scene.depth, 0.0).astype(np.float32)  # nothing around the object
    with pytest.raises(ObservationError, match="support plane estimation failed: only 0 valid readings"):
        fit_support_plane(floating, scene.mask, scene.intrinsics, scene.up)
    pipeline = CompletionPipeline(EchoCompleter(), PipelineConfig(estimate_up=True))
    with pytest.raises(PipelineInputError, match="support plane estimation failed"):
        pipeline.run(floating, scene.mask, scene.intrinsics)


class TruthCompleter(EchoCompleter):
    """Stand-in model: every sample is the ground-truth shape (so grasps exist and hold for all samples)."""

    def __init__(self, view, shape) -> None:
        super().__init__()
        self.view, self.shape = view, shape

    def complete(self, observation, num_samples: int, seed: int, box_temperature: float | None = None
                 ) -> CompletionResult:
        from pssnet_core.data.scenes import ground_truth_occupancy

        truth = ground_truth_occupancy(self.shape, self.view.object_pose, observation.pose, self.view.camera_pose)
        occupancy = np.repeat(truth[None], num_samples, axis=0)
        return CompletionResult(occupancy.astype(np.float32), occupancy, self.grid_size, seed, "truth", 0.0)


def test_grasps_are_ranked_camera_frame_poses_around_the_object(scene):
    from pssnet_core.shapes import make_shape

    shape = make_shape("mug", 2_000_000)
    config = PipelineConfig(num_samples=4, up_vector=tuple(scene.up), grasp_top_k=5)
    pipeline = CompletionPipeline(TruthCompleter(scene, shape), config)
    result = pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=True)
    grasps = result.grasps
    assert 1 <= len(grasps) <= 5 and grasps.holds.shape[1] == 4
    assert np.all(np.diff(grasps.scores) <= 0) and grasps.scores[0] == 1.0  # the truth is graspable
    rotations = grasps.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-6)
    centre = result.observation.points.mean(axis=0)
    assert np.all(np.linalg.norm(grasps.poses[:, :3, 3] - centre, axis=1) < 0.15)
    assert np.all((grasps.widths > 0) & (grasps.widths <= config.grasps.gripper.max_opening))
    assert pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False).grasps is None
    strict = CompletionPipeline(TruthCompleter(scene, shape), replace(config, grasp_min_score=1.0, grasp_top_k=100))
    assert np.all(strict.run(scene.depth, scene.mask, scene.intrinsics).grasps.scores == 1.0)


def test_box_temperature_reaches_the_model_and_zero_means_the_models_own(scene, tiny_pipeline):
    echo = EchoCompleter()
    pipeline = CompletionPipeline(echo, PipelineConfig(num_samples=2, up_vector=tuple(scene.up)))
    pipeline.run(scene.depth, scene.mask, scene.intrinsics)
    assert echo.box_temperatures == [None]  # 0: the completer's default (calibrated with the model)
    with pytest.raises(ValueError, match="no box latent"):  # the echo model has no box part
        pipeline.check_config(PipelineConfig(box_temperature=1.5))
    with pytest.raises(ValueError, match="box_temperature"):
        PipelineConfig(box_temperature=-1.0)
    pipeline.check_config(PipelineConfig(box_temperature=1.0))
    tiny_pipeline.check_config(PipelineConfig(box_temperature=1.5))  # PSSNet: any temperature in range


def test_the_node_precision_parameter_reaches_the_model(tmp_path):
    """The node's `precision` parameter picks the network's precision (bf16 is emulated on CPUs without it)."""
    from pssnet_ros import params
    from pssnet_ros.completion_io import load_pipeline

    path = str(tiny_checkpoint(tmp_path / "tiny.pt"))
    for precision in ("fp32", "bf16"):
        pipeline = load_pipeline(dict(params.defaults(), model_path=path, threads=1, precision=precision))
        assert pipeline.completer.precision == precision
    with pytest.raises(ValueError, match="precision"):
        load_pipeline(dict(params.defaults(), model_path=path, threads=1, precision="fp8"))
