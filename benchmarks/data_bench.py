"""Dataset generation speed: samples per second on one core, per dataset and grid size.

Run: ``.venv/bin/python benchmarks/data_bench.py [--objects 4] [--grids 32 64]`` .
Each sample is made exactly as ``pssnet dataset build`` makes it (shape, render, observe, ground truth, box,
crop) in this one process with one open3d thread; shard compression and writing are timed separately.
Also prints the handle-hidden fraction and clipping rate of the samples made (small-sample estimates).
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from pssnet_core.data.datasets import dataset_specs, make_sample
from pssnet_core.data.scenes import ObjectScene
from pssnet_core.data.store import write_shard
from pssnet_core.shapes import shape_of


def bench(name: str, grid: int, objects: int) -> dict[str, float]:
    specs = dataset_specs("all", "train", grid_size=grid, num_objects=objects) + \
        dataset_specs("ycb", "test", grid_size=grid, num_objects=objects)
    spec = next(s for s in specs if s.name == name)
    samples = []
    start = time.perf_counter()
    for identity in spec.object_identities():
        scene = ObjectScene(shape_of(identity), threads=1)
        obj = len(samples) // spec.views
        samples.extend(make_sample(spec, i, scene) for i in range(obj * spec.views, (obj + 1) * spec.views))
    made = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as root:
        start = time.perf_counter()
        write_shard(root, 0, samples)
        written = time.perf_counter() - start
    handle = [s["handle_visible"] for s in samples if s["handle_visible"] is not None]
    return {"samples": len(samples), "per_s": len(samples) / (made + written), "make_ms": 1e3 * made / len(samples),
            "write_ms": 1e3 * written / len(samples),
            "hidden": 1 - float(np.mean(handle)) if handle else float("nan"),
            "clipped": float(np.mean([s["clipped"] for s in samples]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=4, help="objects per dataset (default 4)")
    parser.add_argument("--grids", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--datasets", nargs="+", default=["mugs", "ycb", "ycb_narrow"])
    args = parser.parse_args()
    print(f"{'dataset':<11} {'grid':>4} {'samples':>7} {'samples/s/core':>14} {'make ms':>8} {'write ms':>8} "
          f"{'handle hidden':>13} {'clipped':>8}")
    for grid in args.grids:
        for name in args.datasets:
            r = bench(name, grid, args.objects)
            hidden = "-" if np.isnan(r["hidden"]) else f"{100 * r['hidden']:.1f}%"
            print(f"{name:<11} {grid:>4} {r['samples']:>7} {r['per_s']:>14.1f} {r['make_ms']:>8.1f} "
                  f"{r['write_ms']:>8.1f} {hidden:>13} {100 * r['clipped']:>7.1f}%", flush=True)


if __name__ == "__main__":
    main()
