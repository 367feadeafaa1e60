"""One-off replay (stop 63): the contact normals the planner's friction-cone check measured for the oracle's chosen
grasp in given scenes of a grasp-trials run (the run's settings and scene seeds: the same grasp). It wraps the private
``pssnet_core.grasps.scoring._outside_friction_cone`` to print, per pad, the angle between the closing axis and the
patch-summed voxel normal the check compares with ``atan(friction)``; kept with the results it produced, not a tool.

    OMP_NUM_THREADS=1 .venv/bin/python results/grasp_trials/oracle_kinds/contact_normal_replay.py \\
        results/grasp_trials/dense_below/mug_oracle1 25,140
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

import pssnet_core.grasps.scoring as scoring
from pssnet_core.grasps.planning import check_grasps
from pssnet_core.inference import Completer
from pssnet_core.trials.run import config_of_run, scene_seed, strategist_of
from pssnet_core.trials.scenarios import SceneFactory

CHECK = scoring._outside_friction_cone


def measuring_check(bits, origins, rot, widths, touch, slices, patches, pad, cells, friction, judged):
    """The check, after printing the angle each pad's summed normal makes with the closing axis (as it computes it)."""
    (fw, fl), (nx, nz) = pad, cells
    xs, zs = np.linspace(-fw / 2, fw / 2, nx), np.linspace(-fl, 0.0, nz)
    cell_x, cell_z = (a.ravel()[:, None, None] for a in np.meshgrid(xs, zs, indexing="ij"))
    grasp, completion = np.nonzero(judged)
    print(f"  judged pairs {len(grasp)}, friction {friction}, cone {math.degrees(math.atan(friction)):.1f} deg")
    if len(grasp):
        axes = rot[grasp]
        in_pad = origins[grasp][None] + cell_x * axes[None, :, :, 0] + cell_z * axes[None, :, :, 2]
        step = widths[grasp] / max(slices - 1, 1)
        for sign, first, touching in zip((1.0, -1.0), touch, patches, strict=True):
            across = (first[grasp, completion] * step - widths[grasp] / 2 - sign)[:, None] * axes[:, :, 1]
            voxel = np.clip(np.floor(in_pad + across[None]).astype(np.intp), 0, bits.size - 1)
            cells_touching = touching[:, grasp, completion]
            normal = np.einsum("cp,cpd->pd", cells_touching.astype(np.float32),
                               bits.inward_normals[completion[None], voxel[..., 0], voxel[..., 1], voxel[..., 2]])
            cos = sign * (normal @ axes[0, :, 1]) / np.linalg.norm(normal, axis=1)
            depth = cell_z.ravel()[cells_touching[:, 0]]
            angle = math.degrees(math.acos(float(np.clip(cos[0], -1, 1))))
            print(f"   pad {sign:+.0f}: {int(cells_touching.sum())} touching cells, z {depth.min()} to {depth.max()} "
                  f"voxels, normal {angle:.1f} deg off the closing axis")
    return CHECK(bits, origins, rot, widths, touch, slices, patches, pad, cells, friction, judged)


def main() -> None:
    run, indices = Path(sys.argv[1]), [int(x) for x in sys.argv[2].split(",")]
    config = config_of_run(run)
    strategist = strategist_of(config, Completer.from_checkpoint(None, threads=1))
    factory = SceneFactory(config.scenario, config.grasps.gripper)
    for index in indices:
        scene = factory.scene("mug_hidden_handle", index, config.seed)
        seed = scene_seed(config.seed, index)
        scoring._outside_friction_cone = CHECK  # plan as the run did
        result = strategist._complete("pssnet", scene, seed)
        truth = scene.ground_truth(result.observation.pose)[None]
        grasps = strategist._plan(truth, result, scene, seed)
        best = grasps.grid.subset(np.array([0]))
        print(f"{index}: width {best.widths[0]:.2f} voxels")
        scoring._outside_friction_cone = measuring_check
        checks = check_grasps(best, truth, result.observation.pose, grasps.support_z,
                              replace(strategist.grasps, seed=seed))
        print(f"  squeezed out {bool(checks.squeezed_out[0, 0])}, pad contact {checks.coverage[0, 0]:.2f}, "
              f"holds {bool(checks.holds[0, 0])}")


if __name__ == "__main__":
    main()
