"""Checkpoints, the training loop and the `pssnet train` / `pssnet export-model` commands (tiny data)."""

from __future__ import annotations

import argparse
import csv
import math
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator

import numpy as np
import pytest
import torch
import yaml
from test_models_helpers import TINY_BY_MODEL, export_as_before_stop_38, make_dataset, tiny_model

from pssnet_core.models.checkpoint import (
    CheckpointError,
    export_checkpoint,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from pssnet_core.training import TrainConfig, Trainer, TrainingError, chamfer_mm
from pssnet_core.training.cli import register
from pssnet_core.training.trainer import prefetch, resolve_context

GRID = 16


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("data") / "train", num=24, grid=GRID)


def sample(model, seed=0):
    x = torch.zeros(1, 2, GRID, GRID, GRID)
    x[0, 0, 4, 4:9, 4:9] = 1
    x[0, 1, :4, 4:9, 4:9] = 1
    with torch.inference_mode():
        return model.eval().sample(x, 3, generator=torch.Generator().manual_seed(seed))


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="pssnet")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(list(argv))
    return args.func(args)


@pytest.mark.parametrize("name", ["pssnet", "vae_gan", "recgan"])
def test_checkpoint_round_trip_fp32(tmp_path, name):
    model = tiny_model(name)
    path = save_checkpoint(tmp_path / "m.pt", model, extra={"note": "hi"})
    loaded, config, extra = load_checkpoint(path)
    assert config == model.config and extra["note"] == "hi" and extra["storage_dtype"] == "float32"
    assert type(loaded) is type(model)
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    torch.testing.assert_close(sample(loaded), sample(model), rtol=0, atol=0)


def test_checkpoint_fp16_and_inference_only_export(tmp_path):
    model = tiny_model("pssnet")
    full = save_checkpoint(tmp_path / "full.pt", model)
    half = export_checkpoint(full, tmp_path / "half.pt")
    def weight_bytes(path) -> int:
        return sum(t.numel() * t.element_size() for t in read_checkpoint(path)["state_dict"].values())

    assert weight_bytes(half) <= 0.5 * weight_bytes(full)  # fp16: half the bytes, nothing but state dropped
    loaded, _, extra = load_checkpoint(half)
    assert extra["inference_only"] and extra["storage_dtype"] == "float16" and extra["missing_modules"] == []
    assert all(p.dtype == torch.float32 for p in loaded.parameters())
    assert float((sample(loaded) - sample(model)).abs().max()) < 1e-2
    # The export keeps PSSNet's flow (it maps boxes to the decoder's codes), fp16-rounded.
    torch.testing.assert_close(loaded.flow.layers[0].net[0].weight, model.flow.layers[0].net[0].weight,
                               atol=1e-3, rtol=1e-3)
    # A GAN's discriminator is dropped, and the load says so.
    gan = save_checkpoint(tmp_path / "gan.pt", tiny_model("vae_gan"))
    _, _, gan_extra = load_checkpoint(export_checkpoint(gan, tmp_path / "gan_ship.pt"))
    assert gan_extra["missing_modules"] == ["discriminator."]
    # fp16 storage keeping every module also loads.
    loaded2, _, _ = load_checkpoint(save_checkpoint(tmp_path / "h2.pt", model, half=True))
    torch.testing.assert_close(loaded2.flow.layers[0].net[0].weight, model.flow.layers[0].net[0].weight,
                               atol=1e-3, rtol=1e-3)
    # The export's archive is deflated (the shipped model's 15 MB bound) and loads the same weights as the same
    # checkpoint stored plainly.
    plain = save_checkpoint(tmp_path / "plain.pt", loaded, half=True, inference_only=True)
    with zipfile.ZipFile(half) as archive:
        assert {m.compress_type for m in archive.infolist()} == {zipfile.ZIP_DEFLATED}
    assert half.stat().st_size < plain.stat().st_size
    deflated_state = read_checkpoint(half)["state_dict"]
    for key, value in read_checkpoint(plain)["state_dict"].items():
        assert torch.equal(deflated_state[key], value), key


