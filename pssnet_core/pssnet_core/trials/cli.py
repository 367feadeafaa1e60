"""``pssnet grasp-trials``: every strategy on randomised scenes in MuJoCo; success rates, causes, filmstrips."""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from pssnet_core.grasps.config import RANKINGS, GraspConfig
from pssnet_core.options import config_with
from pssnet_core.trials import (
    ALL_SCENARIOS,
    DEFAULT_STRATEGIES,
    EXTRA_SCENARIOS,
    HEADLESS_GL,
    LOOK_MIN_SEPARABILITY,
    OBJECT_SOURCES,
    SCENARIOS,
    STRATEGIES,
    VAE_STRATEGIES,
)

if TYPE_CHECKING:
    from pssnet_core.trials.run import TrialsConfig


#: GraspConfig fields with a flag of their own (``--grasp-option`` refuses them); the seed comes from ``--seed``.
GRASP_FLAGS = ("rank_by", "observed_points_check", "surface_at_voxel_centres", "seed")


def _names(text: str, known: tuple[str, ...], what: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown or no {what} {unknown}; known: {','.join(known)}")
    return names


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "grasp-trials", help="grasp trials in MuJoCo: PSSNet's multi-completion grasps against the baselines",
        description="Runs every strategy on the same randomised scenes (held-out objects) in MuJoCo and writes "
                    "records.jsonl, summary.md (success rates with 95%% intervals, failure causes, the collision "
                    "shapes' faithfulness) and filmstrip_<scenario>.png to --out. Resumes an interrupted run.")
    p.add_argument("--pssnet-checkpoint", default=None, help="PSSNet checkpoint (default: the shipped model)")
    p.add_argument("--vae-checkpoint", default=None, help="VAE checkpoint (needed by the vae strategy)")
    p.add_argument("--trials", type=int, default=200, help="scenes per scenario; every strategy gets each scene")
    p.add_argument("--scenarios", type=lambda t: _names(t, ALL_SCENARIOS, "scenarios"), default=SCENARIOS,
                   help=f"comma-separated (default {','.join(SCENARIOS)}; also {','.join(EXTRA_SCENARIOS)})")
    p.add_argument("--strategies", type=lambda t: _names(t, STRATEGIES, "strategies"), default=None,
                   help=f"comma-separated, of {','.join(STRATEGIES)} (default {','.join(DEFAULT_STRATEGIES)}, and vae "
                        "with --vae-checkpoint)")
    p.add_argument("--objects", choices=OBJECT_SOURCES, default="procedural",
                   help="procedural: held-out objects of the training data's generator (default); independent: "
                        "objects of the out-of-family generator, which made no training view")
    p.add_argument("--seed", type=int, default=0, help="master seed (scenes, latent noise, candidates)")
    p.add_argument("--num-samples", type=int, default=20, help="completions per view (the node's default: 20)")
    p.add_argument("--sampler", choices=("posterior", "checked"), default="checked",
                   help="how PSSNet and the VAE draw their samples (the node's sampler parameter; default checked)")
    p.add_argument("--sampler-option", action="append", default=[], metavar="NAME=VALUE",
                   help="set one of the checked sampler's parameters (pssnet_core.sampling.CheckedSamplerConfig, "
                        "e.g. turned_rest_low=0.75); repeat for more")
    p.add_argument("--look-threshold", type=float, default=LOOK_MIN_SEPARABILITY, metavar="P",
                   help="the second look's strategies look again when some place tells two samples apart with at "
                        "least this probability (default %(default)s)")
    p.add_argument("--rank-by", choices=RANKINGS, default=GraspConfig.rank_by,
                   help="how the planner ranks grasps (GraspConfig.rank_by; default %(default)s)")
    p.add_argument("--observed-points-check", action=argparse.BooleanOptionalAction,
                   default=GraspConfig.observed_points_check,
                   help="no grasp with an observed point inside a finger or the palm (GraspConfig."
                        "observed_points_check; default %(default)s)")
    p.add_argument("--surface-at-voxel-centres", action=argparse.BooleanOptionalAction,
                   default=GraspConfig.surface_at_voxel_centres,
                   help="the fingers' clearance from the completions' outermost voxels' centres, not their faces "
                        "(GraspConfig.surface_at_voxel_centres; default %(default)s)")
    p.add_argument("--grasp-option", action="append", default=[], metavar="NAME=VALUE",
                   help="set one of the planner's other options (pssnet_core.grasps.GraspConfig, e.g. "
                        "tilted_pitches=20,45,70 or gripper.grip_force=40); repeat for more")
    p.add_argument("--filmstrip-scenes", type=int, default=2, help="scenes per scenario drawn in the filmstrip")
    p.add_argument("--out", type=Path, default=Path("results/grasp_trials"), help="output directory")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="CoACD decomposition cache (default ~/.cache/pssnet/coacd)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run_command)


