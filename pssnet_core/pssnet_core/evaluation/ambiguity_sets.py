"""The plausible sets of the ambiguity measure: what each view allows, independently of any model.

**Mugs with the handle hidden.** The *plausible handle arc* of a view is the set of azimuths ``a``
(``azimuth_step_deg`` steps) at which the same mug, turned about its own vertical axis at the same place so that
its handle lies at ``a`` (:func:`pssnet_core.evaluation.handles.turned`), is accepted by the observation model
(Alg. 1, :mod:`pssnet_core.evaluation.observation_model`) for that view's depth image. The body is a surface of
revolution, so turning the mug moves only its handle, and that is how it is rendered: the body (the mug less
``Shape.handle``) stays, the handle turns (:func:`mug_parts`). Why not turn the whole mesh: the body is
polygonised with 36 segments, so a turn by an odd multiple of 5 degrees moves its facets, and with the paper's
zero outlier allowance that alone rejected the turned mug by one pixel (measured on test mugs: every odd
multiple of 5 degrees rejected, every even one accepted, in the middle of the arc). Azimuths are those of
:func:`pssnet_core.evaluation.handles.handle_azimuths` (true handle = 0), the one way a sampled handle is found.

**Boxes through the narrow slit.** The box is stretched or shrunk along its own axis that points most nearly away
from the camera (the axis closest to the grid's x, the horizontal viewing direction, see
:class:`pssnet_core.geometry.GridPose`), keeping the face nearest the camera where it is, in steps of
``extent_step_voxels`` voxels of length, as long as it stays inside the grid. The lengths the observation model
accepts form the plausible range of the hidden extent. Extents are compared in the grid: the x extent (voxels) of
the largest connected part of an occupancy grid (:func:`grid_x_extent`), the same measure for the samples and for
the accepted boxes voxelised with the project's one occupancy definition. A range that reaches the largest length
the grid holds is *open-ended*: the view allows deeper boxes than a sample can represent.

The observation model's tolerance delta is a parameter: every plausible set is computed for all ``deltas`` at
once (default the evaluation's scaled 1 cm, then the paper's 4 cm; DESIGN.md). Note that a larger delta is not
simply more permissive: the unreliable pixels are those whose depth gradient exceeds delta, so a larger delta
compares more pixels near depth edges, and some candidates accepted at 1 cm fail at 4 cm.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from pssnet_core.evaluation.handles import turned
from pssnet_core.evaluation.observation_model import (
    DepthView,
    MeshRaycaster,
    MultiDeltaView,
    ObservationModelConfig,
)
from pssnet_core.evaluation.plausible import EvalView

#: the evaluation's deltas: scaled to real-size objects (1 cm) first, then the paper's 4 cm (DESIGN.md)
DEFAULT_DELTAS: tuple[float, ...] = (0.01, 0.04)
CACHE_VERSION = 2  # 2: the handle turns, the body stays (see the module docstring)
REJECTED = -1  # violations entry of a candidate rejected on the sparse pixels at every delta


class AmbiguityError(ValueError):
    """Bad input to the ambiguity measurement (no usable views, bad parameters, unreadable cache)."""


@dataclass(frozen=True)
class AmbiguityMeasure:
    """How the ambiguity is measured: the plausible sets' parameters and the scores' tolerances.

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
                         measure: AmbiguityMeasure | None = None) -> HandleArc:
    """Which handle azimuths the view allows: the handle turned to each, judged by the observation model.

    Args:
        view: the test view (its ``object_pose`` places the true mug in the camera frame).
        depth_view: the depth image to judge against (the stored crop or the re-rendered image).
        mug: the mug's body and handle in its own frame (handle along +x, axis at x = y = 0).
        measure: parameters.
    """
    measure = measure or AmbiguityMeasure()
    t0 = time.perf_counter()
    multi = MultiDeltaView(depth_view, measure.observation, measure.deltas, sparse_pixels=measure.sparse_pixels)
    azimuths = measure.azimuths()
    violations = np.array([_judge(multi, MeshRaycaster(*mug.turned(a)), view.object_pose) for a in azimuths],
                          dtype=np.int64)
    pose = np.asarray(view.object_pose, dtype=np.float64)
    camera = -pose[:3, :3].T @ pose[:3, 3]  # the camera centre in the mug's frame
    return HandleArc(index=view.index, identity=view.identity, deltas=tuple(measure.deltas), azimuths_deg=azimuths,
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
                         measure: AmbiguityMeasure | None = None) -> SlitRange:
    """Which lengths of the box's hidden dimension the view allows (see the module docstring).

    Candidate lengths are the true length plus whole steps of ``extent_step_voxels`` voxels, from the shortest
    positive one up to the longest whose far face stays inside the grid (the true length is always included).
    """
    measure = measure or AmbiguityMeasure()
    t0 = time.perf_counter()
    vertices = np.asarray(vertices, dtype=np.float64)
    pose = np.asarray(view.object_pose, dtype=np.float64)
    grid = view.grid_pose
    bounds = np.stack([vertices.min(axis=0), vertices.max(axis=0)])
    axis, front = hidden_axis(pose, grid.rotation, bounds)
    true_length = float(bounds[1, axis] - bounds[0, axis])
    step = measure.extent_step_voxels * grid.voxel_size
    multi = MultiDeltaView(depth_view, measure.observation, measure.deltas, sparse_pixels=measure.sparse_pixels)
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
    violations_a = np.array(violations, dtype=np.int64).reshape(-1, len(measure.deltas))
    accepted_any = ((violations_a != REJECTED) & (violations_a <= multi.any.allowance)).any(axis=1)
    lengths_a = np.array(lengths)
    truth = int(np.argmin(np.abs(lengths_a - true_length)))
    extents = np.full(len(lengths), np.nan)
    for j in np.flatnonzero(accepted_any | (np.arange(len(lengths)) == truth)):
        extents[j] = grid_x_extent(casters[j].occupancy_grid(grid, pose))[0]
    return SlitRange(index=view.index, identity=view.identity, deltas=tuple(measure.deltas), axis=axis, front=front,
                     true_length_m=true_length, lengths_m=lengths_a, violations=violations_a,
                     extents_voxels=extents, voxel_size=float(grid.voxel_size), allowance=multi.any.allowance,
                     seconds=time.perf_counter() - t0)
