"""Scaling of the batch work on Ray: a dataset build and a plausible-set computation, in this process and on a
local Ray with 1, 2, ... workers, plus the costs a cluster estimate needs (per view, per pair, the prefilter).

    .venv/bin/python benchmarks/ray_bench.py [--mugs 8 --views 72 --references 16 --workers 1 2]

Each configuration builds the same test-split mug dataset (``--mugs`` x ``--views`` views, 32^3) into a fresh
directory, then computes the plausible sets of ``--references`` evenly spaced views of it against every other view
(the paper's Alg. 2, deltas 4 and 1 cm). Ray's start and stop are timed apart from the work. Every configuration
must give the same shards and sets (checked).

On a shared machine wall times depend on what else runs, so each stage also reports the CPU time of this process
and its Ray workers (the cost per view and per pair that a cluster estimate scales) and how many cores other
processes kept busy meanwhile (from /proc). ``--empty-tasks N`` also times N tasks that do nothing (Ray's cost per
task, workers warmed up first).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pssnet_core"))  # pssnet_core, also without a venv

from pssnet_core.data.build import build_dataset  # noqa: E402
from pssnet_core.data.datasets import dataset_specs  # noqa: E402
from pssnet_core.data.store import DatasetReader  # noqa: E402
from pssnet_core.evaluation.plausible import PlausibleConfig, ShapeMeshes, compute_plausible_sets  # noqa: E402
from pssnet_core.evaluation.testsets import load_test_set  # noqa: E402
from pssnet_core.ray_tasks import RayConfig, TaskRunner, descendants, process_stats  # noqa: E402
from pssnet_core.spread import evenly_spaced  # noqa: E402

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def machine_busy_seconds() -> float:
    """CPU seconds all cores spent busy since boot (/proc/stat)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields[:8]
    return (user + nice + system + irq + softirq + steal) / CLOCK_TICKS


def own_cpu_seconds() -> float:
    """CPU seconds of this process and its live descendants (the Ray workers, which live until Ray stops)."""
    stats = process_stats()
    tree = descendants(os.getpid(), stats) | {os.getpid()}
    return sum((int(stats[p][11]) + int(stats[p][12])) / CLOCK_TICKS for p in tree if p in stats)


@dataclass
class Stage:
    """One timed stage: wall seconds, our CPU seconds, other processes' CPU seconds."""

    wall: float = 0.0
    own_cpu: float = 0.0
    other_cpu: float = 0.0

    @contextmanager
    def timed(self) -> Iterator[None]:
        wall, busy, own = time.perf_counter(), machine_busy_seconds(), own_cpu_seconds()
        yield
        self.wall = time.perf_counter() - wall
        self.own_cpu = own_cpu_seconds() - own
        self.other_cpu = max(0.0, machine_busy_seconds() - busy - self.own_cpu)


@dataclass
class Measured:
    label: str
    start_s: float
    build: Stage
    views: int
    plausible: Stage
    pairs: int
    stop_s: float
    fingerprint: tuple
    empty_task_ms: float


def _empty(unit: int) -> int:
    return unit


def empty_task_ms(runner: TaskRunner, count: int) -> float:
    """Milliseconds per task that does nothing, after a warm-up; nan when not asked for."""
    if count < 1:
        return float("nan")
    list(runner.map(_empty, list(range(200)), progress=False))
    start = time.perf_counter()
    list(runner.map(_empty, list(range(count)), progress=False))
    return 1e3 * (time.perf_counter() - start) / count


def shard_digest(root: Path) -> str:
    """SHA-256 of a dataset's records and decoded arrays (the files' bytes carry zip timestamps)."""
    reader = DatasetReader(root)
    digest = hashlib.sha256(json.dumps(reader.records).encode())
    for shard in range(reader.num_shards):
        for name, column in sorted(reader.load_shard(shard, images=True).items()):
            digest.update(name.encode())
            for value in column:
                digest.update(np.ascontiguousarray(value).tobytes())
    return digest.hexdigest()


def measure(label: str, config: RayConfig, args: argparse.Namespace) -> Measured:
    spec = dataset_specs("mugs", "test", grid_size=args.grid, num_objects=args.mugs, views=args.views)[0]
    t0 = time.perf_counter()
    runner = TaskRunner(config)
    workers = runner.parallelism  # starts Ray (not in this process)
    t1 = time.perf_counter()
    build, plausible = Stage(), Stage()
    with tempfile.TemporaryDirectory() as root:
        with build.timed():
            built = build_dataset(spec, Path(root) / "mugs", runner=runner, progress=False)
        views, _ = load_test_set(built.path)
        refs = evenly_spaced(len(views), args.references)
        with plausible.timed():
            sets = compute_plausible_sets(views, ShapeMeshes(), PlausibleConfig(deltas=(0.04, 0.01)), refs,
                                          runner=runner, progress=False)
        shards = shard_digest(built.path)
    empty_ms = empty_task_ms(runner, args.empty_tasks)
    t4 = time.perf_counter()
    runner.close()
    t5 = time.perf_counter()
    s = sets.stats
    print(f"{label} ({workers} CPUs): plausible pairs {s['pairs']}, pruned by the diameter bound "
          f"{s['pruned_by_prefilter']}, rejected on sparse pixels {s['rejected_on_sparse_pixels']}, ICP "
          f"{s['icp_seconds']:.1f} s, judge {s['judge_seconds']:.1f} s (wall, summed)", flush=True)
    fingerprint = (shards, sets.other.tobytes(), sets.transforms.tobytes(), sets.violations.tobytes())
    return Measured(label, t1 - t0, build, built.samples, plausible, int(s["pairs"]), t5 - t4, fingerprint, empty_ms)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mugs", type=int, default=8, help="test mugs to build (default 8)")
    parser.add_argument("--views", type=int, default=72, help="views per mug (default 72)")
    parser.add_argument("--grid", type=int, default=32)
    parser.add_argument("--references", type=int, default=16, help="plausible-set references (default 16)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="local Ray sizes (default 1 2)")
    parser.add_argument("--no-in-process", action="store_true", help="skip the in-process baseline")
    parser.add_argument("--empty-tasks", type=int, default=0, help="also time this many empty tasks (default 0)")
    args = parser.parse_args()

    runs = [] if args.no_in_process else [measure("in this process", RayConfig(), args)]
    runs += [measure(f"local Ray, {w} worker(s)", RayConfig(workers=w, address="local"), args) for w in args.workers]
    print("\n| where | Ray start s | build s | views/s | CPU ms/view | other cores | plausible s | pairs/s | "
          "CPU ms/pair | other cores | Ray stop s | ms/empty task |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        b, p = r.build, r.plausible
        print(f"| {r.label} | {r.start_s:.1f} | {b.wall:.1f} | {r.views / b.wall:.1f} | "
              f"{1e3 * b.own_cpu / r.views:.1f} | {b.other_cpu / b.wall:.2f} | {p.wall:.1f} | {r.pairs / p.wall:.0f} | "
              f"{1e3 * p.own_cpu / r.pairs:.2f} | {p.other_cpu / p.wall:.2f} | {r.stop_s:.1f} | "
              f"{r.empty_task_ms:.2f} |")
    base = runs[0]
    for r in runs[1:]:
        print(f"{r.label}: build {base.build.wall / r.build.wall:.2f}x, plausible "
              f"{base.plausible.wall / r.plausible.wall:.2f}x the speed of {base.label}")
    same = all(r.fingerprint == base.fingerprint for r in runs)
    print(f"identical shards and plausible sets in every configuration: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
