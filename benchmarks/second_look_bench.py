"""What a second look costs the node: one view, one view with candidate places scored, two views fused.

Times ``CompletionPipeline.run`` (the node's work for one request, no ROS transport) on a held-out mug with its
handle hidden, shipped model, the node's default (checked) sampler, 20 samples, grasps on, in three settings
interleaved call by call: the view alone; the view with the 16 places of the trials' ring
(:data:`pssnet_core.next_view.RING_PLACES`) scored; the view and a second one from
behind fused. Prints p50 per setting and step, and the ratios to the first (only ratios compare on a loaded machine).

    .venv/bin/python benchmarks/second_look_bench.py [--repeats 15] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from pssnet_core.bench import cpu_kind
from pssnet_core.data.scenes import orbit_camera, render_view
from pssnet_core.next_view import RING_PLACES
from pssnet_core.pipeline import CompletionPipeline, MoreView, PipelineConfig
from pssnet_core.shapes import make_shape, split_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    shape = make_shape("mug", split_seeds("test", 1)[0])
    front = render_view(shape, yaw_deg=0.0, distance=0.6, tilt_deg=30.0)
    back = render_view(shape, yaw_deg=0.0, distance=0.6, tilt_deg=30.0, azimuth_deg=0.0)
    first_from_back = np.linalg.inv(front.camera_pose) @ back.camera_pose
    target = front.camera_pose[:3, 3] + 0.6 * front.camera_pose[:3, 2]
    candidates = [np.linalg.inv(front.camera_pose) @ orbit_camera(target, 0.6, e, a)
                  for a, e in RING_PLACES]
    pipeline = CompletionPipeline.from_checkpoint(None, PipelineConfig(up_vector=tuple(front.up)), threads=args.threads)
    settings = {"one view": {}, "one view + 16 places scored": {"candidate_views": candidates},
                "two views fused": {"more_views": (MoreView(back.depth, back.mask, back.intrinsics, first_from_back),)}}
    times: dict[str, dict[str, list[float]]] = {name: {} for name in settings}
    for repeat in range(args.repeats + 1):
        for name, extra in settings.items():
            t0 = time.perf_counter()
            result = pipeline.run(front.depth, front.mask, front.intrinsics, **extra)
            total = time.perf_counter() - t0
            if repeat == 0:
                continue  # warm-up
            for step, seconds in {**result.timings, "call": total}.items():
                times[name].setdefault(step, []).append(seconds * 1000)
    print(f"[second look] {cpu_kind()}, {args.threads} threads, {args.repeats} calls each, p50 in ms:")
    base = statistics.median(times["one view"]["call"])
    for name, steps in times.items():
        p50 = {step: statistics.median(values) for step, values in steps.items()}
        print(f"  {name:30s} call {p50['call']:7.1f} ({p50['call'] / base:.2f}x)  observe {p50['observe']:6.1f}  "
              f"network {p50['network']:6.1f}  views {p50['views']:6.1f}  grasps {p50['grasps']:6.1f}")


if __name__ == "__main__":
    main()
