"""What a wrong ``up_vector`` costs, and whether the node notices.

Renders held-out procedural mugs (and boxes behind the narrow slit) from cameras pitched ``--tilts`` degrees
down, and completes each view through the pipeline twice: with the true up vector, and with the node's default
(a level camera, ``[0, -1, 0]``). Per setting it prints the samples' mean IoU to the ground truth (on the grid
the pipeline placed), the share of observed voxels a sample leaves empty, the number of sampled voxels in
seen-through space, and the support-plane tilt the pipeline measured against the ``up_vector`` it was given
(what ``up_check_deg`` warns about).

    .venv/bin/python benchmarks/gravity_bench.py [--objects 6] [--tilts 15 30] [--samples 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pssnet_core.bench import cpu_kind
from pssnet_core.data.scenes import Slit, ground_truth_occupancy, render_view
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig
from pssnet_core.shapes import make_shape, split_seeds

LEVEL_CAMERA_UP = PipelineConfig().up_vector  # the node's default: a level camera


def view_scores(pipeline: CompletionPipeline, view, shape, up: tuple[float, float, float]) -> dict[str, float]:
    pipeline.config = pipeline.with_config(up_vector=up)
    result = pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False)
    truth = ground_truth_occupancy(shape, view.object_pose, result.observation.pose, view.camera_pose)
    samples = result.occupancy
    inter = (samples & truth).sum(axis=(1, 2, 3))
    union = (samples | truth).sum(axis=(1, 2, 3))
    observed = result.observation.known_occupied
    return {"iou": float(np.mean(inter / np.maximum(union, 1))),
            "observed_left_empty": float(np.mean((observed & ~samples).sum(axis=(1, 2, 3)) / max(observed.sum(), 1))),
            "seen_through_voxels": float(np.mean((samples & result.observation.known_free).sum(axis=(1, 2, 3)))),
            "measured_tilt_deg": float(result.up_disagreement_deg),
            "warned": float("tilted" in result.note)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=6, help="test objects per family")
    parser.add_argument("--tilts", type=float, nargs="+", default=[15.0, 30.0])
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--sampler", default="posterior", choices=("posterior", "checked"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    pipeline = CompletionPipeline.from_checkpoint(None, PipelineConfig(num_samples=args.samples, sampler=args.sampler),
                                                  threads=args.threads)
    print(f"[gravity] CPU: {cpu_kind()}; shipped model, {args.samples} samples, {args.sampler} sampler")
    cases = [("mug", None), ("box", Slit(width_m=0.036))]
    results: dict[str, dict[str, float]] = {}
    for family, slit in cases:
        shapes = [make_shape(family, seed) for seed in split_seeds("test", args.objects)]
        for tilt in args.tilts:
            rows: dict[str, list[dict[str, float]]] = {"true": [], "level": []}
            for index, shape in enumerate(shapes):
                view = render_view(shape, yaw_deg=37.0 * index, tilt_deg=tilt, slit=slit)
                rows["true"].append(view_scores(pipeline, view, shape, tuple(float(v) for v in view.up)))
                rows["level"].append(view_scores(pipeline, view, shape, LEVEL_CAMERA_UP))
            for setting, scores in rows.items():
                key = f"{family}{'_slit' if slit else ''} tilt {tilt:g} up {setting}"
                results[key] = {name: float(np.nanmean([s[name] for s in scores])) for name in scores[0]}
                r = results[key]
                print(f"[gravity] {key:<28} IoU {r['iou']:.2f}, observed left empty {r['observed_left_empty']:.1%}, "
                      f"seen-through voxels {r['seen_through_voxels']:.1f}, measured tilt "
                      f"{r['measured_tilt_deg']:.1f} deg, warned {r['warned']:.0%} of {len(scores)} views")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
