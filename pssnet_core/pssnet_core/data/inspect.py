"""Looking at built datasets: summary statistics and a PNG preview sheet."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.data.store import GRID_KEYS, INDEX_FILE, DatasetError, DatasetReader


def find_datasets(path: str | Path) -> list[Path]:
    """Dataset directories at ``path``: itself if it holds an index, else every one below it (sorted).

    Raises:
        DatasetError: no dataset there.
    """
    path = Path(path)
    if (path / INDEX_FILE).exists():
        return [path]
    found = sorted(p.parent for p in path.rglob(INDEX_FILE)) if path.is_dir() else []
    if not found:
        raise DatasetError(f"no dataset (no {INDEX_FILE}) at or below {path}; build one with `pssnet dataset build`")
    return found


def dataset_stats(path: str | Path) -> dict[str, Any]:
    """Statistics of one dataset: counts, handle visibility, clipping and occupancy fractions per family.

    Returns:
        ``{"path", "name", "split", "grid_size", "samples", "objects", "families": {family: {...}}, "all": {...}}``
        where each group holds samples, objects, handle_visible (fraction of views of mugs with a handle,
        or None), no_handle (mug views without a handle), clipped (fraction), max_overshoot_voxels,
        occupied / known_occupied / known_free (mean fraction of voxels), slit_width_m (mean or None),
        attempts_mean (draws per sample).
    """
    reader = DatasetReader(path)
    n = reader.grid_size
    fractions: dict[str, np.ndarray] = {k: np.zeros(len(reader)) for k in GRID_KEYS}
    first = 0  # shards hold consecutive samples in order
    for shard in range(reader.num_shards):
        arrays = reader.load_shard(shard, keys=GRID_KEYS)
        for key in GRID_KEYS:
            values = arrays[key].reshape(len(arrays[key]), -1).mean(axis=1)
            fractions[key][first:first + len(values)] = values
        first += len(arrays[GRID_KEYS[0]])
    groups: dict[str, list[int]] = defaultdict(list)
    for i, record in enumerate(reader.records):
        groups[record.get("family", "?")].append(i)
    groups["all"] = list(range(len(reader)))

    def summary(indices: list[int]) -> dict[str, Any]:
        records = [reader.records[i] for i in indices]
        with_handle = [r["handle_visible"] for r in records if r.get("handle_visible") is not None]
        slits = [r["slit_width_m"] for r in records if r.get("slit_width_m") is not None]
        idx = np.asarray(indices)
        return {
            "samples": len(records),
            "objects": len({r.get("identity") for r in records}),
            "handle_visible": float(np.mean(with_handle)) if with_handle else None,
            "handle_views": len(with_handle),
            "no_handle": sum(1 for r in records if r.get("has_handle") is False),
            "clipped": float(np.mean([bool(r.get("clipped")) for r in records])),
            "max_overshoot_voxels": float(max((r.get("overshoot_voxels", 0.0) for r in records), default=0.0)),
            "occupied": float(fractions["occupancy"][idx].mean()),
            "known_occupied": float(fractions["known_occupied"][idx].mean()),
            "known_free": float(fractions["known_free"][idx].mean()),
            "slit_width_m": float(np.mean(slits)) if slits else None,
            "attempts_mean": float(np.mean([r.get("attempts", 1) for r in records])),
        }

    families = {k: summary(v) for k, v in sorted(groups.items()) if k != "all"}
    return {"path": str(path), "name": reader.meta.get("name"), "split": reader.meta.get("split"),
            "grid_size": n, "samples": len(reader), "objects": len({r.get("identity") for r in reader.records}),
            "families": families, "all": summary(groups["all"])}


def format_stats(stats: dict[str, Any]) -> str:
    """A plain-text table of :func:`dataset_stats`."""

    def pct(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.1f}%"

    lines = [f"{stats['path']}: {stats['name']} ({stats['split']}), grid {stats['grid_size']}^3, "
             f"{stats['samples']} samples of {stats['objects']} objects"]
    header = (f"  {'family':<10} {'samples':>7} {'objects':>7} {'handle vis':>10} {'no handle':>9} {'clipped':>8} "
              f"{'max over':>8} {'occupied':>8} {'known occ':>9} {'known free':>10} {'slit cm':>7}")
    lines.append(header)
    for name, s in [*stats["families"].items(), ("all", stats["all"])]:
        slit = "-" if s["slit_width_m"] is None else f"{100 * s['slit_width_m']:.1f}"
        lines.append(
            f"  {name:<10} {s['samples']:>7} {s['objects']:>7} {pct(s['handle_visible']):>10} {s['no_handle']:>9} "
            f"{pct(s['clipped']):>8} {s['max_overshoot_voxels']:>8.2f} {pct(s['occupied']):>8} "
            f"{pct(s['known_occupied']):>9} {pct(s['known_free']):>10} {slit:>7}")
    return "\n".join(lines)


def _side_and_top(sample: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """RGB projections of a sample's grids: side view (x right = away from camera, z up) and top view (x, y)."""
    views = []
    for axis in (1, 2):
        free = sample["known_free"].mean(axis=axis)
        truth = sample["occupancy"].any(axis=axis)
        seen = sample["known_occupied"].any(axis=axis)
        rgb = np.ones((*free.shape, 3))
        rgb *= 1.0 - 0.45 * free[..., None] * np.array([1.0, 0.5, 0.0])  # known free: blue tint
        rgb[truth] = (0.45, 0.45, 0.45)  # ground truth: grey
        rgb[seen] = (0.9, 0.1, 0.1)  # known occupied: red
        views.append(np.transpose(rgb, (1, 0, 2)))  # rows = second axis, columns = grid x
    return views[0], views[1]


