"""The ROS-free facade the completion node calls: one view in, completions and ranked grasps out.

    pipeline = CompletionPipeline.from_checkpoint(None, PipelineConfig(num_samples=20))
    result = pipeline.run(depth_m, mask, intrinsics)
    result.completions[0]        # (M, 3) camera-frame centres of the occupied voxels of sample 0
    result.grasps                # ranked grasps (or None when not asked for)

Steps: input checks -> up vector (parameter, or the support plane around the object) -> the shared
observation code path (:func:`pssnet_core.geometry.observe`) -> sampled completions -> voxel centres in the
camera frame -> grasp candidates scored against every completion. Every input problem raises
:class:`PipelineInputError` (a ValueError) whose message says exactly what is wrong.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pssnet_core.geometry import (
    CameraIntrinsics,
    GridConfig,
    Observation,
    ObservationError,
    check_intrinsics,
    check_object_scale,
    fuse_view,
    observe,
    rigid_inverse,
    valid_depth,
)
from pssnet_core.grasps import GraspConfig, GraspError, GraspSet, plan_grasps
from pssnet_core.next_view import NextViewConfig, rank_views

if TYPE_CHECKING:  # torch is imported only when a model is loaded: `completion_node --help` stays fast
    from pssnet_core.inference import Completer
    from pssnet_core.sampling import CheckedSampler, CheckedSamplerConfig

#: voxel size of the grid when a checkpoint does not record the one it was trained with (GridConfig default)
FALLBACK_VOXEL_SIZE = GridConfig().voxel_size
#: accepted lengths of ``up_vector``: only its direction counts, but a length that over- or underflows when
#: squared normalises to [0, 0, 0] or NaN and breaks every call
UP_VECTOR_LENGTH = (1e-6, 1e6)
#: the steps of :meth:`CompletionPipeline.run` after the observation, as its ``should_stop`` is told them
STEP_NETWORK, STEP_GRASPS = "network", "grasps"
#: Further views and candidate places one call takes: each further view adds an observation and a check along its
#: rays (~3 ms), each place ~8 ms of scoring (BENCHMARKS.md, "A second look's cost"); more is a client's mistake.
MAX_MORE_VIEWS, MAX_CANDIDATE_VIEWS = 8, 64


def up_vector_warning(tilt_deg: float, limit_deg: float) -> str:
    """What to tell the user when the support plane is tilted ``tilt_deg`` from ``up_vector`` ("" within
    ``limit_deg``, when not measured (NaN), or with the check off: ``limit_deg`` 0)."""
    if not tilt_deg > limit_deg > 0:
        return ""
    return (f"the support plane around the object is tilted {tilt_deg:.0f} deg from up_vector (up_check_deg "
            f"{limit_deg:g}): set up_vector to the direction against gravity in the camera frame, or estimate_up")


class PipelineInputError(ValueError):
    """The input (images, intrinsics, request options) cannot be processed; the message says why."""


class ModelOutputError(ValueError):
    """The model's samples failed the integrity check (a sample is empty or fills the grid): a broken model."""


class RunCancelled(RuntimeError):
    """:meth:`CompletionPipeline.run` stopped early because its ``should_stop`` said so."""


@dataclass(frozen=True)
class MoreView:
    """A further look at the same object (a second camera, or the same camera moved), fused into the first view's
    observation by :meth:`CompletionPipeline.run`.

    Attributes:
        depth, mask, intrinsics: the view, as for :meth:`CompletionPipeline.run`.
        first_from_camera: (4, 4) this camera's pose in the first camera's optical frame (first <- this).
    """

    depth: np.ndarray
    mask: np.ndarray
    intrinsics: CameraIntrinsics
    first_from_camera: np.ndarray


