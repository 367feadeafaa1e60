"""The network against this CPU's limit and against other inference backends (encoder once + N samples).

    .venv/bin/python benchmarks/backend_bench.py --peak
    .venv/bin/python benchmarks/backend_bench.py --stages [--grids 32 64] [--samples 20] [--repeats 20]
    .venv/bin/python benchmarks/backend_bench.py --backends [--grids 32 64] [--samples 20] [--repeats 20]
        [--checkpoint32 PATH] [--int8] [--views 24] [--variants SUBSTRING ...]

``--peak``: the fp32 limit, as the best of a 2048^3 torch matmul (MKL) and, when installed, the same matmul
in ONNX Runtime (MLAS) and OpenVINO (oneDNN); plus the nominal FMA peak from the clock in /proc/cpuinfo.
1 MAC = 2 FLOP; GMAC/s throughout.

``--stages``: every kernel-2 stride-2 stage (encoder at batch 1, decoder on the batch of latents), as torch's
layer (oneDNN, channels_last_3d), as the Block layer (one GEMM + its own voxel shuffle) and, for the decoder,
as the GEMM on voxel rows in block order (what Decoder3D runs: no shuffle between stages), with ms, GMAC/s
and % of the measured peak.

``--backends``: the sampling network f(x, eps) = sigmoid(decoder(mu + sigma * eps)), (mu, sigma) from the
encoder run once, timed interleaved in one process: torch fp32 eager and channels_last_3d, fused (current:
what ``VAE.sample`` runs without autograd on the CPU, oneDNN matmuls with bias and activation fused in), the
plain GEMM + ReLU modules with the decoder in block order and per stage, torch's own layers, and the
network exported to ONNX (two
graphs: Conv/ConvTranspose nodes, and the block-order GEMM form) in ONNX Runtime (CPU EP) and OpenVINO
(CPU, f32). ``--int8`` adds ONNX Runtime static (QDQ) post-training quantisation, calibrated on rendered
views of other objects, run in both runtimes, and reports its occupancy agreement (> 0.5) with torch fp32
at the same latents on rendered views (the trained 32^3 model only: random weights give near-0.5
probabilities whose threshold flips mean nothing). bf16 is not tried where the CPU lacks AVX512-BF16/AMX:
there it is emulated and slower than fp32 (BENCHMARKS.md, training table).

onnx, onnxruntime and openvino are optional (not in requirements.txt); a missing one is reported and its
rows skipped. The latents use the Gaussian posterior for every dim (the shipped model's box-mixture head is
a few small matmuls, the same for every backend, and left out).
"""

from __future__ import annotations

import argparse
import copy
import importlib
import multiprocessing
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import nn

from pssnet_core.models import build_model, default_config
from pssnet_core.models.base import cpu_has_fast_bf16
from pssnet_core.models.checkpoint import load_checkpoint
from pssnet_core.models.networks import BlockConv3d, BlockDeconv3d, single_thread, to_memory_format
from pssnet_core.models.vae import VAE

Fn = Callable[[], Any]


def optional(name: str) -> ModuleType | None:
    """The module, or None with a line saying it is missing (the rows that need it are skipped)."""
    try:
        return importlib.import_module(name)
    except ImportError:
        print(f"[{name} is not installed: its rows are skipped; `pip install {name}` to measure it]")
        return None


def cpu_label() -> str:
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    name = next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("model name")),
                "unknown CPU")
    flags = next((set(line.split(":", 1)[1].split()) for line in text.splitlines() if line.startswith("flags")),
                 set())
    isa = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    fma = " + FMA" if "fma" in flags else ""
    bf16 = "native bf16" if cpu_has_fast_bf16() else "no native bf16"
    return f"{name} ({isa}{fma}, {bf16}), {torch.get_num_threads()} threads"


def nominal_peak_gmacs(threads: int) -> float | None:
    """Cores x FMA lanes x clock from /proc/cpuinfo: two 256-bit FMA units (8 fp32 each) per core with AVX2,
    two 512-bit ones with AVX-512. The nominal clock; boost may exceed it."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    mhz = [float(line.split(":")[1]) for line in text.splitlines() if line.startswith("cpu MHz")]
    if not mhz or "fma" not in text:
        return None
    lanes = 16 if "avx512f" in text else 8
    return threads * 2 * lanes * max(mhz) / 1e3


def interleaved(fns: dict[str, Fn], repeats: int, warmup: int = 3) -> dict[str, list[float]]:
    """ms per call of each function, the functions taking turns so that load from other processes on this
    shared machine hits all of them alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t0) * 1e3)
    return times


