"""Memorisation (the paper's appendix question): are completions nearer a training shape than the truth?

For every completion of a test view: the chamfer distance (mm; voxel-centre clouds,
:func:`pssnet_core.evaluation.metrics.chamfer_matrix`) to the nearest ground-truth grid of the training set and
to the view's own ground truth. A model that recalls training shapes rather than completing the view puts many
completions nearer some training shape than the truth (the paper: ~10 % of completions, 2.4 vs 3.8 mm).

Shapes are compared as grids: every training view's ground truth lies in its own observation grid, placed like the
test view's (gravity aligned, from the observed points), so grid-to-grid distance asks whether a completion
reproduces a training *example* as the network saw it, pose included, which is what a memorising network would
output.

Search (why a prefilter): training sets are large (the large set: 160,000 views at 32^3), and an exact chamfer
needs a distance transform per training grid (~2 ms) and a pass over its voxels; all completions against all
training grids would be hours. So the training grids are read once into a compact index (bit-packed grids, 4 KB
each at 32^3, plus prefilter features: 16^3 float16 numbers, 8 KB), every completion is compared with every
training grid by the squared distance between features (one matrix product per chunk), and the exact chamfer is
computed on the ``top_k`` nearest by features only. Memory: ~12 KB per training grid at 32^3 (2 GB for the
160,000-view set); at 64^3 the packed grids take 32 KB each.

The features (:func:`pooled_features`) are the shape's occupancy as a *mass distribution* (divided by its voxel
count), averaged over blocks of ``pool`` voxels a side (default: a 16^3 grid of blocks) and blurred by a voxel:
a chamfer distance averages over points, so two shapes are near when their mass lies in the same places,
whatever their sizes; the blur makes near-but-not-overlapping mass count as near. Measured:

- on 300 varied synthetic shapes with 60 queries (``test_prefilter_finds_the_exact_nearest_on_a_small_set``):
  raw block averages ranked the exact nearest beyond the top 32 for 5 of 30 unseen shapes (the size of the
  other shape dominates when the two do not overlap); normalised and blurred, all 60 within the top 3;
- on 36 completions of the shipped model (4 per view, 9 test views) against the 15,840 training grids of
  ``data/d32/train`` (brute force: 213 s): 8^3 blocks found the exact nearest in the top 16 for 28 of 36
  (worst rank 427); 16^3 blocks for 36 of 36 (worst rank 11).

It is a heuristic, not a bound, so ``verify`` re-checks completions against the whole training set by brute
force and the report says how often the prefilter found the exact nearest.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from pssnet_core.evaluation.metrics import chamfer_matrix, distance_fields
from pssnet_core.spread import evenly_spaced


class MemorisationError(ValueError):
    """Bad input to the memorisation measurement (grids that differ, empty training set, bad parameters)."""


@dataclass(frozen=True)
class MemorisationConfig:
    """Parameters of the nearest-training-shape search.

    Attributes:
        pool: block size (voxels) of the prefilter features; None = grid size / 16 (16^3 features).
        blur: Gaussian blur of the features, sigma in voxels (0 = none).
        top_k: exact chamfer distances per completion (the prefilter's nearest candidates).
        chunk: training grids per matrix product of the prefilter (bounds memory: chunk x features x 4 bytes).
        query_chunk: completions searched together, each against the union of their candidates (best about
            one or two views' samples, which share candidates).
    """

    pool: int | None = None
    blur: float = 1.0
    top_k: int = 16
    chunk: int = 8192
    query_chunk: int = 20

    def __post_init__(self) -> None:
        if self.pool is not None and self.pool < 1:
            raise MemorisationError(f"pool must be >= 1, got {self.pool}")
        if self.blur < 0:
            raise MemorisationError(f"blur must be >= 0, got {self.blur}")
        if self.top_k < 1 or self.chunk < 1 or self.query_chunk < 1:
            raise MemorisationError("top_k, chunk and query_chunk must be >= 1")

    def pool_for(self, grid_size: int) -> int:
        pool = self.pool if self.pool is not None else max(1, grid_size // 16)
        if grid_size % pool:
            raise MemorisationError(f"pool {pool} does not divide the grid size {grid_size}")
        return pool


def pooled_features(grids: np.ndarray, pool: int, normalise: bool = True, blur: float = 1.0) -> np.ndarray:
    """The prefilter's view of a shape, (K, (N / pool)^3) float32 (see the module docstring).

    Args:
        grids: (K, N, N, N) or (N, N, N) occupancy.
        pool: block size in voxels (must divide N).
        normalise: divide by the voxel count (a mass distribution; empty grids give zeros).
        blur: Gaussian blur of the block grid, sigma in voxels (0 = none).
    """
    grids = np.asarray(grids)
    if grids.ndim == 3:
        grids = grids[None]
    k, n = len(grids), grids.shape[1]
    if n % pool:
        raise MemorisationError(f"pool {pool} does not divide the grid size {n}")
    m = n // pool
    blocks = grids.reshape(k, m, pool, m, pool, m, pool).astype(np.float32).mean(axis=(2, 4, 6))
    if normalise:
        blocks /= np.maximum(blocks.reshape(k, -1).sum(axis=1), 1e-12)[:, None, None, None]
    if blur > 0:
        sigma = blur / pool
        blocks = ndimage.gaussian_filter(blocks, sigma=(0, sigma, sigma, sigma), mode="constant")
    return blocks.reshape(k, m**3).astype(np.float32, copy=False)


@dataclass
class TrainingIndex:
    """Training ground-truth grids in memory: bit-packed grids, prefilter features, identities.

    Attributes:
        grid_size: N.
        voxel_size: metres.
        pool: feature block size.
        blur: feature blur (voxels).
        packed: (M, ceil(N^3 / 8)) uint8 bit-packed occupancy.
        features: (M, F) float16 prefilter features (half the memory; scores are computed in float32).
        norms: (M,) float32 squared feature norms.
        identities: (M,) object identity of each grid.
        families: (M,) object family of each grid.
        seconds: time the index took to build.
    """

    grid_size: int
    voxel_size: float
    pool: int
    blur: float
    packed: np.ndarray
    features: np.ndarray
    norms: np.ndarray
    identities: list[str]
    families: list[str]
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.packed)

    @classmethod
    def from_grids(cls, grids: np.ndarray, voxel_size: float, config: MemorisationConfig | None = None,
                   identities: Sequence[str] | None = None, families: Sequence[str] | None = None) -> TrainingIndex:
        """An index of in-memory grids (K, N, N, N) (tests, small sets)."""
        config = config or MemorisationConfig()
        grids = np.asarray(grids, dtype=bool)
        n = grids.shape[1]
        pool = config.pool_for(n)
        features = pooled_features(grids, pool, blur=config.blur).astype(np.float16)
        ids = list(identities) if identities is not None else [str(k) for k in range(len(grids))]
        fams = list(families) if families is not None else [""] * len(grids)
        return cls(grid_size=n, voxel_size=float(voxel_size), pool=pool, blur=config.blur,
                   packed=np.packbits(grids.reshape(len(grids), -1), axis=1), features=features,
                   norms=_squared_norms(features), identities=ids, families=fams)

    @classmethod
    def from_reader(cls, reader: Any, config: MemorisationConfig | None = None,
                    progress: bool = False) -> TrainingIndex:
        """Reads every ground-truth grid of a :class:`~pssnet_core.data.store.DatasetReader`, shard by shard."""
        from tqdm import tqdm

        config = config or MemorisationConfig()
        t0 = time.perf_counter()
        n = int(reader.grid_size)
        pool = config.pool_for(n)
        packed, features = [], []
        for shard in tqdm(range(reader.num_shards), desc="index training grids", unit="shard",
                          disable=not progress, dynamic_ncols=True):
            grids = reader.load_shard(shard, keys=["occupancy"])["occupancy"]
            packed.append(np.packbits(grids.reshape(len(grids), -1), axis=1))
            features.append(pooled_features(grids, pool, blur=config.blur).astype(np.float16))
        if not packed:
            raise MemorisationError("the training set holds no grids")
        feats = np.concatenate(features)
        return cls(grid_size=n, voxel_size=float(reader.voxel_size), pool=pool, blur=config.blur,
                   packed=np.concatenate(packed),
                   features=feats, norms=_squared_norms(feats),
                   identities=[str(r.get("identity", "")) for r in reader.records],
                   families=[str(r.get("family", "")) for r in reader.records], seconds=time.perf_counter() - t0)

    def grids(self, indices: np.ndarray) -> np.ndarray:
        """(K, N, N, N) bool grids of the given training indices."""
        n = self.grid_size
        return np.unpackbits(self.packed[np.asarray(indices, dtype=np.int64)], axis=1,
                             count=n**3).astype(bool).reshape(-1, n, n, n)

    def candidates(self, queries: np.ndarray, top_k: int, chunk: int = 32768) -> np.ndarray:
        """(Q, k) training indices nearest each query by squared feature distance, nearest first.

        Args:
            queries: (Q, N, N, N) bool grids.
            top_k: candidates per query (at most the index size).
            chunk: training grids per matrix product.
        """
        q = pooled_features(np.asarray(queries, dtype=bool), self.pool, blur=self.blur)
        q_norm = (q**2).sum(axis=1)
        k = min(top_k, len(self))
        best_score = np.full((len(q), 0), np.inf, dtype=np.float32)
        best_index = np.zeros((len(q), 0), dtype=np.int64)
        for start in range(0, len(self), chunk):
            stop = min(start + chunk, len(self))
            block = self.features[start:stop].astype(np.float32)
            score = q_norm[:, None] + self.norms[None, start:stop] - 2.0 * (q @ block.T)
            score = np.concatenate([best_score, score.astype(np.float32)], axis=1)
            index = np.concatenate([best_index, np.broadcast_to(np.arange(start, stop), (len(q), stop - start))],
                                   axis=1)
            keep = np.argpartition(score, k - 1, axis=1)[:, :k] if score.shape[1] > k else \
                np.broadcast_to(np.arange(score.shape[1]), score.shape)
            best_score = np.take_along_axis(score, keep, axis=1)
            best_index = np.take_along_axis(index, keep, axis=1)
        order = np.argsort(best_score, axis=1, kind="stable")
        return np.take_along_axis(best_index, order, axis=1)


def _squared_norms(features: np.ndarray) -> np.ndarray:
    return (features.astype(np.float32) ** 2).sum(axis=1)


def nearest_training(queries: np.ndarray, index: TrainingIndex, config: MemorisationConfig | None = None,
                     progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Exact chamfer distance (metres) from each query to its nearest training grid among the prefilter's picks.

    Args:
        queries: (Q, N, N, N) bool grids (completions) of the index's grid size and voxel size.
        index: the training grids.
        config: search parameters.
        progress: tqdm bar over query chunks.

    Returns:
        (distance (Q,) metres, training index (Q,)).
    """
    from tqdm import tqdm

    config = config or MemorisationConfig()
    queries = np.asarray(queries, dtype=bool)
    if queries.ndim != 4 or queries.shape[1] != index.grid_size:
        raise MemorisationError(f"queries must be (Q, {index.grid_size}, ...) grids, got {queries.shape}")
    distance = np.full(len(queries), np.inf)
    nearest = np.full(len(queries), -1, dtype=np.int64)
    # One pass over the training features for all queries (the features are the big array).
    candidates = index.candidates(queries, config.top_k, config.chunk)
    starts = range(0, len(queries), config.query_chunk)
    for start in tqdm(starts, desc="nearest training shape", unit="chunk", disable=not progress,
                      dynamic_ncols=True):
        chunk = queries[start:start + config.query_chunk]
        # Completions of one view share most candidates: the chunk is scored against the union of its
        # candidates in one chamfer matrix (each training grid's distance field made once). Every query thus
        # sees at least its own top-k, so the union can only bring it nearer the exact nearest.
        unique = np.unique(candidates[start:start + config.query_chunk])
        grids = index.grids(unique)
        d = chamfer_matrix(chunk, grids, index.voxel_size, fields_a=distance_fields(chunk),
                           fields_b=distance_fields(grids))
        best = d.argmin(axis=1)
        distance[start:start + len(chunk)] = d[np.arange(len(chunk)), best]
        nearest[start:start + len(chunk)] = unique[best]
    return distance, nearest


def brute_force_nearest(queries: np.ndarray, index: TrainingIndex, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest training grid over the *whole* index (the reference the prefilter is checked against).

    Returns:
        (distance (Q,) metres, training index (Q,)).
    """
    queries = np.asarray(queries, dtype=bool)
    query_fields = distance_fields(queries)
    distance = np.full(len(queries), np.inf)
    nearest = np.full(len(queries), -1, dtype=np.int64)
    for start in range(0, len(index), chunk):
        ids = np.arange(start, min(start + chunk, len(index)))
        d = chamfer_matrix(queries, index.grids(ids), index.voxel_size, fields_a=query_fields)
        best = d.argmin(axis=1)
        better = d[np.arange(len(queries)), best] < distance
        distance[better] = d[np.arange(len(queries)), best][better]
        nearest[better] = ids[best[better]]
    return distance, nearest


# -------------------------------------------------------------------------------------------- run


@dataclass
class MemorisationRun:
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
        config: search parameters.
    """

    train_data: Sequence[str]
    data: str
    out: str
    sets: Sequence[str] = ("mugs", "ycb_narrow", "ycb_wide")
    samples: int = 10
    max_views: int | None = None
    seed: int = 0
    verify: int = 0
    progress: bool = True
    config: MemorisationConfig = field(default_factory=MemorisationConfig)


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


def _spaced(count: int, limit: int | None) -> list[int]:
    if limit is not None and limit < 1:
        raise MemorisationError(f"max_views must be >= 1, got {limit}")
    return evenly_spaced(count, limit)


def run_memorisation(run: MemorisationRun, completers: Mapping[str, Any]) -> dict[str, Path]:
    """Completes test views with every completer and measures each completion's nearest training shape.

    Writes ``memorisation.md``, ``memorisation.json`` (summary, costs, prefilter check),
    ``memorisation_per_completion.csv``, ``memorisation_scatter.png`` and ``memorisation_examples.png``.

    Returns:
        The files written, by kind.
    """
    from tqdm import tqdm

    from pssnet_core.data.store import DatasetReader
    from pssnet_core.evaluation.experiment import write_csv
    from pssnet_core.evaluation.testsets import find_test_set, load_test_set

    if run.samples < 1:
        raise MemorisationError(f"samples must be >= 1, got {run.samples}")
    if not completers:
        raise MemorisationError("no completers given")
    t_start = time.perf_counter()
    roots = dataset_roots(run.train_data)
    train = DatasetReader(roots)
    index = TrainingIndex.from_reader(train, run.config, progress=run.progress)
    costs: dict[str, Any] = {"index_seconds": index.seconds, "training_grids": len(index), "grid_size": index.grid_size,
                             "index_megabytes": (index.packed.nbytes + index.features.nbytes) / 1e6}
    for name, completer in completers.items():
        if getattr(completer, "grid_size", index.grid_size) != index.grid_size:
            raise MemorisationError(f"{name} completes {completer.grid_size}^3 grids but the training grids are "
                                    f"{index.grid_size}^3")
    completions: dict[str, list[np.ndarray]] = {m: [] for m in completers}
    truths: list[np.ndarray] = []
    meta: list[dict[str, Any]] = []
    t_sampling = 0.0
    found_any = False
    for set_name in run.sets:
        root = find_test_set(run.data, set_name)
        if root is None:
            continue
        found_any = True
        views, set_meta = load_test_set(root, progress=run.progress)
        if abs(float(set_meta.get("voxel_size", index.voxel_size)) - index.voxel_size) > 1e-9 or \
                views[0].grid_pose.size != index.grid_size:
            raise MemorisationError(f"{root} has another grid than the training set ({index.grid_size}^3, "
                                    f"{index.voxel_size} m voxels)")
        reader = DatasetReader(root)
        for i in tqdm(_spaced(len(views), run.max_views), desc=f"complete {set_name}", unit="view",
                      disable=not run.progress, dynamic_ncols=True):
            view = views[i]
            truths.append(np.asarray(reader.get(view.index, images=False)["occupancy"], dtype=bool))
            meta.append({"set": set_name, "index": view.index, "identity": view.identity,
                         "family": view.meta.get("family", view.identity.split("-")[0])})
            for name, completer in completers.items():
                t0 = time.perf_counter()
                result = completer.complete(view, num_samples=run.samples, seed=run.seed + view.index)
                t_sampling += time.perf_counter() - t0
                completions[name].append(np.asarray(result.occupancy, dtype=bool))
    if not found_any:
        raise MemorisationError(f"no test sets {list(run.sets)} under {run.data}")
    costs["sampling_seconds"] = t_sampling
    rows: list[dict[str, Any]] = []
    examples: dict[str, list[tuple[float, np.ndarray, int, np.ndarray]]] = {}
    t_search = time.perf_counter()
    t_verify = 0.0
    verify: dict[str, Any] = {}
    # Baseline: how near the truth itself lies to a training grid. A training set with many objects in many poses
    # has some grid near any shape, so completions can be nearer a training shape than their truth without
    # recalling one; the truth's own distance says how near "near" is for this training set.
    d_base, _ = nearest_training(np.stack(truths), index, run.config)
    for m, d in zip(meta, d_base, strict=True):
        m["truth_train_mm"] = float(d * 1000)
    for name in completers:
        queries = np.concatenate(completions[name])  # (views * samples, N, N, N)
        d_train, nearest = nearest_training(queries, index, run.config, progress=run.progress)
        truth_stack = np.repeat(np.stack(truths), run.samples, axis=0)
        d_truth = np.concatenate([chamfer_matrix(samples, truth[None], index.voxel_size)[:, 0]
                                  for samples, truth in zip(completions[name], truths, strict=True)])
        if run.verify > 0:
            t0 = time.perf_counter()
            pick = np.asarray(evenly_spaced(len(queries), run.verify))
            d_brute, _ = brute_force_nearest(queries[pick], index)
            t_verify += time.perf_counter() - t0
            verify[name] = {"completions": int(len(pick)),
                            "prefilter_found_exact_nearest": float(np.mean(np.isclose(d_brute, d_train[pick],
                                                                                      atol=1e-9))),
                            "max_excess_mm": float((d_train[pick] - d_brute).max() * 1000)}
        ranked = []
        for q in range(len(queries)):
            m = meta[q // run.samples]
            j = int(nearest[q])
            rows.append({"method": name, **m, "sample": q % run.samples, "train_mm": float(d_train[q] * 1000),
                         "truth_mm": float(d_truth[q] * 1000), "nearer_training": bool(d_train[q] < d_truth[q]),
                         "train_index": j, "train_identity": index.identities[j],
                         "same_family": index.families[j] == m["family"]})
            ranked.append((float(d_train[q] / max(d_truth[q], 1e-12)), q))
        # Figure: the completions most clearly nearer a training shape than their truth.
        examples[name] = [(r, queries[q], int(nearest[q]), truth_stack[q]) for r, q in sorted(ranked)[:4]]
    costs["search_seconds"] = time.perf_counter() - t_search - t_verify
    costs["verify_seconds"] = t_verify
    costs["total_seconds"] = time.perf_counter() - t_start
    summary = summarise_memorisation(rows, list(completers), list(dict.fromkeys(m["set"] for m in meta)))
    out = Path(run.out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"markdown": out / "memorisation.md", "json": out / "memorisation.json"}
    files["markdown"].write_text(markdown_memorisation(summary, run, roots, costs, verify))
    files["json"].write_text(json.dumps({
        "run": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(run).items() if k != "config"},
        "config": asdict(run.config), "training": [str(r) for r in roots], "summary": summary, "costs": costs,
        "verify": verify}, indent=1))
    files["csv"] = write_csv(out / "memorisation_per_completion.csv", rows)
    files["scatter"] = plot_memorisation(out / "memorisation_scatter.png", rows, list(completers))
    files["examples"] = plot_examples(out / "memorisation_examples.png", examples, index)
    return files


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


def markdown_memorisation(summary: Sequence[dict[str, Any]], run: MemorisationRun, roots: Sequence[Path],
                          costs: dict[str, Any], verify: dict[str, Any]) -> str:
    """The Markdown report."""
    lines = ["# Memorisation: completions against the nearest training shape", "",
             f"Training grids: {costs['training_grids']} from {', '.join(f'`{r}`' for r in roots)}; test sets under "
             f"`{run.data}`; {run.samples} completions per view, seed {run.seed} (view i uses seed + i). Chamfer "
             "distance between voxel-centre clouds in mm, grid to grid (see "
             "`pssnet_core/evaluation/memorisation.py`). Paper (appendix): ~10 % of completions nearer a training "
             "shape, 2.4 mm to it vs 3.8 mm to the truth.", "",
             "| method | test set | views | completions | nearer a training shape | to nearest training (mm, mean "
             "/ median) | to the truth (mm, mean / median) | nearest is same family | truth to nearest training (mm) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for e in summary:
        lines.append(f"| {e['method']} | {e['set']} | {e['views']} | {e['completions']} | "
                     f"{e['nearer_training_fraction']:.1%} | {e['train_mm_mean']:.2f} / {e['train_mm_median']:.2f} | "
                     f"{e['truth_mm_mean']:.2f} / {e['truth_mm_median']:.2f} | {e['same_family_fraction']:.0%} | "
                     f"{e['truth_train_mm_mean']:.2f} |")
    lines += ["", "Last column: the test truth's own distance to the nearest training grid (per view, averaged over "
              "completions). A training set with many objects in many poses has some grid near any shape, so "
              "completions can lie nearer a training shape than their truth without recalling one; compare the "
              "distance to the nearest training shape with this baseline.",
              "", f"Search: prefilter on mass-normalised occupancy averaged over "
              f"{run.config.pool_for(int(costs.get('grid_size', 32)))}-voxel blocks, blurred by {run.config.blur:g} "
              f"voxel; exact chamfer on the top {run.config.top_k}."]
    for name, v in verify.items():
        lines.append(f"Prefilter check ({name}): on {v['completions']} completions searched by brute force over the "
                     f"whole training set, the prefilter found the exact nearest in "
                     f"{v['prefilter_found_exact_nearest']:.0%} (largest excess {v['max_excess_mm']:.2f} mm).")
    lines += ["", f"Cost: index {costs['index_seconds']:.1f} s ({costs['index_megabytes']:.0f} MB in memory), sampling "
              f"{costs['sampling_seconds']:.1f} s, search {costs['search_seconds']:.1f} s, brute-force check "
              f"{costs['verify_seconds']:.1f} s, whole run {costs['total_seconds']:.1f} s."]
    return "\n".join(lines) + "\n"


def plot_memorisation(path: str | Path, rows: Sequence[dict[str, Any]], methods: Sequence[str]) -> Path:
    """Per method: distance to the nearest training shape against distance to the truth (one dot a completion)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.evaluation.figures import save_figure

    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 4.0), squeeze=False)
    for ax, method in zip(axes[0], methods, strict=True):
        chosen = [r for r in rows if r["method"] == method]
        sets = list(dict.fromkeys(r["set"] for r in chosen))
        top = max([1.0] + [max(r["train_mm"], r["truth_mm"]) for r in chosen])
        for k, set_name in enumerate(sets):
            pts = np.array([[r["truth_mm"], r["train_mm"]] for r in chosen if r["set"] == set_name])
            ax.plot(pts[:, 0], pts[:, 1], "o", markersize=3, alpha=0.5, color=plt.get_cmap("tab10")(k % 10),
                    label=set_name)
        ax.plot([0, top], [0, top], color="grey", linewidth=0.8, linestyle=":")
        nearer = np.mean([r["nearer_training"] for r in chosen]) if chosen else math.nan
        ax.set_title(f"{method}: {nearer:.0%} below the diagonal (nearer a training shape)", fontsize=8)
        ax.set_xlabel("chamfer to the test truth (mm)")
        ax.set_ylabel("chamfer to the nearest training shape (mm)")
        ax.legend(fontsize=7)
    return save_figure(fig, path, dpi=100)


def plot_examples(path: str | Path, examples: Mapping[str, list[tuple[float, np.ndarray, int, np.ndarray]]],
                  index: TrainingIndex) -> Path:
    """Rows: completion, its nearest training grid, the test truth (the completions nearest a training shape
    relative to their truth)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.evaluation.figures import draw_voxels, save_figure

    items = [(m, e) for m, es in examples.items() for e in es]
    fig = plt.figure(figsize=(6.0, 2.0 * max(1, len(items))))
    for r, (method, (ratio, completion, j, truth)) in enumerate(items):
        for c, (grid, title, colour) in enumerate((
                (completion, f"{method} completion (train/truth {ratio:.2f})", "tab:blue"),
                (index.grids(np.array([j]))[0], f"nearest training: {index.identities[j]}", "tab:orange"),
                (truth, "test truth", "tab:green"))):
            ax = fig.add_subplot(max(1, len(items)), 3, 3 * r + c + 1, projection="3d")
            draw_voxels(ax, grid, title, colour)
    return save_figure(fig, path, dpi=90)


__all__ = ["MemorisationConfig", "MemorisationError", "MemorisationRun", "TrainingIndex", "brute_force_nearest",
           "dataset_roots", "markdown_memorisation", "nearest_training", "plot_examples", "plot_memorisation",
           "pooled_features", "run_memorisation", "summarise_memorisation"]