@dataclass(frozen=True)
class PipelineConfig:
    """Everything the pipeline needs besides the model.

    Attributes:
        num_samples: completions per call when the caller does not say.
        max_num_samples: requests above this are rejected (bounded time and memory).
        seed: latent-noise seed; the same input and seed give the same completions. -1 draws a fresh seed
            per call from the operating system's entropy (the result reports the seed it used).
        voxel_size: grid voxel size (metres); 0 = the model's (the voxel size it was trained with).
        front_margin: voxels between the grid face and the nearest observed point along the view.
        bottom_margin: voxels between the grid bottom and the lowest observed point.
        up_vector: up (against gravity) in the camera's optical frame; (0, -1, 0) for a level camera.
        estimate_up: fit the support plane around the object instead (``up_vector`` is then the prior).
        support_plane_distance: RANSAC inlier distance of that fit (metres).
        support_plane_max_tilt_deg: the plane's normal must lie this close to ``up_vector``.
        min_depth: readings closer than this are "no reading" (metres).
        max_depth: readings farther than this are "no reading" (metres).
        min_mask_pixels: masks with fewer pixels are rejected.
        min_valid_points: fewer masked pixels with a valid depth is an error.
        min_valid_fraction: a smaller share of the masked pixels with a valid depth is an error: a real depth
            camera reads most of an object it segments; a mask mostly over holes, or a depth image decoded wrongly,
            leaves a few scattered readings to complete from.
        min_object_voxels: an observed object spanning fewer voxels than this along every grid axis is
            implausibly small (wrong depth units or intrinsics); one larger than the grid is refused too.
        grasps: gripper, candidate and scoring options (:class:`pssnet_core.grasps.GraspConfig`; its seed is
            replaced by each call's latent seed).
        grasp_top_k: grasps returned, best first.
        grasp_min_score: grasps holding for a smaller fraction of the completions are not returned.
        box_temperature: factor on the posterior sigma of PSSNet's box latent (wider: more diverse hidden
            parts); 0 = the value calibrated with the model (its checkpoint's, else 1).
        up_check_deg: with ``estimate_up`` off, the support plane around the object is still fitted and, when
            its normal lies more than this many degrees from ``up_vector``, the result says so (a wrong up vector
            tilts the grid and ruins the completions: sample IoU 0.77 -> 0.37 on a camera pitched 30 degrees);
            0 turns the check off.
        sampler: "posterior" (the model's samples as drawn) or "checked" (:mod:`pssnet_core.sampling`: many
            proposals, those the view rules out rejected, the rest spread and weighted; a model without a latent,
            3D-RecGAN++, is sampled as it is).
        check_delta: the checked sampler's depth tolerance (metres).
        proposals_per_sample: the checked sampler's proposals per requested sample.
        refine_steps: the checked sampler's gradient steps on its nearest misses' latents (0: none; each step
            costs about three decodes of ``refine_misses`` (20) latents, ``short_pool_refine_misses`` (60) where
            fewer proposals than requested pass the check).
        sampler_options: ``NAME=VALUE`` settings of the checked sampler's other parameters
            (:class:`pssnet_core.sampling.CheckedSamplerConfig`), applied last; for experiments from the command
            line (``--sampler-option``), the node sets none.
    """

    num_samples: int = 20
    max_num_samples: int = 100
    seed: int = 0
    voxel_size: float = 0.0
    front_margin: float = 1.0
    bottom_margin: float = 1.0
    up_vector: tuple[float, float, float] = (0.0, -1.0, 0.0)
    estimate_up: bool = False
    support_plane_distance: float = 0.005
    support_plane_max_tilt_deg: float = 45.0
    min_depth: float = 0.1
    max_depth: float = 5.0
    min_mask_pixels: int = 50
    min_valid_points: int = 20
    min_valid_fraction: float = 0.25
    min_object_voxels: float = 2.0
    grasps: GraspConfig = field(default_factory=GraspConfig)
    grasp_top_k: int = 10
    grasp_min_score: float = 0.0
    box_temperature: float = 0.0
    up_check_deg: float = 5.0
    sampler: str = "checked"
    check_delta: float = 0.01
    proposals_per_sample: int = 10
    refine_steps: int = 3
    sampler_options: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not 1 <= self.num_samples <= self.max_num_samples:
            raise ValueError(f"num_samples must be in [1, max_num_samples={self.max_num_samples}], "
                             f"got {self.num_samples}")
        if self.seed < -1:
            raise ValueError(f"seed must be >= 0, or -1 for a fresh seed per call, got {self.seed}")
        if not 0 <= self.min_depth < self.max_depth:
            raise ValueError(f"need 0 <= min_depth < max_depth, got {self.min_depth} and {self.max_depth}")
        if self.voxel_size < 0:
            raise ValueError(f"voxel_size must be >= 0 (0 = the model's), got {self.voxel_size}")
        up = np.asarray(self.up_vector, dtype=np.float64)
        with np.errstate(over="ignore", under="ignore"):  # [1e200, 1e200, 0]: its length overflows to inf
            length = float(np.linalg.norm(up)) if up.shape == (3,) else math.nan
        if not UP_VECTOR_LENGTH[0] <= length <= UP_VECTOR_LENGTH[1]:
            raise ValueError(f"up_vector must be 3 finite numbers of length {UP_VECTOR_LENGTH[0]:g} to "
                             f"{UP_VECTOR_LENGTH[1]:g}, got {list(self.up_vector)}")
        if self.min_mask_pixels < 1 or self.min_valid_points < 1:
            raise ValueError("min_mask_pixels and min_valid_points must be >= 1")
        if not 0.0 <= self.min_valid_fraction <= 1.0:
            raise ValueError(f"min_valid_fraction must lie in [0, 1], got {self.min_valid_fraction}")
        if not self.min_object_voxels >= 0:
            raise ValueError(f"min_object_voxels must be >= 0, got {self.min_object_voxels}")
        if not 0.0 <= self.up_check_deg <= 90.0:
            raise ValueError(f"up_check_deg must lie in [0, 90] (0 = off), got {self.up_check_deg}")
        if not (self.box_temperature == 0.0 or 0.0 < self.box_temperature <= 10.0):
            raise ValueError(f"box_temperature must be 0 (the model's) or in (0, 10], got {self.box_temperature}")
        from pssnet_core.sampling import SAMPLERS

        if self.sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {self.sampler!r}")
        self.checked_sampler_config()  # validates check_delta, proposals_per_sample, refine_steps, sampler_options
        if self.grasp_top_k < 1 or not 0.0 <= self.grasp_min_score <= 1.0:
            raise ValueError(f"grasp_top_k must be >= 1 and grasp_min_score in [0, 1], got {self.grasp_top_k} and "
                             f"{self.grasp_min_score}")

    def checked_sampler_config(self) -> CheckedSamplerConfig:
        """The checked sampler's parameters that this config sets."""
        from pssnet_core.sampling import CheckedSamplerConfig, checked_config_with

        return checked_config_with(self.sampler_options, CheckedSamplerConfig(
            delta=self.check_delta, proposals_per_sample=self.proposals_per_sample, refine_steps=self.refine_steps))


