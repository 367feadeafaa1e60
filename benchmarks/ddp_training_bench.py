"""Training across ranks: steps/s and views/s of `pssnet train`, one process against torchrun ranks (gloo),
and the rate at which one thread feeds a rank (shard decoding + batch tensors), which bounds a GPU rank.

    .venv/bin/python benchmarks/ddp_training_bench.py [--data DIR] [--model pssnet] [--steps 60]
        [--configs 1x2:16 2x1:16 2x1:8] [--feed-data DIR [DIR ...]] [--flops-grids 32 64]

A config ``RxT:B`` is R ranks of T threads with B views per rank and step (``--batch-size``); R = 1 runs
``python -m pssnet_core train``, R > 1 ``torchrun --standalone --nproc-per-node R -m pssnet_core train``. Rates
come from train_log.csv between its first and last rows (start-up, flow pre-training and the first
``--log-every`` steps excluded); the flow is pre-trained for 20 steps only. ``--flops-grids`` counts the
floating-point operations of one training step per view (torch's FlopCounterMode: matrix products and
convolutions, forward and backward), the work term of a cluster estimate.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml
from torch.utils.flop_counter import FlopCounterMode

from pssnet_core.data.store import TRAINING_KEYS, DatasetReader
from pssnet_core.models import StepContext, build_model, default_config
from pssnet_core.training.distributed import rank_batches
from pssnet_core.training.trainer import batch_to_tensors


def run_config(config: str, args: argparse.Namespace, work: Path) -> dict[str, float]:
    """Trains ``args.steps`` steps in config ``RxT:B``; returns its rates."""
    shape, batch = config.split(":")
    ranks, threads = (int(v) for v in shape.split("x"))
    out = work / config.replace(":", "_")
    model_config = work / "model.yaml"
    model_config.write_text(yaml.safe_dump({"flow_pretrain_steps": 20}))
    launcher = ([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(ranks)]
                if ranks > 1 else [sys.executable])
    argv = [*launcher, "-m", "pssnet_core", "train", "--model", args.model, "--data", args.data, "--out", str(out),
            "--model-config", str(model_config), "--batch-size", batch, "--threads", str(threads),
            "--max-steps", str(args.steps), "--epochs", "1000", "--log-every", str(args.log_every),
            "--val-every", str(10 * args.steps), "--val-max-samples", "16", "--val-slice", "0", "--no-progress"]
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    rows = list(csv.DictReader(open(out / "train_log.csv")))
    first, last = rows[0], rows[-1]
    steps_per_s = (int(last["step"]) - int(first["step"])) / (float(last["elapsed_s"]) - float(first["elapsed_s"]))
    summary = json.loads((out / "summary.json").read_text())
    return {"ranks": ranks, "threads": threads, "batch": int(batch), "global_batch": ranks * int(batch),
            "steps_per_s": steps_per_s, "views_per_s": steps_per_s * ranks * int(batch), "wall_s": wall,
            "precision": summary["precision"]}


def feed_rate(data: str, batch: int) -> tuple[int, float, float]:
    """(grid, views/s of one process's stream, views/s of a rank's stream): decoding a dataset into training
    tensors on one thread, as a rank's prefetch thread does (the rank stream of rank 0 of 1 reads every shard)."""
    reader = DatasetReader(data)
    rates = []
    for stream in (reader.iter_batches(batch, seed=0, keys=TRAINING_KEYS),
                   rank_batches(reader, batch, 0, 0, 1, TRAINING_KEYS)):
        t0 = time.perf_counter()
        views = sum(len(batch_to_tensors(b)["index"]) for b in stream)
        rates.append(views / (time.perf_counter() - t0))
    return reader.grid_size, rates[0], rates[1]


def step_flops(model_name: str, grid: int, batch: int = 2) -> tuple[float, float, int]:
    """(training-step FLOP per view, forward FLOP per view, parameters besides the flow) at ``grid``^3."""
    torch.manual_seed(0)
    model = build_model(default_config(model_name, grid_size=grid)).to_fast_layout().train()
    g = torch.Generator().manual_seed(0)
    batch_tensors = {"input": (torch.rand(batch, 2, grid, grid, grid, generator=g) > 0.9).float(),
                     "target": (torch.rand(batch, 1, grid, grid, grid, generator=g) > 0.7).float(),
                     "box": torch.rand(batch, 24, generator=g) * grid}
    with FlopCounterMode(display=False) as step:
        model.training_step(batch_tensors, model.make_optimizers(1e-3), StepContext(torch.device("cpu")))
    with FlopCounterMode(display=False) as forward, torch.no_grad():
        model.reconstruct(batch_tensors["input"])
    params = sum(p.numel() for name, p in model.named_parameters() if not name.startswith("flow."))
    return step.get_total_flops() / batch, forward.get_total_flops() / batch, params


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", help="training dataset directory of the --configs runs")
    parser.add_argument("--model", default="pssnet")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--log-every", type=int, default=5)
    parser.add_argument("--configs", nargs="*", default=["1x2:16", "2x1:16", "2x1:8"])
    parser.add_argument("--feed-data", nargs="*", default=[], help="datasets whose one-thread feed rate to measure")
    parser.add_argument("--flops-grids", type=int, nargs="*", default=[], help="grids whose step FLOPs to count")
    args = parser.parse_args()
    if args.configs:
        if not args.data:
            parser.error("--configs needs --data")
        print(f"{args.model} on {args.data}: {args.steps} steps per config")
        print(f"{'ranks x threads':>16} {'views/rank':>10} {'views/step':>10} {'steps/s':>8} {'views/s':>8} "
              f"{'wall s':>7} precision")
        with tempfile.TemporaryDirectory() as tmp:
            for config in args.configs:
                r = run_config(config, args, Path(tmp))
                print(f"{r['ranks']:>10} x {r['threads']:<3} {r['batch']:>10} {r['global_batch']:>10} "
                      f"{r['steps_per_s']:>8.2f} {r['views_per_s']:>8.1f} {r['wall_s']:>7.1f} {r['precision']}")
    for data in args.feed_data:
        grid, single, rank = feed_rate(data, 16)
        print(f"feed, one thread, {grid}^3 ({data}): {single:.0f} views/s (one process: iter_batches), "
              f"{rank:.0f} views/s (a rank: rank_batches)")
    for grid in args.flops_grids:
        step, forward, params = step_flops(args.model, grid)
        print(f"{args.model} {grid}^3: training step {step / 1e9:.2f} GFLOP per view (forward {forward / 1e9:.2f}), "
              f"{params / 1e6:.1f} M parameters besides the flow")


if __name__ == "__main__":
    main()
