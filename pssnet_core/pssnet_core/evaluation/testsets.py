"""Test sets for the evaluation: EvalViews from dataset directories or from freshly rendered views."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.observation_model import DepthView
from pssnet_core.evaluation.plausible import EvalView, PlausibleSetError
from pssnet_core.geometry import CameraIntrinsics, GridConfig, GridPose

#: test-set names of the paper's experiments, as the data module names its test directories
PAPER_TEST_SETS: tuple[str, ...] = ("mugs", "ycb_narrow", "ycb_wide")
#: the out-of-family test sets (objects of the independent generator and real modelled ones), the same experiments,
#: and the mugs seen through the narrow slit (the shipped model's training data shows no mug behind a slit)
OOF_TEST_SETS: tuple[str, ...] = ("oof_mugs", "oof_mugs_narrow", "oof_narrow", "oof_wide")
#: this project's test mugs' views through the narrow slit (built with ``mugs``)
MUGS_NARROW = "mugs_narrow"
#: every test set the evaluation knows
TEST_SETS: tuple[str, ...] = PAPER_TEST_SETS + (MUGS_NARROW,) + OOF_TEST_SETS
#: test sets of the mug experiment (yaw steps; hidden and visible handles)
MUG_SETS: tuple[str, ...] = ("mugs", MUGS_NARROW, "oof_mugs", "oof_mugs_narrow")
#: test sets behind the narrow slit (the hidden extent of boxes)
NARROW_SETS: tuple[str, ...] = ("ycb_narrow", "oof_narrow")


def build_command(name: str) -> str:
    """The command that builds test set ``name``."""
    family = "oof" if name in OOF_TEST_SETS else "mugs" if name in MUG_SETS else "ycb"
    return f"pssnet dataset build --family {family} --split test"


def camera_from_object(camera_pose: np.ndarray, object_pose: np.ndarray) -> np.ndarray:
    """(4, 4) camera <- object from world <- camera and world <- object."""
    return np.linalg.inv(np.asarray(camera_pose, dtype=np.float64)) @ np.asarray(object_pose, dtype=np.float64)


def eval_view_from_render(index: int, identity: str, view: Any, grid: GridConfig, crop: bool = True,
                          meta: dict[str, Any] | None = None) -> EvalView:
    """An EvalView from a ``pssnet_core.data.scenes.RenderedView`` (observes it with ``grid``).

    With ``crop`` the depth and mask are cut to the data module's crop window (what datasets store).
    """
    from pssnet_core.data.scenes import crop_window

    obs = view.observe(grid)
    depth, mask, offset = view.depth, view.mask, (0, 0)
    if crop:
        v0, u0, v1, u1 = crop_window(view, obs.pose)
        depth, mask, offset = depth[v0:v1, u0:u1], mask[v0:v1, u0:u1], (u0, v0)
    record = {"handle_visible": view.handle_visible} if view.handle_visible is not None else {}
    record.update(meta or {})
    return EvalView(index=index, identity=identity,
                    depth_view=DepthView(np.asarray(depth, dtype=np.float32), np.asarray(mask) != 0,
                                         view.intrinsics, offset),
                    object_pose=camera_from_object(view.camera_pose, view.object_pose), grid_pose=obs.pose,
                    known_occupied=obs.known_occupied, known_free=obs.known_free, meta=record)


def _first(record: dict[str, Any], keys: Sequence[str], what: str, index: int) -> Any:
    for key in keys:
        if key in record and record[key] is not None:
            return record[key]
    raise PlausibleSetError(f"sample {index} has no {what} (looked for {list(keys)})")


def find_test_set(data: str | Path, name: str) -> Path | None:
    """The directory of test set ``name`` under ``data`` (``data/name``, ``data/test/name``, or ``data`` itself)."""
    data = Path(data)
    for candidate in (data / name, data / "test" / name):
        if (candidate / "index.json").exists():
            return candidate
    if (data / "index.json").exists() and data.name == name:
        return data
    return None


def load_test_set(root: str | Path, progress: bool = False) -> tuple[list[EvalView], dict[str, Any]]:
    """EvalViews of a test dataset directory written by the data module.

    Args:
        root: a dataset directory (index.json + shards).
        progress: tqdm bar over shards.

    Returns:
        (views in index order, the dataset's meta).
    """
    from tqdm import tqdm

    from pssnet_core.data.store import DatasetReader

    reader = DatasetReader(root)
    views: list[EvalView] = []
    for shard in tqdm(range(reader.num_shards), desc=f"load {Path(root).name}", disable=not progress):
        arrays = reader.load_shard(shard, images=True)
        first = reader._shards[shard]["first"]  # noqa: SLF001 (the reader has no public per-shard offset)
        count = reader._shards[shard]["count"]  # noqa: SLF001
        for offset in range(count):
            k = first + offset
            record = reader.records[k]
            views.append(_view_from_sample(k, record, {name: arr[offset] for name, arr in arrays.items()}))
    return views, reader.meta


def _view_from_sample(k: int, record: dict[str, Any], arrays: dict[str, np.ndarray]) -> EvalView:
    intr = _first(record, ("intrinsics",), "intrinsics", k)
    if isinstance(intr, dict):
        intrinsics = CameraIntrinsics(**{f: intr[f] for f in ("width", "height", "fx", "fy", "cx", "cy")})
    else:
        raise PlausibleSetError(f"sample {k}: intrinsics must be a dict, got {type(intr).__name__}")
    grid_pose = GridPose.from_dict(_first(record, ("grid_pose",), "grid_pose", k))
    camera_pose = np.asarray(_first(record, ("camera_pose",), "camera_pose", k), dtype=np.float64).reshape(4, 4)
    obj_pose = np.asarray(_first(record, ("object_pose",), "object_pose", k), dtype=np.float64).reshape(4, 4)
    identity = str(_first(record, ("identity",), "identity", k))
    depth = np.asarray(arrays["depth"])
    # Stored crops are uint16 millimetres (0 = no reading); float crops are metres.
    depth = (depth.astype(np.float64) / 1000.0).astype(np.float32) if depth.dtype.kind in "ui" else \
        depth.astype(np.float32)
    mask = np.asarray(arrays["mask"]) != 0
    crop = record.get("crop")
    if isinstance(crop, dict):
        offset = (int(crop["u0"]), int(crop["v0"]))
    elif crop is not None:
        v0, u0 = int(crop[0]), int(crop[1])
        offset = (u0, v0)
    else:
        offset = (0, 0)
    meta = {key: value for key, value in record.items()
            if isinstance(value, bool | int | float | str) and key != "identity"}
    return EvalView(index=k, identity=identity, depth_view=DepthView(depth, mask, intrinsics, offset),
                    object_pose=camera_from_object(camera_pose, obj_pose), grid_pose=grid_pose,
                    known_occupied=np.asarray(arrays["known_occupied"], dtype=bool),
                    known_free=np.asarray(arrays["known_free"], dtype=bool), meta=meta)
