"""One view through the whole pipeline (observation, network, grasps) per device and sampler: where a GPU helps.

Times ``CompletionPipeline.run`` (the node's work for one request, without ROS transport) for the shipped model
with each sampler (posterior, checked) on each device in ``--devices``, 20 samples and grasps on, over a few
held-out views (mugs with the handle hidden and seen, a box behind the narrow slit). Prints the p50 of every step
per setting, the checked / posterior ratio per device and each device's speed-up over the first.

Rendering the views needs open3d; a machine without it (the lent GPU machines) reads them from a file written
on one with it:

    .venv/bin/python benchmarks/pipeline_bench.py --write-views views.npz
    PYTHONPATH=$PWD/pssnet_core python3 benchmarks/pipeline_bench.py --views views.npz --devices cuda cpu [--threads 2]
        [--precision auto|fp32|bf16] [--repeats 10] [--samples 20] [--json out.json]
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
from pssnet_core.geometry import CameraIntrinsics
from pssnet_core.pipeline import CompletionPipeline, PipelineConfig
from pssnet_core.sampling import SAMPLERS

STEPS = ("observe", "network", "centres", "grasps", "total")


def write_views(path: Path) -> None:
    from pssnet_core.data.scenes import Slit, render_view
    from pssnet_core.shapes import make_shape, split_seeds

    mug, box = (split_seeds("test", 1)[0],) * 2
    views = {"mug_hidden": render_view(make_shape("mug", mug), yaw_deg=0.0, tilt_deg=30.0),
             "mug_seen": render_view(make_shape("mug", mug), yaw_deg=150.0, tilt_deg=30.0),
             "box_slit": render_view(make_shape("box", box), yaw_deg=20.0, tilt_deg=20.0, slit=Slit(width_m=0.036))}
    arrays: dict[str, np.ndarray] = {}
    for name, view in views.items():
        k = view.intrinsics
        arrays[f"{name}.depth_mm"] = np.round(view.depth * 1000).astype(np.uint16)
        arrays[f"{name}.mask"] = view.mask.astype(np.uint8)
        arrays[f"{name}.intrinsics"] = np.array([k.width, k.height, k.fx, k.fy, k.cx, k.cy], np.float64)
        arrays[f"{name}.up"] = np.asarray(view.up, np.float64)
    np.savez_compressed(path, **arrays)
    print(f"[pipeline] wrote {len(views)} views to {path}")


def read_views(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, CameraIntrinsics, tuple[float, ...]]]:
    data = np.load(path)
    views = {}
    for name in sorted({key.split(".")[0] for key in data.files}):
        w, h, fx, fy, cx, cy = data[f"{name}.intrinsics"]
        views[name] = (data[f"{name}.depth_mm"].astype(np.float32) / 1000.0, data[f"{name}.mask"],
                       CameraIntrinsics(int(w), int(h), fx, fy, cx, cy), tuple(float(v) for v in data[f"{name}.up"]))
    return views


def time_setting(pipeline: CompletionPipeline, views: dict, sampler: str, repeats: int) -> dict[str, float]:
    """p50 seconds of each step over ``repeats`` passes over the views (after one warm-up pass)."""
    per_step: dict[str, list[float]] = {step: [] for step in STEPS}
    for rep in range(repeats + 1):
        for depth, mask, intrinsics, up in views.values():
            pipeline.config = pipeline.with_config(sampler=sampler, up_vector=up)
            result = pipeline.run(depth, mask, intrinsics)
            if rep:
                for step in STEPS:
                    per_step[step].append(result.timings[step])
    return {step: statistics.median(values) for step, values in per_step.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write-views", type=Path, default=None, help="render the views to this file and stop")
    parser.add_argument("--views", type=Path, default=None, help="views written by --write-views")
    parser.add_argument("--devices", nargs="+", default=["cpu"])
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--precision", default="auto", choices=("auto", "fp32", "bf16"))
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--up-check-deg", type=float, default=PipelineConfig().up_check_deg,
                        help="the support-plane check of the up vector (open3d's RANSAC, on the CPU); 0 = off")
    parser.add_argument("--sampler-option", action="append", default=[], metavar="NAME=VALUE",
                        help="a checked sampler parameter for the checked rows (CheckedSamplerConfig; repeatable)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.write_views:
        write_views(args.write_views)
        return 0
    if args.views is None:
        parser.error("--views is required (write it with --write-views on a machine with open3d)")
    views = read_views(args.views)
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    print(f"[pipeline] CPU: {cpu_kind()}; GPU: {gpu}; torch {torch.__version__}, {args.threads} CPU threads; "
          f"{args.samples} samples, grasps on, up check {args.up_check_deg:g} deg, views: {', '.join(views)}; "
          f"checked sampler options: {' '.join(args.sampler_option) or 'none'}")
    results: dict[str, dict[str, float]] = {}
    config = PipelineConfig(num_samples=args.samples, up_check_deg=args.up_check_deg,
                            sampler_options=tuple(args.sampler_option))
    for device in args.devices:
        pipeline = CompletionPipeline.from_checkpoint(None, config, device=device, threads=args.threads,
                                                      precision=args.precision)
        print(f"[pipeline] {device}: precision {pipeline.completer.precision}")
        for sampler in SAMPLERS:
            t0 = time.perf_counter()
            p50 = time_setting(pipeline, views, sampler, args.repeats)
            results[f"{device} {sampler}"] = p50
            print(f"[pipeline] {device:>5} {sampler:<9} p50 ms: "
                  + ", ".join(f"{step} {p50[step] * 1000:.1f}" for step in STEPS)
                  + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        ratio = results[f"{device} checked"]["total"] / results[f"{device} posterior"]["total"]
        print(f"[pipeline] {device}: checked / posterior total p50 = {ratio:.2f}x")
    first = args.devices[0]
    for device in args.devices[1:]:
        for sampler in SAMPLERS:
            speedup = results[f"{device} {sampler}"]["total"] / results[f"{first} {sampler}"]["total"]
            print(f"[pipeline] {sampler}: {device} / {first} total p50 = {speedup:.2f}x")
    if args.json:
        args.json.write_text(json.dumps({"cpu": cpu_kind(), "gpu": gpu, "threads": args.threads,
                                         "samples": args.samples, "up_check_deg": args.up_check_deg,
                                         "p50_s": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
