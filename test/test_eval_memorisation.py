"""Memorisation (pssnet_core.evaluation.memorisation): nearest training shape of each completion.

The prefilter is a heuristic, so it is checked against brute force on a small set of varied shapes; the command
is checked with a planted training shape, whose distance must come out as zero.
"""

from __future__ import annotations

import argparse
import csv
import json

import numpy as np
import pytest

from pssnet_core.data.build import build
from pssnet_core.data.store import DatasetReader, finalize, write_shard
from pssnet_core.evaluation.experiment import write_report
from pssnet_core.evaluation.memorisation import MemorisationConfig, dataset_roots, run_memorisation
from pssnet_core.evaluation.memorisation_report import memorisation_report
from pssnet_core.evaluation.memorisation_search import (
    MemorisationError,
    SearchConfig,
    TrainingIndex,
    brute_force_nearest,
    nearest_training,
    pooled_features,
)
from pssnet_core.evaluation.metrics import chamfer_matrix

N = 16
VOXEL = 0.0125


def test_pooled_features_by_hand():
    grid = np.zeros((4, 4, 4), dtype=bool)
    grid[0:2, 0:2, 0:2] = True  # fills block (0, 0, 0)
    grid[3, 3, 3] = True  # one of 8 voxels of block (1, 1, 1)
    f = pooled_features(grid, 2, normalise=False, blur=0.0)
    assert f.shape == (1, 8)
    np.testing.assert_allclose(f[0], [1, 0, 0, 0, 0, 0, 0, 0.125])
    # As a mass distribution (9 voxels): 8/9 in the first block, 1/9 in the last.
    np.testing.assert_allclose(pooled_features(grid, 2, blur=0.0)[0], [8 / 9, 0, 0, 0, 0, 0, 0, 1 / 9], rtol=1e-6)
    assert pooled_features(grid, 2, blur=1.0)[0, 1] > 0  # blurred: mass next door counts as near
    assert not pooled_features(np.zeros((4, 4, 4), dtype=bool), 2).any()
    with pytest.raises(MemorisationError):
        pooled_features(grid, 3)


def random_shapes(rng: np.random.Generator, count: int) -> np.ndarray:
    """Cuboids, cylinders and hollow cups of random size and place in an N^3 grid (voxel surfaces and solids)."""
    out = np.zeros((count, N, N, N), dtype=bool)
    i, j, k = np.meshgrid(*[np.arange(N) + 0.5] * 3, indexing="ij")
    for s in range(count):
        kind = s % 3
        c = rng.uniform(4, N - 4, size=3)
        size = rng.uniform(1.5, 5.0, size=3)
        if kind == 0:
            shape = np.all(np.abs(np.stack([i, j, k]) - c[:, None, None, None]) <= size[:, None, None, None], axis=0)
        else:
            r = np.hypot(i - c[0], j - c[1])
            shape = (r <= size[0]) & (np.abs(k - c[2]) <= size[2])
            if kind == 2:  # a cup: hollow above its base
                shape &= ~((r <= size[0] - 1.2) & (k > c[2] - size[2] + 1))
        out[s] = shape
    return out


def index_of(grids: np.ndarray, root) -> TrainingIndex:
    """The search index of ``grids`` written as a one-shard training set under ``root``."""
    write_shard(root, 0, [{"occupancy": grid, "identity": str(k)} for k, grid in enumerate(grids)])
    finalize(root, {"grid_size": grids.shape[1], "voxel_size": VOXEL})
    return TrainingIndex.from_reader(DatasetReader(root), SearchConfig(top_k=8))


