"""Where sampled mugs put their handle: the measure behind "hidden handles differ, visible ones are reproduced".

For a test mug with a round body and a handle, every sampled completion is moved into the mug's own frame
(vertical axis at x = y = 0, the true handle along +x, see :mod:`pssnet_core.shapes.procedural`; mugs of the
independent generator and real ones follow the same frame). Voxels
that stick out of the body (radial distance beyond the body's radius plus one voxel) at the height of the
true handle are the sample's handle; their mean azimuth is the handle's position (0 degrees = where the true
handle is). Per view and method this gives:

- ``handle_rate``: fraction of samples that have a handle (at least ``min_voxels`` protruding voxels);
- ``spread_deg``: circular standard deviation of the handle azimuths across samples (0 = all samples agree);
- ``error_deg``: circular mean of |azimuth| (how far samples put the handle from the truth);
- ``pairwise_mm``: mean chamfer distance between pairs of samples (shape diversity of any kind).

Why a handle-specific measure next to the generic pairwise distance: a model can be "diverse" by blurring
the body, which says nothing about whether it proposes the hidden handle in different places.

``pssnet handles`` (:func:`run_handles`) measures every view of the measurable mugs of a test set; its report is
:func:`pssnet_core.evaluation.handles_report.handles_report`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.experiment import Completer, sample_occupancy
from pssnet_core.evaluation.metrics import chamfer_matrix
from pssnet_core.evaluation.plausible import EvalView
from pssnet_core.shapes import Shape

MIN_HANDLE_VOXELS = 3


class HandleMeasureError(ValueError):
    """The mug cannot be measured (no handle, square body) or the inputs disagree."""


@dataclass(frozen=True)
class HandleGeometry:
    """What is needed to find a handle in the mug's frame (metres).

    Attributes:
        body_radius: largest radial distance of the body (the mesh on the side away from the handle).
        z_min, z_max: height range of the true handle.
        reach: largest radial distance of the true handle.
    """

    body_radius: float
    z_min: float
    z_max: float
    reach: float

    @classmethod
    def of(cls, shape: Shape) -> HandleGeometry:
        if shape.handle is None or shape.attributes.get("square_body"):
            raise HandleMeasureError(f"{shape.identity}: only round mugs with a handle can be measured")
        v = np.asarray(shape.mesh.vertices)
        body = v[v[:, 0] < 0]  # the handle points along +x: the -x half is body only
        h = np.asarray(shape.handle.vertices)
        return cls(body_radius=float(np.hypot(body[:, 0], body[:, 1]).max()), z_min=float(h[:, 2].min()),
                   z_max=float(h[:, 2].max()), reach=float(np.hypot(h[:, 0], h[:, 1]).max()))


@dataclass(frozen=True)
class HandleStats:
    """Handle statistics of one method's samples on one view (angles in degrees, distances in mm)."""

    handle_rate: float
    spread_deg: float
    error_deg: float
    pairwise_mm: float
    azimuths_deg: tuple[float, ...]


def handle_geometries(identities: Iterable[str], limit: int | None = None) -> dict[str, HandleGeometry]:
    """:class:`HandleGeometry` of every measurable mug among ``identities`` (mugs of any source: "mug-", "imug-",
    "rmug-" identities).

    Square bodies, handle-less mugs and other families are skipped (they have no handle azimuth).

    Args:
        identities: object identities, in the order wanted (repeats are measured once).
        limit: stop after this many measurable mugs (None = all).
    """
    from pssnet_core.shapes import MUG_FAMILIES, ShapeError, ShapeId, shape_of  # only when meshes are rebuilt

    out: dict[str, HandleGeometry] = {}
    for identity in identities:
        if identity in out:
            continue
        if limit is not None and len(out) >= limit:
            break
        try:
            sid = ShapeId.parse(identity)
        except ShapeError:
            continue
        if sid.family not in MUG_FAMILIES:
            continue
        try:
            out[identity] = HandleGeometry.of(shape_of(sid))
        except HandleMeasureError:
            continue
    return out


