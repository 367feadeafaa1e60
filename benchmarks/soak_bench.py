"""Soak and concurrency benchmark of completion_node over real DDS.

1. Soak: the synthetic camera publishes at ``--rate`` Hz (30) for ``--minutes`` (10) while the node runs in
   continuous mode with grasps; after ``--warmup`` s, every minute: completions per second received by a
   subscriber here, input stamp -> completion received p50/p95, the node's RSS (/proc/PID/status VmRSS) and
   CPU, and its counters (changes over the minute). At the end, a verdict on flatness: RSS growth from the
   first to the last minute (and the fitted slope), latency drift, rate drift.
2. Concurrency: continuous mode off, camera stopped; ``--clients`` (8) client processes, each with its own
   RosClient, call sample_completions in a loop for ``--client-minutes`` (3): calls sent, answered, lost
   (no answer within ``--client-timeout``), p50/p95, the node's RSS before and after.

    .venv/bin/python benchmarks/soak_bench.py [--minutes 10] [--clients 8] [--client-minutes 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.bench import cpu_kind
from pssnet_testing import chaos
from pssnet_testing.client import SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import (
    RosProcess,
    claim_domain_id,
    cpu_seconds,
    machine_cpu,
    ros_env,
    rss_mb,
    stale_shm_files,
)

#: flatness targets of the soak: RSS growth first -> last minute, and drift of the median latency
RSS_GROWTH_TARGET_PCT = 5.0
LATENCY_DRIFT_TARGET_PCT = 20.0
GAUGES = ("latest_set_stamp_ns", "sets_pending", "sets_in_progress")  # states, not counters


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


@dataclass
class Minute:
    """One minute of the soak."""

    index: int
    completions_per_s: float
    latency_p50_ms: float
    latency_p95_ms: float
    rss_mb: float
    rss_max_mb: float
    cpu_pct: float
    machine_busy_pct: float
    grasp_messages: int
    counters: dict[str, int]


class GraspsListener:
    """Counts /pssnet/grasps messages that carry grasps (grasps on in continuous mode)."""

    def __init__(self, ros: RosClient) -> None:
        from geometry_msgs.msg import PoseArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.with_poses = 0
        self._lock = threading.Lock()
        ros.node.create_subscription(PoseArray, "/pssnet/grasps", self._add,
                                     QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def _add(self, msg: Any) -> None:
        with self._lock:
            self.with_poses += bool(msg.poses)

    def count(self) -> int:
        with self._lock:
            return self.with_poses


def soak(args: argparse.Namespace, ros: RosClient, node: RosProcess, domain: int) -> list[Minute]:
    listener = chaos.CompletionsListener(ros)
    grasps = GraspsListener(ros)
    minutes: list[Minute] = []
    with RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", str(args.rate)], ros_env(domain),
                                  name="camera") as camera:
        camera.wait_for(r"publishing", 120)
        wait_until(lambda: len(listener) > 0, 120, "a first completion")
        time.sleep(args.warmup)  # the measured soak starts after a fixed warm-up: a duration, not a wait
        stats, first, grasp_count = ros.stats(), len(listener), grasps.count()
        cpu, machine, start = cpu_seconds(node.pid), machine_cpu(), time.monotonic()
        for index in range(1, int(args.minutes) + 1):
            end = start + 60.0 * index
            rss: list[float] = []
            while time.monotonic() < end:
                rss.append(rss_mb(node.pid))
                time.sleep(max(0.0, min(5.0, end - time.monotonic())))
            rss.append(rss_mb(node.pid))
            now_stats, now_count, now_grasps = ros.stats(), len(listener), grasps.count()
            now_cpu, now_machine = cpu_seconds(node.pid), machine_cpu()
            latencies = [(t - s * 1e-9) * 1000 for t, s in listener.arrivals(first)[:now_count - first]]
            minute = Minute(index=index, completions_per_s=(now_count - first) / 60.0,
                            latency_p50_ms=pct(latencies, 50), latency_p95_ms=pct(latencies, 95), rss_mb=rss[-1],
                            rss_max_mb=max(rss), cpu_pct=(now_cpu - cpu) / 60.0 * 100,
                            machine_busy_pct=(now_machine[0] - machine[0]) / (now_machine[1] - machine[1]) * 100,
                            grasp_messages=now_grasps - grasp_count,
                            counters={k: now_stats[k] - stats[k] for k in now_stats if k not in GAUGES})
            minutes.append(minute)
            c = minute.counters
            print(f"[soak] minute {index}: {minute.completions_per_s:.2f} completions/s, stamp -> received p50 "
                  f"{minute.latency_p50_ms:.0f} ms p95 {minute.latency_p95_ms:.0f} ms, node RSS {minute.rss_mb:.1f} "
                  f"MB (max {minute.rss_max_mb:.1f}), node CPU {minute.cpu_pct:.0f} % (of one core), machine "
                  f"{minute.machine_busy_pct:.0f} % busy (of all cores), grasp messages "
                  f"{minute.grasp_messages}; counters: synchronised {c['sets_synchronised']}, processed "
                  f"{c['sets_processed']}, superseded {c['sets_dropped_superseded']}, stale "
                  f"{c['sets_dropped_stale']}, invalid {c['sets_dropped_invalid']}, messages received "
                  f"{c['messages_received']}, unmatched {c['messages_unmatched']}", flush=True)
            stats, first, grasp_count, cpu, machine = now_stats, now_count, now_grasps, now_cpu, now_machine
    return minutes


def verdict(minutes: list[Minute]) -> dict[str, object]:
    first, last = minutes[0], minutes[-1]
    growth = (last.rss_mb - first.rss_mb) / first.rss_mb * 100
    def slope(values: list[float]) -> float:  # fitted change per minute: less swayed by one noisy minute
        return float(np.polyfit([m.index for m in minutes], values, 1)[0]) if len(minutes) > 1 else 0.0

    rss_slope = slope([m.rss_mb for m in minutes])
    p50_slope = slope([m.latency_p50_ms for m in minutes])
    p50_drift = (last.latency_p50_ms - first.latency_p50_ms) / first.latency_p50_ms * 100
    p95_drift = (last.latency_p95_ms - first.latency_p95_ms) / first.latency_p95_ms * 100
    rate_drift = (last.completions_per_s - first.completions_per_s) / first.completions_per_s * 100
    flat_rss = abs(growth) < RSS_GROWTH_TARGET_PCT
    flat_latency = abs(p50_drift) < LATENCY_DRIFT_TARGET_PCT
    print(f"[soak] verdict: RSS {first.rss_mb:.1f} -> {last.rss_mb:.1f} MB ({growth:+.1f} %, fitted {rss_slope:+.2f} "
          f"MB/min; target |growth| < {RSS_GROWTH_TARGET_PCT:g} %): {'flat' if flat_rss else 'NOT flat'}; latency "
          f"p50 {first.latency_p50_ms:.0f} -> {last.latency_p50_ms:.0f} ms ({p50_drift:+.1f} %, fitted "
          f"{p50_slope:+.1f} ms/min), p95 "
          f"{first.latency_p95_ms:.0f} -> {last.latency_p95_ms:.0f} ms ({p95_drift:+.1f} %; target |p50 drift| < "
          f"{LATENCY_DRIFT_TARGET_PCT:g} %): {'flat' if flat_latency else 'NOT flat'}; rate "
          f"{first.completions_per_s:.2f} -> {last.completions_per_s:.2f}/s ({rate_drift:+.1f} %)")
    return {"rss_growth_pct": growth, "rss_slope_mb_per_min": rss_slope, "p50_slope_ms_per_min": p50_slope,
            "p50_drift_pct": p50_drift,
            "p95_drift_pct": p95_drift, "rate_drift_pct": rate_drift, "flat_rss": flat_rss,
            "flat_latency": flat_latency}


def concurrency(args: argparse.Namespace, ros: RosClient, node: RosProcess, domain: int) -> dict[str, object]:
    result = ros.set_parameters(continuous=False)
    assert all(r.successful for r in result), [r.reason for r in result]
    ros.wait_idle()
    before, rss_before = ros.stats(), rss_mb(node.pid)
    # Every client starts calling at the same moment, once all have started (imports take a while on 2 cores).
    go = time.time() + args.client_start
    workers = [RosProcess([sys.executable, os.path.abspath(__file__), "--worker", str(i), "--worker-go", repr(go),
                           "--worker-seconds", repr(args.client_minutes * 60), "--client-timeout",
                           repr(args.client_timeout), "--samples", str(args.samples)]
                          + ([] if args.client_grasps else ["--no-client-grasps"]), ros_env(domain), name=f"client{i}")
               for i in range(args.clients)]
    # The node's memory while the clients call (every 10 s from the common start): growth or a plateau.
    trace: list[tuple[float, float]] = []
    while time.time() < go + args.client_minutes * 60:
        time.sleep(max(0.0, min(10.0, go + args.client_minutes * 60 - time.time())))
        if time.time() >= go:
            trace.append((time.time() - go, rss_mb(node.pid)))
    reports = []
    for worker in workers:
        line = worker.wait_for(r"^result (.*)$", args.client_start + args.client_minutes * 60 + 4 * args.client_timeout)
        reports.append(json.loads(line.group(1)))
        worker.stop()
    after, rss_after = ros.stats(), rss_mb(node.pid)
    latencies = [ms for r in reports for ms in r["latencies_ms"]]
    total = {k: sum(r[k] for r in reports) for k in ("sent", "answered", "succeeded", "lost")}
    late = max(r["started_late_s"] for r in reports)
    print(f"[concurrency] {args.clients} clients x {args.client_minutes:g} min ({args.samples}"
          f" samples, grasps {'on' if args.client_grasps else 'off'}, timeout {args.client_timeout:g} s): sent "
          f"{total['sent']}, answered {total['answered']} ({total['succeeded']} succeeded), lost {total['lost']}; "
          f"latency p50 {pct(latencies, 50):.0f} ms, p95 {pct(latencies, 95):.0f} ms, max "
          f"{max(latencies, default=float('nan')):.0f} ms; per client answered "
          f"{min(r['answered'] for r in reports)}-{max(r['answered'] for r in reports)}; node service_calls "
          f"+{after['service_calls'] - before['service_calls']}, failures "
          f"+{after['service_failures'] - before['service_failures']}; node RSS {rss_before:.1f} -> "
          f"{rss_after:.1f} MB (during the calls: " + ", ".join(f"{t:.0f} s {mb:.0f}" for t, mb in trace[::3])
          + f" MB); latest client start {late:.1f} s after the common start")
    return {"clients": args.clients, "minutes": args.client_minutes, **total, "p50_ms": pct(latencies, 50),
            "p95_ms": pct(latencies, 95), "rss_before_mb": rss_before, "rss_after_mb": rss_after, "rss_trace": trace,
            "per_client": [{k: v for k, v in r.items() if k != "latencies_ms"} for r in reports]}


def worker(args: argparse.Namespace) -> int:
    """One concurrent client: calls sample_completions from ``--worker-go`` for ``--worker-seconds``."""
    from pssnet_interfaces.srv import SampleCompletions

    request = chaos.scene_request(args.samples, args.client_grasps)
    domain = int(os.environ["ROS_DOMAIN_ID"])
    counts = {"sent": 0, "answered": 0, "succeeded": 0, "lost": 0}
    latencies: list[float] = []
    with RosClient(domain, f"soak_client_{args.worker}") as ros:
        service = ros.service(SampleCompletions, SAMPLE_SERVICE, 120.0, new=True)
        time.sleep(max(0.0, args.worker_go - time.time()))  # the common start: a moment, not a guess
        started_late = time.time() - args.worker_go
        end = time.monotonic() + args.worker_seconds
        while time.monotonic() < end:
            counts["sent"] += 1
            t0 = time.perf_counter()
            try:
                response = ros.call(service, request, args.client_timeout)
            except TimeoutError:
                counts["lost"] += 1
                continue
            latencies.append((time.perf_counter() - t0) * 1000)
            counts["answered"] += 1
            counts["succeeded"] += bool(response.success)
    print("result " + json.dumps(counts | {"started_late_s": started_late, "latencies_ms": latencies}), flush=True)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="", help="checkpoint (default: the shipped model)")
    parser.add_argument("--minutes", type=float, default=10.0, help="soak length (whole minutes; 0: no soak)")
    parser.add_argument("--warmup", type=float, default=30.0, help="seconds of soak before the first minute")
    parser.add_argument("--rate", type=float, default=30.0, help="synthetic camera rate, Hz")
    parser.add_argument("--max-rate", type=float, default=30.0, help="node max_rate_hz")
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2, help="node torch threads")
    parser.add_argument("--clients", type=int, default=8, help="concurrent clients (0: no concurrency phase)")
    parser.add_argument("--client-minutes", type=float, default=3.0)
    parser.add_argument("--client-timeout", type=float, default=30.0, help="a call unanswered this long is lost")
    parser.add_argument("--client-grasps", action=argparse.BooleanOptionalAction, default=True,
                        help="clients ask for grasps too (default: yes)")
    parser.add_argument("--client-start", type=float, default=30.0,
                        help="seconds from starting the clients to their common start")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--worker-go", type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument("--worker-seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker is not None:
        return worker(args)

    domain = claim_domain_id()
    print(f"[soak] CPU: {cpu_kind()}; {os.cpu_count()} cores; {platform.platform()}; ROS_DOMAIN_ID {domain}; "
          f"node threads {args.threads}, {args.samples} samples, camera {args.rate:g} Hz, max_rate_hz "
          f"{args.max_rate:g}, grasps on; load average before: {os.getloadavg()[0]:.2f}", flush=True)
    params: dict[str, object] = dict(up_vector=chaos.scene_up_vector(), threads=args.threads,
                                     num_samples=args.samples, continuous=args.minutes > 0, continuous_grasps=True,
                                     max_rate_hz=float(args.max_rate))
    if args.model:
        params["model_path"] = args.model
    under_test = NodeUnderTest(domain, **params)
    results: dict[str, object] = {"cpu": cpu_kind(), "args": vars(args)}
    try:
        node = under_test.start()
        with RosClient(domain, "soak_bench") as ros:
            if args.minutes > 0:
                minutes = soak(args, ros, node, domain)
                results["minutes"] = [asdict(m) for m in minutes]
                results["verdict"] = verdict(minutes)
            if args.clients > 0:
                results["concurrency"] = concurrency(args, ros, node, domain)
    finally:
        code = under_test.close()
        leftovers = stale_shm_files(under_test.process.shm_files) if under_test.process else set()
    print(f"[soak] node exit code {code}; stale shared memory: {sorted(leftovers) or 'none'}; load average after: "
          f"{os.getloadavg()[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
