"""Turned twins: `pssnet dataset twins`, the reader's twin keys, and PSSNet trained against them (tiny data)."""

from __future__ import annotations

import argparse
import copy
import csv
import json

import numpy as np
import pytest
import torch
import yaml
from test_models_helpers import TINY_PSSNET, tiny_model

from pssnet_core.data import cli as data_cli
from pssnet_core.data.build import build_dataset, dataset_path
from pssnet_core.data.datasets import dataset_specs
from pssnet_core.data.scenes import box_in_grid
from pssnet_core.data.store import TRAINING_KEYS, TWIN_DIR, TWIN_INDEX, TWIN_KEYS, DatasetReader, twins_path
from pssnet_core.data.twins import build_twins, can_turn, twin_azimuths
from pssnet_core.evaluation.handles import HandleGeometry, handle_azimuths, turned
from pssnet_core.geometry import GridPose
from pssnet_core.models.base import StepContext, bce_sum
from pssnet_core.shapes import shape_of
from pssnet_core.training import TrainConfig, TrainingError
from pssnet_core.training.cli import register as register_training
from pssnet_core.training.trainer import batch_to_tensors

GRID = 32
PER_VIEW = 3

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One mug with a handle (4 views, with twins) and one ycb object (2 views, none): ~2 s."""
    root = tmp_path_factory.mktemp("data")
    paths = {}
    for spec in (dataset_specs("mugs", "train", grid_size=GRID, num_objects=1, views=4)[0],
                 dataset_specs("ycb", "train", grid_size=GRID, num_objects=1, views=2)[0]):
        paths[spec.name] = build_dataset(spec, dataset_path(root, spec), progress=False).path
    mug = DatasetReader(paths["mugs"]).get(0, images=False)
    assert mug["has_handle"] and can_turn(shape_of(mug["identity"]))  # the test needs a mug that turns
    results = {name: build_twins(path, per_view=PER_VIEW, seed=0, progress=False) for name, path in paths.items()}
    return paths, results


def stored_twins(root):
    with np.load(twins_path(root, 0)) as data:
        count, per_view = data["azimuth_deg"].shape
        occupancy = np.unpackbits(data["occupancy"], axis=2, count=GRID**3).astype(bool).reshape(
            count, per_view, GRID, GRID, GRID)
        return occupancy, data["box"], data["azimuth_deg"], data["has_twins"]


def object_from_grid(sample, box):
    """Box corners (grid coordinates, (24,)) -> (8, 3) points in the mug's frame."""
    grid_pose = GridPose.from_dict(sample["grid_pose"])
    camera = grid_pose.grid_to_camera(np.asarray(box, dtype=np.float64).reshape(8, 3))
    object_from_camera = np.linalg.inv(np.asarray(sample["object_pose"])) @ np.asarray(sample["camera_pose"])
    return camera @ object_from_camera[:3, :3].T + object_from_camera[:3, 3]


def test_build_counts_and_skips_datasets_without_mugs(built):
    paths, results = built
    assert results["mugs"].samples_with_twins == 4 and results["mugs"].shards_built == 1
    assert json.loads((paths["mugs"] / TWIN_DIR / TWIN_INDEX).read_text())["twins"] == 4 * PER_VIEW
    assert results["ycb"].samples_with_twins == 0 and results["ycb"].shards_built == 0
    assert not (paths["ycb"] / TWIN_DIR).exists()


def test_twin_box_is_the_view_box_turned_about_the_mug_axis(built):
    paths, _ = built
    reader = DatasetReader(paths["mugs"])
    _, boxes, azimuths, has = stored_twins(paths["mugs"])
    assert has.all()
    for i in range(len(reader)):
        sample = reader.get(i, images=False)
        np.testing.assert_allclose(azimuths[i], twin_azimuths(0, sample["index"], PER_VIEW), atol=1e-4)
        shape = shape_of(sample["identity"])
        corners = object_from_grid(sample, sample["box"])
        for k, azimuth in enumerate(azimuths[i]):
            a = np.radians(azimuth)
            turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            # In the mug's frame the twin's corners are the view's turned about z; in the grid the box moved.
            np.testing.assert_allclose(object_from_grid(sample, boxes[i, k]), corners @ turn.T, atol=1e-4)
            assert np.abs(boxes[i, k] - sample["box"]).max() > 1.0
            expected = box_in_grid(shape, turned(np.asarray(sample["object_pose"]), azimuth),
                                   GridPose.from_dict(sample["grid_pose"]), np.asarray(sample["camera_pose"]))
            np.testing.assert_allclose(boxes[i, k], expected, atol=1e-4)


