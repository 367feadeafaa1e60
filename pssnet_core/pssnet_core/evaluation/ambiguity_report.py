"""The report of ``pssnet ambiguity``: Markdown tables, the JSON record, the per-view CSV and three figures."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, fields
from functools import partial
from typing import Any

import numpy as np

from pssnet_core.evaluation.ambiguity import AmbiguityResult, arc_composition, summarise_ambiguity
from pssnet_core.evaluation.ambiguity_plots import plot_handle_arcs, plot_slit_extents, plot_summary
from pssnet_core.evaluation.ambiguity_sets import DEFAULT_DELTAS
from pssnet_core.evaluation.experiment import Figure, Json, Markdown, Report, Table


def _f(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.{digits}f}"


def markdown_ambiguity(summary: Sequence[dict[str, Any]], result: AmbiguityResult) -> str:
    """The Markdown report: one table per delta (rows = method x box temperature), then costs."""
    run, costs, arcs, ranges = result.config, result.costs, result.arcs, result.ranges
    c = run.measure
    lines = ["# Ambiguity: do the samples spread over what the view allows?", "",
             f"Test sets {', '.join(f'`{s}`' for s in run.sets)} under `{run.data}`; {run.samples} samples per view, "
             f"seed {run.seed} (view i uses seed + i, "
             "the same at every box temperature). See `pssnet_core/evaluation/ambiguity.py` for the definitions.", "",
             f"- Hidden handle: plausible arc = azimuths ({c.azimuth_step_deg:g} deg steps) where the mug turned about "
             f"its axis passes the observation model; coverage = arc azimuths with a sampled handle within "
             f"{c.arc_tolerance_deg:g} deg; precision = sampled handles within {c.arc_margin_deg:g} deg of the arc; "
             "spread ratio = circular s.d. of sampled azimuths / that of the arc; handle rate = samples with a "
             "handle. Visible handle: mean |sampled azimuth - truth|.",
             f"- Narrow slit (boxes): the box stretched along its axis away from the camera in "
             f"{c.extent_step_voxels:g}-voxel steps; extents = grid-x extent of the largest connected part; coverage "
             f"within {c.extent_tolerance_voxels:g} voxel, precision margin {c.extent_margin_voxels:g} voxel; "
             "'open' = fraction of views whose plausible range reaches the end of the grid.", ""]
    for delta in c.deltas:
        note = "scaled to real-size objects" if abs(delta - DEFAULT_DELTAS[0]) < 1e-12 else (
            "the paper's value" if abs(delta - DEFAULT_DELTAS[1]) < 1e-12 else "")
        lines += [f"## delta = {delta * 100:g} cm{f' ({note})' if note else ''}", ""]
        header = ["method", "box T", "hidden views", "arc width (deg)", "arc coverage", "arc precision",
                  "arc spread ratio", "handle rate hidden", "visible views", "handle error visible (deg)",
                  "slit views", "plausible extent (mm)", "sampled extent (mm)", "true extent (mm)", "open",
                  "slit coverage", "slit precision", "slit spread ratio"]
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for e in [s for s in summary if abs(s["delta_m"] - delta) < 1e-12]:
            width = e["arc_azimuths"] * c.azimuth_step_deg
            cells = [e["method"], f"{e['box_temperature']:g}", str(e["hidden_views"]), _f(width, 0),
                     _f(e["arc_coverage"]), _f(e["arc_precision"]), _f(e["arc_spread_ratio"]),
                     _f(e["handle_rate_hidden"]), str(e["visible_views"]), _f(e["handle_error_visible_deg"], 1),
                     str(e["slit_views"]),
                     f"{_f(e['slit_plausible_min_mm'], 0)}-{_f(e['slit_plausible_max_mm'], 0)}",
                     f"{_f(e['slit_sample_min_mm'], 0)}-{_f(e['slit_sample_max_mm'], 0)}", _f(e["slit_true_mm"], 0),
                     _f(e["slit_open_ended"]), _f(e["slit_coverage"]), _f(e["slit_precision"]),
                     _f(e["slit_spread_ratio"])]
            lines.append("| " + " | ".join(cells) + " |")
        if arcs:
            truth = np.mean([a.truth_accepted(delta) for a in arcs.values()])
            lines.append("")
            lines.append(f"Arc width = mean number of plausible azimuths x {c.azimuth_step_deg:g} deg; the true "
                         f"mug passes in {truth:.0%} of the hidden views.")
            if delta > min(c.deltas):
                mix = arc_composition(list(arcs.values()), delta, min(c.deltas), tolerance_deg=c.arc_tolerance_deg)
                lines.append(f"At this delta {_f(100 * mix.facing_share, 0)} % of the arc lies within "
                             f"{mix.facing_deg:g} deg of the handle facing the camera (in front of the body, in view, "
                             "less than delta proud of it); "
                             f"a sampler drawing handles exactly over the {min(c.deltas) * 100:g} cm arc would score "
                             f"arc coverage {_f(mix.strict_cover)} here ({mix.views} views).")
        if ranges:
            truth = np.mean([r.truth_accepted(delta) for r in ranges.values()])
            lines.append(f"Extents are means over views of each view's min/max; the true box passes in {truth:.0%} "
                         "of the slit views.")
        lines.append("")
    fallbacks = [e for e in summary if abs(e["delta_m"] - c.deltas[0]) < 1e-12 and any(
        np.isfinite(e[f"nothing_accepted_{kind}"]) for kind in ("hidden", "visible", "slit"))]
    if fallbacks:
        lines += ["## The checked sampler's fall-back", "",
                  "Share of the views on which its check accepted none of the proposals, so that the least-violating "
                  "ones came back (the same at every delta):", ""]
        for e in fallbacks:
            shares = ", ".join(f"{kind} {_f(100 * e[f'nothing_accepted_{kind}'], 0)} %"
                               for kind in ("hidden", "visible", "slit") if np.isfinite(e[f"nothing_accepted_{kind}"]))
            lines.append(f"- {e['method']} (box T {e['box_temperature']:g}): {shares}")
        lines.append("")
    lines += ["## Cost", ""]
    for kind in ("handle_arcs", "slit_ranges"):
        if kind in costs:
            k = costs[kind]
            lines.append(f"- Plausible {kind.replace('_', ' ')} (model-independent, cached in `{k['cache']}`): "
                         f"{k['views']} views, {k['seconds_per_view']:.2f} s per view on one core "
                         f"({k['seconds_all_views']:.1f} s in all; {k['computed_now']} computed in this run, "
                         f"{k['cached']} from the cache).")
    lines.append(f"- Sampling: {costs['sampling_seconds']:.1f} s; whole run {costs['total_seconds']:.1f} s.")
    return "\n".join(lines) + "\n"


def ambiguity_report(result: AmbiguityResult) -> Report:
    """``ambiguity.md`` (tables), ``ambiguity.json`` (run, parameters, summary, costs, per-view rows, plausible
    sets), ``ambiguity_per_view.csv`` and the figures ``handle_arcs.png``, ``slit_extents.png`` and
    ``ambiguity_summary.png`` (at the headline delta)."""
    config, rows, runs = result.config, result.rows, result.runs
    summary = summarise_ambiguity(rows, runs, config.measure.deltas)
    delta = config.measure.deltas[0]
    report: Report = {
        "markdown": Markdown("ambiguity.md", markdown_ambiguity(summary, result)),
        "json": Json("ambiguity.json", {
            "run": {f.name: getattr(config, f.name) for f in fields(config) if f.name != "measure"},
            "config": asdict(config.measure), "summary": summary, "costs": result.costs, "rows": rows,
            "plausible": {"handle_arcs": {str(k): a.to_json() for k, a in result.arcs.items()},
                          "slit_ranges": {str(k): r.to_json() for k, r in result.ranges.items()}}}),
        "csv": Table("ambiguity_per_view.csv", [{k: v for k, v in r.items() if not isinstance(v, list)}
                                                for r in rows]),
    }
    if result.arcs:
        report["handle_figure"] = Figure("handle_arcs.png", partial(
            plot_handle_arcs, arcs=result.arcs, rows=rows, runs=runs, delta=delta, count=config.figure_views))
    if result.ranges:
        report["slit_figure"] = Figure("slit_extents.png", partial(
            plot_slit_extents, ranges=result.ranges, rows=rows, runs=runs, delta=delta,
            count=3 * config.figure_views))
    report["summary_figure"] = Figure("ambiguity_summary.png", partial(
        plot_summary, summary=summary, runs=runs, delta=delta))
    return report
