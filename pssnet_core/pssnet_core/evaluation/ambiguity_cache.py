"""The ambiguity measure's plausible sets on disk, and the test sets they are computed from.

The sets do not depend on the model: they are cached per test set (keyed by its content and by the parameters the
sets depend on, :meth:`AmbiguityMeasure.plausible_key`), so re-runs with other checkpoints only sample.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.data.store import write_json_atomically
from pssnet_core.evaluation.ambiguity_sets import (
    AmbiguityError,
    AmbiguityMeasure,
    HandleArc,
    MugParts,
    SlitRange,
    mug_parts,
    plausible_handle_arc,
    plausible_slit_range,
)
from pssnet_core.evaluation.experiment import nanmean
from pssnet_core.evaluation.observation_model import DepthView
from pssnet_core.evaluation.plausible import EvalView


def cache_path(cache_dir: str | Path, fingerprint: str, kind: str, measure: AmbiguityMeasure) -> Path:
    """Cache file of one test set's plausible sets of one kind ("handle_arcs" or "slit_ranges")."""
    payload = json.dumps({"data": fingerprint, "kind": kind, "config": measure.plausible_key()}, sort_keys=True)
    return Path(cache_dir) / f"{kind}_{hashlib.sha256(payload.encode()).hexdigest()[:24]}.json"


def load_cached(path: Path, kind: str) -> dict[int, HandleArc | SlitRange]:
    """Entries of a cache file by view index ({} when the file does not exist)."""
    if not path.exists():
        return {}
    cls = HandleArc if kind == "handle_arcs" else SlitRange
    try:
        return {int(k): cls.from_json(v) for k, v in json.loads(path.read_text())["views"].items()}
    except (OSError, KeyError, ValueError, TypeError) as error:
        raise AmbiguityError(f"ambiguity cache {path} is unreadable ({error}); delete it to recompute") from error


def save_cached(path: Path, entries: Mapping[int, HandleArc | SlitRange]) -> None:
    """Writes the entries of a cache file (atomically: a reader never sees half a file)."""
    write_json_atomically(path, {"views": {str(k): v.to_json() for k, v in sorted(entries.items())}})


class AmbiguityTestSet:
    """A test set's views, records and meshes (meshes made once per identity)."""

    def __init__(self, root: Path, progress: bool) -> None:
        from pssnet_core.data.store import DatasetReader
        from pssnet_core.evaluation.plausible import dataset_fingerprint
        from pssnet_core.evaluation.testsets import load_test_set

        self.root = root
        self.views, self.meta = load_test_set(root, progress=progress)
        self.records = DatasetReader(root).records
        self.fingerprint = dataset_fingerprint(root)
        self._shapes: dict[str, Any] = {}
        self._parts: dict[str, MugParts] = {}

    def shape(self, identity: str) -> Any:
        from pssnet_core.shapes import shape_of

        if identity not in self._shapes:
            self._shapes[identity] = shape_of(identity)
        return self._shapes[identity]

    def mug(self, identity: str) -> MugParts:
        if identity not in self._parts:
            self._parts[identity] = mug_parts(self.shape(identity))
        return self._parts[identity]

    def depth_view(self, view: EvalView, rerender: bool) -> DepthView:
        if not rerender:
            return view.depth_view
        from pssnet_core.data.datasets import rerender as render_again

        again = render_again(self.records[view.index], self.shape(view.identity))
        return DepthView(np.asarray(again.depth, dtype=np.float32), np.asarray(again.mask) != 0, again.intrinsics)


def cached_plausible(test: AmbiguityTestSet, views: list[EvalView], kind: str, measure: AmbiguityMeasure,
                     cache_dir: Path, progress: bool = True) -> tuple[dict[int, Any], dict[str, Any]]:
    """Plausible sets of one kind ("handle_arcs" or "slit_ranges") of ``views``, from the cache or computed (and
    then cached); returns them by view index, and cost figures."""
    from tqdm import tqdm

    path = cache_path(cache_dir, test.fingerprint, kind, measure)
    entries = load_cached(path, kind)
    missing = [v for v in views if v.index not in entries]
    t0 = time.perf_counter()
    for view in tqdm(missing, desc=f"plausible {kind}", unit="view", disable=not progress, dynamic_ncols=True):
        depth_view = test.depth_view(view, measure.rerender)
        if kind == "handle_arcs":
            entries[view.index] = plausible_handle_arc(view, depth_view, test.mug(view.identity), measure)
        else:
            mesh = test.shape(view.identity).mesh
            entries[view.index] = plausible_slit_range(view, depth_view, np.asarray(mesh.vertices),
                                                       np.asarray(mesh.faces), measure)
    if missing:
        save_cached(path, entries)
    wanted = {v.index: entries[v.index] for v in views}
    cost = {"views": len(views), "computed_now": len(missing), "cached": len(views) - len(missing),
            "seconds_now": time.perf_counter() - t0,
            "seconds_per_view": nanmean([e.seconds for e in wanted.values()]),
            "seconds_all_views": float(sum(e.seconds for e in wanted.values())), "cache": str(path)}
    return wanted, cost
