"""Does the place `next_view.rank_views` ranks first make the best second look? For trial scenes, every candidate place
(`trials.scenarios.look_cameras`) is tried: its true view rendered, fused with the first, completed, and the samples'
mean IoU with the true object measured within what the first view left unknown (neither seen nor seen through: the
hidden side a look can settle; before: the first view's samples). Prints, per scenario, that IoU after a look from
the place ranked first, from a random place the object is seen from, and from the best place in hindsight, and the
rank correlation between each place's score and the IoU it gives.

    .venv/bin/python scripts/look_ranking_check.py --scenario box_slit --scenes 40 \
        --out results/second_look/ranking_box.json
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch
from scipy.stats import spearmanr

from pssnet_core.inference import Completer
from pssnet_core.next_view import NextViewConfig, rank_views, scaled_intrinsics
from pssnet_core.pipeline import CompletionPipeline, MoreView, PipelineConfig, PipelineInputError
from pssnet_core.trials.run import TrialsConfig, scene_seed
from pssnet_core.trials.scenarios import SceneFactory, clutter_depth, look_cameras, render_look


def mean_iou(occupancy: np.ndarray, weights: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    """The samples' IoU with the true occupancy within ``region``, weighted by the samples' weights."""
    inter = (occupancy & truth[None] & region[None]).sum(axis=(1, 2, 3))
    union = ((occupancy | truth[None]) & region[None]).sum(axis=(1, 2, 3))
    return float(np.sum(weights * inter / np.maximum(union, 1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="box_slit")
    parser.add_argument("--scenes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--checkpoint", default=None, help="PSSNet checkpoint (default: the shipped model)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    trials = TrialsConfig()
    factory = SceneFactory(trials.scenario, trials.grasps.gripper)
    pipeline = CompletionPipeline(Completer.from_checkpoint(args.checkpoint, threads=1),
                                  PipelineConfig(num_samples=20))
    config = NextViewConfig()
    rows = []
    for index in range(args.scenes):
        scene = factory.scene(args.scenario, index, args.seed)
        seed = scene_seed(args.seed, index)
        pipeline.config = pipeline.with_config(up_vector=tuple(float(u) for u in scene.view.up), seed=seed)
        view, camera = scene.view, scene.view.camera_pose
        first = pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False)
        truth = scene.ground_truth(first.observation.pose)
        hidden = ~(first.observation.known_occupied | first.observation.known_free)
        cameras = look_cameras(scene)
        small = scaled_intrinsics(view.intrinsics, config.scale)
        scores = rank_views(first.occupancy, first.weights, first.observation.pose,
                            [np.linalg.inv(c.pose) @ camera for c in cameras], view.intrinsics,
                            [clutter_depth(scene.physics.clutter, c.pose, small) for c in cameras], config)
        ious = []
        for look in cameras:
            seen = render_look(scene, look.pose)
            if seen is None or seen.mask.sum() < pipeline.config.min_mask_pixels:
                ious.append(None)
                continue
            more = MoreView(seen.depth, seen.mask, seen.intrinsics, np.linalg.inv(camera) @ look.pose)
            try:
                both = pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False, more_views=(more,))
            except PipelineInputError:
                ious.append(None)
                continue
            ious.append(mean_iou(both.occupancy, both.weights, truth, hidden))
        rows.append({"index": index, "before": mean_iou(first.occupancy, first.weights, truth, hidden),
                     "scores": [float(s) for s in scores], "ious": ious,
                     "places": [(c.azimuth_deg, c.elevation_deg) for c in cameras]})
        print(index, round(rows[-1]["before"], 3), "ranked first:", ious[int(np.argmax(scores))],
              "best:", max(i for i in ious if i is not None), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows))
    rng = np.random.default_rng(0)
    before, first_ranked, random_place, best, rho = [], [], [], [], []
    for row in rows:
        valid = [k for k, iou in enumerate(row["ious"]) if iou is not None]
        ious, scores = np.array([row["ious"][k] for k in valid]), np.array([row["scores"][k] for k in valid])
        before.append(row["before"])
        first_ranked.append(ious[int(np.argmax(scores))])
        random_place.append(float(ious[rng.integers(len(ious))]))
        best.append(float(ious.max()))
        if np.ptp(scores) > 0 and np.ptp(ious) > 0:
            rho.append(spearmanr(scores, ious).statistic)
    print(f"{args.scenario}, {len(rows)} scenes: samples' mean IoU with the truth where the first view saw nothing: "
          f"one view {np.mean(before):.3f}; "
          f"with a second look from the place ranked first {np.mean(first_ranked):.3f}, from a random place the "
          f"object is seen from {np.mean(random_place):.3f}, from the best place in hindsight {np.mean(best):.3f}; "
          f"Spearman rho of score and IoU per scene: median {np.median(rho):.2f} ({len(rho)} scenes)")


if __name__ == "__main__":
    main()
