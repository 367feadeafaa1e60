"""Ambiguity measured directly: do the samples spread over exactly what the view allows?

Two experiments where the shapes a view allows can be enumerated, independently of any model:

**Mugs with the handle hidden** (round mugs with a handle, test views whose record says ``handle_visible``
False). The *plausible handle arc* of a view is the set of azimuths ``a`` (``azimuth_step_deg`` steps) at which
the same mug, turned about its own vertical axis at the same place so that its handle lies at ``a``
(:func:`pssnet_core.evaluation.handles.turned`), is accepted by the observation model (Alg. 1,
:mod:`pssnet_core.evaluation.observation_model`) for that view's depth image. The body is a surface of
revolution, so turning the mug moves only its handle, and that is how it is rendered: the body (the mug less
``Shape.handle``) stays, the handle turns (:func:`mug_parts`). Why not turn the whole mesh: the body is
polygonised with 36 segments, so a turn by an odd multiple of 5 degrees moves its facets, and with the paper's
zero outlier allowance that alone rejected the turned mug by one pixel (measured on test mugs: every odd
multiple of 5 degrees rejected, every even one accepted, in the middle of the arc). Azimuths are those of
:func:`pssnet_core.evaluation.handles.handle_azimuths` (true handle = 0), the one way a sampled handle is found.
Per view and model:

- ``coverage``: fraction of the arc's azimuths within ``arc_tolerance_deg`` (15) of some sample's handle;
- ``precision``: fraction of the sampled handles within ``arc_margin_deg`` (10) of some azimuth of the arc;
- ``spread_ratio``: circular s.d. of the sampled handle azimuths / circular s.d. of the arc's azimuths
  (1 = the samples spread as widely as the view allows; undefined when the arc is a single azimuth);
- ``handle_rate``: fraction of samples with a handle.

On views with the handle visible the samples should agree with the truth: ``error_deg`` = mean circular
distance of the sampled handles from the true one.

**Boxes through the narrow slit** (``ycb_narrow`` or ``oof_narrow``, objects of a box family). The box is
stretched or shrunk along its own axis that points most nearly away from the camera (the axis closest to the
grid's x, the horizontal viewing direction, see :class:`pssnet_core.geometry.GridPose`), keeping the face nearest
the camera where it is, in steps of ``extent_step_voxels`` voxels of length, as long as it stays inside the grid. The
lengths the observation model accepts form the plausible range of the hidden extent. Extents are compared in
the grid: the x extent (voxels) of the largest connected part of an occupancy grid
(:func:`grid_x_extent`), the same measure for the samples and for the accepted boxes voxelised with the
project's one occupancy definition. The same three figures (``coverage`` within ``extent_tolerance_voxels``,
``precision`` with ``extent_margin_voxels``, ``spread_ratio`` of standard deviations over the distinct
plausible extents), plus the extents in millimetres. A range that reaches the largest length the grid holds is
*open-ended*: the view allows deeper boxes than a sample can represent.

The observation model's tolerance delta is a parameter: every plausible set is computed for all
``deltas`` at once (default the evaluation's scaled 1 cm, then the paper's 4 cm; DESIGN.md). Note that a larger
delta is not simply more permissive: the unreliable pixels are those whose depth gradient exceeds delta, so a
larger delta compares more pixels near depth edges, and some candidates accepted at 1 cm fail at 4 cm.

Which test sets: ``sets`` names one mug set (``mugs`` or ``oof_mugs``, of any mug family: procedural, independent
or real) and/or one narrow-slit set (``ycb_narrow`` or ``oof_narrow``); meshes come from
:func:`pssnet_core.shapes.shape_of`, whatever made the object.

The plausible sets are model-independent: :func:`run_ambiguity` computes them once per view and caches them in
the output directory (keyed by the test set's content and the parameters), so re-runs with other checkpoints
only sample.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from pssnet_core.evaluation.handles import (
    HandleGeometry,
    circular_difference_deg,
    circular_spread_deg,
    handle_azimuths,
    handle_geometries,
    turned,
)
from pssnet_core.evaluation.observation_model import (
    DepthView,
    MeshRaycaster,
    MultiDeltaView,
    ObservationModelConfig,
)
from pssnet_core.evaluation.plausible import EvalView
from pssnet_core.spread import evenly_spaced

#: the evaluation's deltas: scaled to real-size objects (1 cm) first, then the paper's 4 cm (DESIGN.md)
DEFAULT_DELTAS: tuple[float, ...] = (0.01, 0.04)
CACHE_VERSION = 2  # 2: the handle turns, the body stays (see the module docstring)
REJECTED = -1  # violations entry of a candidate rejected on the sparse pixels at every delta


class AmbiguityError(ValueError):
    """Bad input to the ambiguity measurement (no usable views, bad parameters, unreadable cache)."""


@dataclass(frozen=True)
class AmbiguityConfig:
    """Parameters of the ambiguity measurement.

    Attributes:
        deltas: observation-model tolerances (metres); the first one is the headline (figures).
        observation: the other observation-model parameters (its delta is ignored).
        azimuth_step_deg: step of the candidate handle azimuths.
        arc_tolerance_deg: an arc azimuth is covered when a sampled handle is this close.
        arc_margin_deg: a sampled handle is inside the arc when an arc azimuth is this close.
        extent_step_voxels: step of the candidate box lengths (voxels of the view's grid).
        extent_tolerance_voxels: a plausible extent is covered when a sample's extent is this close.
        extent_margin_voxels: a sample's extent is inside the plausible range when a plausible extent is this close.
        sparse_pixels: early rejection on a sparse pixel sample (exact; 0 disables it).
        rerender: judge against the whole re-rendered image (:func:`pssnet_core.data.datasets.rerender`) rather
            than the stored crop, so that a candidate reaching beyond the crop meets the scene there.
    """

    deltas: tuple[float, ...] = DEFAULT_DELTAS
    observation: ObservationModelConfig = ObservationModelConfig()
    azimuth_step_deg: float = 5.0
    arc_tolerance_deg: float = 15.0
    arc_margin_deg: float = 10.0
    extent_step_voxels: float = 0.5
    extent_tolerance_voxels: float = 1.0
    extent_margin_voxels: float = 1.0
    sparse_pixels: int = 96
    rerender: bool = True

    def __post_init__(self) -> None:
        if not self.deltas or any(not (math.isfinite(d) and d > 0) for d in self.deltas):
            raise AmbiguityError(f"deltas must be positive numbers of metres, got {self.deltas}")
        if len(set(self.deltas)) != len(self.deltas):
            raise AmbiguityError(f"deltas must be distinct, got {self.deltas}")
        steps = 360.0 / self.azimuth_step_deg if self.azimuth_step_deg > 0 else math.inf
        if not 0 < self.azimuth_step_deg <= 90 or abs(steps - round(steps)) > 1e-9:
            raise AmbiguityError(f"azimuth_step_deg must divide 360 and be in (0, 90], got {self.azimuth_step_deg}")
        if not self.extent_step_voxels > 0:
            raise AmbiguityError(f"extent_step_voxels must be positive, got {self.extent_step_voxels}")
        if min(self.arc_tolerance_deg, self.arc_margin_deg, self.extent_tolerance_voxels,
               self.extent_margin_voxels) < 0:
            raise AmbiguityError("tolerances and margins must be >= 0")

    def azimuths(self) -> np.ndarray:
        """Candidate handle azimuths in [-180, 180) degrees (0 = the true handle)."""
        count = int(round(360 / self.azimuth_step_deg))
        return (np.arange(count) * self.azimuth_step_deg + 180.0) % 360.0 - 180.0

    def plausible_key(self) -> dict[str, Any]:
        """The parameters the plausible sets depend on (the cache key's parameter part)."""
        return {"deltas": list(self.deltas), "observation": asdict(self.observation),
                "azimuth_step_deg": self.azimuth_step_deg, "extent_step_voxels": self.extent_step_voxels,
                "sparse_pixels": self.sparse_pixels, "rerender": self.rerender, "version": CACHE_VERSION}


# ------------------------------------------------------------------------------------ plausible sets


@dataclass
class HandleArc:
    """The plausible handle azimuths of one view.

    Attributes:
        index: the view's index in its test set.
        identity: the mug.
        deltas: the deltas (columns of ``violations``).
        azimuths_deg: (K,) candidate azimuths.
        violations: (K, D) violating pixels per candidate and delta; :data:`REJECTED` = rejected early at every
            delta (on the sparse pixels).
        allowance: violations allowed (the outlier allowance; 0 in the paper).
        camera_azimuth_deg: azimuth of the camera in the mug's frame (where a handle faces the camera).
        seconds: time it took.
    """

    index: int
    identity: str
    deltas: tuple[float, ...]
    azimuths_deg: np.ndarray
    violations: np.ndarray
    allowance: int = 0
    camera_azimuth_deg: float = math.nan
    seconds: float = 0.0

    def accepted(self, delta: float) -> np.ndarray:
        """(K,) bool: which candidates the observation model accepts at ``delta``."""
        v = self.violations[:, _column(self.deltas, delta)]
        return (v != REJECTED) & (v <= self.allowance)

    def arc(self, delta: float) -> np.ndarray:
        """The plausible azimuths (degrees) at ``delta``."""
        return self.azimuths_deg[self.accepted(delta)]

    def truth_accepted(self, delta: float) -> bool:
        """Whether the view's own mug (azimuth 0) is accepted: a check of the pipeline's consistency."""
        zero = np.isclose(self.azimuths_deg, 0.0)
        return bool(self.accepted(delta)[zero].any())

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "identity": self.identity, "deltas": list(self.deltas),
                "azimuths_deg": self.azimuths_deg.tolist(), "violations": self.violations.tolist(),
                "allowance": self.allowance, "camera_azimuth_deg": self.camera_azimuth_deg, "seconds": self.seconds}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> HandleArc:
        return cls(index=int(data["index"]), identity=str(data["identity"]), deltas=tuple(data["deltas"]),
                   azimuths_deg=np.asarray(data["azimuths_deg"], dtype=np.float64),
                   violations=np.asarray(data["violations"], dtype=np.int64).reshape(-1, len(data["deltas"])),
                   allowance=int(data["allowance"]), camera_azimuth_deg=float(data["camera_azimuth_deg"]),
                   seconds=float(data["seconds"]))


@dataclass
class SlitRange:
    """The plausible lengths of a box's hidden dimension for one narrow-slit view.

    Attributes:
        index: the view's index in its test set.
        identity: the box.
        deltas: the deltas (columns of ``violations``).
        axis: the object-frame axis that was stretched (the one pointing most nearly away from the camera).
        front: object-frame coordinate of the face kept in place (the one nearest the camera).
        true_length_m: the box's real length along ``axis``.
        lengths_m: (K,) candidate lengths, ascending; ``true_length_m`` is one of them.
        violations: (K, D) as in :class:`HandleArc`.
        extents_voxels: (K,) grid x extent (:func:`grid_x_extent`) of each candidate accepted at some delta
            (and of the true box); NaN for the others (not voxelised).
        voxel_size: metres.
        allowance: violations allowed.
        seconds: time it took.
    """

    index: int
    identity: str
    deltas: tuple[float, ...]
    axis: int
    front: float
    true_length_m: float
    lengths_m: np.ndarray
    violations: np.ndarray
    extents_voxels: np.ndarray
    voxel_size: float
    allowance: int = 0
    seconds: float = 0.0

    def accepted(self, delta: float) -> np.ndarray:
        """(K,) bool: which lengths the observation model accepts at ``delta``."""
        v = self.violations[:, _column(self.deltas, delta)]
        return (v != REJECTED) & (v <= self.allowance)

    def extents(self, delta: float) -> np.ndarray:
        """Distinct plausible grid x extents (voxels) at ``delta``, ascending."""
        return np.unique(self.extents_voxels[self.accepted(delta)])

    @property
    def true_index(self) -> int:
        return int(np.argmin(np.abs(self.lengths_m - self.true_length_m)))

    @property
    def true_extent_voxels(self) -> float:
        return float(self.extents_voxels[self.true_index])

    def truth_accepted(self, delta: float) -> bool:
        return bool(self.accepted(delta)[self.true_index])

    def open_ended(self, delta: float) -> bool:
        """The longest candidate (as long as the grid holds) is plausible: the view allows deeper still."""
        return bool(self.accepted(delta)[-1])

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "identity": self.identity, "deltas": list(self.deltas), "axis": self.axis,
                "front": self.front, "true_length_m": self.true_length_m, "lengths_m": self.lengths_m.tolist(),
                "violations": self.violations.tolist(),
                "extents_voxels": [None if not np.isfinite(x) else float(x) for x in self.extents_voxels],
                "voxel_size": self.voxel_size, "allowance": self.allowance, "seconds": self.seconds}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SlitRange:
        return cls(index=int(data["index"]), identity=str(data["identity"]), deltas=tuple(data["deltas"]),
                   axis=int(data["axis"]), front=float(data["front"]), true_length_m=float(data["true_length_m"]),
                   lengths_m=np.asarray(data["lengths_m"], dtype=np.float64),
                   violations=np.asarray(data["violations"], dtype=np.int64).reshape(-1, len(data["deltas"])),
                   extents_voxels=np.array([np.nan if x is None else x for x in data["extents_voxels"]],
                                           dtype=np.float64),
                   voxel_size=float(data["voxel_size"]), allowance=int(data["allowance"]),
                   seconds=float(data["seconds"]))


