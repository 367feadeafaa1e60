"""Does the node's memory come back after a burst of bad requests? RSS of completion_node over real DDS.

Starts the real node (shipped model unless ``--model``, 20 samples, grasps), then:

1. warm-up: ``--valid`` / 10 valid requests, idle ``--idle`` s: the baseline RSS;
2. burst: ``--malformed`` malformed requests drawn from ``fuzz_bench``'s refused families, every
   ``--huge-every``-th one a 4000x3000 depth image with a 640x480 mask and camera_info (refused: sizes differ);
3. ``--valid`` valid requests, then idle ``--idle`` s: the final RSS.

It prints VmRSS after each phase and where it lies (``/proc/PID/smaps``: the glibc heaps and anonymous memory,
Fast DDS' shared-memory segments in /dev/shm, the mapped libraries), and the growth of the final RSS over the
baseline (target: < 5 %). ``--env KEY=VALUE`` sets a variable for the node only (e.g. ``MALLOC_ARENA_MAX=2``),
to tell which part of the stack holds the memory.

    .venv/bin/python benchmarks/memory_bench.py [--malformed 2000] [--valid 200] [--idle 60]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from fuzz_bench import REFUSAL, REQUEST_FAMILIES, Fuzzer, rss_kib

from pssnet_core.bench import cpu_kind
from pssnet_testing.client import SAMPLE_SERVICE, RosClient
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import resident_mib_by_kind
from pssnet_testing.synthetic_camera import SceneOptions, render_scene

HUGE = (3000, 4000)  # rows, columns: a 12-megapixel depth image


def huge_request(fuzzer: Fuzzer, stamp_ns: int):
    """A 4000x3000 32FC1 depth image with the scene's 640x480 mask and camera_info: refused for its size."""
    from pssnet_ros.conversions import numpy_to_image

    request = fuzzer.request("valid_32FC1", stamp_ns)
    request.depth = numpy_to_image(np.full(HUGE, 0.6, np.float32), "32FC1", request.depth.header)
    return request


def phase(ros: RosClient, service, requests, timeout: float) -> dict[str, int]:
    outcomes = {"succeeded": 0, "refused": 0, "unanswered": 0}
    for request in requests:
        try:
            response = ros.call(service, request, timeout)
        except TimeoutError:
            outcomes["unanswered"] += 1
            continue
        outcomes["succeeded" if response.success else "refused"] += 1
    return outcomes


def snapshot(pid: int, label: str) -> dict[str, float]:
    row = {"rss_mib": rss_kib(pid) / 1024, **resident_mib_by_kind(pid)}
    print(f"[memory] {label}: RSS {row['rss_mib']:.1f} MiB (" + ", ".join(
        f"{k} {v:.1f}" for k, v in row.items() if k != "rss_mib") + ")", flush=True)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--malformed", type=int, default=2000, help="malformed requests in the burst")
    parser.add_argument("--huge-every", type=int, default=10, help="every n-th malformed request is 4000x3000")
    parser.add_argument("--valid", type=int, default=200, help="valid requests after the burst")
    parser.add_argument("--samples", type=int, default=20, help="num_samples of the valid requests")
    parser.add_argument("--idle", type=float, default=60.0, help="idle seconds before each measurement")
    parser.add_argument("--threads", type=int, default=1, help="node torch threads")
    parser.add_argument("--model", default="", help="checkpoint (default: the shipped model)")
    parser.add_argument("--env", action="append", default=[], help="KEY=VALUE for the node's environment")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = parser.parse_args()
    from pssnet_interfaces.srv import SampleCompletions

    view = render_scene(SceneOptions())
    fuzzer = Fuzzer(view, args.seed, args.samples)
    refused_families = sorted(name for name, (outcome, _) in REQUEST_FAMILIES.items() if outcome == REFUSAL)
    params = {"up_vector": [float(v) for v in view.up], "threads": args.threads, "num_samples": args.samples}
    if args.model:
        params["model_path"] = args.model
    print(f"[memory] CPU: {cpu_kind()}, {os.cpu_count()} cores; node env {args.env or 'default'}", flush=True)
    node = NodeUnderTest(env=dict(item.split("=", 1) for item in args.env), client_name="memory_client", **params)
    rows: dict[str, dict] = {}
    try:
        pid = node.start().pid
        ros = node.ros
        service = ros.service(SampleCompletions, SAMPLE_SERVICE)
        valid = fuzzer.request("valid_32FC1", 1)
        valid.compute_grasps = True
        rows["start"] = snapshot(pid, "ready")
        warm = phase(ros, service, [valid] * max(1, args.valid // 10), 120.0)
        time.sleep(args.idle)
        rows["baseline"] = {**snapshot(pid, f"after {sum(warm.values())} valid and {args.idle:g} s idle"), **warm}
        rng = np.random.default_rng(args.seed)
        burst = (huge_request(fuzzer, i) if (i + 1) % args.huge_every == 0 else
                 fuzzer.request(str(rng.choice(refused_families)), i) for i in range(args.malformed))
        t0 = time.monotonic()
        outcome = phase(ros, service, burst, 60.0)
        rows["burst"] = {**snapshot(pid, f"after {args.malformed} malformed requests "
                                         f"({time.monotonic() - t0:.0f} s: {outcome})"), **outcome}
        outcome = phase(ros, service, [valid] * args.valid, 120.0)
        rows["valid"] = {**snapshot(pid, f"after {args.valid} valid ({outcome})"), **outcome}
        time.sleep(args.idle)
        rows["idle"] = snapshot(pid, f"after {args.idle:g} s idle")
    finally:
        code = node.close()
    growth = 100.0 * (rows["idle"]["rss_mib"] / rows["baseline"]["rss_mib"] - 1.0)
    print(f"[memory] RSS after the burst, {args.valid} valid calls and idle: {growth:+.1f} % over the baseline "
          f"(target < 5 %: {'met' if growth < 5.0 else 'not met'}); node exit code {code}")
    if args.json:
        args.json.write_text(json.dumps({"cpu": cpu_kind(), "env": args.env, "rows": rows, "growth_pct": growth,
                                         "exit_code": code}, indent=2))
    return 0 if code == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