def test_missing_and_corrupt_checkpoints_raise_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint file.*pssnet train"):
        load_checkpoint(tmp_path / "nope.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a zip file at all" * 10)
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(garbage)
    good = save_checkpoint(tmp_path / "good.pt", tiny_model("vae"))
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="not a PSSNet-ROS checkpoint"):
        load_checkpoint(foreign)
    payload = torch.load(good, weights_only=True)
    payload["config"]["channels"] = [4, 8, 8, 32]
    mismatched = tmp_path / "mismatched.pt"
    torch.save(payload, mismatched)
    with pytest.raises(CheckpointError, match="do not fit|do not match"):
        load_checkpoint(mismatched)


def test_chamfer_mm():
    a = np.array([[0, 0, 0]])
    b = np.array([[0, 0, 2]])
    assert chamfer_mm(a, b, 0.005) == pytest.approx(10.0)
    assert chamfer_mm(a, a, 0.005) == 0.0
    assert chamfer_mm(a, np.zeros((0, 3)), 0.005) == math.inf


def test_closing_prefetch_waits_for_its_thread():
    """A consumer that stops early (the last step of a run) leaves no producer thread behind: one still inside
    torch code at interpreter exit aborts the process (the two-rank test's rank 1)."""

    def slow(made: list[int]) -> Iterator[int]:
        for i in range(100):
            time.sleep(0.05)  # the next batch is being made when the consumer stops
            made.append(i)
            yield i

    def broken() -> Iterator[int]:
        yield 1
        raise ValueError("broken shard")

    def producers() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name == "prefetch"]

    for stop_after in (0, 1, 3):
        made: list[int] = []
        stream = prefetch(slow(made))
        assert [next(stream) for _ in range(stop_after)] == list(range(stop_after))
        stream.close()
        assert not producers()
        assert len(made) <= stop_after + 3  # at most 2 queued and the one being made when it stopped
    with pytest.raises(ValueError, match="broken shard"):
        list(prefetch(broken()))
    assert list(prefetch(iter(range(5)))) == list(range(5))
    assert not producers()


@pytest.mark.parametrize("native_bf16", [False, True])
def test_precision_resolution(monkeypatch, native_bf16):
    import pssnet_core.models.base as models_base

    monkeypatch.setattr(models_base, "cpu_has_fast_bf16", lambda: native_bf16)  # both CPU kinds on any machine
    assert resolve_context("cpu", "fp32").autocast_dtype is None
    assert resolve_context("cpu", "bf16").autocast_dtype == torch.bfloat16
    assert resolve_context("cpu", "auto").autocast_dtype == (torch.bfloat16 if native_bf16 else None)
    assert resolve_context("cpu", "auto").precision == ("bf16" if native_bf16 else "fp32")
    with pytest.raises(TrainingError, match="precision must be one of"):
        resolve_context("cpu", "fp16")
    if not torch.cuda.is_available():
        with pytest.raises(TrainingError, match="CUDA"):
            resolve_context("cuda", "auto")


def _write_tiny_config(path, name):
    path.write_text(yaml.safe_dump(TINY_BY_MODEL[name]))
    return str(path)


def test_cli_train_one_epoch_then_resume(tmp_path, dataset):
    out = tmp_path / "run"
    cfg = _write_tiny_config(tmp_path / "tiny.yaml", "pssnet")
    common = ["train", "--model", "pssnet", "--data", str(dataset), "--out", str(out), "--batch-size", "8",
              "--model-config", cfg, "--threads", "1", "--log-every", "1", "--val-slice", "2", "--no-progress"]
    assert run_cli(*common, "--epochs", "1") == 0
    for name in ("last.pt", "best.pt", "train_log.csv", "val_log.csv", "loss_curves.png", "summary.json",
                 "model_config.yaml"):
        assert (out / name).exists(), name
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3]
    assert {"loss", "rec", "kl", "flow", "flow_nll"} <= set(rows[0])
    val = list(csv.DictReader(open(out / "val_log.csv")))
    assert len(val) == 1 and 0.0 <= float(val[0]["val_iou"]) <= 1.0 and float(val[0]["val_bce"]) > 0
    model, config, extra = load_checkpoint(out / "last.pt")
    assert config.channels == [4, 8, 8, 16] and extra["train_state"]["epoch"] == 1
    assert set(extra["optimizers"]) == {"main", "flow"}

    assert run_cli(*common, "--epochs", "2", "--resume") == 0
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    _, _, extra = load_checkpoint(out / "last.pt")
    assert extra["train_state"]["epoch"] == 2 and extra["train_state"]["step"] == 6


