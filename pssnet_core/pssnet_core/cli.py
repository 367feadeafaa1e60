"""The `pssnet` command line: datasets, training, plausible sets, evaluation, grasp trials.

Each area registers its own subcommands (a ``register(subparsers)`` function in its ``cli`` module), so
this file only assembles them. Other installed packages add theirs through the ``pssnet.commands`` entry-point
group (the ROS package adds ``pssnet bag``), so that this ROS-free package imports none of them.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from importlib.metadata import entry_points

# Modules that add subcommands, in the order they appear in --help.
COMMAND_MODULES: tuple[str, ...] = (
    "pssnet_core.data.cli",
    "pssnet_core.training.cli",
    "pssnet_core.evaluation.cli",
    "pssnet_core.trials.cli",
)
#: Entry-point group of the modules other packages add subcommands from (each with a ``register`` function).
PLUGIN_GROUP = "pssnet.commands"


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every area's subcommands."""
    parser = argparse.ArgumentParser(
        prog="pssnet", description="PSSNet: diverse plausible shape completions from one depth image.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    plugins = [entry.value for entry in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name)]
    for name in (*COMMAND_MODULES, *plugins):
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `pssnet` console script."""
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
