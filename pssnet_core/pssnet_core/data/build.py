"""Building datasets: shards as Ray tasks (:mod:`pssnet_core.ray_tasks`), resumable, deterministic.

The unit of work is a shard (``spec.objects_per_shard`` whole objects, so every object's mesh and
ray-casting scene is made once). A shard already on disk is skipped, so an interrupted build resumes
where it stopped; shards are written atomically by :func:`pssnet_core.data.store.write_shard`, by the task that
made them (on a cluster the output directory must be shared storage, at the same path on every node). Each task
uses one open3d thread, so ``--workers N`` uses about N cores. Every sample depends only on ``(spec, index)``,
so the result does not depend on the number of workers, on the nodes or on the order in which shards finish.

Layout: ``OUT/<split>/<name>/`` per dataset (``name``: mugs, ycb, ycb_narrow, ycb_wide, oof_mugs, oof_narrow,
oof_wide), each a dataset
directory of :mod:`pssnet_core.data.store` plus ``build_spec.json`` (the spec the shards were made with;
resuming with a different spec is refused).
"""

from __future__ import annotations

import json
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from pssnet_core.data.datasets import DatasetSpec, DatasetSpecError, dataset_specs, make_sample
from pssnet_core.data.scenes import ObjectScene
from pssnet_core.data.store import finalize, shard_exists, write_shard
from pssnet_core.ray_tasks import TaskRunner
from pssnet_core.shapes import shape_of
from pssnet_core.shapes.registry_objects import fetch_archives

SPEC_FILE = "build_spec.json"
FORMAT_VERSION = 1


@dataclass
class BuildResult:
    """Outcome of building one dataset."""

    spec: DatasetSpec
    path: Path
    samples: int
    shards_built: int
    shards_skipped: int
    seconds: float


def dataset_path(out: str | Path, spec: DatasetSpec) -> Path:
    """Directory of ``spec``'s dataset under a build root: ``OUT/<split>/<name>``."""
    return Path(out) / spec.split / spec.name


def build_shard(spec: DatasetSpec, root: str | Path, shard: int, threads: int = 1) -> int:
    """Makes and writes shard ``shard`` of ``spec`` under ``root``; returns its sample count."""
    samples: list[dict[str, Any]] = []
    identities = spec.object_identities()
    indices = spec.shard_range(shard)
    for obj in range(indices.start // spec.views, indices.stop // spec.views):
        identity = identities[obj]
        scene = ObjectScene(shape_of(identity), threads=threads)
        for index in range(obj * spec.views, (obj + 1) * spec.views):
            samples.append(make_sample(spec, index, scene))
    write_shard(root, shard, samples)
    return len(samples)


def _shard_task(shard: int, spec: DatasetSpec, root: str) -> int:
    return build_shard(spec, root, shard, threads=1)


def _check_spec_file(root: Path, spec: DatasetSpec) -> None:
    path = root / SPEC_FILE
    wanted = json.loads(json.dumps({"format": FORMAT_VERSION, "spec": spec.to_dict()}))  # tuples -> lists
    if path.exists():
        try:
            found = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise DatasetSpecError(f"{path} is corrupt ({error}); delete {root} and build again") from error
        if isinstance(found, dict) and isinstance(found.get("spec"), dict):
            # Specs written before a field existed lack it: read them with that field's default.
            try:
                found["spec"] = json.loads(json.dumps(DatasetSpec.from_dict(found["spec"]).to_dict()))
            except (TypeError, DatasetSpecError):
                pass  # a spec this code cannot read differs from the request; refused below
        if found != wanted:
            raise DatasetSpecError(
                f"{root} holds shards of a different build ({SPEC_FILE} differs from this request); "
                "use another --out or delete that directory")
    else:
        root.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(wanted, indent=1))


def dataset_meta(spec: DatasetSpec) -> dict[str, Any]:
    """The ``meta`` block written to a dataset's index."""
    meta: dict[str, Any] = {
        "name": spec.name, "family": "mugs" if spec.is_mugs else "ycb", "split": spec.split,
        "grid_size": spec.grid_size, "voxel_size": spec.grid_config.voxel_size, "extent_m": spec.grid_config.extent,
        "grid_config": asdict(spec.grid_config),
        "seed": spec.seed, "num_objects": spec.num_objects, "views": spec.views,
        "num_samples": spec.num_samples, "slit_mode": spec.slit_mode, "slit_width_m": spec.slit_width_m,
        "noise": spec.noise is not None, "format": FORMAT_VERSION, "spec": spec.to_dict(),
        "counts": {"samples": spec.num_samples, "objects": spec.num_objects,
                   "families": dict(Counter(i.family for i in spec.object_identities()))},
    }
    return meta


def build_dataset(spec: DatasetSpec, root: str | Path, runner: TaskRunner | None = None,
                  progress: bool = True) -> BuildResult:
    """Builds (or resumes) one dataset in directory ``root`` and writes its index.

    Args:
        spec: what to build.
        root: the dataset directory (created).
        runner: where the shards are made (default: in this process).
        progress: show a tqdm progress bar (per finished shard).

    Raises:
        DatasetSpecError: ``root`` holds shards of a different spec.
    """
    root = Path(root)
    _check_spec_file(root, spec)
    start = time.perf_counter()
    todo = [s for s in range(spec.num_shards) if not shard_exists(root, s)]
    runner = runner or TaskRunner()  # the default runs in this process: nothing to close
    shared = {"spec": spec, "root": str(root.resolve())}  # tasks on other nodes write there: an absolute path
    for _ in runner.map(_shard_task, todo, shared, desc=f"{spec.split}/{spec.name}", unit_name="shard",
                        done=spec.num_shards - len(todo), progress=progress):
        pass
    count = finalize(root, dataset_meta(spec))
    if count != spec.num_samples:
        raise DatasetSpecError(f"{root} holds {count} samples, expected {spec.num_samples}; delete it and rebuild")
    return BuildResult(spec=spec, path=root, samples=count, shards_built=len(todo),
                       shards_skipped=spec.num_shards - len(todo), seconds=time.perf_counter() - start)


def build(family: str, split: str, out: str | Path, grid_size: int = 32, runner: TaskRunner | None = None,
          seed: int = 0, num_objects: int | None = None, views: int | None = None, noise: Any = None,
          front_margin: float | None = None, bottom_margin: float | None = None,
          progress: bool = True, scale: str = "default", slit_fraction: float | None = None) -> list[BuildResult]:
    """Builds every dataset of ``family`` ("mugs", "ycb", "all", "oof") and ``split`` under ``out``.

    See :func:`pssnet_core.data.datasets.dataset_specs` for the datasets and their defaults, and
    :func:`dataset_path` for where each goes. ``runner`` makes the shards (default: in this process).
    """
    specs = dataset_specs(family, split, grid_size=grid_size, seed=seed, num_objects=num_objects, views=views,
                          noise=noise, front_margin=front_margin, bottom_margin=bottom_margin, scale=scale,
                          slit_fraction=slit_fraction)
    fetch_archives(i for spec in specs for i in spec.object_identities())  # real objects: download before the tasks
    return [build_dataset(spec, dataset_path(out, spec), runner=runner, progress=progress) for spec in specs]
