"""Dataset storage: compressed numpy shards plus a JSON index.

Why this format: it needs nothing beyond numpy (training also runs on machines without open3d or
trimesh), zip-deflate shrinks the sparse, bit-packed voxel grids well, and every shard loads on its own,
so a training loop streams a dataset shard by shard without holding it in memory. Shards are written
atomically (temporary file, then rename) and named by their number, so a build that was interrupted
resumes by skipping shards already on disk, and workers in separate processes each write their own.

Layout of a dataset directory::

    index.json                  meta (grid size, voxel size, family, split, ...), shard list, per-sample records
    shards/00000.npz            voxel grids (bit packed), boxes, other same-shape arrays, records of the shard
    shards/00000.images.npz     depth/mask crops and other variable-shape arrays (not read by training)
    twins/                      optional turned twins of the mug views (:mod:`pssnet_core.data.twins`):
    twins/00000.npz             per sample K (occupancy, box) targets of the same mug turned about its axis
    twins/twins.json            written when every shard has its twins file: only then does training read them

A sample is a dict: numpy arrays (grids, box, images) and plain JSON values (identity, flags, poses).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

GRID_KEYS: tuple[str, ...] = ("known_occupied", "known_free", "occupancy")
TRAINING_KEYS: tuple[str, ...] = (*GRID_KEYS, "box")
#: one turned twin per sample (its own occupancy and box where it has none); see :meth:`DatasetReader.load_shard`
TWIN_KEYS: tuple[str, ...] = ("twin_occupancy", "twin_box")
INDEX_FILE = "index.json"
SHARD_DIR = "shards"
TWIN_DIR = "twins"
TWIN_INDEX = "twins.json"  # not index.json: a dataset directory is one that holds an index.json


class DatasetError(ValueError):
    """A dataset directory is missing, incomplete or inconsistent."""


def _shard_paths(root: Path, shard_id: int) -> tuple[Path, Path]:
    base = root / SHARD_DIR / f"{shard_id:05d}"
    return base.with_suffix(".npz"), Path(f"{base}.images.npz")


def write_npz_atomically(path: str | Path, arrays: dict[str, np.ndarray], compressed: bool = True) -> None:
    """Writes ``arrays`` to ``path`` (.npz, its folder made if needed) through a temporary file of this process's
    own and a rename, so that a reader never sees half a file and processes writing the same file (parallel runs
    sharing a cache) never take each other's temporary file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as handle:
        (np.savez_compressed if compressed else np.savez)(handle, **arrays)
    os.replace(tmp, path)


