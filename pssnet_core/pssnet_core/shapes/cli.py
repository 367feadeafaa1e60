"""``pssnet shapes gallery`` and ``pssnet shapes export`` subcommands."""

from __future__ import annotations

import argparse
import sys

from pssnet_core.shapes.mesh_io import LAYOUTS, MeshLoadError, export_shapes, load_mesh_folder
from pssnet_core.shapes.procedural import FAMILIES, SPLIT_RANGES, ShapeError, make_shape, split_seeds


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``shapes gallery`` and ``shapes export`` to the ``pssnet`` command line."""
    shapes = subparsers.add_parser("shapes", help="procedural object families and mesh folders")
    sub = shapes.add_subparsers(dest="shapes_command", required=True, metavar="ACTION")

    g = sub.add_parser("gallery", help="PNG contact sheet of procedural shapes or of a mesh folder")
    g.add_argument("--out", required=True, help="output PNG")
    g.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    g.add_argument("--count", type=int, default=4, help="shapes per family")
    g.add_argument("--split", default="train", choices=sorted(SPLIT_RANGES))
    g.add_argument("--mesh-folder", default=None, help="draw this folder's meshes instead (see load_mesh_folder)")
    g.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS])
    g.add_argument("--target-size", type=float, default=None, help="largest dimension in metres (ShapeNet)")
    g.add_argument("--columns", type=int, default=6)
    g.set_defaults(func=_gallery)

    e = sub.add_parser("export", help="write procedural shapes as .obj files in a ShapeNet/YCB/flat layout")
    e.add_argument("--out", required=True, help="output folder")
    e.add_argument("--layout", default="flat", choices=LAYOUTS)
    e.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    e.add_argument("--count", type=int, default=10, help="shapes per family")
    e.add_argument("--split", default="train", choices=sorted(SPLIT_RANGES))
    e.set_defaults(func=_export)


def _procedural(args: argparse.Namespace) -> list:
    return [make_shape(family, seed) for family in args.families for seed in split_seeds(args.split, args.count)]


def _gallery(args: argparse.Namespace) -> int:
    from pssnet_core.shapes.gallery import save_gallery

    try:
        if args.mesh_folder:
            shapes = load_mesh_folder(args.mesh_folder, args.layout, target_size=args.target_size)
        else:
            shapes = _procedural(args)
        path = save_gallery(shapes, args.out, columns=args.columns)
    except (ShapeError, MeshLoadError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({len(shapes)} shapes)")
    return 0


def _export(args: argparse.Namespace) -> int:
    try:
        paths = export_shapes(_procedural(args), args.out, args.layout)
    except (ShapeError, MeshLoadError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} meshes under {args.out} ({args.layout} layout)")
    return 0
