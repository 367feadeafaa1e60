"""Is a corrupt or untrained model ever served? Each corruption the integrity checks must catch, applied to a
copy of the shipped checkpoint, then loaded and called the way the node does.

Per case, the copy is loaded for serving (``CompletionPipeline.from_checkpoint``, what the node's configure
calls: exit code 2 when it raises) and, if that succeeds, completes a rendered held-out mug (the first
service call). The outcome is ``refused at load``, ``refused at the first call`` (a ValueError: the node answers
``success: false``) or ``SERVED`` (a success: what must never happen to a corrupt model). Corruptions:

- bytes of the file's weight storage as archived (raw, or deflated in an export; ``torch.load`` checks no CRC,
  so a corrupt deflated member mostly inflates to wrong weights): 10 flipped bits, 4 KB zeroed, 4 KB of random
  bytes, each at ``--trials`` random places;
- weights edited in the stored state dict, the integrity record left as it was ("edited"), or the model saved
  again through ``save_checkpoint`` so that its record describes the corrupt weights ("re-saved"): one NaN
  weight, a NaN in the last layer, the output bias at -60000 or +inf, every weight of a freshly initialised model
  (``--trials`` seeds);
- the file truncated, and a config that does not fit the weights (refused before this issue too).

Also times the checks on the intact checkpoint: loading with and without them, and the self-test alone.

    .venv/bin/python benchmarks/integrity_bench.py [--trials 10] [--threads 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import struct
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pssnet_core.data.scenes import render_view
from pssnet_core.inference import DEFAULT_CHECKPOINT
from pssnet_core.models.checkpoint import load_verified, read_checkpoint, save_checkpoint
from pssnet_core.models.registry import build_model
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig
from pssnet_core.shapes import make_shape

LAST_LAYER = "decoder.deconv.{}.{}"  # filled in with the index of the decoder's last layer


@dataclass(frozen=True)
class Outcome:
    case: str
    outcome: str  # "refused at load" | "refused at the first call" | "SERVED"
    reason: str


def weight_storage(path: Path) -> list[tuple[int, int]]:
    """(offset, length) in the file of each tensor storage's bytes as archived: raw where ``torch.save`` stored them,
    deflated in an export (``checkpoint._deflate_archive``)."""
    spans = []
    with zipfile.ZipFile(path) as archive, path.open("rb") as raw:
        for info in archive.infolist():
            if "/data/" in info.filename and info.compress_size:
                raw.seek(info.header_offset)
                header = raw.read(30)
                name_len, extra_len = struct.unpack("<HH", header[26:30])
                spans.append((info.header_offset + 30 + name_len + extra_len, info.compress_size))
    return spans


def pick_offset(spans: list[tuple[int, int]], length: int, rng: np.random.Generator) -> int:
    """A random offset whose ``length`` bytes lie inside one storage (chosen in proportion to its size)."""
    sizes = np.array([max(size - length, 0) + 1 if size >= length else 0 for _, size in spans], float)
    index = int(rng.choice(len(spans), p=sizes / sizes.sum()))
    start, size = spans[index]
    return start + int(rng.integers(0, size - length + 1))


def edit_bytes(path: Path, rng: np.random.Generator, kind: str) -> None:
    data = bytearray(path.read_bytes())
    spans = weight_storage(path)
    if kind == "flip":
        for _ in range(10):
            offset = pick_offset(spans, 1, rng)
            data[offset] ^= 1 << int(rng.integers(0, 8))
    else:
        offset = pick_offset(spans, 4096, rng)
        data[offset:offset + 4096] = bytes(4096) if kind == "zero" else rng.bytes(4096)
    path.write_bytes(bytes(data))


def last_layer_index(state: dict[str, torch.Tensor]) -> int:
    return max(int(name.split(".")[2]) for name in state if name.startswith("decoder.deconv.") and
               name.endswith(".bias"))


def edit_state(path: Path, edit: Callable[[dict[str, torch.Tensor], np.random.Generator], None],
               rng: np.random.Generator, resave: bool) -> None:
    """Applies ``edit`` to the stored weights; ``resave`` writes them through save_checkpoint (a fresh record)."""
    payload = torch.load(path, weights_only=True)
    state = payload["state_dict"]
    edit(state, rng)
    if not resave:
        torch.save(payload, path)
        return
    from pssnet_core.models.config import config_from_dict

    model = build_model(config_from_dict(payload["config"]))
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()}, strict=False)
    save_checkpoint(path, model, extra=payload["extra"], half=True, inference_only=True)


def one_nan(state: dict[str, torch.Tensor], rng: np.random.Generator) -> None:
    names = [n for n, t in state.items() if t.is_floating_point() and t.numel()]
    tensor = state[names[int(rng.integers(0, len(names)))]]
    tensor.view(-1)[int(rng.integers(0, tensor.numel()))] = float("nan")


def nan_last_layer(state: dict[str, torch.Tensor], rng: np.random.Generator) -> None:
    weight = state[LAST_LAYER.format(last_layer_index(state), "weight")]
    weight.view(-1)[int(rng.integers(0, weight.numel()))] = float("nan")


def set_bias(value: float) -> Callable[[dict[str, torch.Tensor], np.random.Generator], None]:
    def edit(state: dict[str, torch.Tensor], rng: np.random.Generator) -> None:
        del rng
        state[LAST_LAYER.format(last_layer_index(state), "bias")].fill_(value)
    return edit


def random_init(config_source: Path) -> Callable[[dict[str, torch.Tensor], np.random.Generator], None]:
    from pssnet_core.models.config import config_from_dict

    config = config_from_dict(read_checkpoint(config_source)["config"])

    def edit(state: dict[str, torch.Tensor], rng: np.random.Generator) -> None:
        torch.manual_seed(int(rng.integers(0, 2**31)))
        fresh = build_model(config).state_dict()
        for name, tensor in state.items():
            tensor.copy_(fresh[name].to(tensor.dtype))
    return edit


def truncate(path: Path, rng: np.random.Generator) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:int(rng.integers(1, len(data)))])


def mismatch_config(path: Path, rng: np.random.Generator) -> None:
    del rng
    payload = torch.load(path, weights_only=True)
    payload["config"]["latent_dim"] = int(payload["config"]["latent_dim"]) + 8
    torch.save(payload, path)


def try_serving(path: Path, scene, threads: int) -> tuple[str, str]:
    try:
        pipeline = CompletionPipeline.from_checkpoint(path, PipelineConfig(num_samples=20), threads=threads)
    except ValueError as error:
        return "refused at load", str(error)
    try:
        result = pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=True)
    except ValueError as error:
        return "refused at the first call", str(error)
    except Exception as error:  # the node answers these "internal error", success: false
        return "refused at the first call", f"internal error: {type(error).__name__}: {error}"
    voxels = sum(len(c) for c in result.completions)
    best = float(result.grasps.scores[0]) if result.grasps is not None and len(result.grasps.scores) else float("nan")
    return "SERVED", f"{result.num_samples} samples, {voxels} voxels, best grasp score {best:.2f}"


def timings(repeats: int) -> dict[str, float]:
    """Median seconds: read + weight checks, full load for serving, the self-test alone, plain torch.load."""
    plain, read, full, test = [], [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.load(DEFAULT_CHECKPOINT, weights_only=True)
        t1 = time.perf_counter()
        read_checkpoint(DEFAULT_CHECKPOINT)
        t2 = time.perf_counter()
        loaded = load_verified(DEFAULT_CHECKPOINT, for_serving=True)
        t3 = time.perf_counter()
        plain.append(t1 - t0)
        read.append(t2 - t1)
        full.append(t3 - t2)
        test.append(loaded.self_test.seconds)
    return {"torch_load_s": statistics.median(plain), "read_and_weight_checks_s": statistics.median(read),
            "load_for_serving_s": statistics.median(full), "self_test_s": statistics.median(test),
            "self_test_max_s": max(test)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10, help="random places / seeds per randomised corruption")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timing-repeats", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    scene = render_view(make_shape("mug", 2_000_000), yaw_deg=0.0, distance=0.6, tilt_deg=30.0)
    cases: list[tuple[str, int, Callable[[Path, np.random.Generator], None]]] = [
        ("intact (control)", 1, lambda p, r: None),
        ("10 flipped bits in the weights", args.trials, lambda p, r: edit_bytes(p, r, "flip")),
        ("4 KB of the weights zeroed", args.trials, lambda p, r: edit_bytes(p, r, "zero")),
        ("4 KB of the weights random", args.trials, lambda p, r: edit_bytes(p, r, "random")),
    ]
    edits = [("one NaN weight", one_nan, args.trials), ("NaN in the last layer", nan_last_layer, 1),
             ("output bias -60000", set_bias(-60000.0), 1), ("output bias +inf", set_bias(float("inf")), 1),
             ("randomly initialised model", random_init(DEFAULT_CHECKPOINT), args.trials)]
    for name, edit, trials in edits:
        for resave in (False, True):
            label = f"{name}, {'re-saved with a fresh record' if resave else 'edited, record stale'}"
            cases.append((label, trials, lambda p, r, edit=edit, resave=resave: edit_state(p, edit, r, resave)))
    cases += [("file truncated", args.trials, truncate), ("config does not fit the weights", 1, mismatch_config)]

    outcomes: list[Outcome] = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, trials, corrupt in cases:
            for trial in range(trials):
                copy = Path(tmp) / f"case{len(outcomes)}.pt"
                shutil.copyfile(DEFAULT_CHECKPOINT, copy)
                corrupt(copy, rng)
                outcome, reason = try_serving(copy, scene, args.threads)
                outcomes.append(Outcome(label, outcome, reason))
                print(f"[integrity] {label} #{trial + 1}: {outcome}: {reason[:160]}", flush=True)
    print("\n| corruption | trials | refused at load | refused at the first call | served |\n|---|---|---|---|---|")
    for label, _, _ in cases:
        rows = [o for o in outcomes if o.case == label]
        count = {k: sum(o.outcome == k for o in rows) for k in ("refused at load", "refused at the first call",
                                                                 "SERVED")}
        print(f"| {label} | {len(rows)} | {count['refused at load']} | {count['refused at the first call']} | "
              f"{count['SERVED']} |")
    served = [o for o in outcomes[1:] if o.outcome == "SERVED"]
    times = timings(args.timing_repeats)
    print(f"\n[integrity] corrupt copies served: {len(served)} of {len(outcomes) - 1}; control: {outcomes[0].outcome}")
    print("[integrity] medians over {} loads: torch.load {:.0f} ms, read + weight checks {:.0f} ms, load for serving "
          "{:.0f} ms, self-test {:.0f} ms (max {:.0f} ms)".format(args.timing_repeats, *(1000 * v for v in (
              times["torch_load_s"], times["read_and_weight_checks_s"], times["load_for_serving_s"],
              times["self_test_s"], times["self_test_max_s"]))))
    if args.json:
        args.json.write_text(json.dumps({"outcomes": [o.__dict__ for o in outcomes], "timings": times}, indent=1))
    return 0 if not served and outcomes[0].outcome == "SERVED" else 1


if __name__ == "__main__":
    raise SystemExit(main())
