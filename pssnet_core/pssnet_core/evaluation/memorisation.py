"""Memorisation (the paper's appendix question): are completions nearer a training shape than the truth?

For every completion of a test view: the chamfer distance (mm; voxel-centre clouds,
:func:`pssnet_core.evaluation.metrics.chamfer_matrix`) to the nearest ground-truth grid of the training set and
to the view's own ground truth. A model that recalls training shapes rather than completing the view puts many
completions nearer some training shape than the truth (the paper: ~10 % of completions, 2.4 vs 3.8 mm).

Shapes are compared as grids: every training view's ground truth lies in its own observation grid, placed like the
test view's (gravity aligned, from the observed points), so grid-to-grid distance asks whether a completion
reproduces a training *example* as the network saw it, pose included, which is what a memorising network would
output.

The search for the nearest training grid (an index and a prefilter) is
:mod:`pssnet_core.evaluation.memorisation_search`; the report is
:func:`pssnet_core.evaluation.memorisation_report.memorisation_report`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.experiment import Completer, sample_occupancy
from pssnet_core.evaluation.memorisation_search import (
    MemorisationError,
    SearchConfig,
    TrainingIndex,
    brute_force_nearest,
    nearest_training,
)
from pssnet_core.evaluation.metrics import chamfer_matrix
from pssnet_core.evaluation.testsets import PAPER_TEST_SETS
from pssnet_core.spread import evenly_spaced


@dataclass(frozen=True)
class MemorisationConfig:
    """One ``pssnet memorisation`` run.

    Attributes:
        train_data: training dataset directories (each a dataset, or a folder of datasets such as ``data/d32/train``).
        data: directory holding the test sets.
        out: output directory.
        sets: test sets to complete.
        samples: completions per test view.
        max_views: at most this many views per test set, evenly spaced (None = all).
        seed: latent seed (view ``i`` uses ``seed + i``).
        verify: completions (evenly spaced) re-searched by brute force over the whole training set.
        progress: tqdm bars.
        search: parameters of the nearest-training-shape search.
    """

    train_data: Sequence[str]
    data: str
    out: str
    sets: Sequence[str] = PAPER_TEST_SETS
    samples: int = 10
    max_views: int | None = None
    seed: int = 0
    verify: int = 0
    progress: bool = True
    search: SearchConfig = field(default_factory=SearchConfig)

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise MemorisationError(f"samples must be >= 1, got {self.samples}")
        if self.max_views is not None and self.max_views < 1:
            raise MemorisationError(f"max_views must be >= 1, got {self.max_views}")
        if self.verify < 0:
            raise MemorisationError(f"verify must be >= 0, got {self.verify}")


@dataclass
class MemorisationResult:
    """What :func:`run_memorisation` measured.

    Attributes:
        config: the run.
        methods: the completers' names.
        roots: the training datasets.
        index: the training grids.
        sets: the test sets found, in order.
        rows: one per completion: its distances to the nearest training grid and to the truth (mm) and which grid.
        examples: per method, the completions most clearly nearer a training shape than their truth
            (distance ratio, completion, training index, truth).
        verify: per method, how often the prefilter found the brute-force nearest.
        costs: seconds per stage and the index's size.
    """

    config: MemorisationConfig
    methods: list[str]
    roots: list[Path]
    index: TrainingIndex
    sets: list[str]
    rows: list[dict[str, Any]]
    examples: dict[str, list[tuple[float, np.ndarray, int, np.ndarray]]]
    verify: dict[str, Any]
    costs: dict[str, Any]


def dataset_roots(paths: Sequence[str | Path]) -> list[Path]:
    """Dataset directories from paths that are datasets or folders of datasets (one level down)."""
    roots: list[Path] = []
    for path in (Path(p) for p in paths):
        if (path / "index.json").exists():
            roots.append(path)
            continue
        found = sorted(p.parent for p in path.glob("*/index.json"))
        if not found:
            raise MemorisationError(f"{path} is neither a dataset nor a folder of datasets (no index.json)")
        roots += found
    return roots



def run_memorisation(config: MemorisationConfig, completers: Mapping[str, Completer]) -> MemorisationResult:
    """Completes test views with every completer and finds each completion's nearest training shape."""
    from tqdm import tqdm

    from pssnet_core.data.store import DatasetReader
    from pssnet_core.evaluation.testsets import find_test_set, load_test_set

    if not completers:
        raise MemorisationError("no completers given")
    t_start = time.perf_counter()
    roots = dataset_roots(config.train_data)
    train = DatasetReader(roots)
    index = TrainingIndex.from_reader(train, config.search, progress=config.progress)
    costs: dict[str, Any] = {"index_seconds": index.seconds, "training_grids": len(index), "grid_size": index.grid_size,
                             "index_megabytes": (index.packed.nbytes + index.features.nbytes) / 1e6}
    for name, completer in completers.items():
        if completer.grid_size != index.grid_size:
            raise MemorisationError(f"{name} completes {completer.grid_size}^3 grids but the training grids are "
                                    f"{index.grid_size}^3")
    completions: dict[str, list[np.ndarray]] = {m: [] for m in completers}
    truths: list[np.ndarray] = []
    meta: list[dict[str, Any]] = []
    t_sampling = 0.0
    found_any = False
    for set_name in config.sets:
        root = find_test_set(config.data, set_name)
        if root is None:
            continue
        found_any = True
        views, set_meta = load_test_set(root, progress=config.progress)
        if abs(float(set_meta.get("voxel_size", index.voxel_size)) - index.voxel_size) > 1e-9 or \
                views[0].grid_pose.size != index.grid_size:
            raise MemorisationError(f"{root} has another grid than the training set ({index.grid_size}^3, "
                                    f"{index.voxel_size} m voxels)")
        reader = DatasetReader(root)
        for i in tqdm(evenly_spaced(len(views), config.max_views), desc=f"complete {set_name}", unit="view",
                      disable=not config.progress, dynamic_ncols=True):
            view = views[i]
            truths.append(np.asarray(reader.get(view.index, images=False)["occupancy"], dtype=bool))
            meta.append({"set": set_name, "index": view.index, "identity": view.identity,
                         "family": view.meta.get("family", view.identity.split("-")[0])})
            for name, completer in completers.items():
                t0 = time.perf_counter()
                completions[name].append(sample_occupancy(completer, view, config.samples, config.seed + view.index))
                t_sampling += time.perf_counter() - t0
    if not found_any:
        raise MemorisationError(f"no test sets {list(config.sets)} under {config.data}")
    costs["sampling_seconds"] = t_sampling
    rows: list[dict[str, Any]] = []
    examples: dict[str, list[tuple[float, np.ndarray, int, np.ndarray]]] = {}
    t_search = time.perf_counter()
    t_verify = 0.0
    verify: dict[str, Any] = {}
    # Baseline: how near the truth itself lies to a training grid. A training set with many objects in many poses
    # has some grid near any shape, so completions can be nearer a training shape than their truth without
    # recalling one; the truth's own distance says how near "near" is for this training set.
    d_base, _ = nearest_training(np.stack(truths), index, config.search)
    for m, d in zip(meta, d_base, strict=True):
        m["truth_train_mm"] = float(d * 1000)
    for name in completers:
        queries = np.concatenate(completions[name])  # (views * samples, N, N, N)
        d_train, nearest = nearest_training(queries, index, config.search, progress=config.progress)
        truth_stack = np.repeat(np.stack(truths), config.samples, axis=0)
        d_truth = np.concatenate([chamfer_matrix(samples, truth[None], index.voxel_size)[:, 0]
                                  for samples, truth in zip(completions[name], truths, strict=True)])
        if config.verify > 0:
            t0 = time.perf_counter()
            pick = np.asarray(evenly_spaced(len(queries), config.verify))
            d_brute, _ = brute_force_nearest(queries[pick], index)
            t_verify += time.perf_counter() - t0
            verify[name] = {"completions": int(len(pick)),
                            "prefilter_found_exact_nearest": float(np.mean(np.isclose(d_brute, d_train[pick],
                                                                                      atol=1e-9))),
                            "max_excess_mm": float((d_train[pick] - d_brute).max() * 1000)}
        ranked = []
        for q in range(len(queries)):
            m = meta[q // config.samples]
            j = int(nearest[q])
            rows.append({"method": name, **m, "sample": q % config.samples, "train_mm": float(d_train[q] * 1000),
                         "truth_mm": float(d_truth[q] * 1000), "nearer_training": bool(d_train[q] < d_truth[q]),
                         "train_index": j, "train_identity": index.identities[j],
                         "same_family": index.families[j] == m["family"]})
            ranked.append((float(d_train[q] / max(d_truth[q], 1e-12)), q))
        # Figure: the completions most clearly nearer a training shape than their truth.
        examples[name] = [(r, queries[q], int(nearest[q]), truth_stack[q]) for r, q in sorted(ranked)[:4]]
    costs["search_seconds"] = time.perf_counter() - t_search - t_verify
    costs["verify_seconds"] = t_verify
    costs["total_seconds"] = time.perf_counter() - t_start
    return MemorisationResult(config=config, methods=list(completers), roots=roots, index=index,
                              sets=list(dict.fromkeys(m["set"] for m in meta)), rows=rows, examples=examples,
                              verify=verify, costs=costs)


def summarise_memorisation(rows: Sequence[dict[str, Any]], methods: Sequence[str],
                           sets: Sequence[str]) -> list[dict[str, Any]]:
    """Per method and test set (and "all"): fraction nearer a training shape, mean distances (mm)."""
    out = []
    for method in methods:
        for set_name in [*sets, "all"]:
            chosen = [r for r in rows if r["method"] == method and (set_name == "all" or r["set"] == set_name)]
            if not chosen:
                continue
            train = np.array([r["train_mm"] for r in chosen])
            truth = np.array([r["truth_mm"] for r in chosen])
            out.append({"method": method, "set": set_name, "completions": len(chosen),
                        "views": len({(r["set"], r["index"]) for r in chosen}),
                        "nearer_training_fraction": float(np.mean([r["nearer_training"] for r in chosen])),
                        "train_mm_mean": float(train.mean()), "truth_mm_mean": float(truth.mean()),
                        "train_mm_median": float(np.median(train)), "truth_mm_median": float(np.median(truth)),
                        "truth_train_mm_mean": float(np.mean([r["truth_train_mm"] for r in chosen])),
                        "same_family_fraction": float(np.mean([r["same_family"] for r in chosen]))})
    return out
