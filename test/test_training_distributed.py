"""Data-parallel training (torch.distributed, gloo on localhost): 2 CPU ranks against 1 process, tiny data."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
import yaml
from test_models_helpers import TINY_BY_MODEL, make_dataset, tiny_model

from pssnet_core.data.store import DatasetReader
from pssnet_core.models.base import StepContext
from pssnet_core.models.checkpoint import load_checkpoint
from pssnet_core.training import TrainConfig, Trainer
from pssnet_core.training.distributed import DistributedRun, min_rank_samples, rank_batches
from pssnet_core.training.trainer import batch_to_tensors

GRID = 16
BATCH = 4  # per rank
STEPS = 3
CPU = StepContext(torch.device("cpu"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    # 4 shards of 8: two per rank, 4 steps of 2 x 4 views per epoch
    return make_dataset(tmp_path_factory.mktemp("ddp") / "train", num=32, grid=GRID, shard_size=8)


def combined_batches(data: Path) -> list[dict[str, torch.Tensor]]:
    """STEPS batches of 2 x BATCH views, the same in every process."""
    batches = DatasetReader(data).iter_batches(2 * BATCH, shuffle=True, seed=3, drop_last=True)
    return [batch_to_tensors(b) for _, b in zip(range(STEPS), batches, strict=False)]


def half(batch: dict[str, torch.Tensor], rank: int) -> dict[str, torch.Tensor]:
    return {k: v[rank * BATCH:(rank + 1) * BATCH] for k, v in batch.items()}


def sgd(model: torch.nn.Module, groups: dict[str, str]) -> dict[str, torch.optim.Optimizer]:
    """Plain SGD per optimiser of the model (Adam's first steps amplify float noise to +-lr)."""
    return {name: torch.optim.SGD(getattr(model, net).parameters(), lr=1e-3) for name, net in groups.items()}


def flat_state(model: torch.nn.Module) -> torch.Tensor:
    return torch.cat([t.detach().reshape(-1).double() for t in model.state_dict().values() if t.is_floating_point()])


def assert_ranks_identical(model: torch.nn.Module, what: str) -> None:
    mine = flat_state(model)
    every = [torch.empty_like(mine) for _ in range(dist.get_world_size())]
    dist.all_gather(every, mine)
    assert all(torch.equal(every[0], other) for other in every[1:]), f"ranks differ after {what}"


def boxes_of(batches: list[dict[str, torch.Tensor]], rank: int | None):
    def source(batch_size: int):
        del batch_size
        for batch in batches:
            yield batch["box"] if rank is None else half(batch, rank)["box"]
    return source


def _rank_worker(rank: int, world: int, store: str, data: str, out: str, resume_dir: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        run = DistributedRun(rank, world)
        batches = combined_batches(Path(data))

        # (a) + (b): 3D-RecGAN++ (deterministic; two optimisers, a discriminator) against one process.
        model = tiny_model("recgan", GRID).to_fast_layout()
        model.set_wrappers(run.wrap(model))
        optimizers = sgd(model, {"main": "generator", "disc": "discriminator"})
        for step, batch in enumerate(batches):
            model.training_step(half(batch, rank), optimizers, CPU)
            assert_ranks_identical(model, f"recgan step {step}")
        if rank == 0:
            torch.save(model.state_dict(), Path(out) / "recgan.pt")

        # (b) for PSSNet's flow pre-training (without batch norm: per-rank statistics differ by design).
        model = tiny_model("pssnet", GRID, flow_batchnorm_every=0, flow_pretrain_steps=STEPS)
        model.set_wrappers(run.wrap(model))
        model.pretrain(boxes_of(batches, rank), CPU)
        assert_ranks_identical(model, "flow pre-training")
        if rank == 0:
            torch.save(model.flow.state_dict(), Path(out) / "flow.pt")

        # (a) for PSSNet with batch norm and a mixture box head, and for VAE-GAN, with their Adam optimisers:
        # every rank draws its own noise, yet the weights and running statistics stay identical.
        for name, overrides in (("pssnet", {"box_components": 2, "flow_pretrain_steps": STEPS}), ("vae_gan", {})):
            model = tiny_model(name, GRID, **overrides).to_fast_layout()
            torch.manual_seed(100 + rank)
            model.set_wrappers(run.wrap(model))
            optimizers = model.make_optimizers(1e-3)
            model.pretrain(boxes_of(batches, rank), CPU)
            run.average_buffers(model)
            for step, batch in enumerate(batches):
                model.training_step(half(batch, rank), optimizers, CPU)
                run.average_buffers(model)
                assert_ranks_identical(model, f"{name} step {step}")

        # A run saved by one process resumes on two ranks (the trainer joins the process group set up here).
        summary = Trainer(TrainConfig(model="pssnet", data=data, out=resume_dir, resume=True, epochs=5,
                                      batch_size=BATCH, max_steps=4, val_slice=0, progress=False, log_every=1,
                                      precision="fp32")).fit()
        assert summary["steps"] == 4 and summary["world_size"] == 2 and summary["global_batch"] == 2 * BATCH
    finally:
        dist.destroy_process_group()


def test_two_ranks_step_like_one_process_on_the_combined_batch_and_resume_its_run(tmp_path, dataset, one_torch_thread):
    # A one-process run of 2 steps, for the workers to resume on two ranks.
    resume_dir = tmp_path / "one_then_two"
    config = tmp_path / "pssnet.yaml"
    config.write_text(yaml.safe_dump(TINY_BY_MODEL["pssnet"]))
    Trainer(TrainConfig(model="pssnet", data=str(dataset), out=str(resume_dir), epochs=5, batch_size=BATCH,
                        max_steps=2, val_slice=0, progress=False, log_every=1, precision="fp32",
                        model_config=str(config))).fit()

    mp.spawn(_rank_worker, args=(2, str(tmp_path / "store"), str(dataset), str(tmp_path), str(resume_dir)),
             nprocs=2, join=True)

    batches = combined_batches(dataset)
    single = tiny_model("recgan", GRID).to_fast_layout()
    optimizers = sgd(single, {"main": "generator", "disc": "discriminator"})
    for batch in batches:
        single.training_step(batch, optimizers, CPU)
    two_ranks = torch.load(tmp_path / "recgan.pt", weights_only=True)
    initial = tiny_model("recgan", GRID).state_dict()
    assert max(float((v - initial[k]).abs().max()) for k, v in two_ranks.items()) > 1e-3  # the steps moved them
    for key, value in single.state_dict().items():
        torch.testing.assert_close(two_ranks[key], value, rtol=1e-5, atol=1e-6, msg=key)

    flow_model = tiny_model("pssnet", GRID, flow_batchnorm_every=0, flow_pretrain_steps=STEPS)
    flow_model.pretrain(boxes_of(batches, None), CPU)
    two_ranks = torch.load(tmp_path / "flow.pt", weights_only=True)
    for key, value in flow_model.flow.state_dict().items():
        torch.testing.assert_close(two_ranks[key], value, rtol=1e-5, atol=1e-6, msg=key)

    _, _, extra = load_checkpoint(resume_dir / "last.pt")
    assert extra["train_state"]["step"] == 4 and extra["train_state"]["world_size"] == 2
    assert extra["optimizers"]["main"]["state"][0]["step"] == 4  # one optimiser, continued across world sizes
    rows = list(csv.DictReader(open(resume_dir / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert float(rows[2]["samples_per_s"]) > 0


def test_rank_batches_are_disjoint_full_and_reshuffled(dataset):
    reader = DatasetReader(dataset)
    assert min_rank_samples(reader, 2) == 16
    first_rank = []
    for epoch in (0, 1):
        batches = [list(rank_batches(reader, BATCH, epoch, rank, 2, ("box",))) for rank in (0, 1)]
        assert [[len(b["index"]) for b in r] for r in batches] == [[BATCH] * 4] * 2  # full batches, equal counts
        indices = [{int(i) for b in r for i in b["index"]} for r in batches]
        assert not indices[0] & indices[1] and len(indices[0] | indices[1]) == 32
        first_rank.append(indices[0])
    assert first_rank[0] != first_rank[1]  # shards are dealt anew every epoch


def test_torchrun_sigterm_saves_once_and_resumes_in_one_process(tmp_path, dataset):
    out = tmp_path / "run"
    config = tmp_path / "pssnet.yaml"
    config.write_text(yaml.safe_dump(TINY_BY_MODEL["pssnet"]))
    argv = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
            "-m", "pssnet_core", "train", "--model", "pssnet", "--data", str(dataset), "--out", str(out),
            "--model-config", str(config), "--batch-size", str(BATCH), "--epochs", "1000", "--max-steps", "2000",
            "--log-every", "1", "--val-every", "2", "--val-slice", "0", "--threads", "1", "--precision", "fp32",
            "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        log = out / "train_log.csv"
        while not log.exists() or len(log.read_text().splitlines()) < 4:  # past a validation (step 2) on rank 0
            assert process.poll() is None and time.monotonic() < deadline, process.stdout.read()
            time.sleep(0.2)
        process.send_signal(signal.SIGTERM)  # torchrun forwards it to both ranks
        output, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:  # a failed check: torchrun stops its workers on SIGTERM (they run in sessions
            process.terminate()     # of their own, so killing torchrun would orphan them)
            try:
                process.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
    assert output.count("interrupted: saving last.pt") == 1, output  # rank 0 alone saves
    _, _, extra = load_checkpoint(out / "last.pt")
    state = extra["train_state"]
    assert state["step"] >= 3 and state["world_size"] == 2
    assert state["samples_in_epoch"] == state["batch_in_epoch"] * 2 * BATCH
    assert extra["optimizers"]["main"]["state"][0]["step"] == state["step"]
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, len(rows) + 1))  # one writer, no duplicates
    assert int(next(csv.DictReader(open(out / "val_log.csv")))["step"]) == 2  # rank 1 waited for it

    summary = Trainer(TrainConfig(model="pssnet", data=str(dataset), out=str(out), resume=True, epochs=1000,
                                  batch_size=BATCH, max_steps=state["step"] + 2, val_slice=0, progress=False,
                                  log_every=1, precision="fp32")).fit()
    assert summary["steps"] == state["step"] + 2 and summary["world_size"] == 1
    _, _, extra = load_checkpoint(out / "last.pt")
    assert extra["optimizers"]["main"]["state"][0]["step"] == state["step"] + 2
