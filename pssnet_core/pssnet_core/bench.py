"""`pssnet bench NAME [ARGS...]`: runs one of the benchmark scripts in the repository's benchmarks/ folder.

The scripts print their numbers; BENCHMARKS.md records them with the command used. They live beside the
package rather than in it because they are tools for developers, not part of the library.
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

#: benchmarks/ at the repository root, two levels above this module (pssnet_core/pssnet_core/bench.py)
BENCHMARK_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def available() -> list[str]:
    """Names of the benchmark scripts found next to the package (empty when installed without them)."""
    return sorted(p.stem for p in BENCHMARK_DIR.glob("*.py")) if BENCHMARK_DIR.is_dir() else []


def run(args: argparse.Namespace) -> int:
    names = available()
    if args.name not in names:
        print(f"unknown benchmark {args.name!r}; available: {', '.join(names) or 'none (no benchmarks/ folder)'}",
              file=sys.stderr)
        return 2
    saved = sys.argv
    sys.argv = [str(BENCHMARK_DIR / f"{args.name}.py"), *args.args]
    try:
        runpy.run_path(sys.argv[0], run_name="__main__")
    except SystemExit as done:
        return int(done.code or 0)
    finally:
        sys.argv = saved
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help="run a benchmark script from benchmarks/ and print its numbers")
    parser.add_argument("name", help=f"benchmark name ({', '.join(available())})")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the benchmark")
    parser.set_defaults(func=run)


# The machine description every benchmark prints with its numbers. It lives here, with the benchmark runner,
# and not in the ROS test harness (pssnet_testing), because most benchmarks need no ROS at all and must run
# where only pssnet_core is installed (e.g. a lent GPU machine without ROS).
def cpu_kind() -> str:
    """The CPU's model name (lscpu's "Model name", from /proc/cpuinfo) and whether it has AVX512-BF16 / AMX."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return "unknown CPU"
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set(fields.get("flags", "").split())
    kind = f"{fields.get('model name', 'unknown CPU')}, avx512_bf16 {'present' if 'avx512_bf16' in flags else 'absent'}"
    return kind + (", amx_bf16 present" if "amx_bf16" in flags else "")