@dataclass
class PipelineResult:
    """Completions (and grasps) of one view; all points in the camera's optical frame, metres.

    Attributes:
        observation: the observation grid the network saw (with the grid pose).
        voxel_size: edge of one voxel (metres).
        known_occupied: (M, 3) float32 centres of the known-occupied voxels.
        completions: per sample, (M_i, 3) float32 centres of its occupied voxels.
        occupancy: (n, N, N, N) bool sampled occupancy grids.
        grasps: the best ``grasp_top_k`` grasps, ranked, scored against every completion; None when not asked
            for.
        up: (3,) the up vector used.
        seed: the latent-noise seed used.
        timings: seconds per step (``observe``, ``network``, ``views``: scoring candidate views, ``centres``,
            ``grasps``, ``total``).
        weights: (n,) share of the plausible shapes each sample stands for (sums to 1; equal for the posterior
            sampler).
        note: what the caller should know ("" when nothing): that no proposal agreed with the view, or that
            the support plane disagrees with ``up_vector``.
        up_disagreement_deg: angle between ``up_vector`` and the support plane's normal around the object (NaN
            when not checked: ``estimate_up`` on, the check off, or no plane in view).
        view_scores: per candidate view asked about, the probability that its depth image tells two samples apart
            (:func:`pssnet_core.next_view.rank_views`); empty when none was asked about.
    """

    observation: Observation
    voxel_size: float
    known_occupied: np.ndarray
    completions: list[np.ndarray]
    occupancy: np.ndarray
    grasps: GraspSet | None
    up: np.ndarray
    seed: int
    timings: dict[str, float]
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    note: str = ""
    up_disagreement_deg: float = math.nan
    view_scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    @property
    def num_samples(self) -> int:
        return len(self.completions)

    def merged(self) -> tuple[np.ndarray, np.ndarray]:
        """All samples' voxel centres in one (M, 3) array and the (M,) sample index of each point."""
        if not self.completions:
            return np.zeros((0, 3), np.float32), np.zeros(0, np.uint32)
        points = np.concatenate(self.completions, axis=0)
        index = np.concatenate([np.full(len(c), i, np.uint32) for i, c in enumerate(self.completions)])
        return points, index