# ------------------------------------------------------------------------------------------------ peak
def _matmul_onnx(onnx: ModuleType, n: int) -> bytes:
    helper, tp = onnx.helper, onnx.TensorProto
    node = helper.make_node("MatMul", ["a", "b"], ["c"])
    graph = helper.make_graph([node], "matmul", [helper.make_tensor_value_info(k, tp.FLOAT, [n, n]) for k in "ab"],
                              [helper.make_tensor_value_info("c", tp.FLOAT, [n, n])])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


def measure_peak(threads: int, repeats: int = 20, n: int = 2048) -> dict[str, float]:
    """Best GMAC/s of an n^3 fp32 matmul per library (the best run: the limit, not the typical)."""
    a, b = np.random.default_rng(0).standard_normal((2, n, n), dtype=np.float32)
    fns: dict[str, Fn] = {"torch (MKL)": lambda: torch.from_numpy(a) @ torch.from_numpy(b)}
    onnx, ort, ov = optional("onnx"), optional("onnxruntime"), optional("openvino")
    if onnx is not None and ort is not None:
        session = ort_session(ort, _matmul_onnx(onnx, n), threads)
        fns["onnxruntime (MLAS)"] = lambda: session.run(None, {"a": a, "b": b})
    if onnx is not None and ov is not None:
        compiled = ov_compile(ov, _matmul_onnx(onnx, n), threads)
        fns["openvino (oneDNN)"] = lambda: compiled({"a": a, "b": b})
    times = interleaved(fns, repeats, warmup=2)
    return {name: n**3 / min(t) / 1e6 for name, t in times.items()}


def print_peak(threads: int) -> float:
    peaks = measure_peak(threads)
    for name, gmacs in peaks.items():
        print(f"  2048^3 matmul, {name:<20} {gmacs:6.1f} GMAC/s ({2 * gmacs:6.1f} GFLOP/s), best run")
    nominal = nominal_peak_gmacs(threads)
    if nominal is not None:
        print(f"  nominal FMA peak ({threads} cores, cpuinfo clock) {nominal:6.1f} GMAC/s")
    # A shared machine rarely gives a quiet window for the matmul; boost clocks exceed the nominal one.
    best = max(*peaks.values(), nominal or 0.0)
    print(f"  peak used for %: {best:.1f} GMAC/s (the larger of the best matmul and the nominal peak)")
    return best


