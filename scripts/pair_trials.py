"""Pairs grasp-trial runs made separately on the same scenes (same scenario, seed and scene index): each strategy
against the first, scene by scene, with the exact sign test of the scenes only one of them lifted
(`pssnet_core.trials.run.paired_lines`, as in each run's own summary.md).

    .venv/bin/python scripts/pair_trials.py results/second_look/mug:pssnet_second_look \\
        results/shipped_with_flow/trials/new_mug:pssnet results/grasp_trials/draw_rounds/mug:one_completion
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from pssnet_core.trials.run import paired_lines, read_run_records, summarise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="RUN_DIR:STRATEGY (a run directory holding records.jsonl or "
                                                "records.jsonl.gz); the first is the reference")
    args = parser.parse_args()
    records, labels = [], []
    for spec in args.runs:
        directory, _, strategy = spec.rpartition(":")
        label = f"{strategy} ({directory})"
        chosen = [replace(r, strategy=label) for r in read_run_records(Path(directory)) if r.strategy == strategy]
        if label in labels:
            parser.error(f"{spec} is given twice")
        if not chosen:
            parser.error(f"{spec}: no records of {strategy!r} in {directory}")
        records += chosen
        labels.append(label)
    scenarios = tuple(sorted({r.scenario for r in records}))
    for summary in summarise(records, scenarios, tuple(labels)):
        low, high = summary.interval
        print(f"{summary.scenario}: {summary.strategy}: {100 * summary.rate:.1f} % of {summary.n} "
              f"({100 * low:.0f}-{100 * high:.0f} %)")
    print("\n".join(paired_lines(records, scenarios, tuple(labels), reference=labels[0])))


if __name__ == "__main__":
    main()
