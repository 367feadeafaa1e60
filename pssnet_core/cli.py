"""The `pssnet` command line: datasets, training, plausible sets, evaluation, benchmarks.

Each area registers its own subcommands (a ``register(subparsers)`` function in its ``cli`` module), so
this file only assembles them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Modules that add subcommands, in the order they appear in --help.
COMMAND_MODULES: tuple[str, ...] = (
    "pssnet_core.data.cli",
    "pssnet_core.training.cli",
    "pssnet_core.evaluation.cli",
    "pssnet_core.trials.cli",
    "pssnet_core.bench",
    "pssnet_core.bag_cli",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every area's subcommands."""
    parser = argparse.ArgumentParser(
        prog="pssnet", description="PSSNet: diverse plausible shape completions from one depth image.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `pssnet` console script."""
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