def test_prefilter_finds_the_exact_nearest_on_a_small_set(tmp_path):
    rng = np.random.default_rng(0)
    train = random_shapes(rng, 300)
    # Queries: unseen shapes of the same kinds, and training shapes with a tenth of their voxels moved.
    novel = random_shapes(rng, 30)
    noisy = train[rng.choice(len(train), 30, replace=False)].copy()
    for grid in noisy:
        occupied = np.argwhere(grid)
        drop = occupied[rng.choice(len(occupied), max(1, len(occupied) // 10), replace=False)]
        grid[tuple(drop.T)] = False
        grid[tuple(np.clip(drop + rng.integers(-1, 2, size=drop.shape), 0, N - 1).T)] = True
    queries = np.concatenate([novel, noisy])
    index = index_of(train, tmp_path)
    assert index.identities[:2] == ["0", "1"] and len(index) == len(train)
    exact, exact_at = brute_force_nearest(queries, index)
    # query_chunk 1: each query sees its own top 8 only (no help from the candidates of other queries).
    found, found_at = nearest_training(queries, index, SearchConfig(top_k=8, query_chunk=1))
    np.testing.assert_allclose(found, exact, atol=1e-12)
    # The brute force is right: the first query against every training grid, directly.
    np.testing.assert_allclose(exact[0], chamfer_matrix(queries[:1], train, VOXEL).min(), atol=1e-12)
    # The candidates are ordered nearest first and exclude nothing nearer by features.
    cands = index.candidates(queries[:3], 5)
    f = pooled_features(queries[:3], index.pool, blur=index.blur)
    scores = ((f[:, None, :] - index.features[None].astype(np.float32)) ** 2).sum(-1)
    np.testing.assert_allclose(np.take_along_axis(scores, cands, 1), np.sort(scores, 1)[:, :5], rtol=1e-3, atol=1e-7)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("memorisation_data")
    build("mugs", "train", root, grid_size=N, num_objects=2, views=3, progress=False)
    build("ycb", "train", root, grid_size=N, num_objects=2, views=3, progress=False)
    build("mugs", "test", root, grid_size=N, num_objects=1, views=3, progress=False)
    return root


class PlantingCompleter:
    """Fake completer: per view, a planted training grid, then the view's own truth."""

    grid_size = N

    def __init__(self, test_root, planted: np.ndarray) -> None:
        reader = DatasetReader(test_root)
        self.truth = {}
        for k in range(len(reader)):
            s = reader.get(k, images=False)
            self.truth[s["known_occupied"].tobytes() + s["known_free"].tobytes()] = s["occupancy"]
        self.planted = planted

    def complete(self, observation, num_samples=2, seed=0):
        x = observation.network_input() > 0.5
        truth = self.truth[x[0].tobytes() + x[1].tobytes()]
        return argparse.Namespace(occupancy=np.stack([self.planted, truth][:num_samples]))


def test_a_planted_training_shape_is_found(tiny_data, tmp_path):
    train = DatasetReader(dataset_roots([tiny_data / "train"]))
    planted_at = 4
    planted = train.get(planted_at, images=False)
    completer = PlantingCompleter(tiny_data / "test" / "mugs", planted["occupancy"])
    config = MemorisationConfig(train_data=[str(tiny_data / "train")], data=str(tiny_data),
                                out=str(tmp_path / "out"), sets=("mugs",), samples=2, verify=2, progress=False)
    files = write_report(memorisation_report(run_memorisation(config, {"planter": completer})), config.out)
    rows = list(csv.DictReader(open(files["csv"])))
    assert len(rows) == 3 * 2
    for row in rows:
        if row["sample"] == "0":  # the planted training grid
            assert float(row["train_mm"]) == 0.0 and row["nearer_training"] == "True"
            assert row["train_identity"] == planted["identity"]
        else:  # the truth: a test object, never a training one; its distance is the truth's baseline
            assert float(row["truth_mm"]) == 0.0 and float(row["train_mm"]) > 0 and row["nearer_training"] == "False"
            assert float(row["train_mm"]) == pytest.approx(float(row["truth_train_mm"]))
    result = json.loads(files["json"].read_text())
    overall = next(e for e in result["summary"] if e["set"] == "all")
    assert overall["nearer_training_fraction"] == 0.5 and overall["completions"] == 6
    assert result["verify"]["planter"]["prefilter_found_exact_nearest"] == 1.0
    assert "| planter | mugs |" in files["markdown"].read_text()
    assert files["scatter"].stat().st_size > 0 and files["examples"].stat().st_size > 0


def test_cli_and_bad_inputs(tiny_data, tmp_path, one_torch_thread):
    from pssnet_core.cli import main
    from pssnet_core.models.checkpoint import save_checkpoint
    from pssnet_core.models.registry import build_model, default_config

    checkpoint = save_checkpoint(tmp_path / "vae.pt",
                                 build_model(default_config("vae", grid_size=N, channels=[4, 8, 8, 8])))
    out = tmp_path / "out"
    args = ["memorisation", "--models", "vae", "--checkpoints", str(checkpoint), "--data", str(tiny_data),
            "--samples", "2", "--max-views", "2", "--out", str(out), "--no-progress"]
    assert main([*args, "--train-data", f"{tiny_data / 'train' / 'mugs'},{tiny_data / 'train' / 'ycb'}"]) == 0
    summary = json.loads((out / "memorisation.json").read_text())["summary"]
    assert {e["set"] for e in summary} == {"mugs", "all"} and summary[0]["completions"] == 4
    assert main([*args, "--train-data", str(tmp_path)]) == 2  # not a dataset: an error message, not a crash
    with pytest.raises(MemorisationError):
        dataset_roots([tmp_path])
