"""Are a model's boxes behind the slit bigger than the truth? The samples' size against the true box's, on the
scenes of a ``box_slit`` grasp-trials run, for one or more checkpoints.

For each of the run's first scenes every checkpoint completes the trial's view with the run's settings and scene
seeds (the samples the run's PSSNet strategy planned on); per scene the median over the samples of their voxel
count / the truth's and of their extent along the grid's x axis (away from the camera; the largest 26-connected
part's, as ``pssnet ambiguity`` measures it) minus the truth's. Prints a
line per checkpoint: the median and mean of those per-scene values. Used in ``results/slits_from_scratch/``::

    .venv/bin/python scripts/slit_box_size_diagnosis.py results/grasp_trials/dense_below/slit0 \
        pssnet_core/pssnet_core/checkpoints/default_pssnet_32.pt,runs/sl56s0_mix16/export.pt --scenes 40
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from pssnet_core.trials import HEADLESS_GL

os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)

from pssnet_core.evaluation.ambiguity_sets import grid_x_extent  # noqa: E402
from pssnet_core.inference import Completer  # noqa: E402
from pssnet_core.trials.run import config_of_run, scene_seed, strategist_of  # noqa: E402
from pssnet_core.trials.scenarios import SceneFactory  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a box_slit grasp-trials output directory")
    parser.add_argument("checkpoints", help="comma-separated PSSNet checkpoints")
    parser.add_argument("--scenes", type=int, default=40, help="the run's first scenes to look at")
    args = parser.parse_args()
    config = config_of_run(args.run)
    factory = SceneFactory(config.scenario, config.grasps.gripper)
    for checkpoint in args.checkpoints.split(","):
        strategist = strategist_of(config, Completer.from_checkpoint(checkpoint, threads=1))
        size_ratios, depth_excess = [], []
        for index in range(args.scenes):
            scene = factory.scene("box_slit", index, config.seed)
            result = strategist._complete("pssnet", scene, scene_seed(config.seed, index))
            truth = scene.ground_truth(result.observation.pose)
            samples = np.asarray(result.occupancy, dtype=bool)
            size_ratios.append(float(np.median(samples.sum(axis=(1, 2, 3)))) / max(int(truth.sum()), 1))
            depth_excess.append(float(np.nanmedian(grid_x_extent(samples))) - float(grid_x_extent(truth)[0]))
        print(f"{checkpoint}: {args.scenes} scenes; samples' voxels / the truth's: median "
              f"{np.median(size_ratios):.2f}, mean {np.mean(size_ratios):.2f}; depth extent - the truth's "
              f"(voxels): median {np.median(depth_excess):.1f}, mean {np.mean(depth_excess):.2f}", flush=True)


if __name__ == "__main__":
    main()
