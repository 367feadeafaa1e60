"""``pssnet ambiguity``: do the samples spread over exactly what the view allows?

Two experiments where the shapes a view allows can be enumerated, independently of any model
(:mod:`pssnet_core.evaluation.ambiguity_sets` defines the plausible sets, :mod:`pssnet_core.evaluation.ambiguity_cache`
keeps them on disk):

**Mugs with the handle hidden** (round mugs with a handle, test views whose record says ``handle_visible``
False): the *plausible handle arc* is the set of azimuths at which the same mug, its handle turned there, passes
the observation model. Per view and model:

- ``coverage``: fraction of the arc's azimuths within ``arc_tolerance_deg`` (15) of some sample's handle;
- ``precision``: fraction of the sampled handles within ``arc_margin_deg`` (10) of some azimuth of the arc;
- ``spread_ratio``: circular s.d. of the sampled handle azimuths / circular s.d. of the arc's azimuths
  (1 = the samples spread as widely as the view allows; undefined when the arc is a single azimuth);
- ``handle_rate``: fraction of samples with a handle.

On views with the handle visible the samples should agree with the truth: ``error_deg`` = mean circular
distance of the sampled handles from the true one.

**Boxes through the narrow slit** (``ycb_narrow`` or ``oof_narrow``, objects of a box family): the plausible
range of the hidden extent is the set of box lengths along the viewing direction that pass the observation model,
compared as grid x extents (voxels). The same three figures (``coverage`` within ``extent_tolerance_voxels``,
``precision`` with ``extent_margin_voxels``, ``spread_ratio`` of standard deviations over the distinct
plausible extents), plus the extents in millimetres and whether the range is open-ended.

Which test sets: ``sets`` names one mug set (``mugs`` or ``oof_mugs``, of any mug family: procedural, independent
or real, or their views through the narrow slit, ``mugs_narrow`` and ``oof_mugs_narrow``) and/or one narrow-slit
set (``ycb_narrow`` or ``oof_narrow``); meshes come from
:func:`pssnet_core.shapes.shape_of`, whatever made the object.

The plausible sets are model-independent: :func:`run_ambiguity` computes them once per view and caches them
(by default in the output directory), so re-runs with other checkpoints only sample.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.ambiguity_cache import AmbiguityTestSet, cached_plausible
from pssnet_core.evaluation.ambiguity_sets import (
    AmbiguityError,
    AmbiguityMeasure,
    HandleArc,
    SlitRange,
    grid_x_extent,
)
from pssnet_core.evaluation.experiment import Completer, complete_view, nanmean
from pssnet_core.evaluation.handles import (
    HandleGeometry,
    circular_difference_deg,
    circular_spread_deg,
    handle_azimuths,
    handle_geometries,
)
from pssnet_core.evaluation.plausible import EvalView
from pssnet_core.evaluation.testsets import MUG_SETS, NARROW_SETS, build_command, find_test_set
from pssnet_core.sampling import CheckedResult
from pssnet_core.spread import evenly_spaced


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


@dataclass(frozen=True)
class ArcComposition:
    """What one delta's plausible arcs hold beyond those of a stricter delta, over a set of views.

    Why: Alg. 1 compares depths within delta, so at 4 cm a handle turned towards the camera, in front of the
    body and in plain view, passes wherever it stands less than 4 cm proud of the body. A sampler whose samples
    agree with the image at 1 cm cannot draw those handles, and its coverage of the 4 cm arc is bounded by how
    much of it the 1 cm arc reaches within the coverage tolerance.

    Attributes:
        views: views with both arcs.
        facing_deg: how close to facing the camera a handle counts as facing it.
        facing_share: mean share of the arc's azimuths within ``facing_deg`` of facing the camera.
        strict_cover: mean coverage of the arc by the stricter delta's arc (:func:`arc_scores`): what a sampler
            that drew a handle at every azimuth of the stricter arc, and nowhere else, would score.
    """

    views: int
    facing_deg: float
    facing_share: float
    strict_cover: float


def arc_composition(arcs: Sequence[HandleArc], delta: float, strict_delta: float, facing_deg: float = 45.0,
                    tolerance_deg: float = 15.0) -> ArcComposition:
    """:class:`ArcComposition` of the arcs at ``delta`` against those at ``strict_delta``."""
    facing, cover = [], []
    for arc in arcs:
        wide, strict = arc.arc(delta), arc.arc(strict_delta)
        if len(wide) == 0 or not math.isfinite(arc.camera_azimuth_deg):
            continue
        facing.append(float((circular_difference_deg(wide, arc.camera_azimuth_deg) <= facing_deg).mean()))
        cover.append(arc_scores(wide, strict, tolerance_deg).coverage if len(strict) else 0.0)
    return ArcComposition(views=len(facing), facing_deg=facing_deg, facing_share=nanmean(facing),
                          strict_cover=nanmean(cover))


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


# --------------------------------------------------------------------------------------- the experiment


@dataclass(frozen=True)
class AmbiguityConfig:
    """One ``pssnet ambiguity`` run.

    Attributes:
        data: directory holding the test sets (``DATA/mugs`` or ``DATA/test/mugs``, ``.../ycb_narrow``).
        out: output directory (tables, figures, and the plausible-set cache under ``plausible_cache``).
        sets: the test sets to measure: at most one mug set (``mugs``, ``oof_mugs``, or either through the narrow
            slit, ``mugs_narrow``, ``oof_mugs_narrow``) and one narrow-slit set (``ycb_narrow``, ``oof_narrow``).
        samples: completions per view (>= 2, to measure a spread).
        box_temperatures: box temperatures for models with a box part (others run at 1.0 only).
        max_views: at most this many views of each kind (hidden handle, visible handle, slit), evenly spaced.
        seed: latent seed (view ``i`` uses ``seed + i``, the same at every temperature).
        progress: tqdm bars.
        figure_views: views in the arc and slit figures.
        cache_dir: plausible-set cache (default ``out/plausible_cache``).
        measure: the plausible sets' parameters and the scores' tolerances.
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
    measure: AmbiguityMeasure = field(default_factory=AmbiguityMeasure)

    def __post_init__(self) -> None:
        mug_sets = [s for s in self.sets if s in MUG_SETS]
        slit_sets = [s for s in self.sets if s in NARROW_SETS]
        if len(mug_sets) > 1 or len(slit_sets) > 1 or len(mug_sets) + len(slit_sets) != len(self.sets) or \
                not self.sets:
            raise AmbiguityError(f"sets must name at most one mug set {MUG_SETS} and one narrow-slit set "
                                 f"{NARROW_SETS}, got {list(self.sets)}")
        if self.samples < 2:
            raise AmbiguityError(f"samples must be >= 2 to measure a spread, got {self.samples}")
        if not self.box_temperatures or any(not (math.isfinite(t) and t > 0) for t in self.box_temperatures):
            raise AmbiguityError(f"box temperatures must be positive, got {self.box_temperatures}")
        if self.max_views is not None and self.max_views < 1:
            raise AmbiguityError(f"max_views must be >= 1, got {self.max_views}")

    @property
    def cache(self) -> Path:
        """Where the plausible sets are cached."""
        return Path(self.cache_dir) if self.cache_dir else Path(self.out) / "plausible_cache"


