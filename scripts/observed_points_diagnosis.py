"""Do the second look's grasps that fail put a finger or the palm where a camera saw surface?

For the failed scenes of a ``pssnet_second_look`` trial run (and its first lifted ones), the strategy's choice is
made again (deterministic: the run's scene seeds), and the observed points of both views and the true object's
surface are counted inside the chosen grasp's fingers and palm at the grasp and along the approach
(``PhysicsConfig.pre_grasp`` back along it). The planner is set as the run's ``settings.json`` records it (a switch
the run predates is off). Results in ``results/second_look/README.md`` and
``results/grasp_trials/voxel_centres/README.md``::

    .venv/bin/python scripts/observed_points_diagnosis.py results/second_look/box [--successes 25]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import trimesh

from pssnet_core.trials import HEADLESS_GL

os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)

from pssnet_core.grasps import GraspConfig  # noqa: E402
from pssnet_core.grasps.config import VoxelDims  # noqa: E402
from pssnet_core.grasps.lattice import gripper_part_boxes  # noqa: E402
from pssnet_core.inference import Completer  # noqa: E402
from pssnet_core.trials.run import config_of_run, read_run_records, scene_seed, strategist_of  # noqa: E402
from pssnet_core.trials.scenarios import SceneFactory  # noqa: E402

STRATEGY = "pssnet_second_look"


def inside_gripper(points: np.ndarray, width: float, grasps: GraspConfig, back: float) -> tuple[int, int]:
    """Points (gripper frame, metres) inside a finger and inside the palm, swept ``back`` along the approach."""
    centres, halves = gripper_part_boxes(np.array([width]), VoxelDims.of(grasps, 1.0))  # 1 m "voxels": metres
    centres[..., 2] -= back / 2  # each part from where the hand starts to where it stops
    halves[..., 2] += back / 2
    inside = [int((np.abs(points - centres[0, p]) <= halves[0, p]).all(axis=1).sum()) for p in range(3)]
    return inside[0] + inside[1], inside[2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a grasp-trials output directory with pssnet_second_look records")
    parser.add_argument("--successes", type=int, default=25, help="lifted scenes to compare with")
    args = parser.parse_args()
    records = {r.index: r for r in read_run_records(args.run) if r.strategy == STRATEGY}
    failed = sorted(i for i, r in records.items() if not r.success)
    lifted = sorted(i for i, r in records.items() if r.success)[:args.successes]
    config = config_of_run(args.run)  # the scenes and planner as the run had them
    factory = SceneFactory(config.scenario)
    strategist = strategist_of(config, Completer.from_checkpoint(None, threads=1))
    with_points = {"failed": 0, "lifted": 0}
    for label, indices in (("failed", failed), ("lifted", lifted)):
        for index in indices:
            scene = factory.scene(records[index].scenario, index, config.seed)
            seed = scene_seed(config.seed, index)
            first = strategist._complete("pssnet", scene, seed)
            look = strategist._second_look("pssnet", scene, first, seed)
            choice = strategist.choose(scene, (STRATEGY,), seed)[STRATEGY]
            if choice.pose is None:
                continue
            gripper_from_world = np.linalg.inv(choice.pose)
            camera = scene.view.camera_pose
            seen = (look.result or first).observation.points @ camera[:3, :3].T + camera[:3, 3]
            mesh = scene.physics.shape.mesh.copy()
            mesh.apply_transform(scene.physics.object_pose)
            true = trimesh.sample.sample_surface(mesh, 20000, seed=0)[0]
            rotation, translation = gripper_from_world[:3, :3], gripper_from_world[:3, 3]
            seen_in, true_in = (inside_gripper(p @ rotation.T + translation, choice.width, config.grasps,
                                               config.physics.pre_grasp) for p in (seen, true))
            with_points[label] += int(sum(seen_in) > 0)
            print(f"{label} scene {index}: {records[index].outcome}, {choice.kind} grasp scored {choice.score:.2f}, "
                  f"{choice.width * 1000:.1f} mm | observed points in finger / palm {seen_in[0]} / {seen_in[1]} | "
                  f"true surface {true_in[0]} / {true_in[1]}", flush=True)
    print(f"with observed points inside: {with_points['failed']} of {len(failed)} failed, "
          f"{with_points['lifted']} of {len(lifted)} lifted")


if __name__ == "__main__":
    main()
