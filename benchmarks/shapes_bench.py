"""Time procedural shape generation (ms per shape, per family) and the mesh-folder round trip.

Run: `.venv/bin/python benchmarks/shapes_bench.py --count 50`.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from pssnet_core.shapes import FAMILIES, export_shapes, load_mesh_folder, make_shape, split_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--count", type=int, default=50, help="shapes per family")
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    args = parser.parse_args()
    seeds = split_seeds("train", args.count)
    print(f"{'family':<10} {'median ms':>9} {'p90 ms':>7} {'cpu ms':>7} {'faces':>6} {'diag max m':>10}")
    shapes = []
    for family in args.families:
        make_shape(family, 10**5)  # warm-up (imports, first allocations)
        wall, faces, diagonals = [], [], []
        cpu_start = time.process_time()
        for seed in seeds:
            start = time.perf_counter()
            shape = make_shape(family, seed)
            wall.append(time.perf_counter() - start)
            faces.append(len(shape.mesh.faces))
            diagonals.append(shape.attributes["diagonal"])
        cpu = (time.process_time() - cpu_start) / len(seeds)
        shapes.extend(make_shape(family, s) for s in seeds[:5])
        print(f"{family:<10} {1e3 * np.median(wall):9.2f} {1e3 * np.percentile(wall, 90):7.2f} {1e3 * cpu:7.2f} "
              f"{int(np.median(faces)):6d} {max(diagonals):10.3f}")
    for layout in ("shapenet", "ycb", "flat"):
        with tempfile.TemporaryDirectory() as root:
            start = time.perf_counter()
            export_shapes(shapes, root, layout)
            exported = time.perf_counter()
            loaded = load_mesh_folder(root, layout)
            done = time.perf_counter()
        print(f"{layout:<8} export {1e3 * (exported - start) / len(shapes):6.2f} ms/shape, "
              f"load {1e3 * (done - exported) / len(loaded):6.2f} ms/shape ({len(loaded)} shapes)")


if __name__ == "__main__":
    main()