def test_twin_grid_moves_the_handle_and_keeps_the_body(built):
    paths, _ = built
    reader = DatasetReader(paths["mugs"])
    occupancy, _, azimuths, _ = stored_twins(paths["mugs"])
    found = 0
    for i in range(len(reader)):
        sample = reader.get(i, images=False)
        geometry = HandleGeometry.of(shape_of(sample["identity"]))
        grid_pose = GridPose.from_dict(sample["grid_pose"])
        camera_from_object = np.linalg.inv(np.asarray(sample["camera_pose"])) @ np.asarray(sample["object_pose"])
        # The twin's handle lies where it was turned to (NaN: turned out of the grid).
        measured = handle_azimuths(occupancy[i], grid_pose, camera_from_object, geometry)
        off = np.abs((measured - azimuths[i] + 180.0) % 360.0 - 180.0)
        assert np.all(off[np.isfinite(off)] < 15.0), (measured, azimuths[i])
        found += int(np.isfinite(off).sum())
        object_from_camera = np.linalg.inv(camera_from_object)
        for twin in occupancy[i]:
            changed = grid_pose.occupied_centres(twin ^ sample["occupancy"])
            in_object = changed @ object_from_camera[:3, :3].T + object_from_camera[:3, 3]
            outside_body = np.hypot(in_object[:, 0], in_object[:, 1]) > geometry.body_radius
            assert outside_body.mean() > 0.75  # the voxels that differ are the handle's, old and new
            assert (twin & sample["occupancy"]).sum() > 0.8 * sample["occupancy"].sum()
    assert found >= 2 * len(reader)


def test_rerun_is_a_no_op_and_a_lost_shard_comes_back_the_same(built):
    paths, _ = built
    path = twins_path(paths["mugs"], 0)
    before = path.stat().st_mtime_ns, (paths["mugs"] / TWIN_DIR / TWIN_INDEX).stat().st_mtime_ns
    again = build_twins(paths["mugs"], per_view=PER_VIEW, seed=0, progress=False)
    assert again.shards_built == 0 and again.shards_skipped == 1 and again.samples_with_twins == 4
    assert (path.stat().st_mtime_ns, (paths["mugs"] / TWIN_DIR / TWIN_INDEX).stat().st_mtime_ns) == before
    kept = stored_twins(paths["mugs"])
    path.unlink()
    assert build_twins(paths["mugs"], per_view=PER_VIEW, seed=0, progress=False).shards_built == 1
    for a, b in zip(stored_twins(paths["mugs"]), kept, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="another request"):
        build_twins(paths["mugs"], per_view=PER_VIEW + 1, seed=0, progress=False)


def test_reader_gives_one_stored_twin_per_view_or_its_own_grid(built):
    paths, _ = built
    reader = DatasetReader(f"{paths['mugs']},{paths['ycb']}")
    assert reader.has_twins and not DatasetReader(paths["ycb"]).has_twins
    occupancy, boxes, _, _ = stored_twins(paths["mugs"])
    keys = (*TRAINING_KEYS, *TWIN_KEYS)
    plain = next(reader.iter_batches(6, seed=1))
    assert set(plain) == {*TRAINING_KEYS, "index"}  # twin keys only when asked for

    def choices(seed):
        batch = next(reader.iter_batches(6, seed=seed, keys=keys))
        assert batch["twin_occupancy"].shape == (6, GRID, GRID, GRID) and batch["twin_box"].dtype == np.float32
        picked = {}
        for row, index in enumerate(batch["index"]):
            for key in TRAINING_KEYS:
                np.testing.assert_array_equal(batch[key][row], plain[key][list(plain["index"]).index(index)])
            if index >= 4:  # ycb: no twins, its own grid and box
                np.testing.assert_array_equal(batch["twin_occupancy"][row], batch["occupancy"][row])
                np.testing.assert_array_equal(batch["twin_box"][row], batch["box"][row])
                continue
            k = int(np.argmin(np.abs(boxes[index] - batch["twin_box"][row]).max(axis=1)))
            np.testing.assert_array_equal(batch["twin_box"][row], boxes[index, k])
            np.testing.assert_array_equal(batch["twin_occupancy"][row], occupancy[index, k])
            picked[int(index)] = k
        return picked

    assert choices(1) == choices(1)  # seeded by the iteration's seed
    assert any(choices(seed) != choices(1) for seed in range(2, 8))
    # An interrupted twins build (no twins index) is not read.
    index = paths["mugs"] / TWIN_DIR / TWIN_INDEX
    index.rename(index.with_suffix(".bak"))
    try:
        batch = next(DatasetReader(paths["mugs"]).iter_batches(4, keys=keys))
        np.testing.assert_array_equal(batch["twin_box"], batch["box"])
    finally:
        index.with_suffix(".bak").rename(index)


