"""The figures of ``pssnet ambiguity``: plausible handle arcs, slit extent ranges, and the headline scores."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.ambiguity_sets import HandleArc, SlitRange
from pssnet_core.evaluation.figures import save_figure
from pssnet_core.spread import evenly_spaced


def _run_label(name: str, temperature: float) -> str:
    return name if temperature == 1.0 else f"{name} T={temperature:g}"


def plot_handle_arcs(path: str | Path, arcs: Mapping[int, HandleArc], rows: Sequence[dict[str, Any]],
                     runs: Sequence[tuple[str, float]], delta: float, count: int = 4) -> Path:
    """Polar plots of a few hidden-handle views: the plausible arc (shaded) and each run's sampled handles.

    Picks the views with the widest arcs (the most ambiguous). The true handle is at 0 degrees (star); each
    run's samples lie on their own ring.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chosen = sorted(arcs.values(), key=lambda a: (-len(a.arc(delta)), a.index))[:max(1, count)]
    fig, axes = plt.subplots(1, len(chosen), figsize=(4.2 * len(chosen), 4.6), squeeze=False,
                             subplot_kw={"projection": "polar"})
    colours = plt.get_cmap("tab10")
    for ax, arc in zip(axes[0], chosen, strict=True):
        step = np.radians(arc.azimuths_deg[1] - arc.azimuths_deg[0]) if len(arc.azimuths_deg) > 1 else 0.1
        allowed = np.radians(arc.arc(delta))
        ax.bar(allowed, np.full(len(allowed), len(runs) + 1.0), width=step, bottom=0.0, color="tab:green",
               alpha=0.25, label="plausible arc")
        ax.plot([0.0], [len(runs) + 0.6], marker="*", markersize=14, color="black", linestyle="", label="true handle")
        ax.plot([np.radians(arc.camera_azimuth_deg)], [len(runs) + 0.6], marker="s", markersize=8, color="tab:red",
                linestyle="", label="camera")
        for k, (name, temperature) in enumerate(runs):
            row = next((r for r in rows if r["kind"] == "hidden_handle" and r["index"] == arc.index
                        and r["method"] == name and r["box_temperature"] == temperature), None)
            if row is None:
                continue
            az = np.array(row["azimuths_deg"], dtype=np.float64)
            az = az[np.isfinite(az)]
            ax.plot(np.radians(az), np.full(len(az), k + 1.0), "o", color=colours(k % 10), alpha=0.7, markersize=5,
                    label=_run_label(name, temperature))
        ax.set_ylim(0, len(runs) + 1.0)
        ax.set_yticks([])
        ax.set_title(f"view {arc.index} ({arc.identity})\narc {len(allowed)} x {np.degrees(step):.0f} deg", fontsize=8)
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.08, 1.0), fontsize=7)
    fig.suptitle(f"Hidden handles: plausible arc (delta {delta * 100:g} cm) vs sampled handle azimuths "
                 "(0 deg = true handle; one ring per model)", fontsize=9)
    return save_figure(fig, path, dpi=100)


def plot_slit_extents(path: str | Path, ranges: Mapping[int, SlitRange], rows: Sequence[dict[str, Any]],
                      runs: Sequence[tuple[str, float]], delta: float, count: int = 12) -> Path:
    """Per narrow-slit box view: the plausible extent range (bar), the truth and each run's sampled extents."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_index = sorted(ranges.values(), key=lambda r: r.index)
    chosen = [by_index[k] for k in evenly_spaced(len(by_index), max(1, count))]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(chosen) * (1 + 0.15 * len(runs))), 4.2))
    colours = plt.get_cmap("tab10")
    width = 0.8
    for x, plausible in enumerate(chosen):
        mm = plausible.voxel_size * 1000.0
        allowed = plausible.extents(delta) * mm
        ax.bar(x, allowed.max() - allowed.min() + mm, bottom=allowed.min() - 0.5 * mm, width=width,
               color="tab:green", alpha=0.25, label="plausible range" if x == 0 else None)
        ax.plot([x - width / 2, x + width / 2], [plausible.true_extent_voxels * mm] * 2, color="black", linewidth=2,
                label="truth" if x == 0 else None)
        for k, (name, temperature) in enumerate(runs):
            row = next((r for r in rows if r["kind"] == "slit" and r["index"] == plausible.index
                        and r["method"] == name and r["box_temperature"] == temperature
                        and abs(r["delta"] - delta) < 1e-12), None)
            if row is None:
                continue
            ext = np.array(row["extents_mm"], dtype=np.float64)
            ext = ext[np.isfinite(ext)]
            offset = -width / 2 + (k + 0.5) * width / max(len(runs), 1)
            jitter = np.linspace(-0.03, 0.03, len(ext)) if len(ext) > 1 else np.zeros(len(ext))
            ax.plot(x + offset + jitter, ext, "o", color=colours(k % 10), alpha=0.6, markersize=4,
                    label=_run_label(name, temperature) if x == 0 else None)
    ax.set_xticks(range(len(chosen)))
    ax.set_xticklabels([f"{r.index}\n{r.identity}" for r in chosen], fontsize=7)
    ax.set_ylabel("extent along the viewing direction (mm)")
    ax.set_title(f"Boxes through the narrow slit: plausible hidden extent (delta {delta * 100:g} cm) vs samples",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def plot_summary(path: str | Path, summary: Sequence[dict[str, Any]], runs: Sequence[tuple[str, float]],
                 delta: float) -> Path:
    """Bars of the six headline figures per run at ``delta``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("arc_coverage", "arc coverage"), ("arc_precision", "arc precision"),
            ("arc_spread_ratio", "arc spread ratio"), ("slit_coverage", "slit coverage"),
            ("slit_precision", "slit precision"), ("slit_spread_ratio", "slit spread ratio")]
    entries = {(e["method"], e["box_temperature"]): e for e in summary if abs(e["delta_m"] - delta) < 1e-12}
    fig, ax = plt.subplots(figsize=(8.5, 3.8))
    colours = plt.get_cmap("tab10")
    width = 0.8 / max(len(runs), 1)
    for k, run in enumerate(runs):
        e = entries.get(run, {})
        values = [e.get(key, math.nan) for key, _ in keys]
        values = [v if isinstance(v, float) and math.isfinite(v) else 0.0 for v in values]
        ax.bar(np.arange(len(keys)) + (k - (len(runs) - 1) / 2) * width, values, width=width,
               color=colours(k % 10), label=_run_label(*run))
    ax.axhline(1.0, color="grey", linewidth=0.8, linestyle=":")
    ax.set_xticks(range(len(keys)))
    ax.set_xticklabels([label for _, label in keys], fontsize=8)
    ax.set_title(f"Ambiguity figures at delta {delta * 100:g} cm (1 = samples spread as the view allows; "
                 "missing = n/a)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)
