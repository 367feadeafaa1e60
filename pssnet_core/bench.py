"""`pssnet bench NAME [ARGS...]`: runs one of the benchmark scripts in the repository's benchmarks/ folder.

The scripts print their numbers; BENCHMARKS.md records them with the command used. They live beside the
package rather than in it because they are tools for developers, not part of the library.
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

BENCHMARK_DIR = Path(__file__).resolve().parent.parent / "benchmarks"


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
