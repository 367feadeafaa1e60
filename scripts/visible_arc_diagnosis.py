"""Does the view itself pin a seen handle? The plausible arc of each visible-handle view, and the sampled error split
by it.

For every visible-handle view of a mug test set, turns the true mug in 5-degree steps and judges each turn on the
depth image with the observation model (the plausible arc, as ``pssnet ambiguity`` computes it for hidden handles).
A view *pins* its handle when every accepted turn lies within ``--pinned-deg`` of the truth. Then, from the
``ambiguity_per_view.csv`` files of ``pssnet ambiguity`` runs on the same views, each method's mean visible-handle
error on the views that pin the handle and on those that do not: if the samples err as much where the image rules
the error out, the sampler (not the view) is what lets the handle move. Arcs are cached as ``pssnet ambiguity``'s are.

Usage (results/shipped_with_flow/README.md):
    .venv/bin/python scripts/visible_arc_diagnosis.py --data data/oof/test --set oof_mugs \\
        --cache-dir data/oof/visible_arc_cache results/shipped_with_flow/ambiguity/new_oof/ambiguity_per_view.csv
"""

from __future__ import annotations

import argparse
import collections
import csv
from pathlib import Path

import numpy as np

from pssnet_core.evaluation.ambiguity_cache import AmbiguityTestSet, cached_plausible
from pssnet_core.evaluation.ambiguity_sets import AmbiguityMeasure
from pssnet_core.evaluation.handles import circular_difference_deg, handle_geometries
from pssnet_core.evaluation.testsets import find_test_set


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path,
                        help="ambiguity_per_view.csv files of `pssnet ambiguity` runs on the same views")
    parser.add_argument("--data", default="data/oof/test")
    parser.add_argument("--set", default="oof_mugs")
    parser.add_argument("--cache-dir", type=Path, default=Path("data/oof/visible_arc_cache"))
    parser.add_argument("--delta", type=float, default=0.01, help="the arc's observation-model tolerance (m)")
    parser.add_argument("--pinned-deg", type=float, default=15.0)
    args = parser.parse_args()
    mugs = AmbiguityTestSet(find_test_set(args.data, args.set), False)
    geometries = handle_geometries(v.identity for v in mugs.views)
    visible = [v for v in mugs.views if v.identity in geometries and v.meta.get("handle_visible") is True]
    arcs, cost = cached_plausible(mugs, visible, "handle_arcs", AmbiguityMeasure(), args.cache_dir, False)
    reach: dict[int, float] = {}  # the farthest accepted turn from the truth, degrees
    for index, arc in arcs.items():
        turns = circular_difference_deg(arc.azimuths_deg[arc.accepted(args.delta)], 0.0)
        reach[index] = float(turns.max()) if len(turns) else float("nan")
    pinned = {i for i, r in reach.items() if r <= args.pinned_deg}
    print(f"{len(visible)} visible-handle views of {args.set} ({cost['seconds_all_views']:.0f} s of arcs): "
          f"{len(pinned)} pin the handle within {args.pinned_deg:g} deg at delta {args.delta:g} m")
    loose_by_mug = collections.Counter(arcs[i].identity for i in reach if i not in pinned)
    print("views that allow it farther, by mug:", dict(loose_by_mug.most_common()))
    for path in args.runs:
        with path.open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["kind"] == "visible_handle" and r["error_deg"] not in ("", "nan")]
        for method in sorted({r["method"] for r in rows}):
            for label, keep in (("pinned", True), ("not pinned", False)):
                errors = [float(r["error_deg"]) for r in rows
                          if r["method"] == method and (int(r["index"]) in pinned) == keep]
                mean = f"{np.mean(errors):.1f}" if errors else "-"
                print(f"{path} {method}: {label}: {len(errors)} views, mean visible error {mean} deg")


if __name__ == "__main__":
    main()
