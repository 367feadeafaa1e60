"""Runs completers on test observations and scores them against the plausible sets.

For each reference observation: the plausible shapes of every delta are rebuilt once as occupancy grids of the
observation's grid (:func:`pssnet_core.geometry.solid_occupancy`), then each completer draws ``samples``
completions and the metrics of :mod:`pssnet_core.evaluation.metrics` are computed per delta. The result is one row per
(test set, observation, method, delta), which :mod:`pssnet_core.evaluation.report` turns into tables and plots.
Each observation is a Ray task (:mod:`pssnet_core.ray_tasks`); views, meshes, plausible sets and the completers go
into the object store once. Observation ``i`` draws its samples with seed ``seed + i`` wherever it runs.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from pssnet_core.evaluation.metrics import chamfer_matrix, distance_fields, metrics_from_distances
from pssnet_core.evaluation.plausible import (
    EvalView,
    MeshSource,
    MeshTable,
    PlausibleSets,
    plausible_shape_occupancy,
)
from pssnet_core.ray_tasks import TaskRunner


class EvaluationError(ValueError):
    """The evaluation cannot run as asked (mismatched grids, missing sets)."""


class SampleSource(Protocol):
    """What the evaluation needs of a completer (``pssnet_core.inference.Completer`` fits)."""

    grid_size: int

    def complete(self, observation: Any, num_samples: int = 20, seed: int = 0) -> Any:  # -> has .occupancy
        """``observation`` is the :class:`~pssnet_core.evaluation.plausible.EvalView` (``network_input()``, its grids
        and grid pose)."""


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
                       completers: Mapping[str, SampleSource], deltas: Sequence[float], num_samples: int, seed: int,
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
        samples = np.asarray(completer.complete(view, num_samples=num_samples,
                                                seed=seed + i).occupancy, dtype=bool)
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
                 completers: Mapping[str, SampleSource], deltas: Sequence[float], num_samples: int = 100,
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
