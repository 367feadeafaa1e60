"""``pssnet evaluate``: completers scored against the plausible sets (the paper's table and figures).

:func:`run_evaluation` loads the test sets and their plausible sets (:func:`load_test_sets`, cached on disk),
then scores every completer on each set (:func:`evaluate_set`). For each reference observation: the plausible
shapes of every delta are rebuilt once as occupancy grids of the observation's grid
(:func:`pssnet_core.geometry.solid_occupancy`), then each completer draws ``samples`` completions and the metrics
of :mod:`pssnet_core.evaluation.metrics` are computed per delta. The result is one row per (test set, observation,
method, delta), which :func:`pssnet_core.evaluation.report.evaluation_report` turns into tables and plots.
Each observation is a Ray task (:mod:`pssnet_core.ray_tasks`); views, meshes, plausible sets and the completers go
into the object store once. Observation ``i`` draws its samples with seed ``seed + i`` wherever it runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.experiment import Completer, sample_occupancy
from pssnet_core.evaluation.metrics import chamfer_matrix, distance_fields, metrics_from_distances
from pssnet_core.evaluation.observation_model import ObservationModelConfig
from pssnet_core.evaluation.plausible import (
    EvalView,
    MeshSource,
    MeshTable,
    PlausibleConfig,
    PlausibleSets,
    ShapeMeshes,
    cached_plausible_sets,
    dataset_fingerprint,
    plausible_shape_occupancy,
)
from pssnet_core.evaluation.testsets import (
    MUG_SETS,
    NARROW_SETS,
    PAPER_TEST_SETS,
    TEST_SETS,
    build_command,
    find_test_set,
    load_test_set,
)
from pssnet_core.ray_tasks import RayConfig, TaskRunner
from pssnet_core.spread import evenly_spaced

#: the paper's delta (m)
PAPER_DELTA = 0.04
#: the delta scaled to real-size objects (m), see DESIGN.md
SCALED_DELTA = 0.01


class EvaluationError(ValueError):
    """The evaluation cannot run as asked (mismatched grids, missing sets)."""


@dataclass
class KeptExample:
    """Samples and plausible shapes kept for a figure."""

    set_name: str
    index: int
    method: str
    delta: float
    samples: np.ndarray  # (S, N, N, N) bool
    plausible: np.ndarray  # (P, N, N, N) bool, ground truth first
    distances: np.ndarray  # (S, P) metres
    voxel_size: float


@dataclass
class EvaluationOutput:
    """Rows of per-observation metrics, the examples kept for figures, and timings."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    examples: list[KeptExample] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _ObservationScores:
    """What one observation's task returns."""

    rows: list[dict[str, Any]]
    examples: list[KeptExample]
    seconds: dict[str, float]


def _score_observation(i: int, set_name: str, views: Sequence[EvalView], meshes: MeshSource, sets: PlausibleSets,
                       completers: Mapping[str, Completer], deltas: Sequence[float], num_samples: int, seed: int,
                       keep: Collection[int]) -> _ObservationScores:
    """The unit of work (a Ray task): every completer's samples of observation ``i`` against its plausible sets."""
    view = views[i]
    voxel = view.grid_pose.voxel_size
    t0 = time.perf_counter()
    # Union of the members over deltas: each shape is voxelised and distance-transformed once.
    union: dict[int, np.ndarray] = {}
    per_delta: dict[float, list[int]] = {}
    for d in deltas:
        per_delta[d] = []
        for j, transform in sets.members(i, d):
            if j not in union:
                union[j] = transform
            per_delta[d].append(list(union).index(j))
    order = list(union)
    shapes = plausible_shape_occupancy(views, meshes, i, [(j, union[j]) for j in order])
    fields = distance_fields(shapes)
    own = order.index(i)
    out = _ObservationScores(rows=[], examples=[], seconds={"shapes": time.perf_counter() - t0, "models": 0.0,
                                                             "metrics": 0.0})
    meta = {k: v for k, v in view.meta.items() if isinstance(v, bool | int | float | str | np.bool_)}
    for name, completer in completers.items():
        t2 = time.perf_counter()
        samples = sample_occupancy(completer, view, num_samples, seed + i)
        t3 = time.perf_counter()
        out.seconds["models"] += t3 - t2
        dist = chamfer_matrix(samples, shapes, voxel, fields_b=fields)
        for d in deltas:
            cols = per_delta[d]
            m = metrics_from_distances(dist[:, cols], dist[:, own])
            out.rows.append({"set": set_name, "index": i, "identity": view.identity, "method": name,
                             "delta": float(d), **m.to_dict(), **meta})
            if i in keep:
                out.examples.append(KeptExample(set_name, i, name, float(d), samples, shapes[cols],
                                                dist[:, cols], voxel))
        out.seconds["metrics"] += time.perf_counter() - t3
    return out


