"""Turned twins: the mug of a view, in the view's grid, turned about its own axis so that its handle lies elsewhere.

Why: PSSNet's decoder gets ``[box code | rest of the latent]``, and in training both always describe the same view,
so the decoder learnt to read the handle from both. Measured (``scripts/box_code_diagnosis.py``): when the box
code puts a hidden handle away from straight behind the mug, the decoder draws it only 21-43 % of the time with the
rest at the posterior mean, but 98-100 % of the time with the rest at half the mean or at 0: the rest vetoes handles
at the edges of what the view allows. A twin is an extra (box, target) pair of the same view whose box code and
grid disagree with the rest of the latent; ``pssnet train --twin-rate P`` decodes a share P of each batch from a
twin's box code (the rest still from the view) against the twin's grid, so the decoder must follow the box code.

A twin of sample ``index``: the object pose turned about the mug's own z axis, ``object_pose @ Rz(a)`` (the mug
frame's z is the body's axis through the origin and the handle points along +x;
:func:`pssnet_core.evaluation.handles.turned`), with ``a`` uniform in [-180, 180) degrees, ``per_view`` of them drawn
by ``(seed, index)``. Its occupancy and box are made exactly as :func:`~pssnet_core.data.datasets.make_sample` makes
the sample's, in the sample's grid pose and camera. Only mugs with a handle and a round body get twins: a square
or elliptic body would turn with the handle and no longer fit the view. Other samples, and datasets of other
families, get none; training reads their own occupancy and box instead (:meth:`DatasetReader.load_shard`).

Cost (measured on the 2-core development machine, one worker, the machine busy; 4 mugs x 8 views x 4 twins): 9 ms
per twin at 32^3 (the ground truth is 7.5-8 ms of it; box, records and the object's scene are the rest) and 37 ms
at 64^3; stored, 0.2 kB per twin at 32^3 and 0.75 kB at 64^3. So the ~70,000 mug views with a round body and a
handle of ``--scale large`` x 4 twins take about 45 core-minutes (``--workers`` divides that) and ~60 MB.

Layout: ``DIR/twins/NNNNN.npz`` per shard (:func:`pssnet_core.data.store.write_twins`), ``twins/spec.json`` (the
request; resuming with another is refused) and ``twins/twins.json`` (counts), written last: a directory without it
has no twins for training, so an interrupted build is never half used. Shards whose twins file exists are skipped,
so running the same command again resumes.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.data.scenes import ObjectScene, box_in_grid
from pssnet_core.data.store import (
    TWIN_DIR,
    TWIN_INDEX,
    DatasetError,
    DatasetReader,
    SampleTwins,
    read_shard_records,
    twins_path,
    write_json_atomically,
    write_twins,
)
from pssnet_core.evaluation.handles import turned
from pssnet_core.geometry import GridPose
from pssnet_core.ray_tasks import TaskRunner
from pssnet_core.shapes import Shape, shape_of

SPEC_FILE = "spec.json"
FORMAT_VERSION = 1


@dataclass
class TwinsResult:
    """Outcome of building one dataset's twins (``shards_built`` = 0 and no directory for a dataset without mugs)."""

    path: Path
    samples: int
    samples_with_twins: int
    per_view: int
    shards_built: int
    shards_skipped: int
    seconds: float


def can_turn(shape: Shape) -> bool:
    """A mug with a handle and a round body: turned about its axis, only the handle moves."""
    attributes = shape.attributes
    return (shape.handle is not None and not attributes.get("square_body")
            and attributes.get("stretch_x", 1.0) == attributes.get("stretch_y", 1.0))


def twin_azimuths(seed: int, index: int, per_view: int) -> np.ndarray:
    """The ``per_view`` turns (degrees, uniform in [-180, 180)) of sample ``index``'s twins."""
    return np.random.default_rng([seed, index]).uniform(-180.0, 180.0, per_view)


def make_twins(record: dict[str, Any], scene: ObjectScene, azimuths: np.ndarray) -> SampleTwins:
    """The twins of one stored sample (its record) at ``azimuths``; ``scene`` must hold the sample's object."""
    pose = np.asarray(record["object_pose"], dtype=np.float64)
    camera = np.asarray(record["camera_pose"], dtype=np.float64)
    grid_pose = GridPose.from_dict(record["grid_pose"])
    poses = [turned(pose, a) for a in azimuths]  # the turn is in the object frame: any parent frame will do
    return SampleTwins(occupancy=np.stack([scene.ground_truth(p, grid_pose, camera) for p in poses]),
                       box=np.stack([box_in_grid(scene.shape, p, grid_pose, camera) for p in poses]),
                       azimuth_deg=np.asarray(azimuths, dtype=np.float32))


