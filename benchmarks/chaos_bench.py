"""Chaos benchmark of completion_node over real DDS; the scenarios are pssnet_testing.chaos's.

(a) kill -9 of the node in the middle of a service call (``--repeats`` times): how long the client waits
    (its timeout), whether DDS tells it the server is gone and when, how fast a restarted node serves, and
    what became of the killed node's Fast DDS shared memory.
(b) kill -9 of a client process in the middle of its call (``--repeats`` times): the node survives and
    serves the next client (a new process).
(c) stale shared memory: kill -9 of a node with nobody else on its domain leaves its segments; the next
    node start removes them (its log); the cost of that check at start.
(d) stalled subscribers of /pssnet/completions (``--stall-seconds`` each, ``--rounds`` times): a subscriber
    that never spins, one that sleeps 2 s in its callback, one frozen with SIGSTOP, and all three, each right
    after a window with none (the machine is shared: neighbours compare best): the rate and latency a normal
    subscriber sees, service latency, the node's RSS and CPU and the CPU everything else took.
(e) lifecycle transitions mid-work (``--repeats`` times each): deactivate, deactivate+cleanup and shutdown
    sent while a heavy call computes and while a continuous-mode set is completed: calls answered, node
    alive (or stopped cleanly after shutdown) and serving again, how long the transition took.

    .venv/bin/python benchmarks/chaos_bench.py [--repeats 3] [--stall-seconds 30] [--rounds 1] [--only abcde]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from pssnet_interfaces.srv import SampleCompletions

from pssnet_core.bench import cpu_kind
from pssnet_ros.shm import SHM_GRACE_S, clean_stale_shm
from pssnet_testing import chaos
from pssnet_testing.client import SAMPLE_SERVICE, RosClient, wait_until
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import (
    RosProcess,
    claim_domain_id,
    ros_env,
    shm_files,
    stale_shm_files,
)


def node_under_test(domain: int, threads: int, model: str, **params: object) -> NodeUnderTest:
    """A completion node allowing heavy requests (not started; ``close()`` is the caller's)."""
    values = dict(chaos.NODE_PARAMS, up_vector=chaos.scene_up_vector(), threads=threads, **params)
    if model:
        values["model_path"] = model
    return NodeUnderTest(domain, **values)


def mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB"


def seconds(value: float | None, missing: str) -> str:
    return missing if value is None else f"{value:.2f} s"


def node_killed(args: argparse.Namespace, domain: int) -> list[dict]:
    reports = []
    node = node_under_test(domain, args.threads, args.model)
    try:
        process = node.start()
        with RosClient(domain, "chaos_bench_a") as ros:
            for i in range(args.repeats):
                watch = args.watch_server if i == 0 else 0.0  # DDS takes its participant lease to notice
                report, process = chaos.kill_node_mid_call(ros, process, node.start, args.call_timeout,
                                                           watch_server_s=watch)
                fates = {fate: list(report.fates.values()).count(fate) for fate in set(report.fates.values())}
                gone = seconds(report.server_gone_s, f"not within {watch:g} s" if watch else "not watched")
                print(f"[chaos] (a) node killed {report.in_flight_s * 1000:.0f} ms into a {chaos.HEAVY_SAMPLES}-"
                      f"sample call: answered {report.answered}; the client gave up "
                      f"{seconds(report.gave_up_after_kill_s, 'never (hang)')} after the kill (timeout "
                      f"{report.call_timeout_s:g} s: {report.error}); service_is_ready() false after {gone}; "
                      f"restarted node ready in {report.restart_ready_s:.1f} s; the request re-sent from the "
                      f"kill on answered {report.resent_answered} after {report.served_ms / 1000:.1f} s (attempt "
                      f"{report.attempts}); the killed node's shared memory: "
                      f"{len(report.shm_files)} files, {mib(report.shm_bytes)}, "
                      f"{len(report.stale_before_restart)} unused at the restart; fates {fates}")
                reports.append(asdict(report))
    finally:
        node.close()
    return reports


def client_killed(args: argparse.Namespace, domain: int) -> list[dict]:
    reports = []
    dead: dict[str, int] = {}
    node = node_under_test(domain, args.threads, args.model)
    try:
        node.start()
        with RosClient(domain, "chaos_bench_b") as ros:
            for _ in range(args.repeats):
                report = chaos.kill_client_mid_call(ros, node.process, ros_env(domain))
                dead.update(report.killed_files)
                print(f"[chaos] (b) client killed {report.in_flight_s * 1000:.0f} ms into its call (answered "
                      f"before: {report.answered_before_kill}); node alive {report.node_alive}; next client "
                      f"served {report.next_served} in {report.next_ms:.0f} ms (incl. the rest of the dead "
                      f"client's request; node: {report.next_message}); service failures {report.failures}")
                reports.append(asdict(report))
    finally:
        node.close()
    print(f"[chaos] (b) the killed clients' files removed afterwards: {len(chaos.remove_dead_files(dead))}")
    return reports


def stale_shared_memory(args: argparse.Namespace, domain: int) -> dict:
    """A node serves a client; the client leaves cleanly; the node, now alone, is killed; the next start."""
    t0 = time.perf_counter()
    idle = clean_stale_shm()
    check_ms = (time.perf_counter() - t0) * 1000
    lone = node_under_test(domain, args.threads, args.model)
    node = lone.start()
    for _ in range(5):
        lone.ros.call(lone.ros.service(SampleCompletions, SAMPLE_SERVICE), chaos.scene_request(chaos.LIGHT_SAMPLES))
    lone.close_client()  # the client leaves cleanly: the node is alone on its domain
    node.record_shm_files()
    node.proc.send_signal(signal.SIGKILL)
    node.stop()
    owned = dict(node.shm_files)
    left = wait_until(lambda: stale_shm_files(owned), 30.0, "the lone node's files unused")
    left_bytes = chaos.allocated_bytes(owned)
    wait_until(lambda: all(time.time() - os.stat(p).st_mtime >= SHM_GRACE_S for p in left if os.path.exists(p)),
               SHM_GRACE_S + 30, "the files older than the grace period")
    restarted = lone.start()
    lone.close()
    logged = [line for line in restarted.lines() if "stale Fast DDS" in line]
    current = shm_files()
    remaining = sorted(p for p, inode in owned.items() if current.get(p) == inode)
    print(f"[chaos] (c) clean_stale_shm() with nothing to remove: {check_ms:.1f} ms ({idle.kept} Fast DDS "
          f"segments/ports of live processes kept); a lone node killed -9 left {len(left)} of its "
          f"{len(owned)} segments/ports unused ({mib(left_bytes)} allocated); the next start: "
          f"{logged[0].split('] ', 2)[-1] if logged else 'removed nothing'}; the killed node's files left "
          f"after it: {remaining or 'none'}")
    return {"check_ms": check_ms, "owned": len(owned), "left": len(left), "left_bytes": left_bytes,
            "restart_log": logged, "remaining": remaining}


def stalled_subscribers(args: argparse.Namespace, domain: int) -> list[dict]:
    node = node_under_test(domain, args.threads, args.model, continuous=True, max_rate_hz=float(args.max_rate))
    env = ros_env(domain)
    windows = []
    try:
        process = node.start()
        with RosClient(domain, "chaos_bench_d") as ros, \
                RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", str(args.camera_rate)], env,
                                         name="camera") as camera:
            listener = chaos.CompletionsListener(ros)
            camera.wait_for(r"publishing", 120)
            wait_until(lambda: len(listener) > 0, 120, "a first completion")
            request = chaos.scene_request(chaos.LIGHT_SAMPLES, grasps=False)
            # Each stalled case follows a window alone: the machine is shared, so compare neighbours.
            cases = [(), *((m,) for m in chaos.SUBSCRIBER_MODES), chaos.SUBSCRIBER_MODES]
            for modes in [case for _ in range(args.rounds) for stalled in cases[1:] for case in ((), stalled)]:
                window, lines = chaos.run_with_subscribers(ros, listener, process, env, modes, args.stall_seconds,
                                                           request, timeout=120)
                print(f"[chaos] (d) {window.summary()}; the subscribers: {lines or '-'}")
                windows.append(asdict(window) | {"rate_hz": window.rate_hz, "subscribers": lines})
    finally:
        node.close()
    return windows