def _column(deltas: Sequence[float], delta: float) -> int:
    for k, d in enumerate(deltas):
        if abs(d - delta) < 1e-12:
            return k
    raise AmbiguityError(f"no plausible set for delta {delta}; computed for {list(deltas)}")


def _judge(multi: MultiDeltaView, caster: MeshRaycaster, pose: np.ndarray) -> list[int]:
    results = multi.judge(caster, pose)
    if results is None:
        return [REJECTED] * len(multi.deltas)
    return [int(results[d].violations) for d in multi.deltas]


@dataclass(frozen=True)
class MugParts:
    """A mug split into its body (the mesh less the handle) and its handle, both in the mug's frame.

    Attributes:
        body_vertices, body_faces: the body (cavity included).
        handle_vertices, handle_faces: the part of the handle outside the body (``Shape.handle``).
    """

    body_vertices: np.ndarray
    body_faces: np.ndarray
    handle_vertices: np.ndarray
    handle_faces: np.ndarray

    def turned(self, azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the mug with its handle turned to ``azimuth_deg`` about the body's axis.

        Body and handle are two abutting solids in one triangle soup: a ray's first hit is the union's surface.
        """
        rotation = turned(np.eye(4), azimuth_deg)[:3, :3]
        vertices = np.concatenate([self.body_vertices, self.handle_vertices @ rotation.T])
        faces = np.concatenate([self.body_faces, self.handle_faces + len(self.body_vertices)])
        return vertices, faces


def mug_parts(shape: Any) -> MugParts:
    """Splits a mug (:class:`pssnet_core.shapes.Shape` with a handle, any source) into body and handle."""
    if shape.handle is None:
        raise AmbiguityError(f"{shape.identity} has no handle")
    body = shape.mesh.difference(shape.handle, engine="manifold")
    return MugParts(np.asarray(body.vertices, dtype=np.float64), np.asarray(body.faces, dtype=np.int64),
                    np.asarray(shape.handle.vertices, dtype=np.float64),
                    np.asarray(shape.handle.faces, dtype=np.int64))


def plausible_handle_arc(view: EvalView, depth_view: DepthView, mug: MugParts,
                         config: AmbiguityConfig | None = None) -> HandleArc:
    """Which handle azimuths the view allows: the handle turned to each, judged by the observation model.

    Args:
        view: the test view (its ``object_pose`` places the true mug in the camera frame).
        depth_view: the depth image to judge against (the stored crop or the re-rendered image).
        mug: the mug's body and handle in its own frame (handle along +x, axis at x = y = 0).
        config: parameters.
    """
    config = config or AmbiguityConfig()
    t0 = time.perf_counter()
    multi = MultiDeltaView(depth_view, config.observation, config.deltas, sparse_pixels=config.sparse_pixels)
    azimuths = config.azimuths()
    violations = np.array([_judge(multi, MeshRaycaster(*mug.turned(a)), view.object_pose) for a in azimuths],
                          dtype=np.int64)
    pose = np.asarray(view.object_pose, dtype=np.float64)
    camera = -pose[:3, :3].T @ pose[:3, 3]  # the camera centre in the mug's frame
    return HandleArc(index=view.index, identity=view.identity, deltas=tuple(config.deltas), azimuths_deg=azimuths,
                     violations=violations, allowance=multi.any.allowance,
                     camera_azimuth_deg=math.degrees(math.atan2(camera[1], camera[0])),
                     seconds=time.perf_counter() - t0)


def hidden_axis(camera_from_object: np.ndarray, grid_rotation: np.ndarray, bounds: np.ndarray) -> tuple[int, float]:
    """The object axis pointing most nearly away from the camera, and the coordinate of its near face.

    Args:
        camera_from_object: 4x4 object pose in the camera frame.
        grid_rotation: (3, 3) the grid's axes in the camera frame (column 0 = horizontal viewing direction).
        bounds: (2, 3) the object's axis-aligned bounds in its own frame.

    Returns:
        (axis, front): ``front`` is ``bounds[0, axis]`` when the axis points away from the camera, else
        ``bounds[1, axis]``: the face the camera looks at, kept in place when the box is stretched.
    """
    away = np.asarray(camera_from_object, dtype=np.float64)[:3, :3].T @ np.asarray(grid_rotation)[:, 0]
    axis = int(np.argmax(np.abs(away)))
    return axis, float(bounds[0, axis] if away[axis] > 0 else bounds[1, axis])


def stretched(vertices: np.ndarray, axis: int, front: float, factor: float) -> np.ndarray:
    """Vertices scaled by ``factor`` along ``axis`` about the plane ``x_axis = front`` (an exact box for a box)."""
    out = np.array(vertices, dtype=np.float64, copy=True)
    out[:, axis] = front + (out[:, axis] - front) * factor
    return out


def grid_x_extent(grids: np.ndarray) -> np.ndarray:
    """Extent along the grid's x (the horizontal viewing direction) in voxels, per grid.

    The extent of the largest 26-connected part, so that a few stray voxels do not count as depth; NaN for an
    empty grid.

    Args:
        grids: (K, N, N, N) or (N, N, N) bool occupancy.

    Returns:
        (K,) float64.
    """
    grids = np.asarray(grids, dtype=bool)
    if grids.ndim == 3:
        grids = grids[None]
    out = np.full(len(grids), np.nan)
    structure = np.ones((3, 3, 3), dtype=bool)
    for k, grid in enumerate(grids):
        labels, count = ndimage.label(grid, structure=structure)
        if count == 0:
            continue
        biggest = int(np.argmax(np.bincount(labels.reshape(-1))[1:])) + 1
        xs = np.flatnonzero((labels == biggest).any(axis=(1, 2)))
        out[k] = float(xs[-1] - xs[0] + 1)
    return out


def plausible_slit_range(view: EvalView, depth_view: DepthView, vertices: np.ndarray, faces: np.ndarray,
                         config: AmbiguityConfig | None = None) -> SlitRange:
    """Which lengths of the box's hidden dimension the view allows (see the module docstring).

    Candidate lengths are the true length plus whole steps of ``extent_step_voxels`` voxels, from the shortest
    positive one up to the longest whose far face stays inside the grid (the true length is always included).
    """
    config = config or AmbiguityConfig()
    t0 = time.perf_counter()
    vertices = np.asarray(vertices, dtype=np.float64)
    pose = np.asarray(view.object_pose, dtype=np.float64)
    grid = view.grid_pose
    bounds = np.stack([vertices.min(axis=0), vertices.max(axis=0)])
    axis, front = hidden_axis(pose, grid.rotation, bounds)
    true_length = float(bounds[1, axis] - bounds[0, axis])
    step = config.extent_step_voxels * grid.voxel_size
    multi = MultiDeltaView(depth_view, config.observation, config.deltas, sparse_pixels=config.sparse_pixels)
    lengths, violations, casters = [], [], []
    k = -int(math.ceil(true_length / step)) + 1
    while True:
        length = true_length + k * step
        factor = length / true_length
        moved = stretched(vertices, axis, front, factor)
        far = grid.camera_to_grid(moved @ pose[:3, :3].T + pose[:3, 3])[:, 0].max()
        if k > 0 and far > grid.size:  # the grid holds no deeper box
            break
        caster = MeshRaycaster(moved, faces)
        lengths.append(length)
        violations.append(_judge(multi, caster, pose))
        casters.append(caster)
        k += 1
    violations_a = np.array(violations, dtype=np.int64).reshape(-1, len(config.deltas))
    accepted_any = ((violations_a != REJECTED) & (violations_a <= multi.any.allowance)).any(axis=1)
    lengths_a = np.array(lengths)
    truth = int(np.argmin(np.abs(lengths_a - true_length)))
    extents = np.full(len(lengths), np.nan)
    for j in np.flatnonzero(accepted_any | (np.arange(len(lengths)) == truth)):
        extents[j] = grid_x_extent(casters[j].occupancy_grid(grid, pose))[0]
    return SlitRange(index=view.index, identity=view.identity, deltas=tuple(config.deltas), axis=axis, front=front,
                     true_length_m=true_length, lengths_m=lengths_a, violations=violations_a,
                     extents_voxels=extents, voxel_size=float(grid.voxel_size), allowance=multi.any.allowance,
                     seconds=time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------- scores


@dataclass(frozen=True)
class SpreadScores:
    """How samples spread over a plausible set (one view, one delta).

    Attributes:
        coverage: fraction of the plausible values with a sample within the tolerance (0 if no sample measured).
        precision: fraction of the measured samples with a plausible value within the margin (NaN if none).
        spread_ratio: spread of the samples / spread of the plausible values (NaN when either is undefined:
            fewer than two measured samples, or a single plausible value).
        rate: fraction of the samples that could be measured (with a handle / not empty).
    """

    coverage: float
    precision: float
    spread_ratio: float
    rate: float


def arc_scores(arc_deg: np.ndarray, sample_azimuths_deg: np.ndarray, tolerance_deg: float = 15.0,
               margin_deg: float = 10.0) -> SpreadScores:
    """Coverage, precision and spread ratio of sampled handle azimuths (NaN = no handle) against an arc."""
    arc = np.asarray(arc_deg, dtype=np.float64)
    samples = np.asarray(sample_azimuths_deg, dtype=np.float64)
    found = samples[np.isfinite(samples)]
    rate = float(len(found) / len(samples)) if len(samples) else math.nan
    if len(arc) == 0:
        raise AmbiguityError("the plausible arc is empty (not even the truth was accepted)")
    if len(found) == 0:
        return SpreadScores(coverage=0.0, precision=math.nan, spread_ratio=math.nan, rate=rate)
    distance = circular_difference_deg(arc[:, None], found[None, :])  # (arc, samples)
    coverage = float((distance.min(axis=1) <= tolerance_deg + 1e-9).mean())
    precision = float((distance.min(axis=0) <= margin_deg + 1e-9).mean())
    arc_spread = circular_spread_deg(arc)
    ratio = circular_spread_deg(found) / arc_spread if math.isfinite(arc_spread) and arc_spread > 0 else math.nan
    return SpreadScores(coverage=coverage, precision=precision, spread_ratio=float(ratio), rate=rate)


def extent_scores(plausible: np.ndarray, sample_extents: np.ndarray, tolerance: float = 1.0,
                  margin: float = 1.0) -> SpreadScores:
    """Coverage, precision and spread ratio of sampled extents (NaN = empty sample) against the plausible ones.

    Spreads are population standard deviations over the *distinct* plausible extents (every extent the view
    allows counts once) and over the samples.
    """
    allowed = np.unique(np.asarray(plausible, dtype=np.float64))
    samples = np.asarray(sample_extents, dtype=np.float64)
    found = samples[np.isfinite(samples)]
    rate = float(len(found) / len(samples)) if len(samples) else math.nan
    if len(allowed) == 0:
        raise AmbiguityError("the plausible extent range is empty (not even the truth was accepted)")
    if len(found) == 0:
        return SpreadScores(coverage=0.0, precision=math.nan, spread_ratio=math.nan, rate=rate)
    distance = np.abs(allowed[:, None] - found[None, :])
    coverage = float((distance.min(axis=1) <= tolerance + 1e-9).mean())
    precision = float((distance.min(axis=0) <= margin + 1e-9).mean())
    spread = float(allowed.std())
    ratio = float(found.std()) / spread if len(found) >= 2 and spread > 0 else math.nan
    return SpreadScores(coverage=coverage, precision=precision, spread_ratio=ratio, rate=rate)


# ------------------------------------------------------------------------------------------ cache


def _atomic_write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def cache_path(cache_dir: str | Path, fingerprint: str, kind: str, config: AmbiguityConfig) -> Path:
    """Cache file of one test set's plausible sets of one kind ("handle_arcs" or "slit_ranges")."""
    payload = json.dumps({"data": fingerprint, "kind": kind, "config": config.plausible_key()}, sort_keys=True)
    return Path(cache_dir) / f"{kind}_{hashlib.sha256(payload.encode()).hexdigest()[:24]}.json"


def load_cached(path: Path, kind: str) -> dict[int, HandleArc | SlitRange]:
    """Entries of a cache file by view index ({} when the file does not exist)."""
    if not path.exists():
        return {}
    cls = HandleArc if kind == "handle_arcs" else SlitRange
    try:
        return {int(k): cls.from_json(v) for k, v in json.loads(path.read_text())["views"].items()}
    except (OSError, KeyError, ValueError, TypeError) as error:
        raise AmbiguityError(f"ambiguity cache {path} is unreadable ({error}); delete it to recompute") from error


def save_cached(path: Path, entries: Mapping[int, HandleArc | SlitRange]) -> None:
    _atomic_write_json(path, {"views": {str(k): v.to_json() for k, v in sorted(entries.items())}})


# -------------------------------------------------------------------------------------------- run


@dataclass
class AmbiguityRun:
    """One ``pssnet ambiguity`` run.

    Attributes:
        data: directory holding the test sets (``DATA/mugs`` or ``DATA/test/mugs``, ``.../ycb_narrow``).
        sets: the test sets to measure: at most one mug set (``mugs``, ``oof_mugs``) and one narrow-slit set
            (``ycb_narrow``, ``oof_narrow``).
        out: output directory (tables, figures, and the plausible-set cache under ``plausible_cache``).
        samples: completions per view.
        box_temperatures: box temperatures for models with a box part (others run at 1.0 only).
        max_views: at most this many views of each kind (hidden handle, visible handle, slit), evenly spaced.
        seed: latent seed (view ``i`` uses ``seed + i``, the same at every temperature).
        progress: tqdm bars.
        figure_views: views in the arc and slit figures.
        cache_dir: plausible-set cache (default ``out/plausible_cache``).
        config: measurement parameters.
    """

    data: str
    out: str
    sets: tuple[str, ...] = ("mugs", "ycb_narrow")
    samples: int = 20
    box_temperatures: tuple[float, ...] = (1.0,)
    max_views: int | None = None
    seed: int = 0
    progress: bool = True
    figure_views: int = 4
    cache_dir: str | None = None
    config: AmbiguityConfig = field(default_factory=AmbiguityConfig)


def supports_box_temperature(completer: Any) -> bool:
    """Whether a completer samples a box part that a temperature can widen (PSSNet)."""
    model = getattr(completer, "model", completer)
    return int(getattr(model, "box_dim", 0) or 0) > 0


def _sample(completer: Any, view: EvalView, samples: int, seed: int, temperature: float) -> np.ndarray:
    # Models with a box part get the temperature explicitly (a completer may carry another default); the others
    # run at 1.0 only and are called without it.
    if supports_box_temperature(completer):
        result = completer.complete(view, num_samples=samples, seed=seed, box_temperature=temperature)
    else:
        result = completer.complete(view, num_samples=samples, seed=seed)
    return np.asarray(result.occupancy, dtype=bool)


def _spaced(items: list[Any], count: int | None) -> list[Any]:
    if count is not None and count < 1:
        raise AmbiguityError(f"max_views must be >= 1, got {count}")
    return [items[k] for k in evenly_spaced(len(items), count)]


def _nanmean(values: Sequence[float]) -> float:
    a = np.asarray(values, dtype=np.float64)
    return float(np.nanmean(a)) if len(a) and np.isfinite(a).any() else math.nan


class _TestSet:
    """A test set's views, records and meshes (meshes made once per identity)."""

    def __init__(self, root: Path, progress: bool) -> None:
        from pssnet_core.data.store import DatasetReader
        from pssnet_core.evaluation.plausible import dataset_fingerprint
        from pssnet_core.evaluation.testsets import load_test_set

        self.root = root
        self.views, self.meta = load_test_set(root, progress=progress)
        self.records = DatasetReader(root).records
        self.fingerprint = dataset_fingerprint(root)
        self._shapes: dict[str, Any] = {}
        self._parts: dict[str, MugParts] = {}

    def shape(self, identity: str) -> Any:
        from pssnet_core.shapes import shape_of

        if identity not in self._shapes:
            self._shapes[identity] = shape_of(identity)
        return self._shapes[identity]

    def mug(self, identity: str) -> MugParts:
        if identity not in self._parts:
            self._parts[identity] = mug_parts(self.shape(identity))
        return self._parts[identity]

    def depth_view(self, view: EvalView, rerender: bool) -> DepthView:
        if not rerender:
            return view.depth_view
        from pssnet_core.data.datasets import rerender as render_again

        again = render_again(self.records[view.index], self.shape(view.identity))
        return DepthView(np.asarray(again.depth, dtype=np.float32), np.asarray(again.mask) != 0, again.intrinsics)


def _plausible_sets(test: _TestSet, views: list[EvalView], kind: str, run: AmbiguityRun,
                    cache_dir: Path) -> tuple[dict[int, Any], dict[str, Any]]:
    """Cached or computed plausible sets of ``views``; returns them and cost figures."""
    from tqdm import tqdm

    path = cache_path(cache_dir, test.fingerprint, kind, run.config)
    entries = load_cached(path, kind)
    missing = [v for v in views if v.index not in entries]
    t0 = time.perf_counter()
    for view in tqdm(missing, desc=f"plausible {kind}", unit="view", disable=not run.progress, dynamic_ncols=True):
        depth_view = test.depth_view(view, run.config.rerender)
        if kind == "handle_arcs":
            entries[view.index] = plausible_handle_arc(view, depth_view, test.mug(view.identity), run.config)
        else:
            mesh = test.shape(view.identity).mesh
            entries[view.index] = plausible_slit_range(view, depth_view, np.asarray(mesh.vertices),
                                                       np.asarray(mesh.faces), run.config)
    if missing:
        save_cached(path, entries)
    wanted = {v.index: entries[v.index] for v in views}
    cost = {"views": len(views), "computed_now": len(missing), "cached": len(views) - len(missing),
            "seconds_now": time.perf_counter() - t0,
            "seconds_per_view": _nanmean([e.seconds for e in wanted.values()]),
            "seconds_all_views": float(sum(e.seconds for e in wanted.values())), "cache": str(path)}
    return wanted, cost


def run_ambiguity(run: AmbiguityRun, completers: Mapping[str, Any]) -> dict[str, Path]:
    """Measures every completer (at each box temperature) on hidden/visible-handle mugs and narrow-slit boxes.

    Writes ``ambiguity.md`` (tables), ``ambiguity.json`` (summary, per-view rows, plausible sets, costs),
    ``ambiguity_per_view.csv`` and the figures ``handle_arcs.png``, ``slit_extents.png`` and
    ``ambiguity_summary.png`` into ``run.out``.

    Args:
        run: what to measure and where to write it.
        completers: method name -> completer (``complete(observation, num_samples, seed[, box_temperature])``
            returning an object with ``occupancy``; ``pssnet_core.inference.Completer`` fits).

    Returns:
        The files written, by kind.
    """
    from tqdm import tqdm

    from pssnet_core.evaluation.testsets import MUG_SETS, NARROW_SETS, build_command, find_test_set
    from pssnet_core.shapes import BOX_FAMILIES

    mug_sets = [s for s in run.sets if s in MUG_SETS]
    slit_sets = [s for s in run.sets if s in NARROW_SETS]
    if len(mug_sets) > 1 or len(slit_sets) > 1 or len(mug_sets) + len(slit_sets) != len(run.sets) or not run.sets:
        raise AmbiguityError(f"sets must name at most one mug set {MUG_SETS} and one narrow-slit set {NARROW_SETS}, "
                             f"got {list(run.sets)}")
    if run.samples < 2:
        raise AmbiguityError(f"samples must be >= 2 to measure a spread, got {run.samples}")
    if not completers:
        raise AmbiguityError("no completers given")
    if not run.box_temperatures or any(not (math.isfinite(t) and t > 0) for t in run.box_temperatures):
        raise AmbiguityError(f"box temperatures must be positive, got {run.box_temperatures}")
    config = run.config
    out = Path(run.out)
    cache_dir = Path(run.cache_dir) if run.cache_dir else out / "plausible_cache"
    t_start = time.perf_counter()
    mugs_root = find_test_set(run.data, mug_sets[0]) if mug_sets else None
    slit_root = find_test_set(run.data, slit_sets[0]) if slit_sets else None
    if mugs_root is None and slit_root is None:
        raise AmbiguityError(f"none of the test sets {list(run.sets)} under {run.data} (build them with "
                             f"`{build_command(run.sets[0])}`)")
    hidden: list[EvalView] = []
    visible: list[EvalView] = []
    slit: list[EvalView] = []
    geometries: dict[str, HandleGeometry] = {}
    arcs: dict[int, HandleArc] = {}
    ranges: dict[int, SlitRange] = {}
    costs: dict[str, Any] = {}
    if mugs_root is not None:
        mugs = _TestSet(mugs_root, run.progress)
        geometries = handle_geometries(v.identity for v in mugs.views)
        measurable = [v for v in mugs.views if v.identity in geometries]
        hidden = _spaced([v for v in measurable if v.meta.get("handle_visible") is False], run.max_views)
        visible = _spaced([v for v in measurable if v.meta.get("handle_visible") is True], run.max_views)
        arcs, costs["handle_arcs"] = _plausible_sets(mugs, hidden, "handle_arcs", run, cache_dir)
    if slit_root is not None:
        narrow = _TestSet(slit_root, run.progress)
        slit = _spaced([v for v in narrow.views if v.meta.get("family") in BOX_FAMILIES], run.max_views)
        ranges, costs["slit_ranges"] = _plausible_sets(narrow, slit, "slit_ranges", run, cache_dir)
    if not (hidden or visible or slit):
        raise AmbiguityError(f"no measurable views in {list(run.sets)} under {run.data}: no round mug with a handle "
                             "in the mug set and no box in the narrow-slit set")

    for name, completer in completers.items():
        size = (hidden + visible + slit)[0].grid_pose.size
        if getattr(completer, "grid_size", size) != size:
            raise AmbiguityError(f"{name} completes {completer.grid_size}^3 grids but the test views are {size}^3")
    runs = [(name, t) for name, c in completers.items()
            for t in (run.box_temperatures if supports_box_temperature(c) else (1.0,))]
    runs = list(dict.fromkeys(runs))
    rows: list[dict[str, Any]] = []
    t_sampling = 0.0
    jobs = [("hidden_handle", v) for v in hidden] + [("visible_handle", v) for v in visible] + \
        [("slit", v) for v in slit]
    for kind, view in tqdm(jobs, desc="sample and measure", unit="view", disable=not run.progress,
                           dynamic_ncols=True):
        for name, temperature in runs:
            t0 = time.perf_counter()
            samples = _sample(completers[name], view, run.samples, run.seed + view.index, temperature)
            t_sampling += time.perf_counter() - t0
            base = {"method": name, "box_temperature": float(temperature), "kind": kind, "index": view.index,
                    "identity": view.identity, "rotation_deg": view.meta.get("rotation_deg")}
            if kind == "slit":
                rows += _slit_rows(base, ranges[view.index], grid_x_extent(samples), config)
                continue
            az = handle_azimuths(samples, view.grid_pose, view.object_pose, geometries[view.identity])
            if kind == "visible_handle":
                found = az[np.isfinite(az)]
                rows.append({**base, "delta": None, "handle_rate": float(np.isfinite(az).mean()),
                             "error_deg": float(circular_difference_deg(found, 0.0).mean()) if len(found)
                             else math.nan, "azimuths_deg": [float(a) for a in az]})
            else:
                rows += _arc_rows(base, arcs[view.index], az, config)
    summary = summarise_ambiguity(rows, runs, config.deltas)
    costs["sampling_seconds"] = t_sampling
    costs["total_seconds"] = time.perf_counter() - t_start
    out.mkdir(parents=True, exist_ok=True)
    files = {"markdown": out / "ambiguity.md", "json": out / "ambiguity.json"}
    files["markdown"].write_text(markdown_ambiguity(summary, run, costs, arcs, ranges))
    files["json"].write_text(json.dumps(_plain({
        "run": {k: v for k, v in asdict(run).items() if k != "config"}, "config": asdict(run.config),
        "summary": summary, "costs": costs, "rows": rows,
        "plausible": {"handle_arcs": {str(k): a.to_json() for k, a in arcs.items()},
                      "slit_ranges": {str(k): r.to_json() for k, r in ranges.items()}},
    }), indent=1, allow_nan=False))
    from pssnet_core.evaluation.experiment import write_csv

    files["csv"] = write_csv(out / "ambiguity_per_view.csv",
                             [{k: v for k, v in r.items() if not isinstance(v, list)} for r in rows])
    delta = config.deltas[0]
    if arcs:
        files["handle_figure"] = plot_handle_arcs(out / "handle_arcs.png", arcs, rows, runs, delta,
                                                  run.figure_views)
    if ranges:
        files["slit_figure"] = plot_slit_extents(out / "slit_extents.png", ranges, rows, runs, delta,
                                                 3 * run.figure_views)
    files["summary_figure"] = plot_summary(out / "ambiguity_summary.png", summary, runs, delta)
    return files


def _plain(value: Any) -> Any:
    """JSON-ready copy: numpy values as Python ones, NaN/inf as null (standard JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _arc_rows(base: dict[str, Any], arc: HandleArc, azimuths: np.ndarray, config: AmbiguityConfig) -> list[dict]:
    rows = []
    for delta in config.deltas:
        allowed = arc.arc(delta)
        s = arc_scores(allowed, azimuths, config.arc_tolerance_deg, config.arc_margin_deg)
        rows.append({**base, "delta": delta, "coverage": s.coverage, "precision": s.precision,
                     "spread_ratio": s.spread_ratio, "handle_rate": s.rate, "arc_size": int(len(allowed)),
                     "arc_spread_deg": circular_spread_deg(allowed), "sample_spread_deg": circular_spread_deg(azimuths),
                     "truth_in_arc": arc.truth_accepted(delta), "azimuths_deg": [float(a) for a in azimuths]})
    return rows


def _slit_rows(base: dict[str, Any], plausible: SlitRange, extents: np.ndarray, config: AmbiguityConfig) -> list[dict]:
    rows = []
    mm = plausible.voxel_size * 1000.0
    found = extents[np.isfinite(extents)]
    for delta in config.deltas:
        allowed = plausible.extents(delta)
        s = extent_scores(allowed, extents, config.extent_tolerance_voxels, config.extent_margin_voxels)
        rows.append({**base, "delta": delta, "coverage": s.coverage, "precision": s.precision,
                     "spread_ratio": s.spread_ratio, "nonempty_rate": s.rate,
                     "plausible_min_mm": float(allowed.min() * mm), "plausible_max_mm": float(allowed.max() * mm),
                     "true_mm": plausible.true_extent_voxels * mm,
                     "sample_min_mm": float(found.min() * mm) if len(found) else math.nan,
                     "sample_max_mm": float(found.max() * mm) if len(found) else math.nan,
                     "sample_mean_mm": float(found.mean() * mm) if len(found) else math.nan,
                     "open_ended": plausible.open_ended(delta), "truth_accepted": plausible.truth_accepted(delta),
                     "extents_mm": [float(x * mm) for x in extents]})
    return rows


SUMMARY_KEYS: tuple[tuple[str, str, str], ...] = (
    # (summary key, row kind, row key)
    ("hidden_views", "hidden_handle", "count"),
    ("arc_azimuths", "hidden_handle", "arc_size"),
    ("arc_coverage", "hidden_handle", "coverage"),
    ("arc_precision", "hidden_handle", "precision"),
    ("arc_spread_ratio", "hidden_handle", "spread_ratio"),
    ("handle_rate_hidden", "hidden_handle", "handle_rate"),
    ("truth_in_arc", "hidden_handle", "truth_in_arc"),
    ("visible_views", "visible_handle", "count"),
    ("handle_error_visible_deg", "visible_handle", "error_deg"),
    ("handle_rate_visible", "visible_handle", "handle_rate"),
    ("slit_views", "slit", "count"),
    ("slit_coverage", "slit", "coverage"),
    ("slit_precision", "slit", "precision"),
    ("slit_spread_ratio", "slit", "spread_ratio"),
    ("slit_plausible_min_mm", "slit", "plausible_min_mm"),
    ("slit_plausible_max_mm", "slit", "plausible_max_mm"),
    ("slit_true_mm", "slit", "true_mm"),
    ("slit_sample_min_mm", "slit", "sample_min_mm"),
    ("slit_sample_max_mm", "slit", "sample_max_mm"),
    ("slit_open_ended", "slit", "open_ended"),
)


def summarise_ambiguity(rows: Sequence[dict[str, Any]], runs: Sequence[tuple[str, float]],
                        deltas: Sequence[float]) -> list[dict[str, Any]]:
    """Means over views per (method, box temperature, delta) (NaN-aware; visible-handle rows at every delta),
    plus the medians of the spread ratios."""
    out = []
    for name, temperature in runs:
        for delta in deltas:
            entry: dict[str, Any] = {"method": name, "box_temperature": temperature, "delta_m": delta}
            for key, kind, column in SUMMARY_KEYS:
                chosen = [r for r in rows if r["method"] == name and r["box_temperature"] == temperature
                          and r["kind"] == kind and (r["delta"] is None or abs(r["delta"] - delta) < 1e-12)]
                if column == "count":
                    entry[key] = len(chosen)
                else:
                    entry[key] = _nanmean([float(r[column]) for r in chosen])
            # A view whose plausible set is narrow makes its spread ratio large: the medians show how much the
            # means owe to a few such views.
            for key, kind in (("arc_spread_ratio_median", "hidden_handle"), ("slit_spread_ratio_median", "slit")):
                values = np.array([r["spread_ratio"] for r in rows if r["method"] == name
                                   and r["box_temperature"] == temperature and r["kind"] == kind
                                   and abs(r["delta"] - delta) < 1e-12], dtype=np.float64)
                entry[key] = float(np.nanmedian(values)) if np.isfinite(values).any() else math.nan
            out.append(entry)
    return out


def _f(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.{digits}f}"


def markdown_ambiguity(summary: Sequence[dict[str, Any]], run: AmbiguityRun, costs: dict[str, Any],
                       arcs: Mapping[int, HandleArc], ranges: Mapping[int, SlitRange]) -> str:
    """The Markdown report: one table per delta (rows = method x box temperature), then costs."""
    c = run.config
    lines = ["# Ambiguity: do the samples spread over what the view allows?", "",
             f"Test sets {', '.join(f'`{s}`' for s in run.sets)} under `{run.data}`; {run.samples} samples per view, "
             f"seed {run.seed} (view i uses seed + i, "
             "the same at every box temperature). See `pssnet_core/evaluation/ambiguity.py` for the definitions.", "",
             f"- Hidden handle: plausible arc = azimuths ({c.azimuth_step_deg:g} deg steps) where the mug turned about "
             f"its axis passes the observation model; coverage = arc azimuths with a sampled handle within "
             f"{c.arc_tolerance_deg:g} deg; precision = sampled handles within {c.arc_margin_deg:g} deg of the arc; "
             "spread ratio = circular s.d. of sampled azimuths / that of the arc; handle rate = samples with a "
             "handle. Visible handle: mean |sampled azimuth - truth|.",
             f"- Narrow slit (boxes): the box stretched along its axis away from the camera in "
             f"{c.extent_step_voxels:g}-voxel steps; extents = grid-x extent of the largest connected part; coverage "
             f"within {c.extent_tolerance_voxels:g} voxel, precision margin {c.extent_margin_voxels:g} voxel; "
             "'open' = fraction of views whose plausible range reaches the end of the grid.", ""]
    for delta in c.deltas:
        note = "scaled to real-size objects" if abs(delta - DEFAULT_DELTAS[0]) < 1e-12 else (
            "the paper's value" if abs(delta - DEFAULT_DELTAS[1]) < 1e-12 else "")
        lines += [f"## delta = {delta * 100:g} cm{f' ({note})' if note else ''}", ""]
        header = ["method", "box T", "hidden views", "arc width (deg)", "arc coverage", "arc precision",
                  "arc spread ratio", "handle rate hidden", "visible views", "handle error visible (deg)",
                  "slit views", "plausible extent (mm)", "sampled extent (mm)", "true extent (mm)", "open",
                  "slit coverage", "slit precision", "slit spread ratio"]
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for e in [s for s in summary if abs(s["delta_m"] - delta) < 1e-12]:
            width = e["arc_azimuths"] * c.azimuth_step_deg
            cells = [e["method"], f"{e['box_temperature']:g}", str(e["hidden_views"]), _f(width, 0),
                     _f(e["arc_coverage"]), _f(e["arc_precision"]), _f(e["arc_spread_ratio"]),
                     _f(e["handle_rate_hidden"]), str(e["visible_views"]), _f(e["handle_error_visible_deg"], 1),
                     str(e["slit_views"]),
                     f"{_f(e['slit_plausible_min_mm'], 0)}-{_f(e['slit_plausible_max_mm'], 0)}",
                     f"{_f(e['slit_sample_min_mm'], 0)}-{_f(e['slit_sample_max_mm'], 0)}", _f(e["slit_true_mm"], 0),
                     _f(e["slit_open_ended"]), _f(e["slit_coverage"]), _f(e["slit_precision"]),
                     _f(e["slit_spread_ratio"])]
            lines.append("| " + " | ".join(cells) + " |")
        if arcs:
            truth = np.mean([a.truth_accepted(delta) for a in arcs.values()])
            lines.append("")
            lines.append(f"Arc width = mean number of plausible azimuths x {c.azimuth_step_deg:g} deg; the true "
                         f"mug passes in {truth:.0%} of the hidden views.")
        if ranges:
            truth = np.mean([r.truth_accepted(delta) for r in ranges.values()])
            lines.append(f"Extents are means over views of each view's min/max; the true box passes in {truth:.0%} "
                         "of the slit views.")
        lines.append("")
    lines += ["## Cost", ""]
    for kind in ("handle_arcs", "slit_ranges"):
        if kind in costs:
            k = costs[kind]
            lines.append(f"- Plausible {kind.replace('_', ' ')} (model-independent, cached in `{k['cache']}`): "
                         f"{k['views']} views, {k['seconds_per_view']:.2f} s per view on one core "
                         f"({k['seconds_all_views']:.1f} s in all; {k['computed_now']} computed in this run, "
                         f"{k['cached']} from the cache).")
    lines.append(f"- Sampling: {costs['sampling_seconds']:.1f} s; whole run {costs['total_seconds']:.1f} s.")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------- figures


def _run_label(name: str, temperature: float) -> str:
    return name if temperature == 1.0 else f"{name} T={temperature:g}"


def plot_handle_arcs(path: str | Path, arcs: Mapping[int, HandleArc], rows: Sequence[dict[str, Any]],
                     runs: Sequence[tuple[str, float]], delta: float, count: int = 4) -> Path:
    """Polar plots of a few hidden-handle views: the plausible arc (shaded) and each run's sampled handles.

    Picks the views with the widest arcs (the most ambiguous). The true handle is at 0 degrees (star); each
    run's samples lie on their own ring.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.evaluation.figures import save_figure

    chosen = sorted(arcs.values(), key=lambda a: (-len(a.arc(delta)), a.index))[:max(1, count)]
    fig, axes = plt.subplots(1, len(chosen), figsize=(4.2 * len(chosen), 4.6), squeeze=False,
                             subplot_kw={"projection": "polar"})
    colours = plt.get_cmap("tab10")
    for ax, arc in zip(axes[0], chosen, strict=True):
        step = np.radians(arc.azimuths_deg[1] - arc.azimuths_deg[0]) if len(arc.azimuths_deg) > 1 else 0.1
        allowed = np.radians(arc.arc(delta))
        ax.bar(allowed, np.full(len(allowed), len(runs) + 1.0), width=step, bottom=0.0, color="tab:green",
               alpha=0.25, label="plausible arc")
        ax.plot([0.0], [len(runs) + 0.6], marker="*", markersize=14, color="black", linestyle="", label="true handle")
        ax.plot([np.radians(arc.camera_azimuth_deg)], [len(runs) + 0.6], marker="s", markersize=8, color="tab:red",
                linestyle="", label="camera")
        for k, (name, temperature) in enumerate(runs):
            row = next((r for r in rows if r["kind"] == "hidden_handle" and r["index"] == arc.index
                        and r["method"] == name and r["box_temperature"] == temperature), None)
            if row is None:
                continue
            az = np.array(row["azimuths_deg"], dtype=np.float64)
            az = az[np.isfinite(az)]
            ax.plot(np.radians(az), np.full(len(az), k + 1.0), "o", color=colours(k % 10), alpha=0.7, markersize=5,
                    label=_run_label(name, temperature))
        ax.set_ylim(0, len(runs) + 1.0)
        ax.set_yticks([])
        ax.set_title(f"view {arc.index} ({arc.identity})\narc {len(allowed)} x {np.degrees(step):.0f} deg", fontsize=8)
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.08, 1.0), fontsize=7)
    fig.suptitle(f"Hidden handles: plausible arc (delta {delta * 100:g} cm) vs sampled handle azimuths "
                 "(0 deg = true handle; one ring per model)", fontsize=9)
    return save_figure(fig, path, dpi=100)