def preview(path: str | Path, out: str | Path, count: int = 8, seed: int = 0) -> Path:
    """Writes a PNG sheet of ``count`` samples spread over the dataset.

    Each row: depth crop, mask crop, side view of the grids (grid x = horizontal viewing direction to the
    right, z up), top view (x right, y up). In the views, grey is ground truth, red known occupied, and the
    blue tint the fraction of known-free voxels along the projection.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    reader = DatasetReader(path)
    count = min(count, len(reader))
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(len(reader), size=count, replace=False))
    fig, axes = plt.subplots(count, 4, figsize=(12, 2.9 * count), squeeze=False)
    for row, index in zip(axes, picks, strict=True):
        sample = reader.get(int(index))
        depth = sample["depth"].astype(np.float32) / 1000.0
        shown = np.ma.masked_equal(depth, 0.0)
        on_object = depth[(sample["mask"] != 0) & (depth > 0)]
        limits = (on_object.min() - 0.05, on_object.max() + 0.15) if on_object.size else (None, None)
        row[0].imshow(shown, cmap="viridis", vmin=limits[0], vmax=limits[1])
        row[0].set_title(f"#{index} {sample['identity']} depth (m)", fontsize=8)
        row[1].imshow(sample["mask"], cmap="gray", vmin=0, vmax=1)
        flags = [f"yaw {sample['rotation_deg']:.0f}"]
        if sample.get("tip_deg"):
            flags.append(f"tip {sample['tip_deg']:.0f}")
        if sample.get("handle_visible") is not None:
            flags.append("handle visible" if sample["handle_visible"] else "handle HIDDEN")
        if sample.get("slit_width_m") is not None:
            flags.append(f"slit {100 * sample['slit_width_m']:.1f} cm")
        if sample.get("clipped"):
            flags.append("CLIPPED")
        row[1].set_title("mask: " + ", ".join(flags), fontsize=8)
        side, top = _side_and_top(sample)
        row[2].imshow(side, origin="lower", interpolation="nearest")
        row[2].set_title("side (x right, z up): grey GT, red known occ", fontsize=8)
        row[3].imshow(top, origin="lower", interpolation="nearest")
        row[3].set_title("top (x right, y up); blue = known free", fontsize=8)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(f"{reader.meta.get('split')}/{reader.meta.get('name')}: {len(reader)} samples, "
                 f"grid {reader.grid_size}^3 ({1000 * reader.voxel_size:.2f} mm voxels)", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.985))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out
