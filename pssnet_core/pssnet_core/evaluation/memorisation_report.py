"""The report of ``pssnet memorisation``: a Markdown table, the JSON record, the per-completion CSV, figures."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, fields
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.experiment import Figure, Json, Markdown, Report, Table
from pssnet_core.evaluation.figures import draw_voxels, save_figure
from pssnet_core.evaluation.memorisation import MemorisationResult, summarise_memorisation
from pssnet_core.evaluation.memorisation_search import TrainingIndex


def memorisation_report(result: MemorisationResult) -> Report:
    """``memorisation.md``, ``memorisation.json`` (run, search parameters, summary, costs, prefilter check),
    ``memorisation_per_completion.csv``, ``memorisation_scatter.png`` and ``memorisation_examples.png``."""
    config = result.config
    summary = summarise_memorisation(result.rows, result.methods, result.sets)
    return {
        "markdown": Markdown("memorisation.md", markdown_memorisation(summary, result)),
        "json": Json("memorisation.json", {
            "run": {f.name: getattr(config, f.name) for f in fields(config) if f.name != "search"},
            "config": asdict(config.search), "training": [str(r) for r in result.roots], "summary": summary,
            "costs": result.costs, "verify": result.verify}),
        "csv": Table("memorisation_per_completion.csv", result.rows),
        "scatter": Figure("memorisation_scatter.png", partial(plot_memorisation, rows=result.rows,
                                                              methods=result.methods)),
        "examples": Figure("memorisation_examples.png", partial(plot_examples, examples=result.examples,
                                                                index=result.index)),
    }


def markdown_memorisation(summary: Sequence[dict[str, Any]], result: MemorisationResult) -> str:
    """The Markdown report: one table row per method and test set, then the search and its cost."""
    run, roots, costs, verify = result.config, result.roots, result.costs, result.verify
    lines = ["# Memorisation: completions against the nearest training shape", "",
             f"Training grids: {costs['training_grids']} from {', '.join(f'`{r}`' for r in roots)}; test sets under "
             f"`{run.data}`; {run.samples} completions per view, seed {run.seed} (view i uses seed + i). Chamfer "
             "distance between voxel-centre clouds in mm, grid to grid (see "
             "`pssnet_core/evaluation/memorisation.py`). Paper (appendix): ~10 % of completions nearer a training "
             "shape, 2.4 mm to it vs 3.8 mm to the truth.", "",
             "| method | test set | views | completions | nearer a training shape | to nearest training (mm, mean "
             "/ median) | to the truth (mm, mean / median) | nearest is same family | truth to nearest training (mm) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for e in summary:
        lines.append(f"| {e['method']} | {e['set']} | {e['views']} | {e['completions']} | "
                     f"{e['nearer_training_fraction']:.1%} | {e['train_mm_mean']:.2f} / {e['train_mm_median']:.2f} | "
                     f"{e['truth_mm_mean']:.2f} / {e['truth_mm_median']:.2f} | {e['same_family_fraction']:.0%} | "
                     f"{e['truth_train_mm_mean']:.2f} |")
    lines += ["", "Last column: the test truth's own distance to the nearest training grid (per view, averaged over "
              "completions). A training set with many objects in many poses has some grid near any shape, so "
              "completions can lie nearer a training shape than their truth without recalling one; compare the "
              "distance to the nearest training shape with this baseline.",
              "", f"Search: prefilter on mass-normalised occupancy averaged over "
              f"{run.search.pool_for(int(costs.get('grid_size', 32)))}-voxel blocks, blurred by {run.search.blur:g} "
              f"voxel; exact chamfer on the top {run.search.top_k}."]
    for name, v in verify.items():
        lines.append(f"Prefilter check ({name}): on {v['completions']} completions searched by brute force over the "
                     f"whole training set, the prefilter found the exact nearest in "
                     f"{v['prefilter_found_exact_nearest']:.0%} (largest excess {v['max_excess_mm']:.2f} mm).")
    lines += ["", f"Cost: index {costs['index_seconds']:.1f} s ({costs['index_megabytes']:.0f} MB in memory), sampling "
              f"{costs['sampling_seconds']:.1f} s, search {costs['search_seconds']:.1f} s, brute-force check "
              f"{costs['verify_seconds']:.1f} s, whole run {costs['total_seconds']:.1f} s."]
    return "\n".join(lines) + "\n"


def plot_memorisation(path: str | Path, rows: Sequence[dict[str, Any]], methods: Sequence[str]) -> Path:
    """Per method: distance to the nearest training shape against distance to the truth (one dot a completion)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 4.0), squeeze=False)
    for ax, method in zip(axes[0], methods, strict=True):
        chosen = [r for r in rows if r["method"] == method]
        sets = list(dict.fromkeys(r["set"] for r in chosen))
        top = max([1.0] + [max(r["train_mm"], r["truth_mm"]) for r in chosen])
        for k, set_name in enumerate(sets):
            pts = np.array([[r["truth_mm"], r["train_mm"]] for r in chosen if r["set"] == set_name])
            ax.plot(pts[:, 0], pts[:, 1], "o", markersize=3, alpha=0.5, color=plt.get_cmap("tab10")(k % 10),
                    label=set_name)
        ax.plot([0, top], [0, top], color="grey", linewidth=0.8, linestyle=":")
        nearer = np.mean([r["nearer_training"] for r in chosen]) if chosen else math.nan
        ax.set_title(f"{method}: {nearer:.0%} below the diagonal (nearer a training shape)", fontsize=8)
        ax.set_xlabel("chamfer to the test truth (mm)")
        ax.set_ylabel("chamfer to the nearest training shape (mm)")
        ax.legend(fontsize=7)
    return save_figure(fig, path, dpi=100)


def plot_examples(path: str | Path, examples: Mapping[str, list[tuple[float, np.ndarray, int, np.ndarray]]],
                  index: TrainingIndex) -> Path:
    """Rows: completion, its nearest training grid, the test truth (the completions nearest a training shape
    relative to their truth)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    items = [(m, e) for m, es in examples.items() for e in es]
    fig = plt.figure(figsize=(6.0, 2.0 * max(1, len(items))))
    for r, (method, (ratio, completion, j, truth)) in enumerate(items):
        for c, (grid, title, colour) in enumerate((
                (completion, f"{method} completion (train/truth {ratio:.2f})", "tab:blue"),
                (index.grids(np.array([j]))[0], f"nearest training: {index.identities[j]}", "tab:orange"),
                (truth, "test truth", "tab:green"))):
            ax = fig.add_subplot(max(1, len(items)), 3, 3 * r + c + 1, projection="3d")
            draw_voxels(ax, grid, title, colour)
    return save_figure(fig, path, dpi=90)