def evaluate_set(set_name: str, views: Sequence[EvalView], meshes: MeshSource, sets: PlausibleSets,
                 completers: Mapping[str, Completer], deltas: Sequence[float], num_samples: int = 100,
                 seed: int = 0, references: Sequence[int] | None = None, keep: Collection[int] = (),
                 progress: bool = True, output: EvaluationOutput | None = None, runner: TaskRunner | None = None,
                 gpus_per_task: float = 0.0) -> EvaluationOutput:
    """Scores every completer on the reference observations of one test set.

    Args:
        set_name: name used in the rows ("mugs", "ycb_narrow", ...).
        views: the whole test set.
        meshes: identity -> (vertices, faces).
        sets: plausible sets covering ``references`` at every delta in ``deltas``.
        completers: method name -> completer (picklable: Ray tasks get them through the object store).
        deltas: the deltas to report.
        num_samples: completions per observation (paper: 100).
        seed: latent seed (observation ``i`` uses ``seed + i``).
        references: observations to score (default: those in ``sets``).
        keep: observations whose samples are kept for figures.
        progress: tqdm bar.
        output: append to this output.
        runner: where the observations are scored (default: in this process).
        gpus_per_task: GPUs each Ray task reserves (completers on a GPU).

    Returns:
        The :class:`EvaluationOutput` (rows have keys set, index, identity, method, delta, the four metrics,
        num_samples, num_plausible, and the view's meta values that are plain scalars), in reference order.
    """
    out = output or EvaluationOutput()
    refs = [int(i) for i in (sets.references if references is None else references)]
    missing = sorted(set(refs) - set(int(r) for r in sets.references))
    if missing:
        raise EvaluationError(f"{set_name}: no plausible sets for observations {missing[:10]}")
    for d in deltas:
        sets.delta_column(d)  # raises when a delta was not computed
    for name, completer in completers.items():
        size = views[refs[0]].grid_pose.size if refs else completer.grid_size
        if completer.grid_size != size:
            raise EvaluationError(f"{name} completes {completer.grid_size}^3 grids but {set_name} has {size}^3")
    # Only the meshes of this set, made once here and shared by every task.
    table = MeshTable({identity: meshes(identity) for identity in sorted({v.identity for v in views})})
    shared = {"set_name": set_name, "views": list(views), "meshes": table, "sets": sets, "completers": dict(completers),
              "deltas": tuple(deltas), "num_samples": num_samples, "seed": seed, "keep": frozenset(keep)}
    runner = runner or TaskRunner()  # the default runs in this process: nothing to close
    scores = dict(runner.map(_score_observation, refs, shared, desc=f"evaluate {set_name}", unit_name="obs",
                             progress=progress, gpus_per_task=gpus_per_task))
    seconds = {"shapes": 0.0, "models": 0.0, "metrics": 0.0}
    for i in refs:  # reference order, wherever and whenever each ran
        out.rows.extend(scores[i].rows)
        out.examples.extend(scores[i].examples)
        for key, value in scores[i].seconds.items():
            seconds[key] += value
    out.timings[f"{set_name}_plausible_shapes_s"] = seconds["shapes"]
    out.timings[f"{set_name}_sampling_s"] = seconds["models"]
    out.timings[f"{set_name}_metrics_s"] = seconds["metrics"]
    return out


# --------------------------------------------------------------------------------------- the experiment