@dataclass
class AmbiguityResult:
    """What :func:`run_ambiguity` measured.

    Attributes:
        config: the run.
        runs: (method, box temperature) pairs sampled, in order.
        rows: one per (run, view, delta) (visible-handle views: one per run and view, delta None).
        arcs: plausible handle arcs of the hidden-handle views, by view index.
        ranges: plausible extent ranges of the slit views, by view index.
        costs: seconds per stage and the plausible sets' cache figures.
    """

    config: AmbiguityConfig
    runs: list[tuple[str, float]]
    rows: list[dict[str, Any]]
    arcs: dict[int, HandleArc]
    ranges: dict[int, SlitRange]
    costs: dict[str, Any]


def _spaced(items: list[EvalView], count: int | None) -> list[EvalView]:
    return [items[k] for k in evenly_spaced(len(items), count)]


def run_ambiguity(config: AmbiguityConfig, completers: Mapping[str, Completer]) -> AmbiguityResult:
    """Measures every completer (at each box temperature) on hidden/visible-handle mugs and narrow-slit boxes."""
    from tqdm import tqdm

    from pssnet_core.shapes import BOX_FAMILIES

    if not completers:
        raise AmbiguityError("no completers given")
    measure = config.measure
    t_start = time.perf_counter()
    mug_sets = [s for s in config.sets if s in MUG_SETS]
    slit_sets = [s for s in config.sets if s in NARROW_SETS]
    mugs_root = find_test_set(config.data, mug_sets[0]) if mug_sets else None
    slit_root = find_test_set(config.data, slit_sets[0]) if slit_sets else None
    if mugs_root is None and slit_root is None:
        raise AmbiguityError(f"none of the test sets {list(config.sets)} under {config.data} (build them with "
                             f"`{build_command(config.sets[0])}`)")
    hidden: list[EvalView] = []
    visible: list[EvalView] = []
    slit: list[EvalView] = []
    geometries: dict[str, HandleGeometry] = {}
    arcs: dict[int, HandleArc] = {}
    ranges: dict[int, SlitRange] = {}
    costs: dict[str, Any] = {}
    if mugs_root is not None:
        mugs = AmbiguityTestSet(mugs_root, config.progress)
        geometries = handle_geometries(v.identity for v in mugs.views)
        measurable = [v for v in mugs.views if v.identity in geometries]
        hidden = _spaced([v for v in measurable if v.meta.get("handle_visible") is False], config.max_views)
        visible = _spaced([v for v in measurable if v.meta.get("handle_visible") is True], config.max_views)
        arcs, costs["handle_arcs"] = cached_plausible(mugs, hidden, "handle_arcs", measure, config.cache,
                                                      config.progress)
    if slit_root is not None:
        narrow = AmbiguityTestSet(slit_root, config.progress)
        slit = _spaced([v for v in narrow.views if v.meta.get("family") in BOX_FAMILIES], config.max_views)
        ranges, costs["slit_ranges"] = cached_plausible(narrow, slit, "slit_ranges", measure, config.cache,
                                                        config.progress)
    if not (hidden or visible or slit):
        raise AmbiguityError(f"no measurable views in {list(config.sets)} under {config.data}: no round mug with a "
                             "handle in the mug set and no box in the narrow-slit set")

    size = (hidden + visible + slit)[0].grid_pose.size
    for name, completer in completers.items():
        if completer.grid_size != size:
            raise AmbiguityError(f"{name} completes {completer.grid_size}^3 grids but the test views are {size}^3")
    runs = [(name, t) for name, c in completers.items()
            for t in (config.box_temperatures if c.has_box_latent else (1.0,))]
    runs = list(dict.fromkeys(runs))
    rows: list[dict[str, Any]] = []
    t_sampling = 0.0
    jobs = [("hidden_handle", v) for v in hidden] + [("visible_handle", v) for v in visible] + \
        [("slit", v) for v in slit]
    for kind, view in tqdm(jobs, desc="sample and measure", unit="view", disable=not config.progress,
                           dynamic_ncols=True):
        for name, temperature in runs:
            t0 = time.perf_counter()
            # Models with a box part get the temperature explicitly (a completer may carry another default).
            result = complete_view(completers[name], view, config.samples, config.seed + view.index,
                                   box_temperature=temperature)
            samples = np.asarray(result.occupancy, dtype=bool)
            t_sampling += time.perf_counter() - t0
            # The checked sampler's accepted proposals: none means the least-violating ones came back.
            accepted = result.accepted if isinstance(result, CheckedResult) else None
            base = {"method": name, "box_temperature": float(temperature), "kind": kind, "index": view.index,
                    "identity": view.identity, "rotation_deg": view.meta.get("rotation_deg"), "accepted": accepted,
                    "nothing_accepted": math.nan if accepted is None else float(accepted == 0)}
            if kind == "slit":
                rows += _slit_rows(base, ranges[view.index], grid_x_extent(samples), measure)
                continue
            az = handle_azimuths(samples, view.grid_pose, view.object_pose, geometries[view.identity])
            if kind == "visible_handle":
                found = az[np.isfinite(az)]
                rows.append({**base, "delta": None, "handle_rate": float(np.isfinite(az).mean()),
                             "error_deg": float(circular_difference_deg(found, 0.0).mean()) if len(found)
                             else math.nan, "azimuths_deg": [float(a) for a in az]})
            else:
                rows += _arc_rows(base, arcs[view.index], az, measure)
    costs["sampling_seconds"] = t_sampling
    costs["total_seconds"] = time.perf_counter() - t_start
    return AmbiguityResult(config=config, runs=runs, rows=rows, arcs=arcs, ranges=ranges, costs=costs)