def chosen_strategies(args: argparse.Namespace) -> tuple[str, ...]:
    """``--strategies``, or the default ones (with the VAE when a VAE checkpoint is given)."""
    if args.strategies is not None:
        return args.strategies
    return (*DEFAULT_STRATEGIES, "vae") if args.vae_checkpoint else DEFAULT_STRATEGIES


def trials_config(args: argparse.Namespace) -> TrialsConfig:
    """The run's :class:`~pssnet_core.trials.run.TrialsConfig` from the command line (imported here: the module
    imports MuJoCo, which ``run_command`` must first point at a headless GL).

    Raises:
        ValueError: a ``--grasp-option`` the planner's config refuses.
    """
    from pssnet_core.trials.run import SHIPPED_CHECKPOINT, TrialsConfig

    checkpoints = {"pssnet": str(args.pssnet_checkpoint or SHIPPED_CHECKPOINT), "vae": str(args.vae_checkpoint or "")}
    config = TrialsConfig(scenarios=args.scenarios, strategies=chosen_strategies(args), trials=args.trials,
                          seed=args.seed, num_samples=args.num_samples, sampler=args.sampler,
                          sampler_options=tuple(args.sampler_option), look_threshold=args.look_threshold,
                          filmstrip_scenes=args.filmstrip_scenes, checkpoints=checkpoints)
    grasps = config_with(config.grasps, args.grasp_option, "grasp option", refused=GRASP_FLAGS)
    scenario = replace(config.scenario, objects=args.objects)
    if args.cache_dir is not None:
        scenario = replace(scenario, cache_dir=args.cache_dir)
    return replace(config, scenario=scenario,
                   grasps=replace(grasps, rank_by=args.rank_by, observed_points_check=args.observed_points_check,
                                  surface_at_voxel_centres=args.surface_at_voxel_centres))


def run_command(args: argparse.Namespace) -> int:
    os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)  # before MuJoCo is first imported (pssnet_core.trials)
    from pssnet_core.inference import CheckpointError, Completer
    from pssnet_core.trials.run import markdown_table, run_trials, strategist_of, summarise

    try:
        config = trials_config(args)
        if args.trials < 1 or args.num_samples < 1:
            raise ValueError("--trials and --num-samples must be >= 1")
        if set(VAE_STRATEGIES) & set(config.strategies) and args.vae_checkpoint is None:
            raise ValueError(f"the strategies {', '.join(VAE_STRATEGIES)} need --vae-checkpoint (or leave them out of "
                             "--strategies)")
        pssnet = Completer.from_checkpoint(args.pssnet_checkpoint, threads=args.threads)
        vae = Completer.from_checkpoint(args.vae_checkpoint, threads=args.threads) if args.vae_checkpoint else None
        records = run_trials(config, strategist_of(config, pssnet, vae), args.out, progress=not args.no_progress)
    except (CheckpointError, ValueError, OSError) as error:
        print(f"pssnet grasp-trials: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print(markdown_table(summarise(records, config.scenarios, config.strategies)))
    print(f"written: {args.out / 'summary.md'}, {args.out / 'records.jsonl'}, filmstrips in {args.out}")
    return 0