@dataclass(frozen=True)
class TestSetsConfig:
    """The test observations to score and how their plausible sets are made (Alg. 2, cached on disk).

    Attributes:
        data: directory holding the test sets (``DATA/mugs`` or ``DATA/test/mugs``, ...).
        sets: test-set names; a set not found under ``data`` is skipped with a note.
        max_observations: score only this many observations per set, evenly spaced (None = all); the candidates
            of each plausible set are always all.
        dense_mugs: with ``max_observations``: also score every ``dense_step``-th view of the first K mugs with a
            handle (a full turn for the coverage-vs-rotation plot).
        dense_step: view stride of ``dense_mugs``.
        cache_dir: plausible-set cache (None = ``DATA_SET/plausible_cache``).
        recompute: ignore cached plausible sets.
        observation: the observation model's outlier allowance (its delta is set per delta).
        record_fraction: store candidates up to this violating fraction (allowances up to it need no recompute).
        progress: tqdm bars.
    """

    __test__ = False  # a config, not a pytest class (test modules import it by its name)
    data: str
    sets: tuple[str, ...] = PAPER_TEST_SETS
    max_observations: int | None = None
    dense_mugs: int = 0
    dense_step: int = 2
    cache_dir: str | None = None
    recompute: bool = False
    observation: ObservationModelConfig = ObservationModelConfig()
    record_fraction: float = 0.01
    progress: bool = True

    def __post_init__(self) -> None:
        unknown = [n for n in self.sets if n not in TEST_SETS]
        if unknown:
            raise EvaluationError(f"unknown test sets {unknown}; known: {list(TEST_SETS)}")
        if self.max_observations is not None and self.max_observations < 1:
            raise EvaluationError(f"max_observations must be >= 1, got {self.max_observations}")
        if self.dense_mugs < 0 or self.dense_step < 1:
            raise EvaluationError(f"dense_mugs must be >= 0 and dense_step >= 1, got {self.dense_mugs} and "
                                  f"{self.dense_step}")

    def plausible_config(self, deltas: Sequence[float]) -> PlausibleConfig:
        """The plausible-set parameters at ``deltas``."""
        return PlausibleConfig(deltas=tuple(deltas), observation=self.observation,
                               record_fraction=max(self.record_fraction, self.observation.outlier_fraction))


@dataclass
class ScoredSet:
    """One loaded test set: its views, their plausible sets, and the observations to score (ascending)."""

    views: list[EvalView]
    sets: PlausibleSets
    references: list[int]


def dense_mug_views(views: Sequence[Any], count: int, step: int) -> list[int]:
    """Every ``step``-th view of the first ``count`` mugs that have a handle (views of a mug are consecutive)."""
    if count < 0 or step < 1:
        raise EvaluationError(f"dense_mugs must be >= 0 and dense_step >= 1, got {count} and {step}")
    mugs: list[str] = []
    for view in views:
        if view.meta.get("has_handle") and view.identity not in mugs:
            mugs.append(view.identity)
    chosen = set(mugs[:count])
    out, seen = [], {}
    for k, view in enumerate(views):
        if view.identity in chosen:
            if seen.setdefault(view.identity, 0) % step == 0:
                out.append(k)
            seen[view.identity] += 1
    return out


def load_test_sets(config: TestSetsConfig, deltas: Sequence[float], runner: TaskRunner,
                   log: Callable[[str], None] = print) -> dict[str, ScoredSet]:
    """Loads each test set of ``config`` and its plausible sets (cached, resumed or computed by ``runner``).

    ``log`` gets one line per set (sizes, cache state, where the sets are stored) and one per set skipped.

    Raises:
        EvaluationError: none of the sets was found.
    """
    plausible = config.plausible_config(deltas)
    out: dict[str, ScoredSet] = {}
    for name in config.sets:
        root = find_test_set(config.data, name)
        if root is None:
            log(f"{name}: no test set under {config.data} (skipped; build it with `{build_command(name)}`)")
            continue
        views, _ = load_test_set(root, progress=config.progress)
        refs = None if config.max_observations is None or config.max_observations >= len(views) else \
            evenly_spaced(len(views), config.max_observations)
        if name in MUG_SETS and refs is not None and config.dense_mugs:
            refs = sorted(set(refs) | set(dense_mug_views(views, config.dense_mugs, config.dense_step)))
        cache = Path(config.cache_dir) if config.cache_dir else root / "plausible_cache"
        t0 = time.perf_counter()
        sets, path, hit = cached_plausible_sets(views, ShapeMeshes(), dataset_fingerprint(root), cache, plausible,
                                                refs, runner=runner, progress=config.progress,
                                                desc=f"plausible {name}", recompute=config.recompute)
        s = sets.stats
        state = "cached" if hit else f"computed in {time.perf_counter() - t0:.1f} s"
        if not hit and s.get("resumed_references"):
            state += f", {s['resumed_references']} references resumed from an interrupted run"
        sizes = {d: float(np.mean(list(sets.sizes(d).values()))) for d in deltas}
        where = s.get("executor") or f"{s['workers']} workers"  # caches written before Ray lack "executor"
        log(f"{name}: {len(views)} observations, {len(sets.references)} references, {s['pairs']} pairs "
            f"({state}; {s['pairs_per_second']:.0f} pairs/s, {where}, when computed); "
            f"mean set size {', '.join(f'{d * 100:g} cm: {v:.1f}' for d, v in sizes.items())}; "
            f"own ground truth plausible: {s['own_ground_truth_plausible_rate']} -> {path}")
        out[name] = ScoredSet(views, sets, [int(i) for i in sets.references])
    if not out:
        raise EvaluationError(f"no test sets {','.join(config.sets)} found under {config.data}")
    return out


