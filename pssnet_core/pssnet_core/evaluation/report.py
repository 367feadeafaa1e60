"""The report of ``pssnet evaluate``: tables (markdown + CSV, in the shape of the paper's Table 1) and figures."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.evaluate import EvaluationResult, KeptExample
from pssnet_core.evaluation.experiment import Figure, Json, Markdown, Report, Table
from pssnet_core.evaluation.figures import draw_voxels, save_figure
from pssnet_core.evaluation.metrics import METRIC_NAMES
from pssnet_core.evaluation.testsets import MUG_SETS
from pssnet_core.spread import evenly_spaced


def _hidden(row: dict[str, Any]) -> bool:
    return row.get("handle_visible") in (False, 0, "False")


#: (subset label, test set, extra row predicate), in the paper's column order, then the out-of-family sets', then
#: the mugs behind the narrow slit
SUBSETS: tuple[tuple[str, str, Callable[[dict[str, Any]], bool] | None], ...] = (
    ("all mugs", "mugs", None),
    ("occluded-handle mugs", "mugs", _hidden),
    ("ycb wide slit", "ycb_wide", None),
    ("ycb narrow slit", "ycb_narrow", None),
    ("oof all mugs", "oof_mugs", None),
    ("oof occluded-handle mugs", "oof_mugs", _hidden),
    ("oof wide slit", "oof_wide", None),
    ("oof narrow slit", "oof_narrow", None),
    ("mugs narrow slit", "mugs_narrow", None),
    ("oof mugs narrow slit", "oof_mugs_narrow", None),
)

METRIC_LABELS = {"best_accuracy_mm": "best acc", "coverage_mm": "coverage",
                 "plausibility_mm": "avg plausibility", "plausible_diversity_mm": "plausible diversity"}

#: record keys that may hold a mug view's rotation angle in degrees, tried in order
ROTATION_KEYS: tuple[str, ...] = ("rotation_deg", "rotation", "yaw_deg", "yaw", "angle_deg", "angle")


def summarise(rows: Sequence[dict[str, Any]], methods: Sequence[str], deltas: Sequence[float]) -> list[dict[str, Any]]:
    """Mean metrics per (delta, subset, method): the long-format table, for the subsets of the sets in ``rows``."""
    present = {r["set"] for r in rows}
    table = []
    for delta in deltas:
        for label, set_name, predicate in [s for s in SUBSETS if s[1] in present]:
            for method in methods:
                chosen = [r for r in rows if r["set"] == set_name and r["method"] == method
                          and abs(r["delta"] - delta) < 1e-12 and (predicate is None or predicate(r))]
                entry: dict[str, Any] = {"delta_m": delta, "subset": label, "method": method, "count": len(chosen)}
                for name in METRIC_NAMES:
                    entry[name] = float(np.mean([r[name] for r in chosen])) if chosen else float("nan")
                entry["mean_plausible_set_size"] = (float(np.mean([r["num_plausible"] for r in chosen]))
                                                    if chosen else float("nan"))
                table.append(entry)
    return table


def _fmt(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.1f}"


def markdown_table(summary: Sequence[dict[str, Any]], methods: Sequence[str], deltas: Sequence[float],
                   delta_notes: dict[float, str] | None = None) -> str:
    """Markdown: one table per delta, rows = methods, columns = subset x metric (mm), as the paper's Table 1."""
    lines: list[str] = []
    index = {(e["delta_m"], e["subset"], e["method"]): e for e in summary}
    subsets = [s for s in SUBSETS if any(e["subset"] == s[0] for e in summary)]
    for delta in deltas:
        note = (delta_notes or {}).get(delta, "")
        lines.append(f"### delta = {delta * 100:g} cm{(' (' + note + ')') if note else ''}")
        lines.append("")
        header = ["method"]
        for label, _, _ in subsets:
            counts = {index[(delta, label, m)]["count"] for m in methods if (delta, label, m) in index}
            n = max(counts) if counts else 0
            header += [f"{label} (n={n}): {METRIC_LABELS[name]}" for name in METRIC_NAMES]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "---|" * len(header))
        for method in methods:
            cells = [method]
            for label, _, _ in subsets:
                e = index.get((delta, label, method))
                cells += [_fmt(e[name]) if e else "n/a" for name in METRIC_NAMES]
            lines.append("| " + " | ".join(cells) + " |")
        sizes = []
        for label, _, _ in subsets:
            e = index.get((delta, label, methods[0])) if methods else None
            if e and e["count"]:
                sizes.append(f"{label}: {e['mean_plausible_set_size']:.1f}")
        if sizes:
            lines.append("")
            lines.append("Mean plausible-set size: " + "; ".join(sizes) + ".")
        lines.append("")
    return "\n".join(lines)


def rotation_of(row: dict[str, Any]) -> float | None:
    """A mug view's rotation angle in degrees from its row, if recorded."""
    for key in ROTATION_KEYS:
        if key in row and isinstance(row[key], int | float) and not isinstance(row[key], bool):
            return float(row[key]) % 360.0
    return None