def test_init_from_starts_a_new_run_from_another_runs_weights(tmp_path, dataset):
    cfg = _write_tiny_config(tmp_path / "tiny.yaml", "pssnet")
    common = ["--data", str(dataset), "--batch-size", "8", "--threads", "1", "--val-slice", "0", "--no-progress"]
    assert run_cli("train", "--model", "pssnet", "--out", str(tmp_path / "a"), "--model-config", cfg,
                   "--epochs", "1", *common) == 0
    source, _, source_extra = load_checkpoint(tmp_path / "a" / "last.pt")
    # Stop right after the first step: the weights must be the source's moved by exactly one update.
    summary = Trainer(TrainConfig(model="pssnet", data=str(dataset), out=str(tmp_path / "b"), epochs=1,
                                  batch_size=8, max_minutes=1e-6, val_slice=0, progress=False,
                                  log_every=1, init_from=str(tmp_path / "a" / "last.pt"))).fit()
    assert summary["steps"] == 1 and summary["init_from"] == str(tmp_path / "a" / "last.pt")
    assert summary["pretrain"] is None  # the flow comes trained from the source
    warm, config, extra = load_checkpoint(tmp_path / "b" / "last.pt")
    assert config.channels == [4, 8, 8, 16]  # the source's config, no --model-config needed
    assert extra["train_state"]["step"] == 1 and extra["train_state"]["epoch"] == 0
    assert extra["optimizers"]["main"]["state"][0]["step"] == source_extra["optimizers"]["main"]["state"][0]["step"] + 1
    moved = [float((a - b).abs().max()) for a, b in zip(warm.state_dict().values(), source.state_dict().values(),
                                                         strict=True) if a.is_floating_point()]
    assert 0 < max(moved) < 0.05  # one Adam step at lr 1e-3 away from the source, not a fresh init
    rows = list(csv.DictReader(open(tmp_path / "b" / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1]

    with pytest.raises(TrainingError, match="cannot be combined"):
        TrainConfig(model="pssnet", data=str(dataset), out=str(tmp_path / "c"), resume=True,
                    init_from=str(tmp_path / "a" / "last.pt"))
    assert run_cli("train", "--model", "vae", "--out", str(tmp_path / "d"), "--init-from",
                   str(tmp_path / "a" / "last.pt"), *common) == 2


def test_init_from_best_pt_keeps_the_flow_its_decoder_was_trained_against(tmp_path, dataset):
    cfg = _write_tiny_config(tmp_path / "tiny.yaml", "pssnet")
    assert run_cli("train", "--model", "pssnet", "--out", str(tmp_path / "a"), "--model-config", cfg,
                   "--epochs", "1", "--data", str(dataset), "--batch-size", "8", "--threads", "1",
                   "--val-slice", "0", "--no-progress") == 0
    source, _, source_extra = load_checkpoint(tmp_path / "a" / "best.pt")
    assert "optimizers" not in source_extra
    summary = Trainer(TrainConfig(model="pssnet", data=str(dataset), out=str(tmp_path / "b"), epochs=1,
                                  batch_size=8, max_steps=1, val_slice=0, progress=False,
                                  init_from=str(tmp_path / "a" / "best.pt"))).fit()
    assert summary["pretrain"] is None  # a new flow would change every box code the loaded decoder reads
    warm, _, extra = load_checkpoint(tmp_path / "b" / "last.pt")
    assert extra["optimizers"]["main"]["state"][0]["step"] == 1  # best.pt has no optimiser states: fresh ones
    # Weights (not the batch-norm statistics, which every training batch moves) one flow step at 1e-5 away.
    flow = {k: v for k, v in source.named_parameters() if k.startswith("flow.")}
    warm_weights = dict(warm.named_parameters())
    assert max(float((warm_weights[k] - v).detach().abs().max()) for k, v in flow.items()) < 1e-4


def test_init_from_an_inference_only_export_takes_its_weights_and_its_flow(tmp_path, dataset, monkeypatch):
    cfg = _write_tiny_config(tmp_path / "tiny.yaml", "pssnet")
    assert run_cli("train", "--model", "pssnet", "--out", str(tmp_path / "a"), "--model-config", cfg,
                   "--epochs", "1", "--data", str(dataset), "--batch-size", "8", "--threads", "1",
                   "--val-slice", "0", "--no-progress") == 0
    assert run_cli("export-model", str(tmp_path / "a" / "last.pt"), str(tmp_path / "ship.pt")) == 0

    def warm_start(export: str, out: str) -> dict:
        return Trainer(TrainConfig(model="pssnet", data=str(dataset), out=str(tmp_path / out), epochs=1,
                                   batch_size=8, max_steps=1, val_slice=0, progress=False, log_every=1,
                                   init_from=str(tmp_path / export))).fit()

    # An export written before exports kept the flow (the shipped model's kind): a new flow is pre-trained.
    export_as_before_stop_38(tmp_path / "a" / "last.pt", tmp_path / "old_ship.pt", monkeypatch)
    assert load_checkpoint(tmp_path / "old_ship.pt")[2]["missing_modules"] == ["flow."]
    assert warm_start("old_ship.pt", "old")["pretrain"] is not None
    # Today's export brings its flow, which the decoder was trained against: kept, not pre-trained again.
    shipped, _, _ = load_checkpoint(tmp_path / "ship.pt")
    summary = warm_start("ship.pt", "b")
    assert summary["steps"] == 1 and summary["stopped_by"] == "max_steps"
    assert summary["pretrain"] is None
    warm, _, extra = load_checkpoint(tmp_path / "b" / "last.pt")
    torch.testing.assert_close(warm.flow.layers[0].net[0].weight, shipped.flow.layers[0].net[0].weight,
                               atol=1e-3, rtol=0)  # one step at flow_lr from the exported flow
    assert extra["optimizers"]["main"]["state"][0]["step"] == 1  # fresh optimiser, one update
    shipped_state = shipped.state_dict()
    moved = [float((v - shipped_state[k].float()).abs().max()) for k, v in warm.state_dict().items()
             if not k.startswith("flow.") and v.is_floating_point()]
    assert 0 < max(moved) < 0.05  # one step away from the exported weights (fp16-rounded), not a fresh init
    with pytest.raises(TrainingError, match="holds a 'pssnet' model"):
        Trainer(TrainConfig(model="vae", data=str(dataset), out=str(tmp_path / "c"), epochs=1, batch_size=8,
                            progress=False, init_from=str(tmp_path / "ship.pt"))).fit()


def test_max_steps_stops_the_run_and_counts_across_resume(tmp_path, dataset):
    cfg = _write_tiny_config(tmp_path / "tiny.yaml", "vae")
    run = {"model": "vae", "data": str(dataset), "out": str(tmp_path / "r"), "epochs": 5, "batch_size": 8,
           "model_config": cfg, "val_slice": 0, "progress": False, "log_every": 1, "precision": "fp32"}
    summary = Trainer(TrainConfig(**run, max_steps=2)).fit()
    assert summary["steps"] == 2 and summary["stopped_by"] == "max_steps"
    summary = Trainer(TrainConfig(**{**run, "model_config": None}, max_steps=4, resume=True)).fit()
    assert summary["steps"] == 4 and summary["stopped_by"] == "max_steps"
    with pytest.raises(TrainingError, match="max_steps"):
        TrainConfig(**run, max_steps=0)


@pytest.mark.parametrize("name", ["vae", "vae_gan", "recgan"])
def test_trainer_runs_every_model(tmp_path, dataset, name):
    summary = Trainer(TrainConfig(model=name, data=str(dataset), out=str(tmp_path / name), epochs=1,
                                  batch_size=8, model_config=_write_tiny_config(tmp_path / "c.yaml", name),
                                  progress=False, val_slice=1, precision="fp32")).fit()
    assert summary["steps"] == 3 and summary["stopped_by"] == "epochs"
    assert math.isfinite(summary["last_validation"]["val_bce"])


def test_sigterm_saves_last_checkpoint_like_ctrl_c(tmp_path, dataset):
    out = tmp_path / "run"
    argv = [sys.executable, "-c", "import sys; from pssnet_core.cli import main; sys.exit(main())", "train",
            "--model", "vae", "--data", str(dataset), "--out", str(out), "--epochs", "1000", "--batch-size", "4",
            "--model-config", _write_tiny_config(tmp_path / "c.yaml", "vae"), "--threads", "1", "--log-every", "1",
            "--val-slice", "0", "--no-progress"]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "train_log.csv").exists() or len((out / "train_log.csv").read_text().splitlines()) < 3:
            assert process.poll() is None and time.monotonic() < deadline, process.stdout.read()
            time.sleep(0.2)
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130, output
    assert "interrupted: saving last.pt" in output
    _, _, extra = load_checkpoint(out / "last.pt")
    assert extra["train_state"]["step"] >= 2


def test_max_minutes_stops_and_saves(tmp_path, dataset):
    summary = Trainer(TrainConfig(model="vae", data=str(dataset), out=str(tmp_path / "r"), epochs=50,
                                  batch_size=4, max_minutes=1e-6, val_slice=0, progress=False,
                                  model_config=_write_tiny_config(tmp_path / "c.yaml", "vae"))).fit()
    assert summary["stopped_by"] == "max_minutes" and summary["steps"] == 1
    assert (tmp_path / "r" / "last.pt").exists()


def test_train_errors_are_clear(tmp_path, dataset, capsys):
    assert run_cli("train", "--model", "vae", "--data", str(tmp_path / "none"), "--out", str(tmp_path)) == 2
    assert "index.json is missing" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("grid_size: 32\n")
    assert run_cli("train", "--model", "vae", "--data", str(dataset), "--out", str(tmp_path / "o"),
                   "--model-config", str(bad)) == 2
    assert "grid_size 32 != dataset grid 16" in capsys.readouterr().err


def test_cli_export_model(tmp_path):
    src = save_checkpoint(tmp_path / "best.pt", tiny_model("pssnet"))
    assert run_cli("export-model", str(src), str(tmp_path / "ship.pt")) == 0
    _, _, extra = load_checkpoint(tmp_path / "ship.pt")
    assert extra["inference_only"] and extra["storage_dtype"] == "float16"
    assert run_cli("export-model", str(tmp_path / "missing.pt"), str(tmp_path / "x.pt")) == 2


def test_training_inference_packages_import_without_open3d_trimesh_cv2_rclpy():
    code = ("import sys; import pssnet_core.models, pssnet_core.training, pssnet_core.training.cli, "
            "pssnet_core.inference, pssnet_core.data.store; "
            "bad = [m for m in ('open3d', 'trimesh', 'manifold3d', 'cv2', 'rclpy') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


def test_command_line_builds_without_the_renderer_and_shape_generators():
    # `pssnet train` must run on a GPU machine without open3d or manifold3d (the lent ones have neither).
    code = ("import sys; from pssnet_core.cli import build_parser; build_parser(); "
            "bad = [m for m in ('open3d', 'trimesh', 'manifold3d', 'mujoco', 'rclpy') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