@dataclass(frozen=True)
class EvaluateConfig:
    """One ``pssnet evaluate`` run.

    Attributes:
        test_sets: the observations to score and their plausible sets.
        out: output directory.
        samples: completions per observation (paper: 100).
        delta: the paper's delta (m).
        scaled_delta: the delta scaled to real-size objects (m); <= 0 (or equal to ``delta``) to skip.
        seed: latent seed (observation ``i`` uses ``seed + i``).
        plot_mugs: mugs in the coverage-vs-rotation plot.
        ray: where the observations are scored.
        gpus_per_task: GPUs each Ray task reserves (completers on a GPU take a whole one).
    """

    test_sets: TestSetsConfig
    out: str = "results"
    samples: int = 100
    delta: float = PAPER_DELTA
    scaled_delta: float = SCALED_DELTA
    seed: int = 0
    plot_mugs: int = 3
    ray: RayConfig = RayConfig()
    gpus_per_task: float = 0.0

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise EvaluationError(f"samples must be >= 1, got {self.samples}")

    @property
    def deltas(self) -> tuple[float, ...]:
        """The deltas scored: ``delta``, then ``scaled_delta`` when positive and different."""
        deltas = (self.delta,) + ((self.scaled_delta,) if self.scaled_delta and self.scaled_delta > 0 else ())
        return deltas if len(set(deltas)) == len(deltas) else (self.delta,)


@dataclass
class EvaluationResult:
    """What :func:`run_evaluation` measured: rows (see :func:`evaluate_set`), figure examples, timings."""

    config: EvaluateConfig
    methods: list[str]
    test_sets: dict[str, ScoredSet]
    rows: list[dict[str, Any]]
    examples: list[KeptExample]
    timings: dict[str, float]


def _figure_examples(name: str, scored: ScoredSet) -> list[int]:
    """One example per figure set: the middle occluded-handle mug, the middle narrow-slit observation."""
    if name in MUG_SETS:
        hidden = [i for i in scored.references if scored.views[i].meta.get("handle_visible") is False]
        return hidden[len(hidden) // 2:][:1]
    if name in NARROW_SETS:
        return scored.references[len(scored.references) // 2:][:1]
    return []


def run_evaluation(config: EvaluateConfig, completers: Mapping[str, Completer]) -> EvaluationResult:
    """Scores every completer on the test sets of ``config`` against their plausible sets (one Ray for all)."""
    output = EvaluationOutput()
    with TaskRunner(config.ray) as runner:
        loaded = load_test_sets(config.test_sets, config.deltas, runner)
        t0 = time.perf_counter()
        for name, scored in loaded.items():
            evaluate_set(name, scored.views, ShapeMeshes(), scored.sets, completers, config.deltas, config.samples,
                         config.seed, scored.references, keep=_figure_examples(name, scored),
                         progress=config.test_sets.progress, output=output, runner=runner,
                         gpus_per_task=config.gpus_per_task)
    timings = dict(output.timings, evaluate_seconds=time.perf_counter() - t0)
    return EvaluationResult(config=config, methods=list(completers), test_sets=loaded, rows=output.rows,
                            examples=output.examples, timings=timings)
