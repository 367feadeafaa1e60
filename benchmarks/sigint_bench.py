"""Clean shutdown on SIGINT, many times over: completion_node with the synthetic camera, a service call, then SIGINT
at a random moment; repeated. Prints every exit code that is not 0 with the process's last output.

Why: one fresh-clone CI run (stop 53) saw completion_node exit 1 on the demo's SIGINT after a complete demo, with
nothing to say why. This replays that ending (``--camera first``: the camera is stopped first, as the demo does) or
a harder one (``--camera running``: the node is stopped while frames still arrive), with the delay between the
last answer and the signal drawn from [0, ``--max-delay``] s.

    .venv/bin/python benchmarks/sigint_bench.py [--runs 40] [--camera first|running] [--max-delay 1.5]
"""

from __future__ import annotations

import argparse
import random
import sys
import time

from pssnet_core.bench import cpu_kind
from pssnet_testing.demo import run_client
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import RosProcess, claim_domain_id, ros_env
from pssnet_testing.synthetic_camera import SceneOptions, render_scene

SAMPLES = 6  # as the demo test asks for


def one_shutdown(domain: int, up: tuple[float, float, float], camera_first: bool, delay: float,
                 timeout: float) -> dict[str, int]:
    """Starts the node and the camera, calls the service once, stops both; returns their exit codes (and prints
    the last output of any that did not exit 0)."""
    node = NodeUnderTest(domain, timeout=timeout, client_name="sigint_bench_ready", up_vector=up,
                         num_samples=SAMPLES)
    node.start()
    node.close_client()
    camera = RosProcess.python_module("pssnet_testing.synthetic_camera", ["--rate", "5", "--mug-seed", "0"],
                                      ros_env(domain), name="synthetic_camera")
    try:
        camera.wait_for(r"publishing mug", timeout=timeout)
        run_client(domain, SAMPLES, 1, timeout)
    finally:
        order = (camera, node.process) if camera_first else (node.process, camera)
        codes = {}
        for position, process in enumerate(order):
            if position == 1:
                time.sleep(delay)
            codes[process.name] = process.stop()
    for process in order:
        if codes[process.name] != 0:
            print(f"--- {process.name} exited {codes[process.name]}; its last output:\n"
                  + "\n".join(process.lines()[-40:]), flush=True)
    return codes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--camera", choices=("first", "running"), default="first",
                        help="stop the camera before the node (the demo's order) or after it")
    parser.add_argument("--max-delay", type=float, default=1.5, help="seconds; the delay before the second stop")
    parser.add_argument("--timeout", type=float, default=180.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.runs < 1 or args.max_delay < 0:
        parser.error("--runs must be >= 1 and --max-delay >= 0")
    domain = claim_domain_id()
    up = tuple(render_scene(SceneOptions(mug_seed=0)).up)
    rng = random.Random(args.seed)
    failed = 0
    print(f"# {cpu_kind()}; {args.runs} runs, camera {args.camera}, delay 0-{args.max_delay} s", flush=True)
    for run in range(args.runs):
        delay = rng.uniform(0.0, args.max_delay)
        codes = one_shutdown(domain, up, args.camera == "first", delay, args.timeout)
        failed += any(code != 0 for code in codes.values())
        print(f"run {run}: delay {delay:.2f} s, exit codes {codes}", flush=True)
    print(f"not clean: {failed} of {args.runs}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
