"""Every speed target of the project in one run (`python benchmarks/all.py`): measured value, target, ratio, met.

    .venv/bin/python benchmarks/all.py [--quick] [--precision auto|fp32|bf16] [--plausible-data DIR] [--json OUT]

Runs the benchmark scripts next to this file, each in its own process (thread pools of one runtime slow the
next one in the same process), and reads back the numbers each writes with ``--json``:
- inference_bench: encoder once + 20 samples at 32^3 (the shipped model) and 64^3 (random weights);
- grasp_bench: candidate generation + scoring of 500 candidates x 20 completions at 32^3;
- service_bench: the node over real DDS: service p50 against the network time of the same call, and the topic
  rate in continuous mode with grasps (camera at 30 Hz);
- plausible_bench: plausible-set pairs per second (synthetic mugs unless ``--plausible-data``).

Targets depend on the CPU kind: fp32 on AVX2-only CPUs, bf16 where the CPU has AVX512-BF16 or AMX.
The first lines say which kind this is; the network rows say which inference path ran (fused fp32, fused bf16,
unfused). ``--precision`` forces the network rows' precision (default auto: bf16 where native), so that both
paths can be timed on any CPU (bf16 on an AVX2-only CPU is emulated: slow); the service and topic rows run the
node, at its own precision. On a shared machine compare ratios, not milliseconds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pssnet_core.bench import cpu_kind
from pssnet_core.models.base import PRECISIONS, cpu_has_fast_bf16

HERE = Path(__file__).resolve().parent
SHIPPED_MODEL = HERE.parent / "pssnet_core" / "checkpoints" / "default_pssnet_32.pt"
#: Plausible-set pairs per second before the plausible-set speed-up (BENCHMARKS.md: 8 references of the mug test
#: set, 2 workers, AVX2 CPU); the target is ten times that.
PLAUSIBLE_BASELINE_PAIRS_S = 218.0


@dataclass(frozen=True)
class Target:
    """A speed target: ``at_most`` (times) or at least (rates) ``avx2`` / ``bf16`` depending on the CPU kind."""

    what: str
    unit: str
    avx2: float
    bf16: float
    at_most: bool = True


TARGETS = {
    "network32": Target("network, encoder + 20 samples, 32^3", "ms", 25.0, 6.0),
    "network64": Target("network, encoder + 20 samples, 64^3", "ms", 200.0, 50.0),
    "service": Target("service p50 / network (640x480, 20 samples)", "x", 1.3, 1.3),
    "grasps": Target("grasp generation + scoring, 500 x 20, 32^3", "ms", 30.0, 30.0),
    "topics": Target("topics with grasps, camera 30 Hz", "Hz", 5.0, 10.0, at_most=False),
    "plausible": Target("plausible sets", "pairs/s", 10 * PLAUSIBLE_BASELINE_PAIRS_S,
                        10 * PLAUSIBLE_BASELINE_PAIRS_S, at_most=False),
}


def run_step(script: str, args: list[str], out: Path) -> dict:
    """Runs ``benchmarks/<script>.py args --json out`` and returns its numbers (its output goes to ours)."""
    command = [sys.executable, str(HERE / f"{script}.py"), *args, "--json", str(out)]
    print(f"[all] {' '.join(command[1:])}", flush=True)
    done = subprocess.run(command, check=False)
    if done.returncode != 0 or not out.is_file():
        raise RuntimeError(f"{script} exited {done.returncode}")
    return json.loads(out.read_text())


def measure(args: argparse.Namespace, tmp: Path) -> tuple[dict[str, float | str], dict[str, float], dict[str, str]]:
    """Target key -> measured value (a median), or the reason it could not be measured; the best run where the
    benchmark reports one (on a shared machine the closest to an idle one); and the inference path of the
    network rows."""
    repeats = "5" if args.quick else "15"
    values: dict[str, float | str] = {}
    best: dict[str, float] = {}
    paths: dict[str, str] = {}
    steps = {
        "inference": ("inference_bench", ["--grids", "32", "64", "--repeats", repeats, "--precision", args.precision,
                                          "--checkpoint32", str(SHIPPED_MODEL)]),
        "grasps": ("grasp_bench", ["--sizes", "32", "--repeats", repeats]),
        "service": ("service_bench", ["--calls", "20" if args.quick else "100",
                                      "--seconds", "5" if args.quick else "10"]),
        "plausible": ("plausible_bench", (["--data", args.plausible_data] if args.plausible_data else
                                          ["--synthetic-mugs", "4", "--views", "72"])
                      + ["--references", "4" if args.quick else "8", "--workers", "2"]),
    }
    for name, (script, script_args) in steps.items():
        try:
            numbers = run_step(script, script_args, tmp / f"{name}.json")
        except RuntimeError as error:
            keys = {"inference": ["network32", "network64"], "service": ["service", "topics"]}.get(name, [name])
            values.update({key: str(error) for key in keys})
            continue
        if name == "inference":
            for grid in ("32", "64"):
                values[f"network{grid}"] = numbers["grids"][grid]["ms"]
                best[f"network{grid}"] = numbers["grids"][grid]["best_ms"]
                paths[f"network{grid}"] = numbers["grids"][grid]["path"]
        elif name == "grasps":
            values["grasps"] = numbers["sizes"]["32"]["generate_ms"] + numbers["sizes"]["32"]["score_ms"]
        elif name == "service":
            values["service"] = numbers["service_over_network"]
            values["topics"] = numbers["topics"]["output_hz"]
        else:
            values["plausible"] = numbers["pairs_per_second"]
    return values, best, paths


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and calls (a few minutes)")
    parser.add_argument("--precision", default="auto", choices=PRECISIONS,
                        help="precision of the network rows (auto: bf16 where the CPU runs it natively, else fp32)")
    parser.add_argument("--plausible-data", default=None, help="a test dataset directory (default: synthetic mugs)")
    parser.add_argument("--json", type=Path, default=None, help="also write the table here")
    args = parser.parse_args()
    # The same test precision "auto" uses to choose bf16: the targets follow the CPU kind, whatever --precision says.
    model, bf16 = cpu_kind(), cpu_has_fast_bf16()
    kind = ("bf16 targets" if bf16 else "fp32 targets") + f", network rows at precision {args.precision}"
    print(f"[all] CPU: {model}: {kind}")
    with tempfile.TemporaryDirectory() as tmp:
        values, best, paths = measure(args, Path(tmp))
    rows, failures = [], 0
    print(f"\n[all] CPU: {model}: {kind}")
    print(f"{'what':<48} {'measured':>12} {'target':>12} {'ratio':>7}  met  (best run)")
    for key, target in TARGETS.items():
        goal = target.bf16 if bf16 else target.avx2
        value = values.get(key, "not run")
        if isinstance(value, str):
            failures += 1
            print(f"{target.what:<48} {'-':>12} {goal:>9g} {target.unit:<3}{'-':>7}  {value}")
            rows.append({"what": target.what, "error": value, "target": goal, "unit": target.unit})
            continue
        # ratio <= 1 means met, whichever way the target points
        ratio = value / goal if target.at_most else goal / value if value > 0 else float("inf")
        sign = "<=" if target.at_most else ">="
        extra = f"  ({best[key]:.2f} {target.unit})" if key in best else ""
        extra += f"  [{paths[key]}]" if key in paths else ""
        print(f"{target.what:<48} {value:>8.2f} {target.unit:<3} {sign}{goal:>7g} {target.unit:<3}"
              f"{ratio:>6.2f}x  {'yes' if ratio <= 1 else 'no '}{extra}")
        rows.append({"what": target.what, "measured": value, "best": best.get(key), "path": paths.get(key),
                     "target": goal, "unit": target.unit, "at_most": target.at_most, "ratio": ratio, "met": ratio <= 1})
    print("[all] measured: medians (grasps: CPU time); ratio: measured / target for times, target / measured for "
          "rates (<= 1 is met); best run: the fastest of the repeats; [the inference path that ran]")
    if args.json:
        args.json.write_text(json.dumps({"cpu": model, "bf16": bf16, "precision": args.precision, "rows": rows},
                                        indent=2))
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