def checkpoint_voxel_size(completer: Completer) -> float | None:
    """Voxel size (metres) the completer's model was trained with, when its checkpoint records it."""
    info = getattr(completer, "info", {}) or {}
    for source in (info, info.get("grid") or {}, info.get("data_meta") or {}):
        if isinstance(source, dict) and source.get("voxel_size"):
            return float(source["voxel_size"])
    return None


class CompletionPipeline:
    """Observation -> completions -> grasps for one loaded model. Thread-safe (one run at a time).

    Args:
        completer: the loaded model.
        config: pipeline options; see :meth:`check_config` for what must agree with the model.
    """

    def __init__(self, completer: Completer, config: PipelineConfig | None = None) -> None:
        self.completer = completer
        self.model_voxel_size = checkpoint_voxel_size(completer)
        self._lock = threading.Lock()
        self._checked: CheckedSampler | None = None
        self._config = PipelineConfig()
        self.config = config or PipelineConfig()
        self._seed_rng = np.random.default_rng()  # seed -1: a fresh seed per call, not a replayed sequence

    @classmethod
    def from_checkpoint(cls, path: str | Path | None, config: PipelineConfig | None = None,
                        device: str = "cpu", threads: int | None = None,
                        precision: str = "auto") -> CompletionPipeline:
        """Loads a checkpoint (None = the shipped default) for ``Completer`` with ``device``, ``threads`` and
        ``precision`` ("auto", "fp32" or "bf16"), checked for serving (integrity record required, self-test that
        refuses a model that empties or fills the grid); raises ``CheckpointError`` with the reason (a
        ValueError, as is a bad device or precision)."""
        from pssnet_core.inference import Completer

        return cls(Completer.from_checkpoint(path, device=device, threads=threads, precision=precision,
                                             for_serving=True), config)

    @property
    def grid_size(self) -> int:
        return int(self.completer.grid_size)

    @property
    def config(self) -> PipelineConfig:
        return self._config

    @config.setter
    def config(self, config: PipelineConfig) -> None:
        self.check_config(config)
        self._config = config

    def check_config(self, config: PipelineConfig) -> None:
        """Raises ValueError when ``config`` does not fit the model (voxel size, grid margins)."""
        voxel = self.voxel_size_for(config)
        if self.model_voxel_size is not None and not np.isclose(voxel, self.model_voxel_size, rtol=1e-6):
            raise ValueError(f"voxel_size {voxel} m differs from the {self.model_voxel_size} m the model was "
                             "trained with; set it to 0 to use the model's")
        self.grid_config(config)
        has_box = getattr(getattr(self.completer, "model", None), "box_dim", 0) > 0
        if config.box_temperature not in (0.0, 1.0) and not has_box:
            raise ValueError(f"box_temperature {config.box_temperature}: this model has no box latent; use 0 or 1")

    def _sampler(self, config: PipelineConfig) -> Any:
        """The completer, or the checked sampler around it (kept while its parameters stay the same). A model
        without a latent (3D-RecGAN++) has nothing to propose from: it is sampled as it is."""
        from pssnet_core.sampling import CheckedSampler

        if config.sampler == "posterior" or not CheckedSampler.applies_to(self.completer):
            return self.completer
        wanted = config.checked_sampler_config()
        if self._checked is None or self._checked.sampler_config != wanted:
            self._checked = CheckedSampler(self.completer, wanted)
        return self._checked

    def voxel_size_for(self, config: PipelineConfig) -> float:
        if config.voxel_size > 0:
            return float(config.voxel_size)
        return self.model_voxel_size or FALLBACK_VOXEL_SIZE

    def grid_config(self, config: PipelineConfig | None = None) -> GridConfig:
        """The observation grid for ``config`` (default: the current one) and this model's grid size."""
        config = config or self._config
        try:
            return GridConfig(size=self.grid_size, voxel_size=self.voxel_size_for(config),
                              front_margin=config.front_margin, bottom_margin=config.bottom_margin)
        except ObservationError as error:
            raise ValueError(str(error)) from error

    def _up_vector(self, depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
                   config: PipelineConfig) -> tuple[np.ndarray, float]:
        """The up vector to use, and its disagreement with the support plane (degrees; NaN when not checked)."""
        prior = np.asarray(config.up_vector, dtype=np.float64)
        prior = prior / np.linalg.norm(prior)
        if not config.estimate_up and config.up_check_deg == 0:
            return prior, math.nan
        from pssnet_core.support_plane import SupportPlaneConfig, fit_support_plane  # open3d: only when used

        # The check accepts any tilt (a wrong up vector is what it is looking for); the estimate keeps its limit.
        max_tilt = config.support_plane_max_tilt_deg if config.estimate_up else 90.0
        try:
            plane = fit_support_plane(depth, mask, intrinsics, prior,
                                      SupportPlaneConfig(distance=config.support_plane_distance, max_tilt_deg=max_tilt),
                                      config.min_depth, config.max_depth)
        except ObservationError:
            if config.estimate_up:
                raise
            return prior, math.nan  # no plane in view: nothing to check against
        if config.estimate_up:
            return plane.up, math.nan
        return prior, float(plane.tilt_deg)

    def check_input(self, depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
                    num_samples: int | None, config: PipelineConfig) -> int:
        """Validates one request; returns the number of samples to draw."""
        if not np.issubdtype(depth.dtype, np.floating):
            raise PipelineInputError(f"depth must be float metres, got dtype {depth.dtype}")
        n = config.num_samples if not num_samples else int(num_samples)
        if n < 0 or n > config.max_num_samples:
            raise PipelineInputError(f"num_samples {n} is out of range: ask for 1..{config.max_num_samples} "
                                     "(max_num_samples), or 0 for the node's default")
        if depth.ndim != 2 or mask.ndim != 2:
            raise PipelineInputError(f"depth and mask must be 2-D images, got shapes {depth.shape} and {mask.shape}")
        if mask.shape != depth.shape:
            raise PipelineInputError(f"mask is {mask.shape[1]}x{mask.shape[0]} but depth is "
                                     f"{depth.shape[1]}x{depth.shape[0]}: they must be the same size")
        if depth.shape != (intrinsics.height, intrinsics.width):
            raise PipelineInputError(f"depth is {depth.shape[1]}x{depth.shape[0]} but camera_info says "
                                     f"{intrinsics.width}x{intrinsics.height}")
        try:
            check_intrinsics(intrinsics)
        except ObservationError as error:
            raise PipelineInputError(f"intrinsics: {error}") from error
        mask_pixels = int(np.count_nonzero(mask))
        if mask_pixels < config.min_mask_pixels:
            what = "empty" if mask_pixels == 0 else "too small"
            raise PipelineInputError(f"mask is {what}: {mask_pixels} pixels marked, need at least "
                                     f"{config.min_mask_pixels} (min_mask_pixels)")
        object_depth = depth[mask != 0]
        if not np.isfinite(object_depth).any():
            raise PipelineInputError("depth has no finite reading inside the mask (all NaN/Inf)")
        valid = int(np.count_nonzero(valid_depth(object_depth, config.min_depth, config.max_depth)))
        # Fewer than min_valid_points: observe() says so, with that limit.
        if config.min_valid_points <= valid < config.min_valid_fraction * mask_pixels:
            raise PipelineInputError(f"only {valid} of the {mask_pixels} masked pixels ({valid / mask_pixels:.0%}) "
                                     f"have a depth in [{config.min_depth}, {config.max_depth}] m; need "
                                     f"{config.min_valid_fraction:.0%} (min_valid_fraction)")
        return n

    def run(self, depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
            num_samples: int | None = None, compute_grasps: bool = True,
            should_stop: Callable[[str], bool] | None = None,
            more_views: Sequence[MoreView] = (), candidate_views: Sequence[np.ndarray] = ()) -> PipelineResult:
        """Completes one view (or several of the same object, fused into the first one's grid).

        Args:
            depth: (H, W) float depth in metres (0/NaN/Inf = no reading).
            mask: (H, W), non-zero = target object.
            intrinsics: intrinsics of the depth image.
            num_samples: completions to draw; None or 0 = ``config.num_samples``.
            compute_grasps: also generate and score grasps.
            should_stop: asked before each later step with its name (``STEP_NETWORK``, ``STEP_GRASPS``); True
                ends the run with :class:`RunCancelled` (a node leaving the active state, or a client cancelling
                its goal, stops the call so); a caller may also report the step as progress.
            more_views: further looks at the same object (:func:`pssnet_core.geometry.fuse_view`): what they see
                is added to the observation, and the checked sampler checks every proposal against each view.
            candidate_views: places the camera (same intrinsics) could look from next, each (4, 4) its pose in the
                first camera's frame (first <- candidate): each is scored in ``view_scores`` by how well its depth
                image would tell the samples apart (:mod:`pssnet_core.next_view`; nothing in front of the object
                is known here, so a candidate behind an obstacle scores as if it were not).

        Raises:
            RunCancelled: ``should_stop`` returned True.
            PipelineInputError: the input cannot be processed (the message says why).
            ModelOutputError: a sample is empty or fills the grid (a broken model; a ValueError too).
        """
        t0 = time.perf_counter()
        config = self._config  # one consistent snapshot even if the node updates parameters meanwhile
        depth, mask = np.asarray(depth), np.asarray(mask)
        n = self.check_input(depth, mask, intrinsics, num_samples, config)
        grid = self.grid_config(config)
        try:
            up, up_disagreement = self._up_vector(depth, mask, intrinsics, config)
            observation = observe(depth, mask, intrinsics, up, grid, config.min_depth, config.max_depth,
                                  config.min_valid_points)
            check_object_scale(observation.points, observation.pose, grid, config.min_object_voxels)
        except ObservationError as error:
            raise PipelineInputError(str(error)) from error
        if len(more_views) > MAX_MORE_VIEWS or len(candidate_views) > MAX_CANDIDATE_VIEWS:
            raise PipelineInputError(f"{len(more_views)} further views and {len(candidate_views)} candidate views: "
                                     f"at most {MAX_MORE_VIEWS} and {MAX_CANDIDATE_VIEWS} per call")
        for number, view in enumerate(more_views, start=2):
            try:
                view_depth, view_mask = np.asarray(view.depth), np.asarray(view.mask)
                self.check_input(view_depth, view_mask, view.intrinsics, n, config)
                observation = fuse_view(observation, view_depth, view_mask, view.intrinsics, view.first_from_camera,
                                        config.min_depth, config.max_depth, config.min_valid_points)
            except (PipelineInputError, ObservationError) as error:
                raise PipelineInputError(f"view {number}: {error}") from error
        try:
            candidates_from_first = [rigid_inverse(c, f"candidate view {k}") for k, c in enumerate(candidate_views)]
        except ObservationError as error:
            raise PipelineInputError(str(error)) from error
        self._stop_if(should_stop, STEP_NETWORK)
        t1 = time.perf_counter()
        from pssnet_core.inference import CompletionInputError
        from pssnet_core.models.integrity import IntegrityError, check_samples

        with self._lock:
            seed = config.seed if config.seed >= 0 else int(self._seed_rng.integers(0, 2**31 - 1))
            try:
                completion = self._sampler(config).complete(observation, num_samples=n, seed=seed,
                                                            box_temperature=config.box_temperature or None)
            except CompletionInputError as error:
                raise PipelineInputError(str(error)) from error
        try:
            check_samples(completion.occupancy)  # an empty or full sample is a broken model, never a result
        except IntegrityError as error:
            raise ModelOutputError(str(error)) from error
        weights = getattr(completion, "weights", None)  # the checked sampler's; the posterior's weigh alike
        if weights is None:
            weights = np.full(n, 1.0 / n, np.float32)
        t2 = time.perf_counter()
        view_scores = np.zeros(0, np.float32)
        if candidates_from_first:
            view_scores = rank_views(completion.occupancy, weights, observation.pose, candidates_from_first, intrinsics,
                                     config=NextViewConfig(delta=config.check_delta)).astype(np.float32)
        t_views = time.perf_counter()
        pose = observation.pose
        completions = pose.occupied_centres_per_grid(completion.occupancy)
        known = pose.occupied_centres(observation.known_occupied).astype(np.float32)
        t3 = time.perf_counter()
        grasps = None
        if compute_grasps:
            self._stop_if(should_stop, STEP_GRASPS)
            try:
                grasps = plan_grasps(completion.occupancy, pose, observation.points, replace(config.grasps, seed=seed),
                                     known_occupied=observation.known_occupied, weights=weights)
            except GraspError as error:
                raise PipelineInputError(f"grasp planning failed: {error}") from error
            grasps = grasps.top(config.grasp_top_k, config.grasp_min_score)
        t4 = time.perf_counter()
        timings = {"observe": t1 - t0, "network": t2 - t1, "views": t_views - t2, "centres": t3 - t_views,
                   "grasps": t4 - t3, "total": t4 - t0}
        return PipelineResult(observation=observation, voxel_size=grid.voxel_size, known_occupied=known,
                              completions=completions, occupancy=completion.occupancy, grasps=grasps, up=up,
                              seed=seed, timings=timings, weights=np.asarray(weights, np.float32),
                              note=self._note(completion, up_disagreement, config), up_disagreement_deg=up_disagreement,
                              view_scores=view_scores)

    @staticmethod
    def _stop_if(should_stop: Callable[[str], bool] | None, step: str) -> None:
        if should_stop is not None and should_stop(step):
            raise RunCancelled(f"stopped before the {step}")

    @staticmethod
    def _note(completion: Any, up_disagreement: float, config: PipelineConfig) -> str:
        notes = [str(getattr(completion, "note", "")), up_vector_warning(up_disagreement, config.up_check_deg)]
        return "; ".join(n for n in notes if n)

    def with_config(self, **changes: Any) -> PipelineConfig:
        """A copy of the current config with ``changes`` applied and checked against the model."""
        config = replace(self._config, **changes)
        self.check_config(config)
        return config