def transitions_mid_work(args: argparse.Namespace, domain: int) -> list[dict]:
    """Each transition sequence ``--repeats`` times during a heavy call, then during topic sets, at delays
    spread over 0-1 s after the work started (so that every step of the pipeline is hit)."""
    reports: list[dict] = []
    delays = np.random.default_rng(0).uniform(0.0, 1.0, size=args.repeats)
    node = node_under_test(domain, args.threads, args.model, num_samples=chaos.HEAVY_SAMPLES, max_rate_hz=20.0)
    camera = None
    try:
        process = node.start()
        with RosClient(domain, "chaos_bench_e") as ros:
            for work in chaos.WORK_KINDS:
                continuous = work == "topics"
                if continuous:
                    camera = RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", "10"],
                                                      ros_env(domain), name="camera")
                    camera.wait_for(r"publishing", 60)
                    assert ros.set_parameters(continuous=True)[0].successful
                    node.params["continuous"] = True  # for the node started again after "shutdown"
                for transition in chaos.TRANSITION_SEQUENCES:
                    for delay in delays:
                        try:
                            report, process = chaos.transition_mid_work(ros, process, transition, work, node.start,
                                                                        delay_s=float(delay), timeout=120.0)
                        except Exception:
                            if process.running():  # a hung node prints its threads' stacks on SIGUSR1
                                process.proc.send_signal(signal.SIGUSR1)
                                time.sleep(2.0)
                            print("[chaos] (e) the node's last output:\n" + "\n".join(process.lines()[-200:]))
                            raise
                        reports.append(asdict(report))
                        if not (report.node_alive and report.restored):
                            print(f"[chaos] (e) FAILED: {report}", flush=True)
                    done = [r for r in reports if r["work"] == work and r["transition"] == transition]
                    print(f"[chaos] (e) {transition} during {work}: {summarise_transitions(done)}", flush=True)
    finally:
        if camera is not None:
            camera.stop()
        node.close()
    return reports