def build_twin_shard(root: str | Path, shard_id: int, per_view: int, seed: int, threads: int = 1) -> int:
    """Makes and writes the twins file of shard ``shard_id`` of the dataset in ``root``; returns how many of its
    samples have twins."""
    records = read_shard_records(root, shard_id)
    scenes: dict[str, ObjectScene | None] = {}  # by identity: a shard holds whole objects, each scene made once
    twins: list[SampleTwins | None] = []
    for record in records:
        identity = record["identity"]
        if record.get("has_handle") and identity not in scenes:
            shape = shape_of(identity)
            scenes[identity] = ObjectScene(shape, threads=threads) if can_turn(shape) else None
        scene = scenes.get(identity)
        twins.append(None if scene is None else
                     make_twins(record, scene, twin_azimuths(seed, int(record["index"]), per_view)))
    write_twins(root, shard_id, twins, per_view, int(records[0]["grid_pose"]["size"]))
    return sum(t is not None for t in twins)


def _shard_task(shard_id: int, root: str, per_view: int, seed: int) -> int:
    return build_twin_shard(root, shard_id, per_view, seed, threads=1)


def _check_spec(directory: Path, spec: dict[str, Any]) -> None:
    path = directory / SPEC_FILE
    if path.exists():
        try:
            found = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise DatasetError(f"{path} is corrupt ({error}); delete {directory} and build the twins again") from error
        if found != spec:
            raise DatasetError(f"{directory} holds twins of another request ({found}, asked for {spec}): use the "
                               "same --per-view and --seed, or delete that directory")
    else:
        directory.mkdir(parents=True, exist_ok=True)
        write_json_atomically(path, spec)


def build_twins(root: str | Path, per_view: int = 4, seed: int = 0, runner: TaskRunner | None = None,
                progress: bool = True) -> TwinsResult:
    """Builds (or resumes) the twins of the dataset directory ``root`` (see the module docstring).

    Args:
        root: a dataset directory written by ``pssnet dataset build``.
        per_view: twins per sample with a handle.
        seed: seeds the turns.
        runner: where the shards are made (default: in this process).
        progress: show a tqdm progress bar (per finished shard).

    Raises:
        DatasetError: ``root`` is no dataset, or holds twins of another ``per_view`` or ``seed``.
    """
    if per_view < 1:
        raise DatasetError(f"per_view must be >= 1, got {per_view}")
    root = Path(root)
    start = time.perf_counter()
    reader = DatasetReader(root)
    if reader.meta.get("family") != "mugs":
        return TwinsResult(path=root, samples=len(reader), samples_with_twins=0, per_view=per_view, shards_built=0,
                           shards_skipped=0, seconds=time.perf_counter() - start)
    directory = root / TWIN_DIR
    spec = {"format": FORMAT_VERSION, "per_view": per_view, "seed": seed}
    _check_spec(directory, spec)
    shard_ids = list(range(reader.num_shards))  # finalize() numbers a dataset's shards 0..K-1
    todo = [s for s in shard_ids if not twins_path(root, s).exists()]
    runner = runner or TaskRunner()  # the default runs in this process: nothing to close
    shared = {"root": str(root.resolve()), "per_view": per_view, "seed": seed}  # tasks elsewhere write there
    for _ in runner.map(_shard_task, todo, shared, desc=f"twins {root.parent.name}/{root.name}", unit_name="shard",
                        done=len(shard_ids) - len(todo), progress=progress):
        pass
    with_twins = 0
    for shard_id in shard_ids:
        with np.load(twins_path(root, shard_id)) as data:
            with_twins += int(data["has_twins"].sum())
    index = {**spec, "samples": len(reader), "samples_with_twins": with_twins, "twins": with_twins * per_view,
             "shards": len(shard_ids)}
    index_path = directory / TWIN_INDEX
    if not index_path.exists() or json.loads(index_path.read_text()) != index:
        write_json_atomically(index_path, index)
    return TwinsResult(path=root, samples=len(reader), samples_with_twins=with_twins, per_view=per_view,
                       shards_built=len(todo), shards_skipped=len(shard_ids) - len(todo),
                       seconds=time.perf_counter() - start)
