"""Grasp scoring benchmark: 500 candidates x 20 completions at 32^3 and 64^3 (median of repeats).

    .venv/bin/python benchmarks/grasp_bench.py [--candidates 500] [--completions 20] [--repeats 15]

Scoring cost does not depend on how good the candidates are, so the candidates here are grasps of the
generator's orientation set placed at random occupied voxels with random widths (seeded); the completions
are mugs of the project's procedural family rendered into the grid with their handle turned to different
angles. Also timed: candidate generation and the whole ``plan_grasps`` call on the same completions.
Single-threaded numpy (the scoring is gathers and bitwise reductions, no BLAS).
"""

from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import numpy as np

from pssnet_core.geometry import GridConfig
from pssnet_core.grasps import (
    GraspCandidates,
    GraspConfig,
    approach_orientations,
    generate_candidates,
    plan_grasps,
    score_grasps,
)


def completions(size: int, count: int, seed: int = 0) -> tuple[np.ndarray, object, np.ndarray]:
    from pssnet_core.data.scenes import ObjectScene, object_pose, render_view
    from pssnet_core.shapes import make_shape

    shape = make_shape("mug", 2000003)
    scene = ObjectScene(shape)
    view = render_view(shape, yaw_deg=0.0, distance=0.6, tilt_deg=30.0, scene=scene)
    observation = view.observe(GridConfig.for_size(size))
    yaws = np.linspace(-40.0, 40.0, count)
    occ = np.stack([scene.ground_truth(object_pose(shape.mesh, yaw), observation.pose, view.camera_pose)
                    for yaw in yaws])
    return occ, observation.pose, observation.points


def random_candidates(occ: np.ndarray, count: int, config: GraspConfig, voxel: float,
                      seed: int = 0) -> GraspCandidates:
    rng = np.random.default_rng(seed)
    voxels = np.argwhere(occ.any(axis=0)) + 0.5
    rotations, kinds = approach_orientations(config)
    pick = rng.integers(0, len(rotations), count)
    wmax = config.gripper.max_opening / voxel
    return GraspCandidates(voxels[rng.integers(0, len(voxels), count)] + rng.uniform(-0.5, 0.5, (count, 3)),
                           rotations[pick], rng.uniform(0.1 * wmax, wmax, count), kinds[pick])


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidates", type=int, default=500)
    parser.add_argument("--completions", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    args = parser.parse_args()
    config = GraspConfig(max_candidates=args.candidates)
    print(f"{'grid':>5} {'cand x compl':>13} {'score ms':>9} {'generate ms':>12} {'plan_grasps ms':>15} "
          f"{'generated':>10}")
    for size in args.sizes:
        occ, pose, points = completions(size, args.completions)
        cands = random_candidates(occ, args.candidates, config, pose.voxel_size)
        support = 1.0
        score_ms = timed(partial(score_grasps, cands, occ, pose, support, config), args.repeats)
        reps = max(3, args.repeats // 3)
        gen_ms = timed(partial(generate_candidates, occ, pose, points, config, support), reps)
        plan_ms = timed(partial(plan_grasps, occ, pose, points, config), reps)
        generated = len(generate_candidates(occ, pose, points, config, support))
        print(f"{size:>4}^3 {args.candidates:>6} x {args.completions:<4} {score_ms:>9.1f} {gen_ms:>12.1f} "
              f"{plan_ms:>15.1f} {generated:>10}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
