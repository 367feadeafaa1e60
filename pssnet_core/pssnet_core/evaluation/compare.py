"""Paired differences between methods scored on the same observations, with bootstrap intervals.

Every method of an evaluation is scored on the same views against the same plausible sets, so the
difference of two methods' means is best judged per observation (paired): the spread between views (a
narrow-slit view is harder than a mug view for every method) cancels. The interval is the percentile
bootstrap of the mean paired difference (scipy.stats.bootstrap, resampling observations).
"""

from __future__ import annotations

import csv
import gzip
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from pssnet_core.evaluation.metrics import METRIC_NAMES
from pssnet_core.evaluation.report import SUBSETS
from pssnet_core.spread import evenly_spaced


class CompareError(ValueError):
    """Rows or names that cannot be compared."""


@dataclass(frozen=True)
class CompareConfig:
    metric: str = "plausible_diversity_mm"
    confidence: float = 0.95
    resamples: int = 10_000
    seed: int = 0
    #: score only the observations `pssnet evaluate --max-observations N` would pick (None = all rows)
    references: int | None = None

    def __post_init__(self) -> None:
        if self.metric not in METRIC_NAMES:
            raise CompareError(f"unknown metric {self.metric!r}; known: {list(METRIC_NAMES)}")
        if not 0.5 <= self.confidence < 1.0:
            raise CompareError(f"confidence must be in [0.5, 1), got {self.confidence}")
        if self.resamples < 100:
            raise CompareError(f"resamples must be >= 100, got {self.resamples}")
        if self.references is not None and self.references < 1:
            raise CompareError(f"references must be >= 1, got {self.references}")


@dataclass(frozen=True)
class PairedDifference:
    delta_m: float
    subset: str
    method: str
    baseline: str
    count: int
    method_mean: float
    baseline_mean: float
    difference: float  # method - baseline (lower metric = better, so negative favours the method)
    low: float
    high: float


def read_per_observation(paths: Iterable[str | Path]) -> list[dict[str, Any]]:
    """Rows of one or more ``per_observation.csv`` files (plain or gzipped, as ``results/`` keeps them), with the
    fields the comparison needs typed."""
    rows: list[dict[str, Any]] = []
    for path in paths:
        path = Path(path)
        if not path.is_file():
            raise CompareError(f"{path}: no such file")
        opener = gzip.open if path.suffix == ".gz" else open
        with opener(path, "rt", newline="") as f:
            for line, row in enumerate(csv.DictReader(f), start=2):
                try:
                    row["index"] = int(row["index"])
                    row["delta"] = float(row["delta"])
                    for name in METRIC_NAMES:
                        row[name] = float(row[name])
                except (KeyError, TypeError, ValueError) as error:
                    raise CompareError(f"{path}:{line}: not a per_observation.csv row ({error})") from None
                rows.append(row)
    if not rows:
        raise CompareError("no rows to compare")
    return rows


def paired_differences(rows: Sequence[dict[str, Any]], methods: Sequence[str], baseline: str,
                       config: CompareConfig | None = None) -> list[PairedDifference]:
    """Mean ``method - baseline`` of ``config.metric`` over the observations both were scored on, per delta and
    paper subset, with its bootstrap interval."""
    config = config or CompareConfig()
    known = {r["method"] for r in rows}
    missing = [m for m in (*methods, baseline) if m not in known]
    if missing:
        raise CompareError(f"methods {missing} are not in the rows; present: {sorted(known)}")
    set_sizes: dict[str, int] = {}
    for r in rows:
        set_sizes[r["set"]] = max(set_sizes.get(r["set"], 0), r["index"] + 1)
    # the views `pssnet evaluate --max-observations N` scores (without --dense-mugs)
    chosen = ({name: set(evenly_spaced(size, config.references)) for name, size in set_sizes.items()}
              if config.references is not None else None)
    # (delta, set, index) -> method -> row: the pairing key of one observation
    by_key: dict[tuple[float, str, int], dict[str, dict[str, Any]]] = {}
    for r in rows:
        if chosen is None or r["index"] in chosen[r["set"]]:
            by_key.setdefault((round(r["delta"], 9), r["set"], r["index"]), {})[r["method"]] = r
    rng = np.random.default_rng(config.seed)
    out = []
    for delta in sorted({k[0] for k in by_key}, reverse=True):
        for label, set_name, predicate in SUBSETS:
            for method in methods:
                pairs = [(scored[method][config.metric], scored[baseline][config.metric])
                         for (d, s, _), scored in by_key.items()
                         if d == delta and s == set_name and method in scored and baseline in scored
                         and (predicate is None or predicate(scored[baseline]))]
                if not pairs:
                    continue
                a, b = np.array(pairs).T
                low, high = _interval(a - b, config, rng)
                out.append(PairedDifference(delta, label, method, baseline, len(pairs), float(a.mean()),
                                            float(b.mean()), float((a - b).mean()), low, high))
    return out


def _interval(differences: np.ndarray, config: CompareConfig, rng: np.random.Generator) -> tuple[float, float]:
    if len(differences) < 2 or np.ptp(differences) == 0:
        return float(differences.mean()), float(differences.mean())  # nothing to resample
    result = stats.bootstrap((differences,), np.mean, confidence_level=config.confidence,
                             n_resamples=config.resamples, method="percentile", random_state=rng)
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def markdown(differences: Sequence[PairedDifference], config: CompareConfig) -> str:
    """One table per delta: rows = methods, columns = subsets, cells = difference (interval) and n."""
    percent = f"{config.confidence * 100:g} %"
    lines = []
    for delta in sorted({d.delta_m for d in differences}, reverse=True):
        at = [d for d in differences if d.delta_m == delta]
        subsets = [label for label, _, _ in SUBSETS if any(d.subset == label for d in at)]
        baseline = at[0].baseline
        lines += [f"### delta = {delta * 100:g} cm: {config.metric} of method - {baseline}, mm "
                  f"(paired over observations; {percent} bootstrap interval)", "",
                  "Bold: the interval excludes zero. Cells: difference (interval), the two means, observations.", "",
                  "| method | " + " | ".join(subsets) + " |", "|---|" + "---|" * len(subsets)]
        for method in dict.fromkeys(d.method for d in at):
            cells = []
            for label in subsets:
                d = next((d for d in at if d.method == method and d.subset == label), None)
                if d is None:
                    cells.append("n/a")
                    continue
                mark = "**" if significant(d) else ""
                cells.append(f"{mark}{d.difference:+.2f}{mark} ({d.low:+.2f} to {d.high:+.2f}), "
                             f"{d.method_mean:.2f} vs {d.baseline_mean:.2f}, n={d.count}")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def significant(difference: PairedDifference) -> bool:
    """Whether the interval excludes zero."""
    return math.isfinite(difference.low) and (difference.low > 0 or difference.high < 0)