def turned(camera_from_object: np.ndarray, azimuth_deg: float) -> np.ndarray:
    """The mug's pose turned about its own vertical axis so that its handle lies at ``azimuth_deg``.

    This is the azimuth :func:`handle_azimuths` measures: the mug frame's z is the body's axis (x = y = 0) and
    the handle points along +x, so ``pose @ Rz(a)`` puts the handle at azimuth ``a`` of the original frame, at
    the same place and height (the body is a surface of revolution, so only the handle moves).
    """
    a = math.radians(float(azimuth_deg))
    rz = np.eye(4)
    rz[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return np.asarray(camera_from_object, dtype=np.float64) @ rz


def handle_azimuths(samples: np.ndarray, grid_pose: Any, camera_from_object: np.ndarray,
                    geometry: HandleGeometry, min_voxels: int = MIN_HANDLE_VOXELS) -> np.ndarray:
    """Handle azimuth (degrees, true handle = 0) of each sample; NaN where a sample has no handle.

    Args:
        samples: (n, N, N, N) bool occupancy in the observation grid.
        grid_pose: the view's :class:`~pssnet_core.geometry.GridPose`.
        camera_from_object: 4x4 pose of the mug in the camera frame.
        geometry: the mug's :class:`HandleGeometry`.
        min_voxels: protruding voxels needed to count as a handle.
    """
    samples = np.asarray(samples, dtype=bool)
    if samples.ndim != 4:
        raise HandleMeasureError(f"samples must be (n, N, N, N), got shape {samples.shape}")
    object_from_camera = np.linalg.inv(np.asarray(camera_from_object, dtype=np.float64))
    voxel = float(grid_pose.voxel_size)
    out = np.full(len(samples), np.nan)
    for k, grid in enumerate(samples):
        cam = grid_pose.occupied_centres(grid)
        if not len(cam):
            continue
        obj = cam @ object_from_camera[:3, :3].T + object_from_camera[:3, 3]
        radius = np.hypot(obj[:, 0], obj[:, 1])
        handle = ((radius > geometry.body_radius + voxel) & (radius < geometry.reach + 2 * voxel)
                  & (obj[:, 2] > geometry.z_min - voxel) & (obj[:, 2] < geometry.z_max + voxel))
        if handle.sum() >= min_voxels:
            angles = np.arctan2(obj[handle, 1], obj[handle, 0])
            out[k] = math.degrees(math.atan2(np.sin(angles).mean(), np.cos(angles).mean()))
    return out


def circular_spread_deg(angles_deg: np.ndarray) -> float:
    """Circular standard deviation sqrt(-2 ln R) in degrees of the finite angles (NaN if fewer than 2)."""
    a = np.radians(np.asarray(angles_deg, dtype=np.float64))
    a = a[np.isfinite(a)]
    if len(a) < 2:
        return math.nan
    r = min(1.0, float(np.hypot(np.sin(a).mean(), np.cos(a).mean())))
    return math.degrees(math.sqrt(-2.0 * math.log(max(r, 1e-12))))


def circular_difference_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| on the circle, in [0, 180] degrees (broadcasting)."""
    d = np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)) % 360.0
    return np.minimum(d, 360.0 - d)


def azimuth_error_deg(azimuths_deg: np.ndarray, truth_deg: float = 0.0) -> float:
    """Mean circular distance of the finite azimuths from the truth (NaN if there are none)."""
    a = np.asarray(azimuths_deg, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(circular_difference_deg(a, truth_deg).mean()) if len(a) else math.nan


def handle_stats(samples: np.ndarray, view: EvalView, geometry: HandleGeometry) -> HandleStats:
    """:class:`HandleStats` of one view's samples."""
    az = handle_azimuths(samples, view.grid_pose, view.object_pose, geometry)
    pair = chamfer_matrix(samples, samples, view.grid_pose.voxel_size)
    off_diagonal = pair[~np.eye(len(samples), dtype=bool)]
    return HandleStats(handle_rate=float(np.isfinite(az).mean()), spread_deg=circular_spread_deg(az),
                       error_deg=azimuth_error_deg(az),
                       pairwise_mm=float(off_diagonal.mean() * 1000) if len(off_diagonal) else 0.0,
                       azimuths_deg=tuple(float(x) for x in az))


def summarise_handles(rows: Sequence[dict[str, Any]], methods: Sequence[str]) -> list[dict[str, Any]]:
    """Mean of each statistic per method and handle visibility (NaN-aware)."""
    out = []
    for method in methods:
        for visible in (False, True):
            chosen = [r for r in rows if r["method"] == method and r["handle_visible"] == visible]
            if not chosen:
                continue
            row: dict[str, Any] = {"method": method, "handle": "visible" if visible else "hidden",
                                   "views": len(chosen)}
            for key in ("handle_rate", "spread_deg", "error_deg", "pairwise_mm"):
                values = np.array([r[key] for r in chosen], dtype=np.float64)
                row[key] = float(np.nanmean(values)) if np.isfinite(values).any() else math.nan
            out.append(row)
    return out


def stats_row(method: str, view: EvalView, stats: HandleStats) -> dict[str, Any]:
    """One CSV row: method, view, visibility and the statistics."""
    row = {"method": method, "index": view.index, "identity": view.identity,
           "rotation_deg": view.meta.get("rotation_deg"), "handle_visible": bool(view.meta.get("handle_visible"))}
    row.update({k: v for k, v in asdict(stats).items() if k != "azimuths_deg"})
    return row


# --------------------------------------------------------------------------------------- the experiment


@dataclass(frozen=True)
class HandlesConfig:
    """One ``pssnet handles`` run.

    Attributes:
        data: the mugs test set, or a directory holding ``mugs`` or ``test/mugs``.
        out: output directory.
        samples: completions per view (>= 2, to measure a spread).
        max_mugs: measure only the first K measurable mugs (None = all).
        seed: latent seed (every view uses it).
        progress: tqdm bar.
    """

    data: str
    out: str = "results/handles"
    samples: int = 20
    max_mugs: int | None = None
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        if self.samples < 2:
            raise HandleMeasureError(f"samples must be >= 2 to measure a spread, got {self.samples}")


@dataclass
class HandleFigure:
    """Samples of one view for a figure: each method's grids and their handle azimuths, and the truth."""

    label: str
    title: str
    truth: np.ndarray
    grids: dict[str, np.ndarray]
    azimuths: dict[str, np.ndarray]


@dataclass
class HandlesResult:
    """What :func:`run_handles` measured: one row per (view, method) (:func:`stats_row`), and the figures."""

    config: HandlesConfig
    root: Path
    methods: list[str]
    mugs: int
    views: int
    rows: list[dict[str, Any]]
    figures: list[HandleFigure]


def _closest(views: Sequence[EvalView], rotation: float) -> EvalView:
    return min(views, key=lambda v: abs((float(v.meta.get("rotation_deg", 0.0)) - rotation + 180) % 360 - 180))


def run_handles(config: HandlesConfig, completers: Mapping[str, Completer]) -> HandlesResult:
    """Samples every view of the round, handled mugs of the test set with every completer and measures the
    handles; then samples the figure views: the first measurable mug with its handle straight behind the body
    (hidden) and seen side-on (visible)."""
    from tqdm import tqdm

    from pssnet_core.data.store import DatasetReader
    from pssnet_core.evaluation.testsets import find_test_set, load_test_set

    root = find_test_set(config.data, "mugs")
    if root is None:
        raise HandleMeasureError(f"no mugs test set under {config.data} (build it with "
                                 "`pssnet dataset build --family mugs --split test`)")
    views, _ = load_test_set(root, progress=config.progress)
    by_mug: dict[str, list[EvalView]] = {}
    for view in views:
        by_mug.setdefault(view.identity, []).append(view)
    # Square bodies and handle-less mugs have no handle azimuth: skipped.
    geometries = handle_geometries(by_mug, config.max_mugs)
    if not geometries:
        raise HandleMeasureError(f"{root} holds no round mug with a handle")
    chosen = [v for identity in geometries for v in by_mug[identity]]
    rows = []
    for view in tqdm(chosen, desc="handles", disable=not config.progress):
        for method, completer in completers.items():
            samples = sample_occupancy(completer, view, config.samples, config.seed)
            rows.append(stats_row(method, view, handle_stats(samples, view, geometries[view.identity])))
    first = by_mug[next(iter(geometries))]
    reader = DatasetReader(root)
    figures = []
    for label, candidates, rotation in (
            ("hidden", [v for v in first if not v.meta.get("handle_visible")], 0.0),
            ("visible", [v for v in first if v.meta.get("handle_visible")], 90.0)):
        if not candidates:
            continue
        view = _closest(candidates, rotation)
        grids, azimuths = {}, {}
        for method, completer in completers.items():
            grids[method] = sample_occupancy(completer, view, 8, config.seed)
            azimuths[method] = handle_azimuths(grids[method], view.grid_pose, view.object_pose,
                                               geometries[view.identity])
        figures.append(HandleFigure(
            label=label, truth=reader.get(view.index, images=False)["occupancy"], grids=grids, azimuths=azimuths,
            title=f"{view.identity}, rotation {view.meta.get('rotation_deg')} deg: handle {label} "
                  f"(true handle azimuth 0 deg)"))
    return HandlesResult(config=config, root=root, methods=list(completers), mugs=len(geometries),
                         views=len(chosen), rows=rows, figures=figures)