def plot_coverage_vs_rotation(path: str | Path, rows: Sequence[dict[str, Any]], methods: Sequence[str],
                              deltas: Sequence[float], num_mugs: int = 3) -> Path | None:
    """Coverage against rotation angle for a few mugs, handle-hidden angles shaded (the paper's figure).

    Picks the mugs with the most evaluated views. Returns None when no mug row has a rotation angle.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mug_rows = [r for r in rows if r["set"] in MUG_SETS and rotation_of(r) is not None]
    if not mug_rows:
        return None
    counts: dict[str, int] = {}
    for r in mug_rows:
        counts[r["identity"]] = counts.get(r["identity"], 0) + 1
    mugs = sorted(counts, key=lambda k: (-counts[k], k))[:num_mugs]
    fig, axes = plt.subplots(len(mugs), len(deltas), figsize=(5.5 * len(deltas), 2.8 * len(mugs)), squeeze=False,
                             sharex=True)
    for row_k, mug in enumerate(mugs):
        for col_k, delta in enumerate(deltas):
            ax = axes[row_k][col_k]
            chosen = [r for r in mug_rows if r["identity"] == mug and abs(r["delta"] - delta) < 1e-12]
            angles = sorted({rotation_of(r) for r in chosen})
            step = float(np.min(np.diff(angles))) if len(angles) > 1 else 5.0
            hidden = sorted({rotation_of(r) for r in chosen if r.get("handle_visible") in (False, 0, "False")})
            for k, a in enumerate(hidden):
                ax.axvspan(a - step / 2, a + step / 2, color="0.85", lw=0, label="handle hidden" if k == 0 else None)
            for method in methods:
                pts = sorted((rotation_of(r), r["coverage_mm"]) for r in chosen if r["method"] == method)
                if pts:
                    ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=".", label=method)
            ax.set_title(f"{mug}, delta {delta * 100:g} cm", fontsize=9)
            ax.set_ylabel("coverage (mm)")
            ax.set_xlim(0, 360)
            if row_k == len(mugs) - 1:
                ax.set_xlabel("rotation about the vertical (deg)")
            if row_k == 0 and col_k == 0:
                ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, path, dpi=110)


def plot_samples_vs_plausible(path: str | Path, examples: Sequence[KeptExample], method: str,
                              max_samples: int = 5) -> Path | None:
    """For one method: per kept example, samples (top) above each one's nearest plausible shape (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chosen = [e for e in examples if e.method == method]
    if not chosen:
        return None
    cols = max_samples + 1
    fig = plt.figure(figsize=(2.0 * cols, 2.1 * 2 * len(chosen)))
    for k, ex in enumerate(chosen):
        # Spread the samples shown over the set: the most diverse-looking choice without extra computation.
        picks = evenly_spaced(len(ex.samples), max_samples)
        ax = fig.add_subplot(2 * len(chosen), cols, 2 * k * cols + 1, projection="3d")
        draw_voxels(ax, ex.plausible[0], f"{ex.set_name} #{ex.index}\nground truth", "tab:green")
        ax = fig.add_subplot(2 * len(chosen), cols, (2 * k + 1) * cols + 1, projection="3d")
        ax.axis("off")
        ax.text2D(0.05, 0.5, f"delta {ex.delta * 100:g} cm\n{len(ex.plausible)} plausible\nshapes", fontsize=7,
                  transform=ax.transAxes)
        for c, s in enumerate(picks):
            nearest = int(np.argmin(ex.distances[s]))
            ax = fig.add_subplot(2 * len(chosen), cols, 2 * k * cols + 2 + c, projection="3d")
            draw_voxels(ax, ex.samples[s], f"{method} sample {s}", "tab:blue")
            ax = fig.add_subplot(2 * len(chosen), cols, (2 * k + 1) * cols + 2 + c, projection="3d")
            draw_voxels(ax, ex.plausible[nearest],
                         f"nearest plausible #{nearest}\n{ex.distances[s, nearest] * 1000:.1f} mm", "tab:orange")
    return save_figure(fig, path, dpi=100)


def evaluation_report(result: EvaluationResult, command: str = "") -> Report:
    """``results.md``, ``results.csv`` (means per delta, subset and method), ``per_observation.csv``,
    ``coverage_vs_rotation.png``, ``samples_<method>.png`` and ``evaluation_info.json`` (deltas, methods,
    timings, plausible-set statistics). ``command`` is the command line shown in the Markdown."""
    config, methods, rows = result.config, result.methods, result.rows
    deltas = config.deltas
    summary = summarise(rows, methods, deltas)
    notes = {config.delta: "the paper's value"}
    if len(deltas) > 1:
        notes[deltas[1]] = "scaled to real-size objects, see DESIGN.md"
    observation = config.test_sets.observation
    header = ["# Plausible-diversity evaluation", "",
              "Chamfer distances between voxel-centre clouds, millimetres (lower is better). best acc = M_A, "
              "coverage = M_C, avg plausibility = M_P, plausible diversity = M_PD = M_C + M_P.", "",
              f"Command: `pssnet evaluate {command}`", "",
              f"Samples per observation: {config.samples}; outlier allowance: fraction {observation.outlier_fraction}, "
              f"count {observation.outlier_count}; sets: "
              f"{', '.join(f'{k} ({len(v.references)} observations)' for k, v in result.test_sets.items())}.",
              ""]
    report: Report = {
        "markdown": Markdown("results.md", "\n".join(header) + markdown_table(summary, methods, deltas, notes)),
        "csv": Table("results.csv", summary),
        "per_observation": Table("per_observation.csv", rows),
        "coverage_plot": Figure("coverage_vs_rotation.png", partial(
            plot_coverage_vs_rotation, rows=rows, methods=methods, deltas=deltas, num_mugs=config.plot_mugs)),
    }
    examples = [e for e in result.examples if abs(e.delta - deltas[-1]) < 1e-12]
    for method in methods:
        report[f"samples_{method}"] = Figure(f"samples_{method}.png", partial(
            plot_samples_vs_plausible, examples=examples, method=method))
    report["info"] = Json("evaluation_info.json", {
        "deltas": deltas, "methods": methods, "samples": config.samples, "timings": result.timings,
        "plausible_stats": {k: v.sets.stats for k, v in result.test_sets.items()}}, indent=2, strict=False)
    return report