def _arc_rows(base: dict[str, Any], arc: HandleArc, azimuths: np.ndarray, measure: AmbiguityMeasure) -> list[dict]:
    rows = []
    for delta in measure.deltas:
        allowed = arc.arc(delta)
        s = arc_scores(allowed, azimuths, measure.arc_tolerance_deg, measure.arc_margin_deg)
        rows.append({**base, "delta": delta, "coverage": s.coverage, "precision": s.precision,
                     "spread_ratio": s.spread_ratio, "handle_rate": s.rate, "arc_size": int(len(allowed)),
                     "arc_spread_deg": circular_spread_deg(allowed), "sample_spread_deg": circular_spread_deg(azimuths),
                     "truth_in_arc": arc.truth_accepted(delta), "azimuths_deg": [float(a) for a in azimuths]})
    return rows


def _slit_rows(base: dict[str, Any], plausible: SlitRange, extents: np.ndarray,
               measure: AmbiguityMeasure) -> list[dict]:
    rows = []
    mm = plausible.voxel_size * 1000.0
    found = extents[np.isfinite(extents)]
    for delta in measure.deltas:
        allowed = plausible.extents(delta)
        s = extent_scores(allowed, extents, measure.extent_tolerance_voxels, measure.extent_margin_voxels)
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
    ("nothing_accepted_hidden", "hidden_handle", "nothing_accepted"),
    ("nothing_accepted_visible", "visible_handle", "nothing_accepted"),
    ("nothing_accepted_slit", "slit", "nothing_accepted"),
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
                    entry[key] = nanmean([float(r[column]) for r in chosen])
            # A view whose plausible set is narrow makes its spread ratio large: the medians show how much the
            # means owe to a few such views.
            for key, kind in (("arc_spread_ratio_median", "hidden_handle"), ("slit_spread_ratio_median", "slit")):
                values = np.array([r["spread_ratio"] for r in rows if r["method"] == name
                                   and r["box_temperature"] == temperature and r["kind"] == kind
                                   and abs(r["delta"] - delta) < 1e-12], dtype=np.float64)
                entry[key] = float(np.nanmedian(values)) if np.isfinite(values).any() else math.nan
            out.append(entry)
    return out
