"""CSV training logs and the loss-curve PNG."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

TRAIN_LOG = "train_log.csv"
VAL_LOG = "val_log.csv"
CURVES_PNG = "loss_curves.png"


class CsvLog:
    """Appends dict rows to a CSV file; the header is fixed by the first row ever written (also on resume)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fields: list[str] | None = None
        if self.path.exists() and self.path.stat().st_size:
            with open(self.path, newline="") as handle:
                self._fields = next(csv.reader(handle), None)

    def write(self, row: dict[str, Any]) -> None:
        new = self._fields is None
        if new:
            self._fields = list(row)
        with open(self.path, "a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=self._fields, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow({k: _fmt(row.get(k, "")) for k in self._fields})


def _fmt(value: Any) -> Any:
    return f"{value:.6g}" if isinstance(value, float) else value


def read_csv(path: str | Path) -> list[dict[str, float]]:
    """Rows of a log as floats (non-numeric cells become NaN)."""
    path = Path(path)
    if not path.exists():
        return []
    rows = []
    with open(path, newline="") as handle:
        for row in csv.DictReader(handle):
            parsed = {}
            for key, value in row.items():
                try:
                    parsed[key] = float(value)
                except (TypeError, ValueError):
                    parsed[key] = math.nan
            rows.append(parsed)
    return rows


def truncate_after_step(path: str | Path, step: int) -> None:
    """Drops rows logged after ``step`` (a resumed run repeats them)."""
    path = Path(path)
    if not path.exists():
        return
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows:
        return
    header, body = rows[0], rows[1:]
    col = header.index("step") if "step" in header else None
    if col is None:
        return
    kept = [r for r in body if r and float(r[col]) <= step]
    with open(path, "w", newline="") as handle:
        csv.writer(handle).writerows([header, *kept])


def plot_curves(out_dir: str | Path, title: str = "") -> Path | None:
    """Writes ``loss_curves.png``: training loss terms per step and validation metrics; None if no logs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    train, val = read_csv(out_dir / TRAIN_LOG), read_csv(out_dir / VAL_LOG)
    if not train and not val:
        return None
    skip = {"step", "epoch", "elapsed_s", "samples_per_s", "lr"}
    loss_keys = [k for k in (train[0] if train else {}) if k not in skip]
    val_keys = [k for k in (val[0] if val else {}) if k not in skip and k != "val_n"]
    panels = len(loss_keys) + len(val_keys)
    cols = min(3, max(panels, 1))
    rows = max(1, math.ceil(panels / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    flat = list(axes.ravel())
    for ax, key in zip(flat, loss_keys, strict=False):
        ax.plot([r["step"] for r in train], [r[key] for r in train], lw=1)
        ax.set_title(f"train {key}")
        ax.set_xlabel("step")
        values = [r[key] for r in train if math.isfinite(r[key])]
        if values and min(values) > 0 and max(values) / min(values) > 50:
            ax.set_yscale("log")
    for ax, key in zip(flat[len(loss_keys):], val_keys, strict=False):
        ax.plot([r["step"] for r in val], [r[key] for r in val], "o-", ms=3, color="C1")
        ax.set_title(key)
        ax.set_xlabel("step")
    for ax in flat[panels:]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = out_dir / CURVES_PNG
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
