"""How the chosen grasp's score and weight share foretell its outcome, for runs made before the trials' summary
carried the table (``pssnet_core.trials.run.calibration_lines``, the same table): per scenario and strategy, the
trials with a grasp binned by the grasp's score and by its weight share (recorded in the notes since stop 47), with
how many lifted the object and how the rest failed.

    .venv/bin/python scripts/grasp_calibration.py results/grasp_trials/weight_shares/mug [RUN ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pssnet_core.trials.run import calibration_lines, read_run_records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="grasp-trials output directories")
    args = parser.parse_args()
    for run in args.runs:
        records = read_run_records(run)
        if not records:
            parser.error(f"{run}: no records")
        print(f"\n{run}")
        for scenario in sorted({r.scenario for r in records}):
            for strategy in sorted({r.strategy for r in records if r.scenario == scenario}):
                print("\n" + "\n".join(calibration_lines(records, scenario, strategy)))


if __name__ == "__main__":
    main()