def write_json_atomically(path: str | Path, data: Any) -> None:
    """Writes ``data`` as JSON to ``path`` (its folder made if needed) through a temporary file and a rename, so
    that a reader never sees half a file and an interrupted write leaves the old one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def twins_path(root: str | Path, shard_id: int) -> Path:
    """The twins file of shard ``shard_id``."""
    return Path(root) / TWIN_DIR / f"{shard_id:05d}.npz"


def has_twins(root: str | Path) -> bool:
    """True when the dataset directory ``root`` holds a finished twins build (its twins index)."""
    return (Path(root) / TWIN_DIR / TWIN_INDEX).exists()


def shard_exists(root: str | Path, shard_id: int) -> bool:
    """True when shard ``shard_id`` is completely written (used to resume a build)."""
    grids, images = _shard_paths(Path(root), shard_id)
    return grids.exists() and images.exists()


def write_shard(root: str | Path, shard_id: int, samples: Sequence[dict[str, Any]]) -> None:
    """Writes one shard atomically.

    Boolean (N, N, N) arrays in GRID_KEYS are bit packed. Other arrays whose shape is the same for every
    sample are stacked into the grid file; arrays whose shape varies (image crops) go to the images file
    as one flat array plus shapes. Non-array values are stored as JSON records.
    """
    if not samples:
        raise DatasetError(f"shard {shard_id} has no samples")
    root = Path(root)
    (root / SHARD_DIR).mkdir(parents=True, exist_ok=True)
    grids_path, images_path = _shard_paths(root, shard_id)
    array_keys = sorted(k for k, v in samples[0].items() if isinstance(v, np.ndarray))
    records = [{k: v for k, v in s.items() if not isinstance(v, np.ndarray)} for s in samples]
    main: dict[str, np.ndarray] = {"records": np.array(json.dumps(records))}
    side: dict[str, np.ndarray] = {}
    for key in array_keys:
        values = [s[key] for s in samples]
        if any(not isinstance(v, np.ndarray) for v in values):
            raise DatasetError(f"key {key!r} is an array in some samples of shard {shard_id} but not in others")
        if key in GRID_KEYS:
            shape = values[0].shape
            if any(v.shape != shape or v.dtype != bool for v in values):
                raise DatasetError(f"grid {key!r} must be bool of one shape within a shard")
            main[key] = np.stack([np.packbits(v.reshape(-1)) for v in values])
            main[f"{key}__shape"] = np.array(shape, dtype=np.int64)
        elif all(v.shape == values[0].shape for v in values) and values[0].size <= 4096:
            main[key] = np.stack(values)
        else:
            side[key] = np.concatenate([v.reshape(-1) for v in values])
            side[f"{key}__shapes"] = np.array([v.shape for v in values], dtype=np.int64)
    # The images file is written first, so a grid file on disk always has its images beside it.
    write_npz_atomically(images_path, side)
    write_npz_atomically(grids_path, main)


def read_shard_records(root: str | Path, shard_id: int) -> list[dict[str, Any]]:
    """The records of one shard, read from the shard itself (not from the dataset's index, which may be large)."""
    grids_path, _ = _shard_paths(Path(root), shard_id)
    try:
        with np.load(grids_path) as data:
            return json.loads(str(data["records"]))
    except (OSError, ValueError, KeyError) as error:
        raise DatasetError(f"shard {grids_path} is unreadable: {error}") from error


@dataclass(frozen=True)
class SampleTwins:
    """The turned twins of one sample (:mod:`pssnet_core.data.twins`).

    Attributes:
        occupancy: (K, N, N, N) bool, each twin's ground truth in the sample's grid.
        box: (K, 24) float32, each twin's box in grid coordinates.
        azimuth_deg: (K,), how far each twin is turned about the mug's axis.
    """

    occupancy: np.ndarray
    box: np.ndarray
    azimuth_deg: np.ndarray


def write_twins(root: str | Path, shard_id: int, twins: Sequence[SampleTwins | None], per_view: int,
                grid_size: int) -> None:
    """Writes the twins file of one shard atomically: one entry per sample of the shard, in its order.

    Layout: ``occupancy`` (count, K, N^3 / 8) bit packed, ``box`` (count, K, 24) float32, ``azimuth_deg``
    (count, K) and ``has_twins`` (count,) bool; rows of samples without twins (None) are zeros, never read.
    """
    shape = (grid_size,) * 3
    count = len(twins)
    packed = np.zeros((count, per_view, (grid_size**3 + 7) // 8), dtype=np.uint8)
    box = np.zeros((count, per_view, 24), dtype=np.float32)
    azimuth = np.zeros((count, per_view), dtype=np.float32)
    for row, sample in enumerate(twins):
        if sample is None:
            continue
        if sample.occupancy.shape != (per_view, *shape) or sample.occupancy.dtype != bool \
                or sample.box.shape != (per_view, 24) or sample.azimuth_deg.shape != (per_view,):
            raise DatasetError(f"twins of sample {row} of shard {shard_id}: expected {per_view} bool {shape} grids, "
                               f"boxes and azimuths, got {sample.occupancy.shape} ({sample.occupancy.dtype}), "
                               f"{sample.box.shape}, {sample.azimuth_deg.shape}")
        packed[row] = np.packbits(sample.occupancy.reshape(per_view, -1), axis=1)
        box[row] = sample.box
        azimuth[row] = sample.azimuth_deg
    write_npz_atomically(twins_path(root, shard_id), {
        "occupancy": packed, "occupancy__shape": np.array(shape, dtype=np.int64), "box": box, "azimuth_deg": azimuth,
        "has_twins": np.array([t is not None for t in twins], dtype=bool)})


def finalize(root: str | Path, meta: dict[str, Any]) -> int:
    """Scans the shards on disk and writes index.json; returns the number of samples.

    Shards must be numbered 0..K-1 without gaps, so an incomplete build is refused rather than indexed.
    """
    root = Path(root)
    shard_files = sorted((root / SHARD_DIR).glob("[0-9][0-9][0-9][0-9][0-9].npz"))
    shards, records = [], []
    for expected, path in enumerate(shard_files):
        shard_id = int(path.stem)
        if shard_id != expected:
            raise DatasetError(f"shard {expected:05d} is missing in {root / SHARD_DIR}; finish the build first")
        with np.load(path) as data:
            shard_records = json.loads(str(data["records"]))
        shards.append({"id": shard_id, "first": len(records), "count": len(shard_records)})
        records.extend(shard_records)
    if not records:
        raise DatasetError(f"no shards found in {root / SHARD_DIR}")
    index = {"meta": meta, "num_samples": len(records), "shards": shards, "records": records}
    write_json_atomically(root / INDEX_FILE, index)
    return len(records)


def _split_roots(root: str | Path | Sequence[str | Path]) -> list[str | Path]:
    if isinstance(root, Path):
        return [root]
    if isinstance(root, str):
        return [part.strip() for part in root.split(",") if part.strip()]
    return list(root)


def _read_index(root: Path) -> dict[str, Any]:
    index_path = root / INDEX_FILE
    if not index_path.exists():
        raise DatasetError(f"{root} is not a dataset: {INDEX_FILE} is missing (build it with "
                           "`pssnet dataset build`)")
    try:
        return json.loads(index_path.read_text())
    except json.JSONDecodeError as error:
        raise DatasetError(f"{index_path} is corrupt: {error}") from error


class DatasetReader:
    """Reads a dataset directory written by :func:`write_shard` + :func:`finalize`.

    ``root`` may also be several dataset directories (a sequence, or one string of paths joined by commas):
    they are read as one dataset, their samples numbered in the order given (e.g. mugs then ycb, to train one
    model on all families). They must share grid size and voxel size; ``meta`` is the first one's. Directories
    with turned twins (:mod:`pssnet_core.data.twins`) and without may be read together: see :meth:`load_shard`.
    """

    def __init__(self, root: str | Path | Sequence[str | Path]) -> None:
        roots = [Path(r) for r in _split_roots(root)]
        if not roots:
            raise DatasetError("no dataset directory given")
        self.roots = roots
        self.root = roots[0]
        self.records: list[dict[str, Any]] = []
        self._shards: list[dict[str, Any]] = []  # id, first (global sample number), count, root
        for path in roots:
            index = _read_index(path)
            if not self._shards:
                self.meta: dict[str, Any] = index["meta"]
            else:
                for key in ("grid_size", "voxel_size"):
                    if index["meta"].get(key) != self.meta.get(key):
                        raise DatasetError(f"{path} has {key} {index['meta'].get(key)}, but {self.root} has "
                                           f"{self.meta.get(key)}: datasets read together must match")
            offset = len(self.records)
            twins = has_twins(path)
            self._shards.extend({**s, "first": s["first"] + offset, "root": path, "twins": twins}
                                for s in index["shards"])
            self.records.extend(index["records"])
        self._cache: tuple[tuple[int, bool], dict[str, np.ndarray]] | None = None

    def __len__(self) -> int:
        return len(self.records)

    @property
    def grid_size(self) -> int:
        return int(self.meta["grid_size"])

    @property
    def voxel_size(self) -> float:
        return float(self.meta["voxel_size"])

    @property
    def num_shards(self) -> int:
        return len(self._shards)

    @property
    def has_twins(self) -> bool:
        """True when at least one of the dataset directories holds turned twins."""
        return any(s["twins"] for s in self._shards)

    def load_shard(self, shard: int, keys: Sequence[str] | None = None, images: bool = False,
                   twin_seed: int = 0) -> dict[str, np.ndarray]:
        """Arrays of one shard, grids unpacked to bool (B, N, N, N); ``keys`` limits what is decoded.

        Variable-shape arrays (with ``images=True``) come back as object arrays of per-sample arrays.
        The :data:`TWIN_KEYS` come only when asked for: each sample gets one of its turned twins, drawn by
        ``twin_seed`` and the shard, or its own occupancy and box when it has none (no handle, not a mug, a
        directory without twins).
        """
        wanted_twins = [k for k in TWIN_KEYS if keys is not None and k in keys]
        if keys is not None and wanted_twins:
            own = [k for k in keys if k not in TWIN_KEYS]
            arrays = self.load_shard(shard, [*own, *(k for k in ("occupancy", "box") if k not in own)], images)
            twins = self._choose_twins(shard, arrays["occupancy"], arrays["box"], twin_seed)
            return {**{k: arrays[k] for k in own}, **{k: twins[k] for k in wanted_twins}}
        grids_path, images_path = _shard_paths(self._shards[shard]["root"], self._shards[shard]["id"])
        out: dict[str, np.ndarray] = {}
        try:
            with np.load(grids_path) as data:
                names = [n for n in data.files if n != "records" and not n.endswith("__shape")]
                for name in names if keys is None else [k for k in keys if k in names]:
                    if name in GRID_KEYS:
                        shape = tuple(data[f"{name}__shape"])
                        count = int(np.prod(shape))
                        packed = data[name]
                        out[name] = np.unpackbits(packed, axis=1, count=count).astype(bool).reshape(
                            (len(packed), *shape))
                    else:
                        out[name] = data[name]
            if images:
                with np.load(images_path) as data:
                    for name in [n for n in data.files if not n.endswith("__shapes")]:
                        if keys is not None and name not in keys:
                            continue
                        shapes = data[f"{name}__shapes"]
                        flat = data[name]
                        sizes = np.prod(shapes, axis=1)
                        parts = np.split(flat, np.cumsum(sizes)[:-1])
                        column = np.empty(len(parts), dtype=object)
                        for i, (part, shape) in enumerate(zip(parts, shapes, strict=True)):
                            column[i] = part.reshape(shape)
                        out[name] = column
        except (OSError, ValueError, KeyError) as error:
            raise DatasetError(f"shard {grids_path} is unreadable: {error}") from error
        if keys is not None and (missing := [k for k in keys if k not in out]):
            raise DatasetError(f"shard {grids_path} has no arrays named {missing}")
        return out

    def _choose_twins(self, shard: int, occupancy: np.ndarray, box: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        """One twin per sample of ``shard`` (see :meth:`load_shard`); ``occupancy`` and ``box`` are its own."""
        info = self._shards[shard]
        twin_occupancy, twin_box = occupancy.copy(), np.asarray(box, dtype=np.float32).copy()
        if info["twins"]:
            path = twins_path(info["root"], info["id"])
            try:
                with np.load(path) as data:
                    packed, boxes, has = data["occupancy"], data["box"], data["has_twins"]
                    shape = tuple(int(n) for n in data["occupancy__shape"])
            except (OSError, ValueError, KeyError) as error:
                raise DatasetError(f"twins file {path} is missing or unreadable: {error}") from error
            if len(has) != len(occupancy) or shape != occupancy.shape[1:]:
                raise DatasetError(f"twins file {path} does not match its shard ({len(has)} samples of grid "
                                   f"{shape}, the shard has {len(occupancy)} of {occupancy.shape[1:]}); "
                                   "build the twins again")
            # Seeded by the shard's first sample number too, so that the shards of one epoch draw differently.
            choice = np.random.default_rng([seed, info["first"]]).integers(packed.shape[1], size=len(has))
            rows = np.flatnonzero(has)
            chosen = packed[rows, choice[rows]]
            twin_occupancy[rows] = np.unpackbits(chosen, axis=1, count=int(np.prod(shape))).astype(bool).reshape(
                (len(rows), *shape))
            twin_box[rows] = boxes[rows, choice[rows]]
        return {"twin_occupancy": twin_occupancy, "twin_box": twin_box}

    def get(self, index: int, images: bool = True) -> dict[str, Any]:
        """One whole sample: its arrays (grids unpacked, image crops) and its record."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} out of range for a dataset of {len(self)}")
        shard = next(i for i, s in enumerate(self._shards) if s["first"] <= index < s["first"] + s["count"])
        if self._cache is None or self._cache[0] != (shard, images):
            self._cache = ((shard, images), self.load_shard(shard, images=images))
        arrays = self._cache[1]
        offset = index - self._shards[shard]["first"]
        sample: dict[str, Any] = dict(self.records[index])
        sample.update({k: v[offset] for k, v in arrays.items()})
        return sample

    def iter_batches(self, batch_size: int, shuffle: bool = True, seed: int = 0, drop_last: bool = False,
                     keys: Sequence[str] | None = TRAINING_KEYS,
                     indices: Sequence[int] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Streams batches of arrays (plus "index", the sample numbers), one shard in memory at a time.

        With ``shuffle``, shard order and sample order within a two-shard window are shuffled by ``seed``:
        mixing across neighbouring shards without loading the dataset. ``indices`` restricts to a subset.
        """
        if batch_size < 1:
            raise DatasetError(f"batch_size must be positive, got {batch_size}")
        rng = np.random.default_rng(seed)
        wanted = None if indices is None else np.zeros(len(self), dtype=bool)
        if wanted is not None:
            wanted[np.asarray(indices, dtype=np.int64)] = True
        order = rng.permutation(self.num_shards) if shuffle else np.arange(self.num_shards)
        pending: dict[str, list[np.ndarray]] = {}
        pending_count = 0
        window: list[dict[str, np.ndarray]] = []

        def emit(parts: list[dict[str, np.ndarray]]) -> Iterator[dict[str, np.ndarray]]:
            nonlocal pending, pending_count
            merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            if shuffle:
                perm = rng.permutation(len(merged["index"]))
                merged = {k: v[perm] for k, v in merged.items()}
            for k, v in merged.items():
                pending.setdefault(k, []).append(v)
            pending_count += len(merged["index"])
            while pending_count >= batch_size:
                joined = {k: np.concatenate(v) for k, v in pending.items()}
                yield {k: v[:batch_size] for k, v in joined.items()}
                pending = {k: [v[batch_size:]] for k, v in joined.items()}
                pending_count -= batch_size

        for shard in order:
            arrays = self.load_shard(int(shard), keys=keys, twin_seed=seed)
            first = self._shards[int(shard)]["first"]
            arrays["index"] = np.arange(first, first + self._shards[int(shard)]["count"], dtype=np.int64)
            if wanted is not None:
                keep = wanted[arrays["index"]]
                arrays = {k: v[keep] for k, v in arrays.items()}
            window.append(arrays)
            if len(window) == 2:
                yield from emit(window)
                window = []
        if window:
            yield from emit(window)
        if pending_count and not drop_last:
            yield {k: np.concatenate(v) for k, v in pending.items()}