def summarise_transitions(reports: list[dict]) -> str:
    calls = [r for r in reports if r["answered"] is not None]
    seconds = [r["transition_s"] for r in reports]
    text = (f"{len(reports)} times, work in flight {sum(r['busy'] for r in reports)}, transition accepted "
            f"{sum(r['accepted'] for r in reports)}, node alive {sum(r['node_alive'] for r in reports)}, served "
            f"again {sum(r['restored'] for r in reports)}; transition took {np.median(seconds):.2f} s median, "
            f"{np.max(seconds):.2f} s max")
    if calls:
        cancelled = sum(r["status"] == SampleCompletions.Response.STATUS_CANCELLED for r in calls)
        text += (f"; calls answered {sum(r['answered'] for r in calls)}/{len(calls)} ({cancelled} cancelled, "
                 f"{sum(bool(r['success']) for r in calls)} completed)")
    else:
        text += f"; topic sets cancelled {sum(r['cancelled_sets'] for r in reports)}"
    exits = [r["clean_exit"] for r in reports if r["clean_exit"] is not None]
    if exits:
        text += f"; clean exits after shutdown {sum(exits)}/{len(exits)}"
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="", help="checkpoint (default: the shipped model)")
    parser.add_argument("--threads", type=int, default=2, help="node torch threads")
    parser.add_argument("--repeats", type=int, default=3, help="kills in (a) and (b); each transition in (e)")
    parser.add_argument("--call-timeout", type=float, default=5.0, help="(a): the client's timeout, s")
    parser.add_argument("--watch-server", type=float, default=40.0,
                        help="(a), first kill: watch service_is_ready() this long, s (0: not at all)")
    parser.add_argument("--stall-seconds", type=float, default=30.0, help="(d): length of each window, s")
    parser.add_argument("--rounds", type=int, default=1, help="(d): repetitions of the windows")
    parser.add_argument("--camera-rate", type=float, default=30.0, help="(d): synthetic camera rate, Hz")
    parser.add_argument("--max-rate", type=float, default=30.0, help="(d): node max_rate_hz")
    parser.add_argument("--only", default="abcde", help="scenarios to run, e.g. 'ad'")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = parser.parse_args()
    domain = claim_domain_id()
    print(f"[chaos] CPU: {cpu_kind()}; {os.cpu_count()} cores; {platform.platform()}; ROS_DOMAIN_ID {domain}; "
          f"node threads {args.threads}")
    results: dict[str, object] = {"cpu": cpu_kind()}
    scenarios = {"a": ("node_killed", node_killed), "b": ("client_killed", client_killed),
                 "c": ("stale_shm", stale_shared_memory), "d": ("stalled_subscribers", stalled_subscribers),
                 "e": ("transitions_mid_work", transitions_mid_work)}
    for key in args.only:
        name, run = scenarios[key]
        t0 = time.monotonic()
        results[name] = run(args, domain)
        print(f"[chaos] ({key}) took {time.monotonic() - t0:.0f} s")
    if "a" in args.only:
        kills = results["node_killed"]
        gave_up = [r["gave_up_after_kill_s"] for r in kills if r["gave_up_after_kill_s"] is not None]
        print(f"[chaos] (a) summary: {sum(r['answered'] for r in kills)} answers from killed nodes, "
              f"{len(kills) - len(gave_up)} clients hung, the others gave up after the kill in "
              f"{np.min(gave_up):.2f}-{np.max(gave_up):.2f} s; requests sent while the node was down and "
              f"re-sent until answered: {sum(r['resent_answered'] for r in kills)}/{len(kills)} answered, "
              f"{sum(not r['resent_answered'] for r in kills)} lost")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
