"""Why do grasps the planner rates as holding slip, on the true shape? The oracle's chosen grasp in each scene of a
grasp-trials run, with what the planner's model says of it, and how the object turns in the hand in the trial.

For every scene where the run's ``oracle`` had a grasp, the grasp is chosen again (the run's settings and scene
seeds: the same grasp) and checked against the true shape (:func:`pssnet_core.grasps.check_grasps`): the share of
the weight the pads hold by the planner's friction model, the pads' contact, and the lever of the weight across the
closing axis. The trial is run again with a frame callback that reads the object's rotation relative to the hand
after the fingers close and at the end, about the hand's approach, closing and pad-width axes. Prints a line per
scene and a table of outcomes by lever and modelled share. Results in ``results/grasp_trials/oracle_slips/``::

    .venv/bin/python scripts/oracle_slip_diagnosis.py results/grasp_trials/voxel_centres/mug [--out FILE.csv]
"""

from __future__ import annotations

import argparse
import csv
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pssnet_core.trials import HEADLESS_GL

os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)

from pssnet_core.grasps import check_grasps  # noqa: E402
from pssnet_core.inference import Completer  # noqa: E402
from pssnet_core.trials.physics import run_trial  # noqa: E402
from pssnet_core.trials.run import config_of_run, read_run_records, scene_seed, strategist_of  # noqa: E402
from pssnet_core.trials.scenarios import SceneFactory  # noqa: E402

LEVER_BINS = (0.0, 1.5, 3.0, np.inf)  # voxels
SHARE_BINS = (0.0, 0.7, 0.9, 1.01)


class HandFrame:
    """A ``run_trial`` frame callback that keeps the object's orientation in the hand's frame at each frame."""

    def __init__(self) -> None:
        self.rotations: list[np.ndarray] = []

    def __call__(self, model, data) -> np.ndarray:
        hand, obj = model.body("hand").id, model.body("object").id
        self.rotations.append(data.xmat[hand].reshape(3, 3).T @ data.xmat[obj].reshape(3, 3))
        return np.zeros((1, 1, 3), np.uint8)

    def turned(self, frame: int) -> np.ndarray:
        """Degrees the object turned in the hand from the first frame to ``frame``, about the hand's x (pad width),
        y (closing) and z (approach) axes (a rotation vector)."""
        change = self.rotations[frame] @ self.rotations[0].T
        return np.degrees(Rotation.from_matrix(change).as_rotvec())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a grasp-trials output directory with oracle records")
    parser.add_argument("--out", type=Path, default=None, help="also write the per-scene rows as CSV here")
    args = parser.parse_args()
    records = {r.index: r for r in read_run_records(args.run) if r.strategy == "oracle" and r.outcome != "no_grasp"}
    config = config_of_run(args.run)
    factory = SceneFactory(config.scenario, config.grasps.gripper)
    strategist = strategist_of(config, Completer.from_checkpoint(None, threads=1))
    rows = []
    for index, record in sorted(records.items()):
        scene = factory.scene(record.scenario, index, config.seed)
        seed = scene_seed(config.seed, index)
        result = strategist._complete("pssnet", scene, seed)
        truth = scene.ground_truth(result.observation.pose)[None]
        grasps = strategist._plan(truth, result, scene, seed)
        checks = check_grasps(grasps.grid.subset(np.array([0])), truth, result.observation.pose, grasps.support_z,
                              replace(config.grasps, seed=seed))
        frames = HandFrame()
        pose = scene.view.camera_pose @ grasps.poses[0]
        outcome = run_trial(scene.physics, pose, float(grasps.widths[0]), config.grasps.gripper, config.physics,
                            render=frames)
        closed, end = frames.turned(1), frames.turned(len(frames.rotations) - 1)
        row = {"scene": index, "object": record.notes["object"], "kind": str(grasps.kinds[0]),
               "outcome": outcome.outcome, "recorded": record.outcome, "share": float(checks.resistance[0, 0]),
               "contact": float(checks.coverage[0, 0]), "lever_voxels": float(checks.lever[0, 0]),
               **{f"closed_{a}_deg": float(v) for a, v in zip("xyz", closed, strict=True)},
               **{f"end_{a}_deg": float(v) for a, v in zip("xyz", end, strict=True)}}
        rows.append(row)
        print(f"scene {index} {row['object']}: {row['kind']} {row['outcome']} (run: {record.outcome}), share "
              f"{row['share']:.2f}, contact {row['contact']:.2f}, lever {row['lever_voxels']:.1f} vox | turned in "
              f"the hand about approach / closing / pad width: {closed[2]:.1f} / {closed[1]:.1f} / {closed[0]:.1f} deg "
              f"closed, {end[2]:.1f} / {end[1]:.1f} / {end[0]:.1f} at the end", flush=True)
    print(f"\nreproduced {sum(r['outcome'] == r['recorded'] for r in rows)} of {len(rows)} outcomes")
    print("\n| lever (voxels) | modelled share of the weight | grasps | lifted |\n|---|---|---:|---:|")
    for lo, hi in zip(LEVER_BINS[:-1], LEVER_BINS[1:], strict=True):
        for s_lo, s_hi in zip(SHARE_BINS[:-1], SHARE_BINS[1:], strict=True):
            cell = [r for r in rows if lo <= r["lever_voxels"] < hi and s_lo <= r["share"] < s_hi]
            print(f"| {lo:g}-{hi:g} | {s_lo:g}-{min(s_hi, 1.0):g} | {len(cell)} | "
                  f"{sum(r['outcome'] == 'success' for r in cell)} |")
    for outcome in ("success", "slipped"):
        turned = np.array([abs(r["end_z_deg"]) for r in rows if r["outcome"] == outcome])
        if len(turned):
            print(f"{outcome}: {len(turned)} grasps, turned about the approach axis by the end: median "
                  f"{np.median(turned):.1f} deg, 90th percentile {np.percentile(turned, 90):.1f}")
    if args.out is not None:
        with args.out.open("w", newline="") as sink:
            writer = csv.DictWriter(sink, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows({k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()} for r in rows)


if __name__ == "__main__":
    main()
