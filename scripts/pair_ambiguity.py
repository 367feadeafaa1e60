"""Pair two `pssnet ambiguity` runs view by view: mean of each measure, the paired difference, and the exact
two-sided sign test over the views where the two differ.

Views are matched by (kind, index, identity, rotation) at one delta, so the two runs must cover the same test set
with the same seed (each view's samples then differ only by the model or the sampler).

    .venv/bin/python scripts/pair_ambiguity.py NEW.csv:METHOD REF.csv:METHOD [--delta 0.04]

e.g. `results/broad_mugs/oof/ambiguity_per_view.csv.gz:bm_s0_checked
results/shipped_with_flow/ambiguity/new_oof/ambiguity_per_view.csv:pssnet_new39_checked` (plain or gzipped CSVs).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from scipy.stats import binomtest

#: the measures the ambiguity issue sets targets on, per kind of view (column names of ambiguity_per_view.csv)
MEASURES: dict[str, tuple[str, ...]] = {
    "hidden_handle": ("coverage", "precision", "spread_ratio", "handle_rate"),
    "visible_handle": ("error_deg",),
    "slit": ("coverage", "precision", "spread_ratio"),
}
#: differences smaller than this count as ties (the measures are ratios and degrees)
TIE = 1e-9

ViewKey = tuple[str, str, str, str]


@dataclass(frozen=True)
class PairedMeasure:
    kind: str
    measure: str
    views: int  # views where both runs have a value
    new_mean: float
    ref_mean: float
    higher: int  # views where the new run's value is higher
    lower: int
    p_value: float

    @property
    def difference(self) -> float:
        return self.new_mean - self.ref_mean


def read_rows(path: Path, method: str, delta: str) -> dict[ViewKey, dict[str, str]]:
    """One run's rows of ``method`` at ``delta`` (visible-handle rows carry no delta and are always kept)."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r["method"] == method and r["delta"] in ("", delta)]
    if not rows:
        raise SystemExit(f"{path}: no rows of method {method!r} at delta {delta}")
    return {(r["kind"], r["index"], r["identity"], r["rotation_deg"]): r for r in rows}


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:  # empty: the measure is undefined for that view (no handle drawn, no spread)
        return math.nan


def pair(new: dict[ViewKey, dict[str, str]], ref: dict[ViewKey, dict[str, str]]) -> Iterable[PairedMeasure]:
    common = sorted(set(new) & set(ref))
    for kind, measures in MEASURES.items():
        keys = [k for k in common if k[0] == kind]
        for measure in measures:
            pairs = [(a, b) for a, b in ((_number(new[k][measure]), _number(ref[k][measure])) for k in keys)
                     if not (math.isnan(a) or math.isnan(b))]
            if not pairs:
                continue
            higher = sum(a - b > TIE for a, b in pairs)
            lower = sum(b - a > TIE for a, b in pairs)
            p_value = binomtest(higher, higher + lower).pvalue if higher + lower else 1.0
            yield PairedMeasure(kind, measure, len(pairs), sum(a for a, _ in pairs) / len(pairs),
                                sum(b for _, b in pairs) / len(pairs), higher, lower, p_value)


def _run(text: str) -> tuple[Path, str]:
    path, sep, method = text.rpartition(":")
    if not sep or not path or not method:
        raise argparse.ArgumentTypeError(f"expected CSV:METHOD, got {text!r}")
    return Path(path), method


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("new", type=_run, help="CSV:METHOD of the run to judge")
    parser.add_argument("ref", type=_run, help="CSV:METHOD of the reference run")
    parser.add_argument("--delta", default="0.04", help="the delta of the rows to pair, as written in the CSV")
    args = parser.parse_args()
    new, ref = read_rows(*args.new, args.delta), read_rows(*args.ref, args.delta)
    print("| kind | measure | views | new | reference | difference | new higher / lower | sign test p |")
    print("|---|---|---|---|---|---|---|---|")
    for m in pair(new, ref):
        print(f"| {m.kind} | {m.measure} | {m.views} | {m.new_mean:.3f} | {m.ref_mean:.3f} | {m.difference:+.3f} | "
              f"{m.higher} / {m.lower} | {m.p_value:.2g} |")


if __name__ == "__main__":
    main()