# ---------------------------------------------------------------------------------------------- stages
def stages(grid: int, samples: int, repeats: int, peak: float) -> None:
    """Per-stage ms (median, min), GMAC/s and % of peak (on the median) of each form of each stage."""
    config = default_config("pssnet", grid_size=grid)
    widths = list(reversed(config.channels))
    side = config.bottleneck
    torch.manual_seed(0)
    cl = torch.channels_last_3d
    print(f"grid {grid}^3 (encoder batch 1, decoder batch {samples}): ms median / min, GMAC/s and % of peak "
          "on the median")
    total: dict[str, float] = {}
    with torch.inference_mode():
        plan = [("encoder", i, c_in, c_out) for i, (c_in, c_out)
                in enumerate(zip([2, *config.channels[:-1]], config.channels, strict=True))]
        plan += [("decoder", i, c_in, c_out) for i, (c_in, c_out)
                 in enumerate(zip(widths, [*widths[1:], 1], strict=True))]
        for part, i, c_in, c_out in plan:
            if part == "encoder":
                size, batch = grid // 2**i, 1
                block: nn.Module = BlockConv3d(c_in, c_out).to(memory_format=cl)
                layer: nn.Module = nn.Conv3d(c_in, c_out, 2, 2).to(memory_format=cl)
                macs = batch * (size // 2) ** 3 * c_in * c_out * 8
            else:
                size, batch = side * 2**i, samples
                block = BlockDeconv3d(c_in, c_out).to(memory_format=cl)
                layer = nn.ConvTranspose3d(c_in, c_out, 2, 2).to(memory_format=cl)
                macs = batch * size**3 * c_in * c_out * 8
            layer.load_state_dict(block.state_dict())
            x = torch.randn(batch, c_in, size, size, size).contiguous(memory_format=cl)
            fns: dict[str, Fn] = {"torch layer": lambda: layer(x), "Block layer": lambda: block(x)}  # noqa: B023
            if part == "decoder":
                rows = x.permute(0, 2, 3, 4, 1).reshape(-1, c_in)
                fns["block order"] = lambda: block.block_rows(rows)  # noqa: B023
            times = interleaved(fns, repeats)
            cells = []
            for name, t in times.items():
                med = statistics.median(t)
                total[f"{part} {name}"] = total.get(f"{part} {name}", 0.0) + med
                gmacs = macs / med / 1e6
                cells.append(f"{name} {med:7.2f} / {min(t):6.2f} ms {gmacs:5.1f} GMAC/s {100 * gmacs / peak:4.0f} %")
            print(f"  {part} {i} {c_in:>4}->{c_out:<4} {size:>3}^3 {macs / 1e6:7.1f} MMAC | " + " | ".join(cells))
    print("  sums of medians: " + ", ".join(f"{k} {v:.2f} ms" for k, v in total.items()))


# -------------------------------------------------------------------------------------------- networks
def per_stage_decode(model: VAE, z: torch.Tensor) -> torch.Tensor:
    """The decoder as its stage modules in a row, each output in spatial order (the path before block order;
    with torch's own layers in ``deconv``, the plain oneDNN decoder)."""
    dec = model.decoder
    h = torch.relu(dec.dense(z)).view(-1, dec.top, dec.side, dec.side, dec.side)
    return dec.deconv(to_memory_format(h, dec.deconv))


def torch_layers(model: VAE) -> VAE:
    """A copy whose kernel-2 stride-2 layers are torch's Conv3d / ConvTranspose3d (same weights)."""
    plain = copy.deepcopy(model)
    for seq, cls in ((plain.encoder.conv, nn.Conv3d), (plain.decoder.deconv, nn.ConvTranspose3d)):
        for i, layer in enumerate(seq):
            if isinstance(layer, BlockConv3d | BlockDeconv3d):
                seq[i] = cls(layer.in_channels, layer.out_channels, 2, 2)
                seq[i].load_state_dict(layer.state_dict())
    return plain


class SampleNet(nn.Module):
    """Encoder once, z = mu + sigma * eps for every row of ``eps``, decoder on all z, sigmoid: the sampling
    network with the noise as an input, so that every backend decodes the same latents.

    ``fused``: what ``VAE.sample`` runs without autograd on the CPU (fused oneDNN matmuls, one gather); else the
    plain GEMM + ReLU modules (the training path), in block order or ``per_stage``.
    """

    def __init__(self, model: VAE, per_stage: bool = False, fused: bool = False) -> None:
        super().__init__()
        self.model = model
        self.per_stage = per_stage
        self.fused = fused

    def forward(self, x: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        enc = self.model.encoder
        if self.fused:
            with single_thread():  # as VAE.sample runs one input's encoder
                mu, logvar = self.model._posterior(enc(x))
        else:
            mu, logvar = self.model._posterior(enc.dense(enc.conv(x).flatten(1)))
        z = mu + torch.exp(0.5 * logvar) * eps
        if self.fused:
            return self.model.decode_probabilities(z)
        return torch.sigmoid(per_stage_decode(self.model, z) if self.per_stage else self.model.decode(z))


def export_onnx(net: nn.Module, x: torch.Tensor, eps: torch.Tensor, path: Path) -> Path:
    with warnings.catch_warnings():  # the TorchScript exporter: the dynamo one would need onnxscript too
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (x, eps), str(path), input_names=["x", "eps"], output_names=["p"],
                          opset_version=17, dynamo=False)
    return path


def ort_session(ort: ModuleType, model: bytes | Path, threads: int) -> Any:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # No spin-waiting after a run: it would take CPU from the variant timed next in the same process.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])


def ov_compile(ov: ModuleType, model: bytes | Path, threads: int) -> Any:
    core = ov.Core()
    network = core.read_model(model, b"") if isinstance(model, bytes) else core.read_model(str(model))
    return core.compile_model(network, "CPU", {"INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": "f32",
                                               "PERFORMANCE_HINT": "LATENCY"})


# ---------------------------------------------------------------------------------------------- views
def rendered_views(grid: int, count: int, seed: int, root: Path) -> list[np.ndarray]:
    """(2, N, N, N) network inputs of rendered views of the validation objects (``seed`` picks them)."""
    from pssnet_core.data.build import build
    from pssnet_core.data.store import DatasetReader

    per = max(1, count // 8)
    results = build("all", "val", root / f"views{grid}_{seed}_{count}", grid_size=grid, seed=seed, num_objects=4,
                    views=per, progress=False)
    views: list[np.ndarray] = []
    for result in results:
        reader = DatasetReader(result.path)
        for shard in range(reader.num_shards):
            s = reader.load_shard(shard, keys=["known_occupied", "known_free"])
            views += [np.stack([o, f]).astype(np.float32) for o, f in zip(s["known_occupied"], s["known_free"],
                                                                          strict=True)]
    return views[:count]


def calibration_reader(ort_quant: ModuleType, views: list[np.ndarray], samples: int, latent: int) -> Any:
    class Reader(ort_quant.CalibrationDataReader):  # type: ignore[name-defined, misc]
        def __init__(self) -> None:
            rng = np.random.default_rng(1)
            self.items = iter([{"x": v[None], "eps": rng.standard_normal((samples, latent), dtype=np.float32)}
                               for v in views])

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.items, None)

    return Reader()


def quantize_int8(ort_quant: ModuleType, src: Path, dst: Path, views: list[np.ndarray], samples: int,
                  latent: int) -> Path:
    """Static QDQ int8: per-channel int8 weights, uint8 activations, only the conv/GEMM nodes (exp, sigmoid
    and the elementwise ops stay fp32). reduce_range: without VNNI, AVX2's u8 x s8 multiply-add saturates at
    16 bits on full-range weights (onnxruntime's quantisation notes)."""
    ort_quant.quantize_static(
        str(src), str(dst), calibration_reader(ort_quant, views, samples, latent),
        quant_format=ort_quant.QuantFormat.QDQ, per_channel=True, reduce_range=True,
        activation_type=ort_quant.QuantType.QUInt8, weight_type=ort_quant.QuantType.QInt8,
        op_types_to_quantize=["Conv", "ConvTranspose", "MatMul", "Gemm"],
        calibrate_method=ort_quant.CalibrationMethod.MinMax)
    return dst


# -------------------------------------------------------------------------------------------- backends
def load_model(grid: int, checkpoint: str | None) -> tuple[VAE, str]:
    if checkpoint:
        model, _, _ = load_checkpoint(checkpoint)
        return model.float().eval(), "trained"
    torch.manual_seed(0)
    return build_model(default_config("pssnet", grid_size=grid)).eval(), "random"


TORCH_VARIANTS = {  # name: (channels_last_3d, per-stage decoder, torch's own layers, fused)
    "torch fp32 channels_last, fused (current)": (True, False, False, True),
    "torch fp32 eager, fused": (False, False, False, True),
    "torch fp32 eager, block order": (False, False, False, False),
    "torch fp32 channels_last, block order": (True, False, False, False),
    "torch fp32 eager, per stage": (False, True, False, False),
    "torch fp32 channels_last, per stage": (True, True, False, False),
    "torch fp32 channels_last, torch layers": (True, True, True, False),
}
REFERENCE = "torch fp32 channels_last, fused (current)"  # what Completer runs on an AVX2 CPU
BEFORE = "torch fp32 channels_last, block order"  # the path before fusion (and the training path)


def make_runner(name: str, grid: int, checkpoint: str | None, graph: str | None,
                threads: int) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """(x, eps) -> probabilities of one variant: a torch one of TORCH_VARIANTS or '<runtime> <graph name>'."""
    torch.set_num_threads(threads)
    if name in TORCH_VARIANTS:
        channels_last, per_stage, plain, fused = TORCH_VARIANTS[name]
        model, _ = load_model(grid, checkpoint)
        model = torch_layers(model) if plain else model
        net = SampleNet(model.to_fast_layout() if channels_last else model, per_stage=per_stage, fused=fused)

        def run_torch(x: np.ndarray, eps: np.ndarray) -> np.ndarray:
            with torch.inference_mode():
                return net(torch.from_numpy(x), torch.from_numpy(eps)).numpy()

        return run_torch
    assert graph is not None
    if name.startswith("onnxruntime"):
        session = ort_session(importlib.import_module("onnxruntime"), Path(graph), threads)
        return lambda x, eps: session.run(None, {"x": x, "eps": eps})[0]
    compiled = ov_compile(importlib.import_module("openvino"), Path(graph), threads)
    return lambda x, eps: compiled({"x": x, "eps": eps})[0]


def worker(conn: Any, name: str, grid: int, checkpoint: str | None, graph: str | None, threads: int) -> None:
    """One variant in its own process. Why: in one process the runtimes' thread pools (OpenMP, TBB, ORT's)
    compete for the 2 cores and spin after each call, which slowed whichever ran next by up to 3x."""
    run = make_runner(name, grid, checkpoint, graph, threads)
    while (msg := conn.recv()) is not None:
        if msg[0] == "time":
            _, x, eps, n = msg
            times = []
            for _ in range(n):
                t0 = time.perf_counter()
                run(x, eps)
                times.append((time.perf_counter() - t0) * 1e3)
            conn.send(times)
        else:
            conn.send(run(msg[1], msg[2]))


class Variants:
    """Worker processes, one per variant, that take turns: only one computes at any time."""

    def __init__(self, specs: dict[str, str | None], grid: int, checkpoint: str | None, threads: int) -> None:
        context = multiprocessing.get_context("spawn")
        self.conns: dict[str, Any] = {}
        self.procs = []
        for name, graph in specs.items():
            parent, child = context.Pipe()
            proc = context.Process(target=worker, args=(child, name, grid, checkpoint, graph, threads), daemon=True)
            proc.start()
            self.conns[name], self.procs = parent, [*self.procs, proc]

    def time(self, x: np.ndarray, eps: np.ndarray, repeats: int, warmup: int = 3) -> dict[str, list[float]]:
        times: dict[str, list[float]] = {name: [] for name in self.conns}
        for round_ in range(warmup + repeats):
            for name, conn in self.conns.items():
                conn.send(("time", x, eps, 1))
                t = conn.recv()
                if round_ >= warmup:
                    times[name] += t
        return times

    def outputs(self, x: np.ndarray, eps: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for name, conn in self.conns.items():
            conn.send(("out", x, eps))
            out[name] = conn.recv()
        return out

    def close(self) -> None:
        for conn in self.conns.values():
            conn.send(None)
        for proc in self.procs:
            proc.join(timeout=30)


def backends(grid: int, samples: int, repeats: int, checkpoint: str | None, int8: bool, views: int,
             threads: int, peak: float, work: Path, only: list[str] | None = None) -> None:
    model, weights = load_model(grid, checkpoint)
    latent = model.latent_dim
    x0 = rendered_views(grid, 1, 0, work)[0][None]
    eps0 = np.random.default_rng(0).standard_normal((samples, latent), dtype=np.float32)
    specs: dict[str, str | None] = dict.fromkeys(TORCH_VARIANTS)
    onnx, ort, ov = optional("onnx"), optional("onnxruntime"), optional("openvino")
    if onnx is not None:
        x_t, eps_t = torch.from_numpy(x0), torch.from_numpy(eps0)
        graphs = {"conv graph": export_onnx(SampleNet(torch_layers(model), per_stage=True), x_t, eps_t,
                                            work / f"conv{grid}.onnx"),
                  "gemm graph": export_onnx(SampleNet(model), x_t, eps_t, work / f"gemm{grid}.onnx")}
        ort_quant = optional("onnxruntime.quantization") if int8 and ort is not None else None
        if ort_quant is not None:
            calib = rendered_views(grid, views, 1, work)
            for name in list(graphs):
                graphs[f"{name} int8"] = quantize_int8(ort_quant, graphs[name], work / f"{name[:4]}{grid}_int8.onnx",
                                                       calib, samples, latent)
        for runtime, module in (("onnxruntime", ort), ("openvino", ov)):
            if module is not None:
                specs |= {f"{runtime} {name}": str(path) for name, path in graphs.items()}
    if only:  # the reference variants stay: the speed-up and the agreement are measured against them
        specs = {k: v for k, v in specs.items() if k in (REFERENCE, BEFORE) or any(o in k for o in only)}
    variants = Variants(specs, grid, checkpoint, threads)
    try:
        times = variants.time(x0, eps0, repeats)
        macs = network_macs(model, samples)
        base = statistics.median(times[BEFORE])
        print(f"grid {grid}^3, {weights} weights, encoder + {samples} samples, {macs / 1e9:.2f} GMAC, each variant "
              f"in its own process, taking turns: ms median / min, GMAC/s and % of peak on the median, speed-up "
              f"(median) vs '{BEFORE}'")
        for name, t in times.items():
            med = statistics.median(t)
            gmacs = macs / med / 1e6
            print(f"  {name:<46} {med:8.1f} / {min(t):8.1f} ms {gmacs:6.1f} GMAC/s {100 * gmacs / peak:4.0f} % "
                  f"{base / med:5.2f}x")
        if weights == "trained":
            agreement(variants, grid, samples, latent, views, work)
    finally:
        variants.close()


def network_macs(model: VAE, samples: int) -> int:
    """Multiply-adds of one call: encoder at batch 1, decoder at batch ``samples`` (convs and dense layers)."""
    def count(module: nn.Module, x: torch.Tensor) -> int:
        total = 0

        def hook(m: nn.Module, inputs: tuple[torch.Tensor, ...], out: torch.Tensor) -> None:
            nonlocal total
            if isinstance(m, nn.Linear):
                total += out.numel() * m.in_features
            elif isinstance(m, nn.Conv3d):  # one output voxel: C_in x 8 MACs per output channel
                total += out.numel() * m.in_channels * 8
            elif isinstance(m, nn.ConvTranspose3d):  # one input voxel: C_in x C_out x 8
                total += inputs[0].numel() * m.out_channels * 8

        handles = [m.register_forward_hook(hook) for m in module.modules()]
        with torch.inference_mode():
            module(x)
        for h in handles:
            h.remove()
        return total

    plain = torch_layers(model)
    dec = plain.decoder
    n = model.grid_size
    return (count(plain.encoder, torch.zeros(1, 2, n, n, n))
            + count(nn.Sequential(dec.dense, nn.Unflatten(1, (dec.top, dec.side, dec.side, dec.side)), dec.deconv),
                    torch.zeros(samples, model.latent_dim)))


def agreement(variants: Variants, grid: int, samples: int, latent: int, count: int, work: Path) -> None:
    """Fraction of voxels whose occupancy (> 0.5) equals torch fp32's (the current fast path), same view and
    latents, over ``count`` rendered views; and the worst single view."""
    views = rendered_views(grid, count, 0, work)
    rng = np.random.default_rng(0)
    equal: dict[str, list[float]] = {}
    for view in views:
        outputs = variants.outputs(view[None], rng.standard_normal((samples, latent), dtype=np.float32))
        ref = outputs[REFERENCE] > 0.5
        for name, out in outputs.items():
            equal.setdefault(name, []).append(float(((out > 0.5) == ref).mean()))
    print(f"  occupancy agreement with '{REFERENCE}' at the same latents, {len(views)} rendered views x {samples} "
          "samples: all voxels (worst view)")
    for name, fractions in equal.items():
        print(f"  {name:<46} {100 * statistics.mean(fractions):8.3f} % ({100 * min(fractions):.3f} %)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--peak", action="store_true", help="the fp32 matmul limit only")
    parser.add_argument("--stages", action="store_true", help="per-stage forms, ms, GMAC/s, %% of peak")
    parser.add_argument("--backends", action="store_true", help="whole network in torch, ONNX Runtime, OpenVINO")
    parser.add_argument("--int8", action="store_true", help="with --backends: static int8 quantisation too")
    parser.add_argument("--grids", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--views", type=int, default=24, help="rendered views for calibration and agreement")
    parser.add_argument("--variants", nargs="+", default=None,
                        help="with --backends: only the variants whose names contain one of these (and the two "
                             "torch reference variants)")
    parser.add_argument("--checkpoint32", default=None)
    parser.add_argument("--checkpoint64", default=None)
    args = parser.parse_args()
    if not (args.peak or args.stages or args.backends):
        parser.error("choose --peak, --stages and/or --backends")
    torch.set_num_threads(args.threads)
    print(f"{cpu_label()}; torch {torch.__version__}")
    peak = print_peak(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        for grid in args.grids:
            if args.stages:
                stages(grid, args.samples, args.repeats, peak)
            if args.backends:
                checkpoint = {32: args.checkpoint32, 64: args.checkpoint64}.get(grid)
                backends(grid, args.samples, args.repeats, checkpoint, args.int8, args.views, args.threads, peak,
                         Path(tmp), args.variants)


if __name__ == "__main__":
    main()
