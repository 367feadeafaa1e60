"""The shape every evaluation experiment shares.

Each experiment (``evaluate``, ``handles``, ``ambiguity``, ``memorisation``) has a frozen config dataclass, a
``run_*(config, completers)`` that samples, measures and returns its rows (with whatever its report needs), and
a ``*_report(result)`` that turns the result into a :data:`Report`. :func:`write_report` writes any report. The
command line only turns arguments into configs.

The experiments use completers through :class:`Completer`: ``pssnet_core.inference.Completer`` and
``pssnet_core.sampling.CheckedSampler`` fit, and so do the tests' stand-ins.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np


class Completions(Protocol):
    """What a completer returns: ``occupancy``, (n, N, N, N) bool."""

    occupancy: np.ndarray


class Completer(Protocol):
    """What the experiments use of a completer.

    ``box_temperature`` (a factor on the posterior sigma of the box latent dims) is passed only to completers
    whose ``has_box_latent`` is true; the others are called without it.
    """

    @property
    def grid_size(self) -> int:
        """N of the (N, N, N) grids it completes."""

    @property
    def has_box_latent(self) -> bool:
        """Whether its model has a box part that a box temperature widens (PSSNet)."""

    def complete(self, observation: Any, num_samples: int = 20, seed: int = 0,
                 box_temperature: float | None = None) -> Completions:
        """``num_samples`` completions of ``observation`` (an evaluation view, with ``network_input()``)."""


def complete_view(completer: Completer, view: Any, num_samples: int, seed: int,
                  box_temperature: float | None = None) -> Completions:
    """The completer's result for ``view``; ``box_temperature`` reaches only completers with a box part."""
    if box_temperature is not None and completer.has_box_latent:
        return completer.complete(view, num_samples=num_samples, seed=seed, box_temperature=box_temperature)
    return completer.complete(view, num_samples=num_samples, seed=seed)


def sample_occupancy(completer: Completer, view: Any, num_samples: int, seed: int,
                     box_temperature: float | None = None) -> np.ndarray:
    """(n, N, N, N) bool completions of ``view`` (:func:`complete_view`'s occupancy)."""
    return np.asarray(complete_view(completer, view, num_samples, seed, box_temperature).occupancy, dtype=bool)


def write_csv(path: str | Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Writes dict rows as CSV (columns: union of keys, first row's order first)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys)
        writer.writeheader()
        for r in rows:
            writer.writerow(r)
    return path


def plain(value: Any) -> Any:
    """JSON-ready copy: numpy values as Python ones, tuples as lists, NaN/inf as None (standard JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def nanmean(values: Sequence[float]) -> float:
    """Mean of the finite values; NaN when there are none."""
    a = np.asarray(values, dtype=np.float64)
    return float(np.nanmean(a)) if len(a) and np.isfinite(a).any() else math.nan


@dataclass(frozen=True)
class Markdown:
    """A Markdown file."""

    name: str
    text: str

    def write(self, path: Path) -> Path:
        path.write_text(self.text)
        return path


@dataclass(frozen=True)
class Table:
    """A CSV file of dict rows (:func:`write_csv`)."""

    name: str
    rows: Sequence[Mapping[str, Any]]

    def write(self, path: Path) -> Path:
        return write_csv(path, self.rows)


@dataclass(frozen=True)
class Json:
    """A JSON file. ``strict``: values through :func:`plain`, NaN refused; otherwise ``json.dumps`` with
    ``default=str`` (objects JSON cannot hold become their string)."""

    name: str
    data: Any
    indent: int = 1
    strict: bool = True

    def write(self, path: Path) -> Path:
        if self.strict:
            text = json.dumps(plain(self.data), indent=self.indent, allow_nan=False)
        else:
            text = json.dumps(self.data, indent=self.indent, default=str)
        path.write_text(text)
        return path


@dataclass(frozen=True)
class Figure:
    """A figure: ``draw(path)`` writes it and returns the path, or None when there is nothing to draw."""

    name: str
    draw: Callable[[Path], Path | None]

    def write(self, path: Path) -> Path | None:
        return self.draw(path)


#: What an experiment writes: kind (the key of :func:`write_report`'s answer) -> file, in writing order.
Report = dict[str, Markdown | Table | Json | Figure]


def write_report(report: Report, out: str | Path) -> dict[str, Path]:
    """Writes every file of ``report`` into the folder ``out`` (created); returns the files written, by kind
    (a figure with nothing to draw is left out)."""
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    for key, entry in report.items():
        written = entry.write(folder / entry.name)
        if written is not None:
            files[key] = written
    return files


__all__ = ["Completer", "Completions", "Figure", "Json", "Markdown", "Report", "Table", "nanmean", "plain",
           "complete_view", "sample_occupancy", "write_csv", "write_report"]
