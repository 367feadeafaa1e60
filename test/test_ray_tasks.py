"""The Ray execution layer: the same results in this process and on a local 2-worker Ray, resuming, clean shutdown.

One local Ray (2 CPUs, a small object store) serves the whole module; its teardown checks that Ray stopped and
left no process behind.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ray
import ray.cloudpickle
from test_eval_plausible import SPECS, render_view, tiny_meshes

from pssnet_core.cli import main
from pssnet_core.data.build import build_dataset
from pssnet_core.data.datasets import dataset_specs
from pssnet_core.data.store import DatasetReader
from pssnet_core.evaluation.evaluate import evaluate_set
from pssnet_core.evaluation.plausible import MeshTable, PlausibleConfig, PlausibleSets, compute_plausible_sets
from pssnet_core.ray_tasks import RAY_ADDRESS_ENV, RayConfig, RayTasksError, TaskRunner, descendants

WORKERS = 2


@pytest.fixture(scope="module")
def ray_runner() -> Iterator[TaskRunner]:
    assert not ray.is_initialized()
    before = descendants(os.getpid())
    # Test fakes reach the workers by value: workers cannot import test modules.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    runner = TaskRunner(RayConfig(workers=WORKERS, address="local", object_store_mb=128))
    assert runner.parallelism == WORKERS  # starts Ray here, so every test (and the CLI) finds it running
    yield runner
    runner.close()
    ray.cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert not ray.is_initialized()
    deadline = time.monotonic() + 15
    while (left := descendants(os.getpid()) - before) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not left, f"Ray left processes behind: {sorted(left)}"


def test_where_units_run(monkeypatch):
    monkeypatch.delenv(RAY_ADDRESS_ENV, raising=False)
    assert RayConfig().in_process and RayConfig(workers=1).resolved_address == "local"
    assert not RayConfig(workers=2).in_process  # a local Ray with 2 CPUs
    assert not RayConfig(workers=1, address="local").in_process  # one worker, under Ray all the same
    assert RayConfig(address="auto").resolved_address == "auto"
    monkeypatch.setenv(RAY_ADDRESS_ENV, "ray://head:10001")
    assert not RayConfig().in_process and RayConfig().resolved_address == "ray://head:10001"
    assert RayConfig(address="local").resolved_address == "local"  # the flag wins over the environment
    with pytest.raises(RayTasksError, match="workers"):
        RayConfig(workers=0)
    with pytest.raises(RayTasksError, match="empty"):
        RayConfig(address=" ")
    # Nothing to do starts nothing.
    running = ray.is_initialized()
    assert list(TaskRunner(RayConfig(workers=2)).map(_affine, [], {"scale": 2, "offset": np.zeros(3)})) == []
    assert ray.is_initialized() == running


def _affine(unit: int, scale: int, offset: np.ndarray) -> tuple[np.ndarray, int]:
    time.sleep(0.05)  # long enough that both workers get units
    return unit * scale + offset, os.getpid()


def _fail_on_three(unit: int) -> int:
    if unit == 3:
        raise ValueError(f"unit {unit} is bad")
    return unit


def test_units_run_alike_in_process_and_on_ray_with_shared_inputs_put_once(ray_runner, monkeypatch):
    shared = {"scale": 3, "offset": np.arange(1000.0)}
    units = list(range(8))
    local = dict(TaskRunner().map(_affine, units, shared, progress=False))
    puts = []
    real_put = ray.put
    monkeypatch.setattr(ray, "put", lambda value: puts.append(value) or real_put(value))
    remote = dict(ray_runner.map(_affine, units, shared, progress=False))
    assert len(puts) == len(shared)  # once per map, not once per task
    assert sorted(remote) == units
    for unit in units:
        assert np.array_equal(local[unit][0], remote[unit][0])
    assert {pid for _, pid in remote.values()} - {os.getpid()}, "no unit ran in a Ray worker"
    assert len({pid for _, pid in remote.values()}) == WORKERS
    # The unit's own error, as in this process; the tasks still running are left to finish, never cancelled (a
    # cancel racing a task's completion aborts the driver in Ray 2.60, ray_tasks.TaskRunner._map_ray).
    monkeypatch.setattr(ray, "cancel", lambda *args, **kwargs: pytest.fail("ray.cancel was called"))
    with pytest.raises(ValueError, match="unit 3 is bad"):
        list(ray_runner.map(_fail_on_three, units, progress=False))


def shard_contents(root: Path) -> list[tuple[str, dict[str, np.ndarray]]]:
    reader = DatasetReader(root)
    return [(json.dumps(reader.records), reader.load_shard(k, images=True)) for k in range(reader.num_shards)]


def assert_same_shards(a: Path, b: Path) -> None:
    for (records_a, arrays_a), (records_b, arrays_b) in zip(shard_contents(a), shard_contents(b), strict=True):
        assert records_a == records_b and arrays_a.keys() == arrays_b.keys()
        for key in arrays_a:
            assert all(np.array_equal(x, y) for x, y in zip(arrays_a[key], arrays_b[key], strict=True)), key


def test_dataset_build_on_ray_equals_in_process_and_resumes(ray_runner, tmp_path):
    spec = dataclasses.replace(dataset_specs("ycb", "train", grid_size=16, num_objects=3, views=2)[0],
                               objects_per_shard=1)
    serial = build_dataset(spec, tmp_path / "serial", progress=False)
    on_ray = build_dataset(spec, tmp_path / "ray", runner=ray_runner, progress=False)
    assert on_ray.shards_built == spec.num_shards == 3 and on_ray.samples == serial.samples == 6
    assert_same_shards(serial.path, on_ray.path)
    # A killed build left shard 0 only (shards are written atomically): the next run makes the other two.
    for shard in (1, 2):
        for path in (on_ray.path / "shards").glob(f"{shard:05d}.*"):
            path.unlink()
    resumed = build_dataset(spec, on_ray.path, runner=ray_runner, progress=False)
    assert resumed.shards_built == 2 and resumed.shards_skipped == 1
    assert_same_shards(serial.path, resumed.path)


def test_dataset_build_command_with_a_local_ray_equals_the_default(ray_runner, tmp_path):
    common = ["dataset", "build", "--family", "mugs", "--split", "test", "--grid", "16", "--num-objects", "2",
              "--views", "2", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "default")]) == 0
    assert main([*common, "--out", str(tmp_path / "ray"), "--ray-address", "local"]) == 0
    assert ray.is_initialized()  # the command used the running Ray and left it running
    assert_same_shards(tmp_path / "default" / "test" / "mugs", tmp_path / "ray" / "test" / "mugs")


@pytest.fixture(scope="module")
def tiny_set() -> tuple[list, MeshTable]:
    meshes = tiny_meshes()
    views = [render_view(k, name, meshes[name], yaw) for k, (name, yaw) in enumerate(SPECS)]
    return views, MeshTable({k: (np.asarray(m.vertices), np.asarray(m.faces)) for k, m in meshes.items()})


def assert_same_sets(a: PlausibleSets, b: PlausibleSets) -> None:
    for field in ("references", "object_pixels", "ref", "other", "transforms", "violations"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field
    assert a.deltas == b.deltas and a.stats["pairs"] == b.stats["pairs"]


class StopAfter:
    """A runner killed after ``count`` finished units (Ctrl-C), recording which units it was given."""

    def __init__(self, runner: TaskRunner, count: int | None = None) -> None:
        self.runner, self.count, self.units = runner, count, []
        self.parallelism, self.describe = runner.parallelism, runner.describe

    def map(self, function: Any, units: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
        self.units.extend(units)
        for n, item in enumerate(self.runner.map(function, units, *args, **kwargs), start=1):
            yield item
            if n == self.count:
                raise KeyboardInterrupt


def test_plausible_sets_on_ray_equal_in_process_and_resume(ray_runner, tiny_set, tmp_path):
    views, table = tiny_set
    config = PlausibleConfig(deltas=(0.04, 0.01))
    serial = compute_plausible_sets(views, table, config, progress=False)
    assert_same_sets(serial, compute_plausible_sets(views, table, config, runner=ray_runner, progress=False))
    # Killed after two references: those are on disk, and the next run computes only the other three.
    parts = tmp_path / "parts"
    killed = StopAfter(ray_runner, count=2)
    with pytest.raises(KeyboardInterrupt):
        compute_plausible_sets(views, table, config, runner=killed, progress=False, parts_dir=parts)
    again = StopAfter(ray_runner)
    resumed = compute_plausible_sets(views, table, config, runner=again, progress=False, parts_dir=parts)
    assert len(again.units) == len(set(again.units)) == len(views) - 2
    assert resumed.stats["resumed_references"] == 2
    assert_same_sets(serial, resumed)


class SeededCompleter:
    """A fake completer: the observed voxels plus random ones drawn from the seed (so seeds must match)."""

    grid_size = 16

    def complete(self, observation: Any, num_samples: int = 20, seed: int = 0) -> argparse.Namespace:
        x = observation.network_input()  # the evaluation hands over its views
        rng = np.random.default_rng(seed)
        noise = rng.random((num_samples, *x.shape[1:])) < 0.02
        return argparse.Namespace(occupancy=noise | (x[0] > 0.5))


def test_evaluation_on_ray_equals_in_process(ray_runner, tiny_set):
    views, table = tiny_set
    sets = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.04, 0.01)), progress=False)
    common = dict(set_name="tiny", views=views, meshes=table, sets=sets, completers={"seeded": SeededCompleter()},
                  deltas=(0.04, 0.01), num_samples=4, seed=7, keep=[3], progress=False)
    serial = evaluate_set(**common)
    on_ray = evaluate_set(**common, runner=ray_runner)
    assert serial.rows == on_ray.rows and len(serial.rows) == len(views) * 2
    assert [(e.index, e.delta) for e in serial.examples] == [(e.index, e.delta) for e in on_ray.examples]
    for a, b in zip(serial.examples, on_ray.examples, strict=True):
        assert np.array_equal(a.samples, b.samples) and np.array_equal(a.distances, b.distances)
