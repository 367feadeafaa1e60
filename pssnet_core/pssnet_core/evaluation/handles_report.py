"""The report of ``pssnet handles``: per-view and summary CSVs, a Markdown table, sample figures."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from pssnet_core.evaluation.experiment import Figure, Markdown, Report, Table
from pssnet_core.evaluation.figures import draw_voxels, save_figure
from pssnet_core.evaluation.handles import HandlesResult, summarise_handles


def handles_report(result: HandlesResult) -> Report:
    """``handles.csv`` (one row per view and method), ``handles_summary.csv`` (means per method and handle
    visibility), ``handles.md`` and ``handle_samples_{hidden,visible}.png``."""
    config = result.config
    summary = summarise_handles(result.rows, result.methods)
    lines = ["# Where sampled mugs put the handle", "",
             f"{result.mugs} round held-out mugs with a handle from `{result.root}`, {result.views} views, "
             f"{config.samples} samples per view, seed {config.seed}. Azimuths in the mug's frame (true handle = 0 "
             "deg); spread = circular standard deviation of the handle azimuth across samples; error = mean "
             "|azimuth|; pairwise = mean chamfer distance between two samples of the same view (mm). "
             "See `pssnet_core/evaluation/handles.py`.", "",
             "| method | handle | views | samples with a handle | azimuth spread (deg) | azimuth error (deg) "
             "| pairwise (mm) |", "|---|---|---|---|---|---|---|"]
    for r in summary:
        lines.append(f"| {r['method']} | {r['handle']} | {r['views']} | {r['handle_rate']:.2f} | "
                     f"{r['spread_deg']:.1f} | {r['error_deg']:.1f} | {r['pairwise_mm']:.2f} |")
    report: Report = {"csv": Table("handles.csv", result.rows),
                      "summary_csv": Table("handles_summary.csv", summary),
                      "markdown": Markdown("handles.md", "\n".join(lines) + "\n")}
    for figure in result.figures:
        report[f"figure_{figure.label}"] = Figure(f"handle_samples_{figure.label}.png", partial(
            plot_handle_samples, ground_truth=figure.truth, samples=figure.grids, azimuths=figure.azimuths,
            title=figure.title))
    return report


def plot_handle_samples(path: str | Path, ground_truth: np.ndarray, samples: dict[str, np.ndarray],
                        azimuths: dict[str, np.ndarray], title: str, count: int = 8) -> Path:
    """One row per method: the ground truth, then ``count`` samples with their handle azimuths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = count + 1
    fig = plt.figure(figsize=(1.9 * cols, 2.0 * len(samples) + 0.4))
    for r, (method, grids) in enumerate(samples.items()):
        ax = fig.add_subplot(len(samples), cols, r * cols + 1, projection="3d")
        draw_voxels(ax, ground_truth, "ground truth", "tab:green")
        for c in range(min(count, len(grids))):
            az = azimuths[method][c]
            label = "no handle" if not np.isfinite(az) else f"handle {az:+.0f} deg"
            ax = fig.add_subplot(len(samples), cols, r * cols + 2 + c, projection="3d")
            draw_voxels(ax, grids[c], f"{method} #{c}: {label}", "tab:blue")
    fig.suptitle(title, fontsize=9)
    return save_figure(fig, path, dpi=100)
