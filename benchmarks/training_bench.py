"""Training speed: ms per sample of one full training step, fp32 vs bf16 autocast (channels_last_3d).

    .venv/bin/python benchmarks/training_bench.py [--grids 32 64] [--model pssnet] [--batch-size 16]
        [--steps 5] [--threads 2] [--device cpu|cuda]

Rows: fp32 contiguous (eager reference), fp32 channels_last_3d, bf16 autocast + channels_last_3d.
Random cuboid-like batches; the median over ``--steps`` steps after two warm-up steps.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pssnet_core.models import StepContext, build_model, default_config


def _batch(grid: int, size: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(size, 2, grid, grid, grid, generator=g) > 0.9).float()
    y = (torch.rand(size, 1, grid, grid, grid, generator=g) > 0.7).float()
    box = torch.rand(size, 24, generator=g) * grid
    return {"input": x, "target": y, "box": box}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grids", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--model", default="pssnet")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {device}, model {args.model}, "
          f"batch {args.batch_size}, median of {args.steps} steps")
    print(f"{'grid':>5} {'mode':>22} {'ms/step':>9} {'ms/sample':>10}")
    for grid in args.grids:
        batch = _batch(grid, args.batch_size)
        for label, layout, dtype in (("fp32 contiguous", False, None), ("fp32 channels_last", True, None),
                                     ("bf16 channels_last", True, torch.bfloat16)):
            torch.manual_seed(0)
            model = build_model(default_config(args.model, grid_size=grid)).to(device).train()
            if layout:
                model.to_fast_layout()
            opts = model.make_optimizers(1e-3)
            ctx = StepContext(device, dtype)
            times = []
            for i in range(args.steps + 2):
                if device.type == "cuda":
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                model.training_step(batch, opts, ctx)
                if device.type == "cuda":
                    torch.cuda.synchronize()
                if i >= 2:
                    times.append((time.perf_counter() - t0) * 1000)
            ms = statistics.median(times)
            print(f"{grid:>5} {label:>22} {ms:>9.1f} {ms / args.batch_size:>10.2f}")


if __name__ == "__main__":
    main()
