"""Why did PSSNet's grasps miss (the fingers closed without both touching the object)? Each missed grasp of a
grasp-trials run, chosen again and checked against the true shape and against the samples it was planned on.

For every scene where the run's ``pssnet`` grasp missed, the view is completed and the grasp chosen again (the
run's settings and scene seeds: the same grasp) and checked with the planner's own model
(:func:`pssnet_core.grasps.check_grasps`): the share of the pads' area in contact with the true shape, and the
median of that share over the samples. A grasp with no contact on the truth closes where the samples put material
and the object has none; one with some closes at the object's edge, where the voxels said it would touch. Prints a
line per scene and the count of each. Used in ``results/slits_from_scratch/``::

    .venv/bin/python scripts/missed_grasp_diagnosis.py results/slits_from_scratch/trials/s0_slit0 \
        --checkpoint runs/sl56s0_mix16/export.pt
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from pssnet_core.trials import HEADLESS_GL

os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)

from pssnet_core.grasps import check_grasps  # noqa: E402
from pssnet_core.inference import Completer  # noqa: E402
from pssnet_core.trials.run import (  # noqa: E402
    config_of_run,
    pssnet_checkpoint_of,
    read_run_records,
    scene_seed,
    strategist_of,
)
from pssnet_core.trials.scenarios import SceneFactory  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a grasp-trials output directory with pssnet records")
    parser.add_argument("--checkpoint", default=None,
                        help="the run's PSSNet checkpoint where its settings.json names another path (default: "
                             "the one it names, or the shipped model where it names that)")
    args = parser.parse_args()
    config = config_of_run(args.run)
    checkpoint = args.checkpoint or pssnet_checkpoint_of(config)
    missed = sorted((r.scenario, r.index) for r in read_run_records(args.run)
                    if r.strategy == "pssnet" and r.outcome == "missed")
    factory = SceneFactory(config.scenario, config.grasps.gripper)
    strategist = strategist_of(config, Completer.from_checkpoint(checkpoint, threads=1))
    on_truth = []
    for scenario, index in missed:
        scene = factory.scene(scenario, index, config.seed)
        seed = scene_seed(config.seed, index)
        result = strategist._complete("pssnet", scene, seed)
        grasps = strategist._plan(result.occupancy, result, scene, seed, result.weights)
        chosen = grasps.grid.subset(np.array([0]))
        settings = replace(config.grasps, seed=seed)
        truth = scene.ground_truth(result.observation.pose)[None]
        contact = float(check_grasps(chosen, truth, result.observation.pose, grasps.support_z, settings).coverage[0, 0])
        samples = check_grasps(chosen, result.occupancy, result.observation.pose, grasps.support_z, settings)
        on_truth.append(contact)
        print(f"{scenario} {index}: {grasps.kinds[0]}, score {grasps.scores[0]:.2f}; pads in contact: truth "
              f"{contact:.2f}, samples' median {np.median(samples.coverage[0]):.2f}", flush=True)
    on_truth = np.asarray(on_truth)
    print(f"\n{len(on_truth)} missed grasps: {int((on_truth == 0).sum())} touch nothing of the true shape, "
          f"{int((on_truth > 0).sum())} touch it (pads' contact share median "
          f"{np.median(on_truth[on_truth > 0]) if (on_truth > 0).any() else 0:.2f})")


if __name__ == "__main__":
    main()
