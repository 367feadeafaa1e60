"""How the chosen grasp's score, weight share and kind foretell its outcome, for runs made before the trials'
summary carried the table (``pssnet_core.trials.run.calibration_lines``, the same table), or over several runs at
once: per scenario and strategy, the trials with a grasp binned by the grasp's score, by its weight share (recorded in
the notes since stop 47) and by its kind, and (where the runs recorded one hand) the grasps opened to within 2 mm of
its full opening, with how many lifted the object and how the rest failed. With ``--pool`` the runs' records make one
table: pass runs of different scene sets (seeds), as nothing here checks that a scene is not counted twice.

    .venv/bin/python scripts/grasp_calibration.py results/grasp_trials/weight_shares/mug [RUN ...] [--pool]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pssnet_core.trials.run import calibration_lines, read_run_records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="grasp-trials output directories")
    parser.add_argument("--pool", action="store_true", help="one table over all the runs' records")
    args = parser.parse_args()
    groups = [args.runs] if args.pool else [[run] for run in args.runs]
    for runs in groups:
        records = [record for run in runs for record in read_run_records(run)]
        if not records:
            parser.error(f"{', '.join(map(str, runs))}: no records")
        # The hand as recorded (runs before stop 44 wrote no settings.json: unknown). Hands unknown or differing: no
        # full-opening row.
        openings = {json.loads((run / "settings.json").read_text())["grasps"]["gripper"]["max_opening"]
                    if (run / "settings.json").exists() else None for run in runs}
        max_opening = openings.pop() if len(openings) == 1 else None
        print(f"\n{', '.join(map(str, runs))}")
        for scenario in sorted({r.scenario for r in records}):
            for strategy in sorted({r.strategy for r in records if r.scenario == scenario}):
                print("\n" + "\n".join(calibration_lines(records, scenario, strategy, max_opening)))


if __name__ == "__main__":
    main()
