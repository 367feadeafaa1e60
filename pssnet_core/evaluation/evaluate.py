"""Runs completers on test observations and scores them against the plausible sets.

For each reference observation: the plausible shapes of every delta are rebuilt once as occupancy grids of the
observation's grid (:func:`pssnet_core.geometry.solid_occupancy`), then each completer draws ``samples``
completions and the metrics of :mod:`pssnet_core.evaluation.metrics` are computed per delta. The result is one row per
(test set, observation, method, delta), which :mod:`pssnet_core.evaluation.report` turns into tables and plots.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from pssnet_core.evaluation.metrics import chamfer_matrix, distance_fields, metrics_from_distances
from pssnet_core.evaluation.observation_model import MeshRaycaster
from pssnet_core.evaluation.plausible import EvalView, MeshSource, PlausibleSets, plausible_shape_occupancy


class EvaluationError(ValueError):
    """The evaluation cannot run as asked (mismatched grids, missing sets)."""


class SampleSource(Protocol):
    """What the evaluation needs of a completer (``pssnet_core.inference.Completer`` fits)."""

    grid_size: int

    def complete(self, observation: Any, num_samples: int = 20, seed: int = 0) -> Any:  # -> has .occupancy
        ...


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


def evaluate_set(set_name: str, views: Sequence[EvalView], meshes: MeshSource, sets: PlausibleSets,
                 completers: Mapping[str, SampleSource], deltas: Sequence[float], num_samples: int = 100,
                 seed: int = 0, references: Sequence[int] | None = None,
                 keep: Callable[[EvalView], bool] | None = None, progress: bool = True,
                 output: EvaluationOutput | None = None) -> EvaluationOutput:
    """Scores every completer on the reference observations of one test set.

    Args:
        set_name: name used in the rows ("mugs", "ycb_narrow", ...).
        views: the whole test set.
        meshes: identity -> (vertices, faces).
        sets: plausible sets covering ``references`` at every delta in ``deltas``.
        completers: method name -> completer.
        deltas: the deltas to report.
        num_samples: completions per observation (paper: 100).
        seed: latent seed (observation ``i`` uses ``seed + i``).
        references: observations to score (default: those in ``sets``).
        keep: predicate choosing observations whose samples are kept for figures.
        progress: tqdm bar.
        output: append to this output.

    Returns:
        The :class:`EvaluationOutput` (rows have keys set, index, identity, method, delta, the four metrics,
        num_samples, num_plausible, and the view's meta values that are plain scalars).
    """
    from tqdm import tqdm

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
    raycasters: dict[str, MeshRaycaster] = {}
    t_shapes = t_models = t_metrics = 0.0
    for i in tqdm(refs, desc=f"evaluate {set_name}", unit="obs", disable=not progress, dynamic_ncols=True):
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
        shapes = plausible_shape_occupancy(views, meshes, i, [(j, union[j]) for j in order], raycasters)
        fields = distance_fields(shapes)
        own = order.index(i)
        t1 = time.perf_counter()
        t_shapes += t1 - t0
        meta = {k: v for k, v in view.meta.items() if isinstance(v, bool | int | float | str | np.bool_)}
        for name, completer in completers.items():
            t2 = time.perf_counter()
            samples = np.asarray(completer.complete(view.network_input(), num_samples=num_samples,
                                                    seed=seed + i).occupancy, dtype=bool)
            t3 = time.perf_counter()
            t_models += t3 - t2
            dist = chamfer_matrix(samples, shapes, voxel, fields_b=fields)
            for d in deltas:
                cols = per_delta[d]
                m = metrics_from_distances(dist[:, cols], dist[:, own])
                out.rows.append({"set": set_name, "index": i, "identity": view.identity, "method": name,
                                 "delta": float(d), **m.to_dict(), **meta})
                if keep is not None and keep(view):
                    out.examples.append(KeptExample(set_name, i, name, float(d), samples, shapes[cols],
                                                    dist[:, cols], voxel))
            t_metrics += time.perf_counter() - t3
    out.timings[f"{set_name}_plausible_shapes_s"] = t_shapes
    out.timings[f"{set_name}_sampling_s"] = t_models
    out.timings[f"{set_name}_metrics_s"] = t_metrics
    return out
