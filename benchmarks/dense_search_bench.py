"""What the planner's denser search costs where it runs: ``plan_grasps`` with and without ``dense_below``.

    .venv/bin/python benchmarks/dense_search_bench.py [--dense-below 0.9] [--densities 1000 4000] [--repeats 15]
        [--threads 1] [--json out.json]

The views of ``pipeline_bench.py`` (a mug with its handle hidden, the same mug with it seen, a box behind the
narrow slit) go through the shipped model once each (checked sampler, 20 samples); the planner then plans on those
completions, interleaved call by call, with the denser search off and with ``--dense-below``. Printed per view:
whether the denser search ran (the default search's best grasp holds less than that share of the weight), the
median CPU time of this thread for each planner and their ratio, and the best grasp's weight share and expected
grip under each. With the default object density (1000 kg/m^3) these open views' best grasps hold the whole
weight, so the denser search does not run; a denser object (``--densities``: 4000 is more than any household
object, chosen so that it runs) times what it costs where it does. How often it runs over many scenes is in the
grasp trials' records.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch
from pipeline_bench import read_views, write_views

from pssnet_core.bench import cpu_kind
from pssnet_core.grasps import GraspConfig, GraspSet, plan_grasps
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig


def timed(plan) -> tuple[float, GraspSet]:
    start = time.thread_time()
    grasps = plan()
    return time.thread_time() - start, grasps


def compare(result, default: GraspConfig, args: argparse.Namespace) -> dict:
    """Both planners on one view's completions, interleaved call by call."""
    obs = result.observation

    def plan(config: GraspConfig) -> GraspSet:
        return plan_grasps(result.occupancy, obs.pose, obs.points, config, known_occupied=obs.known_occupied,
                           weights=result.weights)

    settings = {"default": default, "escalating": replace(default, dense_below=args.dense_below)}
    times: dict[str, list[float]] = {key: [] for key in settings}
    best: dict[str, GraspSet] = {}
    for _ in range(args.repeats + 1):  # the first pass warms up and is not counted
        for key, config in settings.items():
            seconds, best[key] = timed(lambda config=config: plan(config))
            times[key].append(seconds)
    p50 = {key: statistics.median(values[1:]) * 1000 for key, values in times.items()}
    return {"denser_search_ran": bool(len(best["escalating"]) > len(best["default"])), "p50_ms": p50,
            "ratio": p50["escalating"] / p50["default"],
            **{f"{key}_best_weight_share": float(g.weight_shares[0]) if len(g) else 0.0 for key, g in best.items()},
            **{f"{key}_best_grip": float(g.grip[0]) if len(g) else 0.0 for key, g in best.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dense-below", type=float, default=0.9)
    parser.add_argument("--densities", type=float, nargs="+", default=[1000.0, 4000.0],
                        help="object densities the planner's weight check assumes, kg/m^3")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the network; planning is one)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    views_file = Path("/tmp/pssnet_dense_search_views.npz")
    write_views(views_file)
    pipeline = CompletionPipeline.from_checkpoint(None, PipelineConfig(num_samples=20, sampler="checked"),
                                                  threads=args.threads)
    default = replace(pipeline.config.grasps, dense_below=0.0)
    print(f"[dense] CPU: {cpu_kind()}; shipped model, checked sampler, 20 samples; dense_below {args.dense_below:g} "
          f"(denser search: {default.dense_max_candidates} candidates, {default.dense_side_yaws} side yaws, pitches "
          f"{list(default.dense_tilted_pitches)}, depths {list(default.dense_shallow_depths)}); CPU time per plan")
    rows = {}
    for name, (depth, mask, intrinsics, up) in read_views(views_file).items():
        pipeline.config = pipeline.with_config(up_vector=up)
        result = pipeline.run(depth, mask, intrinsics, compute_grasps=False)
        for density in args.densities:
            label = f"{name}, {density:g} kg/m^3"
            rows[label] = row = compare(result, replace(default, object_density=density), args)
            print(f"[dense] {label:<24} denser search {'ran' if row['denser_search_ran'] else 'not needed'}: "
                  f"default {row['p50_ms']['default']:.0f} ms, escalating {row['p50_ms']['escalating']:.0f} ms "
                  f"({row['ratio']:.2f}x); best grasp's weight share {row['default_best_weight_share']:.2f} -> "
                  f"{row['escalating_best_weight_share']:.2f}, expected grip {row['default_best_grip']:.2f} -> "
                  f"{row['escalating_best_grip']:.2f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"cpu": cpu_kind(), "dense_below": args.dense_below, "views": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