def plot_slit_extents(path: str | Path, ranges: Mapping[int, SlitRange], rows: Sequence[dict[str, Any]],
                      runs: Sequence[tuple[str, float]], delta: float, count: int = 12) -> Path:
    """Per narrow-slit box view: the plausible extent range (bar), the truth and each run's sampled extents."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.evaluation.figures import save_figure

    chosen = _spaced(sorted(ranges.values(), key=lambda r: r.index), max(1, count))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(chosen) * (1 + 0.15 * len(runs))), 4.2))
    colours = plt.get_cmap("tab10")
    width = 0.8
    for x, plausible in enumerate(chosen):
        mm = plausible.voxel_size * 1000.0
        allowed = plausible.extents(delta) * mm
        ax.bar(x, allowed.max() - allowed.min() + mm, bottom=allowed.min() - 0.5 * mm, width=width,
               color="tab:green", alpha=0.25, label="plausible range" if x == 0 else None)
        ax.plot([x - width / 2, x + width / 2], [plausible.true_extent_voxels * mm] * 2, color="black", linewidth=2,
                label="truth" if x == 0 else None)
        for k, (name, temperature) in enumerate(runs):
            row = next((r for r in rows if r["kind"] == "slit" and r["index"] == plausible.index
                        and r["method"] == name and r["box_temperature"] == temperature
                        and abs(r["delta"] - delta) < 1e-12), None)
            if row is None:
                continue
            ext = np.array(row["extents_mm"], dtype=np.float64)
            ext = ext[np.isfinite(ext)]
            offset = -width / 2 + (k + 0.5) * width / max(len(runs), 1)
            jitter = np.linspace(-0.03, 0.03, len(ext)) if len(ext) > 1 else np.zeros(len(ext))
            ax.plot(x + offset + jitter, ext, "o", color=colours(k % 10), alpha=0.6, markersize=4,
                    label=_run_label(name, temperature) if x == 0 else None)
    ax.set_xticks(range(len(chosen)))
    ax.set_xticklabels([f"{r.index}\n{r.identity}" for r in chosen], fontsize=7)
    ax.set_ylabel("extent along the viewing direction (mm)")
    ax.set_title(f"Boxes through the narrow slit: plausible hidden extent (delta {delta * 100:g} cm) vs samples",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def plot_summary(path: str | Path, summary: Sequence[dict[str, Any]], runs: Sequence[tuple[str, float]],
                 delta: float) -> Path:
    """Bars of the six headline figures per run at ``delta``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.evaluation.figures import save_figure

    keys = [("arc_coverage", "arc coverage"), ("arc_precision", "arc precision"),
            ("arc_spread_ratio", "arc spread ratio"), ("slit_coverage", "slit coverage"),
            ("slit_precision", "slit precision"), ("slit_spread_ratio", "slit spread ratio")]
    entries = {(e["method"], e["box_temperature"]): e for e in summary if abs(e["delta_m"] - delta) < 1e-12}
    fig, ax = plt.subplots(figsize=(8.5, 3.8))
    colours = plt.get_cmap("tab10")
    width = 0.8 / max(len(runs), 1)
    for k, run in enumerate(runs):
        e = entries.get(run, {})
        values = [e.get(key, math.nan) for key, _ in keys]
        values = [v if isinstance(v, float) and math.isfinite(v) else 0.0 for v in values]
        ax.bar(np.arange(len(keys)) + (k - (len(runs) - 1) / 2) * width, values, width=width,
               color=colours(k % 10), label=_run_label(*run))
    ax.axhline(1.0, color="grey", linewidth=0.8, linestyle=":")
    ax.set_xticks(range(len(keys)))
    ax.set_xticklabels([label for _, label in keys], fontsize=8)
    ax.set_title(f"Ambiguity figures at delta {delta * 100:g} cm (1 = samples spread as the view allows; "
                 "missing = n/a)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


__all__ = ["DEFAULT_DELTAS", "AmbiguityConfig", "AmbiguityError", "AmbiguityRun", "HandleArc", "MugParts",
           "SlitRange",
           "SpreadScores", "arc_scores", "extent_scores", "grid_x_extent", "hidden_axis", "markdown_ambiguity",
           "mug_parts", "plausible_handle_arc", "plausible_slit_range", "plot_handle_arcs", "plot_slit_extents",
           "plot_summary", "run_ambiguity", "stretched", "summarise_ambiguity", "supports_box_temperature"]
