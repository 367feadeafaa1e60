"""Pairs grasp-trial runs made separately on the same scenes: each strategy against the first, scene by scene,
with the exact sign test of the scenes only one of them lifted (`pssnet_core.trials.run.paired_lines`, as in each
run's own summary.md). A comparison may pool several runs (comma-separated directories, e.g. the same strategy on
seeds 0-4): scenes are matched by their run's seed, scenario and physics settings and their index
(`pssnet_core.trials.run.pooled_records`), so runs of other seeds add scenes instead of pairing by index.

    .venv/bin/python scripts/pair_trials.py results/second_look/mug:pssnet_second_look \\
        results/shipped_with_flow/trials/new_mug:pssnet results/grasp_trials/draw_rounds/mug:one_completion
    .venv/bin/python scripts/pair_trials.py RUN_SEED0,RUN_SEED1:pssnet VAE_SEED0,VAE_SEED1:vae
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pssnet_core.trials.run import paired_lines, pooled_records, summarise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="RUN_DIR[,RUN_DIR...]:STRATEGY (run directories holding "
                                                "records.jsonl or records.jsonl.gz, pooled); the first is the "
                                                "reference")
    args = parser.parse_args()
    comparisons = []
    for spec in args.runs:
        directories, _, strategy = spec.rpartition(":")
        paths = [Path(d) for d in directories.split(",") if d]
        label = f"{strategy} ({directories})"
        if not paths or not strategy:
            parser.error(f"{spec}: expected RUN_DIR[,RUN_DIR...]:STRATEGY")
        if label in (c[0] for c in comparisons):
            parser.error(f"{spec} is given twice")
        comparisons.append((label, strategy, paths))
    try:
        records = pooled_records(comparisons)
    except (OSError, ValueError, KeyError) as error:
        parser.error(str(error))
    labels = tuple(c[0] for c in comparisons)
    scenarios = tuple(sorted({r.scenario for r in records}))
    for summary in summarise(records, scenarios, labels):
        low, high = summary.interval
        print(f"{summary.scenario}: {summary.strategy}: {100 * summary.rate:.1f} % of {summary.n} "
              f"({100 * low:.0f}-{100 * high:.0f} %)")
    print("\n".join(paired_lines(records, scenarios, labels, reference=labels[0])))


if __name__ == "__main__":
    main()
