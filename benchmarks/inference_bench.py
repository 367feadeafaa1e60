"""Inference latency: encoder once + decoder on N samples in one batch, at a precision against fp32.

    .venv/bin/python benchmarks/inference_bench.py [--grids 32 64] [--samples 20] [--repeats 15]
        [--threads 2] [--device cpu|cuda] [--precision auto|fp32|bf16] [--checkpoint32 PATH] [--checkpoint64 PATH]
    .venv/bin/python benchmarks/inference_bench.py --layers [--grids 32 64] [--samples 20]
    .venv/bin/python benchmarks/inference_bench.py --tail-chunks [--grids 32 64] [--repeats 15]

Without a checkpoint the model is randomly initialised (same FLOPs, so the same latency); the numeric
difference between bf16 and fp32 is only meaningful on trained weights, so pass checkpoints for it.
The first line names the CPU kind. Prints one row per grid: median ms in fp32, median ms at ``--precision``
("auto" by default: bf16 where the CPU runs it natively, else fp32; "bf16" forces it, emulated and slow on
AVX2-only CPUs), the path that ran (fused fp32 / fused bf16 / unfused), speed-up, and max |p - p_fp32| and the
fraction of voxels whose occupancy (> 0.5) differs. The two are timed interleaved, call by call, so that a
shared machine's load falls on both alike.

``--tail-chunks`` times the decoder with its later stages whole and in chunks of rows, interleaved (see
``Decoder3D.probabilities``). ``--layers`` instead times every kernel-2 stride-2 stage, channels_last_3d:
encoder convolutions at batch 1, decoder transposed convolutions on the batch of latents, each as torch's
layer (oneDNN) and as the BlockConv3d / BlockDeconv3d GEMM form the models use, with the GMAC/s each
reaches: the measurement behind that choice.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from pssnet_core.bench import cpu_kind
from pssnet_core.inference import Completer
from pssnet_core.models import PRECISIONS, build_model, default_config
from pssnet_core.models.checkpoint import load_checkpoint
from pssnet_core.models.networks import BlockConv3d, BlockDeconv3d


def _observation(grid: int, seed: int = 0) -> np.ndarray:
    """A box-like partial view: a front face and the free space in front of it."""
    rng = np.random.default_rng(seed)
    x = np.zeros((2, grid, grid, grid), np.float32)
    lo, hi = grid // 4 + rng.integers(0, 3), 3 * grid // 4
    x[0, lo, lo:hi, lo:hi] = 1
    x[1, :lo, lo:hi, lo:hi] = 1
    return x


def _time_interleaved(completers: list[Completer], x: np.ndarray, samples: int, repeats: int,
                      device: str) -> list[tuple[float, float, np.ndarray]]:
    """(median ms, best ms, probabilities) of each completer over ``repeats`` calls after a warm-up, taking turns
    call by call (on a shared machine only such numbers compare)."""
    for completer in completers:
        for _ in range(3):  # warm-up (weight packing, oneDNN primitive creation, allocator)
            completer.complete(x, samples, seed=0)
    times: list[list[float]] = [[] for _ in completers]
    results = [completer.complete(x, samples, seed=0).probabilities for completer in completers]
    for _ in range(repeats):
        for completer, own in zip(completers, times, strict=True):
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            completer.complete(x, samples, seed=0)
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            own.append((time.perf_counter() - t0) * 1000)
    return [(statistics.median(t), min(t), p) for t, p in zip(times, results, strict=True)]


def _median_ms(fn, repeats: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def layer_stages(grid: int, samples: int, repeats: int) -> None:
    """Every encoder stage (batch 1) and decoder stage (batch ``samples``): torch's layer vs the Block one."""
    config = default_config("pssnet", grid_size=grid)
    enc = list(zip([2, *config.channels[:-1]], config.channels, strict=True))
    widths = list(reversed(config.channels))
    dec = list(zip(widths, [*widths[1:], 1], strict=True))
    print(f"grid {grid}: stage     in->out  input   batch   torch ms (GMAC/s)   Block ms (GMAC/s)   max|diff|")
    torch.manual_seed(0)
    stages = [("encoder", i, c_in, c_out, grid // 2**i, 1, BlockConv3d, torch.nn.Conv3d)
              for i, (c_in, c_out) in enumerate(enc)]
    side = grid // 2 ** len(config.channels)
    stages += [("decoder", i, c_in, c_out, side * 2**i, samples, BlockDeconv3d, torch.nn.ConvTranspose3d)
               for i, (c_in, c_out) in enumerate(dec)]
    with torch.inference_mode():
        for part, i, c_in, c_out, size, batch, block_cls, torch_cls in stages:
            block = block_cls(c_in, c_out).to(memory_format=torch.channels_last_3d)
            reference = torch_cls(c_in, c_out, 2, 2).to(memory_format=torch.channels_last_3d)
            reference.load_state_dict(block.state_dict())
            x = torch.randn(batch, c_in, size, size, size).contiguous(memory_format=torch.channels_last_3d)
            out_voxels = batch * (size // 2 if part == "encoder" else size) ** 3
            gmac = out_voxels * c_in * c_out * 8 / 1e9
            t_torch = _median_ms(lambda: reference(x), repeats)  # noqa: B023 (called inside the loop)
            t_block = _median_ms(lambda: block(x), repeats)  # noqa: B023
            diff = (reference(x) - block(x)).abs().max().item()
            print(f"  {part} {i} {c_in:>5}->{c_out:<4} {size:>3}^3 {batch:>6} "
                  f"{t_torch:>10.2f} ({gmac / t_torch * 1e3:5.1f}) {t_block:>10.2f} ({gmac / t_block * 1e3:5.1f}) "
                  f"{diff:>10.1e}")


def tail_chunks(grid: int, samples: int, repeats: int) -> None:
    """``Decoder3D.probabilities`` with its later stages whole and in chunks (the default), interleaved call by
    call in this process (on a noisy machine only such ratios compare); checks that both give the same output."""
    from pssnet_core.models import networks

    torch.manual_seed(0)
    decoder = build_model(default_config("pssnet", grid_size=grid)).eval().decoder
    z = torch.randn(samples, decoder.dense.in_features)
    variants = {"whole": 1 << 60, "chunks": networks._TAIL_CHUNK_BYTES}
    times: dict[str, list[float]] = {name: [] for name in variants}
    outputs = {}
    try:
        with torch.inference_mode():
            for round_ in range(repeats + 2):  # two warm-up rounds
                for name, chunk_bytes in variants.items():
                    networks._TAIL_CHUNK_BYTES = chunk_bytes
                    t0 = time.perf_counter()
                    outputs[name] = decoder.probabilities(z)
                    if round_ >= 2:
                        times[name].append((time.perf_counter() - t0) * 1000)
    finally:
        networks._TAIL_CHUNK_BYTES = variants["chunks"]
    diff = (outputs["whole"] - outputs["chunks"]).abs().max().item()
    print(f"grid {grid}, decoder on {samples} latents, {repeats} interleaved rounds (ms median / min): "
          + ", ".join(f"{name} {statistics.median(t):.1f} / {min(t):.1f}" for name, t in times.items())
          + f"; max |difference| {diff:.1e}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grids", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--model", default="pssnet")
    parser.add_argument("--precision", default="auto", choices=PRECISIONS,
                        help="precision timed against fp32 (auto: bf16 where the CPU runs it natively, else fp32)")
    parser.add_argument("--checkpoint32", default=None)
    parser.add_argument("--checkpoint64", default=None)
    parser.add_argument("--layers", action="store_true",
                        help="time each kernel-2 stride-2 stage, torch layer vs Block layer")
    parser.add_argument("--tail-chunks", action="store_true",
                        help="time the decoder's later stages whole vs in chunks of rows (random weights)")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.tail_chunks:
        print(f"torch {torch.__version__}, threads {torch.get_num_threads()}")
        for grid in args.grids:
            tail_chunks(grid, args.samples, args.repeats)
        return
    if args.layers:
        print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, median of {args.repeats}")
        for grid in args.grids:
            layer_stages(grid, args.samples, args.repeats)
        return
    print(f"CPU: {cpu_kind()}; torch {torch.__version__}, threads {torch.get_num_threads()}, device {args.device}, "
          f"{args.samples} samples, median of {args.repeats}, precision {args.precision}")
    print(f"{'grid':>5} {'weights':>9} {'fp32 ms':>9} {'ms':>9}  {'path':<28} {'speed-up':>9} "
          f"{'max|dp|':>9} {'occ diff':>9}")
    numbers: dict[str, dict[str, float | str]] = {}
    for grid in args.grids:
        path = {32: args.checkpoint32, 64: args.checkpoint64}.get(grid)
        if path:
            model, config, _ = load_checkpoint(path)
            weights = "trained"
        else:
            torch.manual_seed(0)
            config = default_config(args.model, grid_size=grid)
            model = build_model(config)
            weights = "random"
        copy = build_model(config)
        copy.load_state_dict(model.state_dict())
        ref = Completer(model, config, device=args.device, precision="fp32")
        timed = Completer(copy, config, device=args.device, precision=args.precision)
        (fp32_ms, _, p_ref), (ms, best_ms, p) = _time_interleaved([ref, timed], _observation(grid), args.samples,
                                                                 args.repeats, args.device)
        diff = np.abs(p - p_ref)
        occ = float(((p > 0.5) != (p_ref > 0.5)).mean())
        print(f"{grid:>5} {weights:>9} {fp32_ms:>9.1f} {ms:>9.1f}  {timed.inference_path:<28} "
              f"{fp32_ms / ms:>8.2f}x {diff.max():>9.4f} {occ:>9.5f}   (best {best_ms:.1f} ms)")
        numbers[str(grid)] = {"weights": weights, "fp32_ms": fp32_ms, "ms": ms, "best_ms": best_ms,
                              "precision": timed.precision, "path": timed.inference_path,
                              "max_prob_diff": float(diff.max()), "occupancy_differs": occ}
    if args.json:
        args.json.write_text(json.dumps({"cpu": cpu_kind(), "samples": args.samples, "threads": args.threads,
                                         "grids": numbers}, indent=2))


if __name__ == "__main__":
    main()