def test_training_step_with_twin_rate_1_decodes_the_twin_box_against_the_twin_grid(built):
    paths, _ = built
    batch = batch_to_tensors(next(DatasetReader(paths["mugs"]).iter_batches(4, keys=(*TRAINING_KEYS, *TWIN_KEYS))))
    assert not torch.equal(batch["twin_target"], batch["target"])
    # An untrained decoder gives about 0.5 everywhere, so the grids' few hundred differing voxels would hardly move the
    # loss: the complement of the view's grid as the twin's makes a step that ignores it stand out.
    batch["twin_target"] = 1.0 - batch["target"]
    model = tiny_model("pssnet", grid=GRID, twin_rate=1.0).train()
    before = copy.deepcopy(model)
    decoded = []
    model.decoder.register_forward_hook(lambda module, args, output: decoded.append(args[0].detach()))
    ctx = StepContext(torch.device("cpu"), None)
    torch.manual_seed(3)
    losses = model.training_step(batch, model.make_optimizers(1e-3), ctx)
    assert losses["twins"] == 1.0

    # The step's first part by hand on the copy: the flow's update on the true box, the turned rows' draw, the latent.
    optimizers = before.make_optimizers(1e-3)
    torch.manual_seed(3)
    flow_nll = before.flow_nll(before.normalise_box(batch["box"]))
    optimizers["flow"].zero_grad()
    flow_nll.backward()
    optimizers["flow"].step()
    torch.rand(4)
    with torch.no_grad():
        z, _, _, _ = before._vae_forward(batch["input"], ctx)
        twin_code = before.embed_box(before.normalise_box(batch["twin_box"]))
        own_code = before.embed_box(before.normalise_box(batch["box"]))
        z_dec = decoded[0]
        rec_twin = float(bce_sum(before.decoder(z_dec), batch["twin_target"]))
        rec_own = float(bce_sum(before.decoder(z_dec), batch["target"]))
    k = model.box_dim
    torch.testing.assert_close(z_dec[:, :k], twin_code)  # the twin's box code ...
    assert float((z_dec[:, :k] - own_code).abs().max()) > 0.1
    torch.testing.assert_close(z_dec[:, k:], z[:, k:])  # ... with the rest of the view's latent
    assert losses["rec"] == pytest.approx(rec_twin, rel=1e-6)  # against the twin's grid
    assert abs(rec_own - rec_twin) > 0.1 * rec_twin

    with pytest.raises(ValueError, match="twin_box and twin_target"):
        model.training_step({k: v for k, v in batch.items() if not k.startswith("twin")},
                            model.make_optimizers(1e-3), ctx)


def test_twin_rate_is_validated():
    with pytest.raises(ValueError, match="twin_rate"):
        tiny_model("pssnet", grid=GRID, twin_rate=1.5)
    with pytest.raises(TrainingError, match="PSSNet"):
        TrainConfig(model="vae", data="x", out="y", twin_rate=0.5)


def run(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="pssnet")
    subparsers = parser.add_subparsers(dest="command", required=True)
    data_cli.register(subparsers)
    register_training(subparsers)
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_cli_builds_twins_and_trains_and_fine_tunes_with_them(built, tmp_path, capsys):
    paths, _ = built
    assert run("dataset", "twins", "--data", str(paths["mugs"].parent), "--per-view", str(PER_VIEW), "--quiet") == 0
    out = capsys.readouterr().out
    assert "4 of 4 views have 3 twins each (built 0 shards, 1 already there)" in out and "no mugs" in out

    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY_PSSNET))
    data = f"{paths['mugs']},{paths['ycb']}"
    common = ["--data", data, "--batch-size", "2", "--threads", "1", "--val-slice", "0", "--log-every", "1",
              "--no-progress", "--precision", "fp32"]
    assert run("train", "--model", "pssnet", "--out", str(tmp_path / "a"), "--model-config", str(config),
               "--twin-rate", "0.5", "--max-steps", "3", *common) == 0
    assert yaml.safe_load((tmp_path / "a" / "model_config.yaml").read_text())["twin_rate"] == 0.5
    rows = list(csv.DictReader(open(tmp_path / "a" / "train_log.csv")))
    assert len(rows) == 3 and all(0.0 <= float(r["twins"]) <= 1.0 for r in rows)

    # Fine-tuning from best.pt keeps the flow its decoder was trained against.
    assert run("train", "--model", "pssnet", "--out", str(tmp_path / "b"), "--init-from",
               str(tmp_path / "a" / "best.pt"), "--twin-rate", "1", "--max-steps", "1", *common) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["pretrain"] is None and summary["steps"] == 1
    assert yaml.safe_load((tmp_path / "b" / "model_config.yaml").read_text())["twin_rate"] == 1.0

    capsys.readouterr()
    assert run("train", "--model", "pssnet", "--out", str(tmp_path / "c"), "--model-config", str(config),
               "--twin-rate", "0.5", *[str(paths["ycb"]) if a == data else a for a in common]) == 2
    assert "needs turned twins" in capsys.readouterr().err
    assert run("train", "--model", "vae", "--out", str(tmp_path / "d"), "--twin-rate", "0.5", *common) == 2
    assert "PSSNet" in capsys.readouterr().err
