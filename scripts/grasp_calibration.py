"""How the chosen grasp's score and weight share foretell its outcome: per strategy in grasp-trials runs, the trials
binned by the grasp's score (weighted share of the strategy's shapes it holds for) and by its weight share (the mean
share of the weight its pads hold by friction over those shapes, ``GraspSet.weight_shares``; recorded in the notes
since stop 47), with how many lifted the object and how the rest failed. Scenes without a grasp are left out.

    .venv/bin/python scripts/grasp_calibration.py results/grasp_trials/weight_shares/mug [RUN ...]
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from pssnet_core.trials.run import TrialRecord, read_run_records

BINS = (0.0, 0.5, 0.7, 0.9, 1.0)
FAILURES = ("collision", "missed", "slipped")


def binned(records: list[TrialRecord], value_of, label: str) -> list[str]:
    """Table rows: for each bin of ``value_of(record)``, the trials, lifted and the failures by cause."""
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        last = hi == BINS[-1]
        cell = [r for r in records if lo <= value_of(r) < hi or (last and value_of(r) == hi)]
        causes = Counter(r.outcome for r in cell)
        lifted = causes["success"]
        rate = f"{100 * lifted / len(cell):.0f} %" if cell else "-"
        rows.append(f"| {label} {lo:g}-{hi:g} | {len(cell)} | {lifted} ({rate}) | "
                    + " | ".join(str(causes[c]) for c in FAILURES) + " |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="grasp-trials output directories")
    args = parser.parse_args()
    for run in args.runs:
        records = [r for r in read_run_records(run) if r.outcome != "no_grasp"]
        if not records:
            parser.error(f"{run}: no trials with a grasp")
        for scenario in sorted({r.scenario for r in records}):
            for strategy in sorted({r.strategy for r in records if r.scenario == scenario}):
                chosen = [r for r in records if r.scenario == scenario and r.strategy == strategy]
                print(f"\n{run}: {scenario}, {strategy}: {len(chosen)} grasps, "
                      f"{sum(r.success for r in chosen)} lifted\n")
                print("| bin | grasps | lifted | " + " | ".join(FAILURES) + " |\n|---|---:|---:|"
                      + "---:|" * len(FAILURES))
                print("\n".join(binned(chosen, lambda r: r.score, "score")))
                shared = [r for r in chosen if "weight_share" in r.notes]
                if shared:
                    print("\n".join(binned(shared, lambda r: float(r.notes["weight_share"]), "weight share")))


if __name__ == "__main__":
    main()
