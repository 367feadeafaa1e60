"""``pssnet plausible`` (build/cache plausible sets), ``pssnet evaluate`` (the paper's table and figures),
``pssnet handles`` (where sampled mugs put a hidden or visible handle), ``pssnet ambiguity`` (samples against
what each view allows: plausible handle arcs, plausible box depths through a slit), ``pssnet memorisation``
(completions against the nearest training shape) and ``pssnet compare`` (paired differences between the methods
of an evaluation)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pssnet_core.evaluation.observation_model import ObservationModelConfig, ObservationModelError
from pssnet_core.evaluation.plausible import (
    PlausibleConfig,
    PlausibleSetError,
    PlausibleSets,
    ShapeMeshes,
    cached_plausible_sets,
    dataset_fingerprint,
)
from pssnet_core.evaluation.testsets import (
    MUG_SETS,
    NARROW_SETS,
    PAPER_TEST_SETS,
    TEST_SETS,
    build_command,
    find_test_set,
    load_test_set,
)
from pssnet_core.ray_tasks import TaskRunner, add_ray_options, ray_config
from pssnet_core.spread import evenly_spaced

PAPER_DELTA = 0.04
SCALED_DELTA = 0.01


class EvaluationCliError(ValueError):
    """Bad command-line input (missing data/checkpoints, unknown names)."""


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _add_plausible_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, help="directory holding the test sets (DATA/mugs or DATA/test/mugs, ...)")
    p.add_argument("--sets", default=",".join(PAPER_TEST_SETS),
                   help=f"test sets (default {','.join(PAPER_TEST_SETS)}; known: {','.join(TEST_SETS)})")
    p.add_argument("--max-observations", type=int, default=None,
                   help="score only this many observations per set (evenly spaced); candidates are always all")
    p.add_argument("--dense-mugs", type=int, default=0,
                   help="with --max-observations: also score every --dense-step-th view of the first K mugs with a "
                        "handle (a full turn for the coverage-vs-rotation plot)")
    p.add_argument("--dense-step", type=int, default=2, help="view stride of --dense-mugs (2 = every 10 degrees)")
    add_ray_options(p, default_workers=2, what="plausible sets and scores of the observations")
    p.add_argument("--cache-dir", default=None, help="plausible-set cache (default DATA_SET/plausible_cache)")
    p.add_argument("--recompute", action="store_true", help="ignore cached plausible sets")
    p.add_argument("--outlier-fraction", type=float, default=0.0,
                   help="fraction of a view's object pixels allowed to exceed delta (paper: 0)")
    p.add_argument("--outlier-count", type=int, default=0, help="violating pixels always allowed (paper: 0)")
    p.add_argument("--record-fraction", type=float, default=0.01,
                   help="store candidates up to this violating fraction (allowances up to it need no recompute)")
    p.add_argument("--no-progress", action="store_true")


def _add_sampler_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samplers", type=_names, default=("posterior",),
                   help="posterior sampling only, or also each model behind the plausibility-checked sampler (method "
                        "<model>_checked): posterior, checked or posterior,checked")
    p.add_argument("--check-delta", type=float, default=None,
                   help="the checked sampler's depth tolerance in metres (default 0.01)")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Adds ``plausible``, ``evaluate``, ``handles``, ``ambiguity`` and ``memorisation`` to ``pssnet``."""
    p = subparsers.add_parser(
        "plausible", help="build (and cache) the plausible sets of the test sets (paper Alg. 2)",
        description="For every test observation, every other observation's ground truth aligned by ICP and kept "
                    "if the observation model (Alg. 1) accepts it. Cached on disk by dataset content and parameters.")
    _add_plausible_options(p)
    p.add_argument("--deltas", type=_floats, default=(PAPER_DELTA, SCALED_DELTA),
                   help="observation-model tolerances in metres (default 0.04,0.01)")
    p.set_defaults(func=_guard(_plausible_command))

    e = subparsers.add_parser(
        "evaluate", help="score completion models against the plausible sets: the paper's table and figures",
        description="Writes OUT/results.md, OUT/results.csv, OUT/per_observation.csv, "
                    "OUT/coverage_vs_rotation.png and OUT/samples_<method>.png.")
    e.add_argument("--models", default="pssnet,vae,vae_gan,recgan", help="method names (checkpoint order)")
    e.add_argument("--checkpoints", required=True,
                   help="a directory (DIR/<model>.pt or DIR/<model>/best.pt) or a comma list, one per model")
    _add_plausible_options(e)
    e.add_argument("--samples", type=int, default=100, help="completions per observation (paper: 100)")
    _add_sampler_options(e)
    e.add_argument("--delta", type=float, default=PAPER_DELTA, help="the paper's delta (m)")
    e.add_argument("--scaled-delta", type=float, default=SCALED_DELTA,
                   help="the delta scaled to real-size objects (m); <= 0 to skip")
    e.add_argument("--out", default="results", help="output directory")
    e.add_argument("--device", default="cpu")
    e.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--plot-mugs", type=int, default=3, help="mugs in the coverage-vs-rotation plot")
    e.add_argument("--model-box-temperatures", type=_floats, default=None,
                   help="one box temperature per model, comma separated (PSSNet's box sigma factor; 1 for models "
                        "without a box part); default 1 for all. The same checkpoint may appear twice under two "
                        "names to compare temperatures")
    e.set_defaults(func=_guard(_evaluate_command))

    h = subparsers.add_parser(
        "handles", help="where each model's samples put the handle of held-out mugs (hidden vs visible)",
        description="For every view of the round, handled mugs of a test set: the fraction of samples with a "
                    "handle, the circular spread of its azimuth, its distance from the true handle and the "
                    "mean pairwise chamfer distance between samples. Writes OUT/handles.md, OUT/handles.csv "
                    "and OUT/handle_samples_{hidden,visible}.png.")
    h.add_argument("--models", default="pssnet,vae", help="method names (checkpoint order)")
    h.add_argument("--checkpoints", required=True,
                   help="a directory (DIR/<model>.pt or DIR/<model>/best.pt) or a comma list, one per model")
    h.add_argument("--data", required=True, help="the mugs test set (or a directory holding test/mugs)")
    h.add_argument("--samples", type=int, default=20, help="completions per view")
    h.add_argument("--max-mugs", type=int, default=None, help="measure only the first K measurable mugs")
    h.add_argument("--out", default="results/handles", help="output directory")
    h.add_argument("--device", default="cpu")
    h.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    h.add_argument("--seed", type=int, default=0)
    h.add_argument("--no-progress", action="store_true")
    h.set_defaults(func=_guard(_handles_command))

    a = subparsers.add_parser(
        "ambiguity", help="do samples spread over what each view allows? (plausible handle arcs, slit box depths)",
        description="Hidden-handle mugs: the azimuths where the same mug, handle turned there, passes the "
                    "observation model (the plausible arc) against the sampled handles (arc coverage, precision, "
                    "spread ratio, handle rate); visible handles: error to the truth. Boxes through the narrow "
                    "slit: the plausible range of the hidden extent against the samples' extents. The plausible "
                    "sets do not depend on the model and are cached in OUT/plausible_cache. Writes "
                    "OUT/ambiguity.md, OUT/ambiguity.json, OUT/ambiguity_per_view.csv and OUT/handle_arcs.png, "
                    "OUT/slit_extents.png, OUT/ambiguity_summary.png.")
    a.add_argument("--models", default="pssnet", help="method names (checkpoint order)")
    a.add_argument("--checkpoints", required=True,
                   help="a directory (DIR/<model>.pt or DIR/<model>/best.pt) or a comma list, one per model")
    a.add_argument("--data", required=True, help="directory holding the test sets (mugs, ycb_narrow)")
    a.add_argument("--sets", default="mugs,ycb_narrow",
                   help="one mug set and/or one narrow-slit set (default mugs,ycb_narrow; the out-of-family ones: "
                        "oof_mugs,oof_narrow)")
    a.add_argument("--samples", type=int, default=20, help="completions per view")
    _add_sampler_options(a)
    a.add_argument("--box-temperatures", type=_floats, default=(1.0,),
                   help="box temperatures for models with a box part, e.g. 1,1.5,2,3 (others run at 1 only)")
    a.add_argument("--max-views", type=int, default=None,
                   help="at most K views of each kind (hidden handle, visible handle, slit box), evenly spaced")
    a.add_argument("--deltas", type=_floats, default=(SCALED_DELTA, PAPER_DELTA),
                   help="observation-model tolerances in metres, headline first (default 0.01,0.04)")
    a.add_argument("--outlier-fraction", type=float, default=0.0,
                   help="fraction of a view's object pixels allowed to exceed delta (paper: 0)")
    a.add_argument("--outlier-count", type=int, default=0, help="violating pixels always allowed (paper: 0)")
    a.add_argument("--azimuth-step", type=float, default=5.0, help="candidate handle azimuth step (deg)")
    a.add_argument("--arc-tolerance", type=float, default=15.0, help="coverage tolerance of the arc (deg)")
    a.add_argument("--arc-margin", type=float, default=10.0, help="precision margin of the arc (deg)")
    a.add_argument("--extent-step", type=float, default=0.5, help="candidate box length step (voxels)")
    a.add_argument("--extent-tolerance", type=float, default=1.0, help="coverage tolerance of extents (voxels)")
    a.add_argument("--extent-margin", type=float, default=1.0, help="precision margin of extents (voxels)")
    a.add_argument("--no-rerender", action="store_true",
                   help="judge against the stored depth crop instead of the re-rendered whole image")
    a.add_argument("--figure-views", type=int, default=4, help="hidden-handle views in the arc figure")
    a.add_argument("--cache-dir", default=None, help="plausible-set cache (default OUT/plausible_cache)")
    a.add_argument("--out", default="results/ambiguity", help="output directory")
    a.add_argument("--device", default="cpu")
    a.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--no-progress", action="store_true")
    a.set_defaults(func=_guard(_ambiguity_command))

    m = subparsers.add_parser(
        "memorisation", help="distance of each completion to the nearest training shape and to the truth",
        description="The paper's appendix question: for every completion of the test views, the chamfer distance "
                    "(mm) to the nearest training ground truth (prefilter on block-averaged occupancy, exact "
                    "chamfer on the top-k) and to the view's truth. Writes OUT/memorisation.md, "
                    "OUT/memorisation.json, OUT/memorisation_per_completion.csv, OUT/memorisation_scatter.png "
                    "and OUT/memorisation_examples.png.")
    m.add_argument("--models", default="pssnet", help="method names (checkpoint order)")
    m.add_argument("--checkpoints", required=True,
                   help="a directory (DIR/<model>.pt or DIR/<model>/best.pt) or a comma list, one per model")
    m.add_argument("--train-data", required=True,
                   help="training datasets, comma separated; each a dataset or a folder of them (data/d32/train)")
    m.add_argument("--data", required=True, help="directory holding the test sets")
    m.add_argument("--sets", default=",".join(PAPER_TEST_SETS),
                   help=f"test sets (default {','.join(PAPER_TEST_SETS)}; known: {','.join(TEST_SETS)})")
    m.add_argument("--samples", type=int, default=10, help="completions per view")
    m.add_argument("--max-views", type=int, default=None, help="at most K views per test set, evenly spaced")
    m.add_argument("--top-k", type=int, default=16, help="exact chamfer on this many prefilter candidates")
    m.add_argument("--pool", type=int, default=None, help="prefilter block size in voxels (default grid / 8)")
    m.add_argument("--verify", type=int, default=0,
                   help="re-search this many completions by brute force over the whole training set (slow on large "
                        "sets: one distance transform per training grid, ~11 s per 1,000 grids measured here)")
    m.add_argument("--out", default="results/memorisation", help="output directory")
    m.add_argument("--device", default="cpu")
    m.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--no-progress", action="store_true")
    m.set_defaults(func=_guard(_memorisation_command))

    c = subparsers.add_parser(
        "compare", help="paired differences between methods of an evaluation, with bootstrap intervals",
        description="From `pssnet evaluate`'s per_observation.csv (one or several runs on the same test sets): "
                    "for every method, the mean difference to a baseline per paper subset and delta, paired "
                    "over the observations both were scored on, with a percentile bootstrap interval. Writes "
                    "OUT (markdown) and OUT with .csv.")
    c.add_argument("--per-observation", required=True,
                   help="per_observation.csv files, comma separated (rows of one observation pair by set and index)")
    c.add_argument("--methods", required=True, help="methods to compare, comma separated")
    c.add_argument("--baseline", required=True, help="the method every other is compared with")
    c.add_argument("--metric", default="plausible_diversity_mm",
                   help="best_accuracy_mm, coverage_mm, plausibility_mm or plausible_diversity_mm (default)")
    c.add_argument("--references", type=int, default=None,
                   help="only the observations `pssnet evaluate --max-observations N` picks (default: all rows)")
    c.add_argument("--confidence", type=float, default=0.95)
    c.add_argument("--resamples", type=int, default=10_000)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", default="results/comparison.md", help="markdown file (the CSV goes beside it)")
    c.set_defaults(func=_guard(_compare_command))


def _guard(handler):
    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except (EvaluationCliError, PlausibleSetError, ObservationModelError, ValueError, OSError) as error:
            # (HandleMeasureError, CheckpointError and DatasetError are ValueErrors too)
            print(f"pssnet {args.command}: error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return 130
    return run


def _set_names(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [n for n in names if n not in TEST_SETS]
    if unknown:
        raise EvaluationCliError(f"unknown test sets {unknown}; known: {list(TEST_SETS)}")
    return names


def _references(count: int, max_observations: int | None) -> list[int] | None:
    if max_observations is None or max_observations >= count:
        return None
    if max_observations < 1:
        raise EvaluationCliError(f"--max-observations must be >= 1, got {max_observations}")
    return evenly_spaced(count, max_observations)


def _dense_mug_views(views: list[Any], count: int, step: int) -> list[int]:
    """Every ``step``-th view of the first ``count`` mugs that have a handle (views of a mug are consecutive)."""
    if count < 0 or step < 1:
        raise EvaluationCliError(f"--dense-mugs must be >= 0 and --dense-step >= 1, got {count} and {step}")
    mugs: list[str] = []
    for view in views:
        if view.meta.get("has_handle") and view.identity not in mugs:
            mugs.append(view.identity)
    chosen = set(mugs[:count])
    out, seen = [], {}
    for k, view in enumerate(views):
        if view.identity in chosen:
            if seen.setdefault(view.identity, 0) % step == 0:
                out.append(k)
            seen[view.identity] += 1
    return out


def _plausible_for(args: argparse.Namespace, deltas: tuple[float, ...],
                   runner: TaskRunner) -> dict[str, tuple[list, PlausibleSets, list[int]]]:
    """Loads each requested test set and its plausible sets (cached, resumed or computed by ``runner``)."""
    progress = not args.no_progress
    config = PlausibleConfig(deltas=deltas, record_fraction=max(args.record_fraction, args.outlier_fraction),
                             observation=ObservationModelConfig(outlier_fraction=args.outlier_fraction,
                                                                outlier_count=args.outlier_count))
    out = {}
    found_any = False
    for name in _set_names(args.sets):
        root = find_test_set(args.data, name)
        if root is None:
            print(f"{name}: no test set under {args.data} (skipped; build it with `{build_command(name)}`)")
            continue
        found_any = True
        views, _ = load_test_set(root, progress=progress)
        refs = _references(len(views), args.max_observations)
        if name in MUG_SETS and refs is not None and getattr(args, "dense_mugs", 0):
            refs = sorted(set(refs) | set(_dense_mug_views(views, args.dense_mugs, args.dense_step)))
        cache = Path(args.cache_dir) if args.cache_dir else root / "plausible_cache"
        t0 = time.perf_counter()
        sets, path, hit = cached_plausible_sets(views, ShapeMeshes(), dataset_fingerprint(root), cache, config,
                                                refs, runner=runner, progress=progress,
                                                desc=f"plausible {name}", recompute=args.recompute)
        s = sets.stats
        state = "cached" if hit else f"computed in {time.perf_counter() - t0:.1f} s"
        if not hit and s.get("resumed_references"):
            state += f", {s['resumed_references']} references resumed from an interrupted run"
        sizes = {d: float(np.mean(list(sets.sizes(d).values()))) for d in deltas}
        where = s.get("executor") or f"{s['workers']} workers"  # caches written before Ray lack "executor"
        print(f"{name}: {len(views)} observations, {len(sets.references)} references, {s['pairs']} pairs "
              f"({state}; {s['pairs_per_second']:.0f} pairs/s, {where}, when computed); "
              f"mean set size {', '.join(f'{d * 100:g} cm: {v:.1f}' for d, v in sizes.items())}; "
              f"own ground truth plausible: {s['own_ground_truth_plausible_rate']} -> {path}")
        out[name] = (views, sets, [int(i) for i in sets.references])
    if not found_any:
        raise EvaluationCliError(f"no test sets {args.sets} found under {args.data}")
    return out


def _plausible_command(args: argparse.Namespace) -> int:
    with TaskRunner(ray_config(args)) as runner:
        _plausible_for(args, tuple(args.deltas), runner)
    return 0


def resolve_checkpoints(models: list[str], spec: str) -> dict[str, Path]:
    """Checkpoint path per model from a directory or a comma list (see ``--checkpoints``)."""
    path = Path(spec)
    if path.is_dir():
        out = {}
        for m in models:
            tried = [path / f"{m}.pt", path / m / "best.pt", path / m / "model.pt"]
            hit = next((t for t in tried if t.is_file()), None)
            if hit is None:
                raise EvaluationCliError(f"no checkpoint for {m} in {path} (tried {', '.join(map(str, tried))})")
            out[m] = hit
        return out
    items = [Path(s.strip()) for s in spec.split(",") if s.strip()]
    if len(items) != len(models):
        raise EvaluationCliError(f"{len(items)} checkpoints for {len(models)} models ({','.join(models)})")
    for item in items:
        if not item.is_file():
            raise EvaluationCliError(f"checkpoint {item} does not exist")
    return dict(zip(models, items, strict=True))


def load_completers(models: list[str], spec: str, device: str, threads: int | None,
                    samplers: tuple[str, ...] = ("posterior",), check_delta: float | None = None,
                    box_temperatures: tuple[float, ...] | None = None) -> dict[str, Any]:
    """Completers by method name (``pssnet_core.inference.Completer``).

    With ``samplers`` holding "checked", each latent-variable model also appears as ``<model>_checked``: the same
    checkpoint behind :class:`pssnet_core.sampling.CheckedSampler` (``check_delta`` metres, default its own). A
    model without a latent (3D-RecGAN++) has no checked variant and is listed once, with a note on stderr.
    """
    from pssnet_core.inference import Completer
    from pssnet_core.models.base import check_box_temperature
    from pssnet_core.sampling import SAMPLERS, CheckedSampler, CheckedSamplerConfig

    if not samplers or any(s not in SAMPLERS for s in samplers):
        raise EvaluationCliError(f"samplers must be a non-empty list of {', '.join(SAMPLERS)}, got {samplers}")
    temperatures = box_temperatures or (1.0,) * len(models)
    if len(temperatures) != len(models):
        raise EvaluationCliError(f"{len(temperatures)} box temperatures for {len(models)} models")
    try:
        config = CheckedSamplerConfig() if check_delta is None else CheckedSamplerConfig(delta=check_delta)
    except ValueError as error:
        raise EvaluationCliError(f"--check-delta: {error}") from error
    out: dict[str, Any] = {}
    for (model, path), temperature in zip(resolve_checkpoints(models, spec).items(), temperatures, strict=True):
        completer = Completer.from_checkpoint(path, device=device, threads=threads)
        try:
            completer.box_temperature = check_box_temperature(temperature, getattr(completer.model, "box_dim", 0) > 0)
        except ValueError as error:
            raise EvaluationCliError(f"{model}: {error}") from error
        if "posterior" in samplers:
            out[model] = completer
        if "checked" in samplers:
            if CheckedSampler.applies_to(completer):
                out[f"{model}_checked"] = CheckedSampler(completer, config)
            else:
                print(f"note: {model} has no latent to propose from: sampled as it is, no {model}_checked",
                      file=sys.stderr)
                out.setdefault(model, completer)
    return out


def run_evaluation(args: argparse.Namespace, completers: dict[str, Any]) -> dict[str, Path]:
    """The evaluation behind ``pssnet evaluate`` with given completers (tests pass fakes). Returns written files."""
    from pssnet_core.evaluation.evaluate import EvaluationOutput, evaluate_set
    from pssnet_core.evaluation.report import (
        markdown_table,
        plot_coverage_vs_rotation,
        plot_samples_vs_plausible,
        summarise,
        write_csv,
    )

    if args.samples < 1:
        raise EvaluationCliError(f"--samples must be >= 1, got {args.samples}")
    deltas = (args.delta,) + ((args.scaled_delta,) if args.scaled_delta and args.scaled_delta > 0 else ())
    if len(set(deltas)) != len(deltas):
        deltas = (args.delta,)
    out_dir = Path(args.out)
    output = EvaluationOutput()
    # One Ray for the whole command; completers on a GPU take a whole GPU per task.
    gpus_per_task = 1.0 if str(getattr(args, "device", "cpu")).startswith("cuda") else 0.0
    with TaskRunner(ray_config(args)) as runner:
        loaded = _plausible_for(args, deltas, runner)
        out_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        for name, (views, sets, refs) in loaded.items():
            # One example per figure set: the first occluded-handle mug, the first narrow-slit observation.
            if name in MUG_SETS:
                hidden = [i for i in refs if views[i].meta.get("handle_visible") is False]
                keep = hidden[len(hidden) // 2:][:1]
            elif name in NARROW_SETS:
                keep = refs[len(refs) // 2:][:1]
            else:
                keep = []
            evaluate_set(name, views, ShapeMeshes(), sets, completers, deltas, args.samples, args.seed, refs,
                         keep=keep, progress=not args.no_progress, output=output, runner=runner,
                         gpus_per_task=gpus_per_task)
    methods = list(completers)
    summary = summarise(output.rows, methods, deltas)
    notes = {args.delta: "the paper's value"}
    if len(deltas) > 1:
        notes[deltas[1]] = "scaled to real-size objects, see DESIGN.md"
    header = ["# Plausible-diversity evaluation", "",
              "Chamfer distances between voxel-centre clouds, millimetres (lower is better). best acc = M_A, "
              "coverage = M_C, avg plausibility = M_P, plausible diversity = M_PD = M_C + M_P.", "",
              f"Command: `pssnet evaluate {' '.join(sys.argv[2:]) if sys.argv[1:2] == ['evaluate'] else ''}`", "",
              f"Samples per observation: {args.samples}; outlier allowance: fraction {args.outlier_fraction}, "
              f"count {args.outlier_count}; sets: "
              f"{', '.join(f'{k} ({len(v[2])} observations)' for k, v in loaded.items())}.",
              ""]
    files = {"markdown": out_dir / "results.md"}
    files["markdown"].write_text("\n".join(header) + markdown_table(summary, methods, deltas, notes))
    files["csv"] = write_csv(out_dir / "results.csv", summary)
    files["per_observation"] = write_csv(out_dir / "per_observation.csv", output.rows)
    plot = plot_coverage_vs_rotation(out_dir / "coverage_vs_rotation.png", output.rows, methods, deltas,
                                     args.plot_mugs)
    if plot is not None:
        files["coverage_plot"] = plot
    for method in methods:
        examples = [e for e in output.examples if abs(e.delta - deltas[-1]) < 1e-12]
        png = plot_samples_vs_plausible(out_dir / f"samples_{method}.png", examples, method)
        if png is not None:
            files[f"samples_{method}"] = png
    timings = dict(output.timings, evaluate_seconds=time.perf_counter() - t0)
    (out_dir / "evaluation_info.json").write_text(json.dumps(
        {"deltas": deltas, "methods": methods, "samples": args.samples, "timings": timings,
         "plausible_stats": {k: v[1].stats for k, v in loaded.items()}}, indent=2, default=str))
    return files


def _evaluate_command(args: argparse.Namespace) -> int:
    completers = load_completers(_models(args.models), args.checkpoints, args.device, args.threads, args.samplers,
                                 args.check_delta, args.model_box_temperatures)
    files = run_evaluation(args, completers)
    print((Path(args.out) / "results.md").read_text())
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def _closest(views: list[Any], rotation: float) -> Any:
    return min(views, key=lambda v: abs((float(v.meta.get("rotation_deg", 0.0)) - rotation + 180) % 360 - 180))


def run_handles(args: argparse.Namespace, completers: dict[str, Any]) -> dict[str, Path]:
    """The measurement behind ``pssnet handles`` with given completers. Returns the files written."""
    from tqdm import tqdm

    from pssnet_core.data.store import DatasetReader
    from pssnet_core.evaluation.handles import (
        handle_azimuths,
        handle_geometries,
        handle_stats,
        plot_handle_samples,
        stats_row,
        summarise_handles,
    )
    from pssnet_core.evaluation.report import write_csv

    if args.samples < 2:
        raise EvaluationCliError(f"--samples must be >= 2 to measure a spread, got {args.samples}")
    root = find_test_set(args.data, "mugs")
    if root is None:
        raise EvaluationCliError(f"no mugs test set under {args.data} (build it with "
                                 "`pssnet dataset build --family mugs --split test`)")
    views, _ = load_test_set(root, progress=not args.no_progress)
    by_mug: dict[str, list[Any]] = {}
    for view in views:
        by_mug.setdefault(view.identity, []).append(view)
    # Square bodies and handle-less mugs have no handle azimuth: skipped.
    geometries = handle_geometries(by_mug, args.max_mugs)
    if not geometries:
        raise EvaluationCliError(f"{root} holds no round mug with a handle")
    chosen = [v for identity in geometries for v in by_mug[identity]]
    rows = []
    for view in tqdm(chosen, desc="handles", disable=args.no_progress):
        for method, completer in completers.items():
            samples = completer.complete(view, num_samples=args.samples, seed=args.seed).occupancy
            rows.append(stats_row(method, view, handle_stats(samples, view, geometries[view.identity])))
    methods = list(completers)
    summary = summarise_handles(rows, methods)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": write_csv(out / "handles.csv", rows),
             "summary_csv": write_csv(out / "handles_summary.csv", summary)}
    lines = ["# Where sampled mugs put the handle", "",
             f"{len(geometries)} round held-out mugs with a handle from `{root}`, {len(chosen)} views, "
             f"{args.samples} samples per view, seed {args.seed}. Azimuths in the mug's frame (true handle = 0 deg); "
             "spread = circular standard deviation of the handle azimuth across samples; error = mean |azimuth|; "
             "pairwise = mean chamfer distance between two samples of the same view (mm). "
             "See `pssnet_core/evaluation/handles.py`.", "",
             "| method | handle | views | samples with a handle | azimuth spread (deg) | azimuth error (deg) "
             "| pairwise (mm) |", "|---|---|---|---|---|---|---|"]
    for r in summary:
        lines.append(f"| {r['method']} | {r['handle']} | {r['views']} | {r['handle_rate']:.2f} | "
                     f"{r['spread_deg']:.1f} | {r['error_deg']:.1f} | {r['pairwise_mm']:.2f} |")
    files["markdown"] = out / "handles.md"
    files["markdown"].write_text("\n".join(lines) + "\n")
    # Figures: the first measurable mug, handle straight behind the body (hidden) and seen side-on (visible).
    first = by_mug[next(iter(geometries))]
    reader = DatasetReader(root)
    for label, candidates, rotation in (
            ("hidden", [v for v in first if not v.meta.get("handle_visible")], 0.0),
            ("visible", [v for v in first if v.meta.get("handle_visible")], 90.0)):
        if not candidates:
            continue
        view = _closest(candidates, rotation)
        grids, azimuths = {}, {}
        for method, completer in completers.items():
            grids[method] = completer.complete(view, num_samples=8, seed=args.seed).occupancy
            azimuths[method] = handle_azimuths(grids[method], view.grid_pose, view.object_pose,
                                               geometries[view.identity])
        truth = reader.get(view.index, images=False)["occupancy"]
        files[f"figure_{label}"] = plot_handle_samples(
            out / f"handle_samples_{label}.png", truth, grids, azimuths,
            f"{view.identity}, rotation {view.meta.get('rotation_deg')} deg: handle {label} "
            f"(true handle azimuth 0 deg)")
    return files


def _handles_command(args: argparse.Namespace) -> int:
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    if not models:
        raise EvaluationCliError("--models is empty")
    files = run_handles(args, load_completers(models, args.checkpoints, args.device, args.threads))
    print((Path(args.out) / "handles.md").read_text())
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def _names(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _models(text: str) -> list[str]:
    models = [m.strip() for m in text.split(",") if m.strip()]
    if not models:
        raise EvaluationCliError("--models is empty")
    if len(set(models)) != len(models):  # names key the results: a repeated one would hide a model
        raise EvaluationCliError(f"--models names must differ (they label the results), got {text!r}")
    return models


def ambiguity_run(args: argparse.Namespace) -> Any:
    """The :class:`~pssnet_core.evaluation.ambiguity.AmbiguityRun` of ``pssnet ambiguity``'s arguments."""
    from pssnet_core.evaluation.ambiguity import AmbiguityConfig, AmbiguityRun

    config = AmbiguityConfig(
        deltas=tuple(args.deltas),
        observation=ObservationModelConfig(outlier_fraction=args.outlier_fraction, outlier_count=args.outlier_count),
        azimuth_step_deg=args.azimuth_step, arc_tolerance_deg=args.arc_tolerance, arc_margin_deg=args.arc_margin,
        extent_step_voxels=args.extent_step, extent_tolerance_voxels=args.extent_tolerance,
        extent_margin_voxels=args.extent_margin, rerender=not args.no_rerender)
    return AmbiguityRun(data=args.data, out=args.out, sets=tuple(_set_names(args.sets)), samples=args.samples,
                        box_temperatures=tuple(args.box_temperatures), max_views=args.max_views, seed=args.seed,
                        progress=not args.no_progress, figure_views=args.figure_views, cache_dir=args.cache_dir,
                        config=config)


def _ambiguity_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.ambiguity import run_ambiguity

    run = ambiguity_run(args)  # parameters checked before the models load
    files = run_ambiguity(run, load_completers(_models(args.models), args.checkpoints, args.device, args.threads,
                                                    args.samplers, args.check_delta))
    print(files["markdown"].read_text())
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def memorisation_run(args: argparse.Namespace) -> Any:
    """The :class:`~pssnet_core.evaluation.memorisation.MemorisationRun` of ``pssnet memorisation``'s arguments."""
    from pssnet_core.evaluation.memorisation import MemorisationConfig, MemorisationRun

    return MemorisationRun(train_data=[p.strip() for p in args.train_data.split(",") if p.strip()], data=args.data,
                           out=args.out, sets=tuple(_set_names(args.sets)), samples=args.samples,
                           max_views=args.max_views, seed=args.seed, verify=args.verify,
                           progress=not args.no_progress,
                           config=MemorisationConfig(pool=args.pool, top_k=args.top_k))


def _memorisation_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.memorisation import run_memorisation

    run = memorisation_run(args)
    files = run_memorisation(run, load_completers(_models(args.models), args.checkpoints, args.device, args.threads))
    print(files["markdown"].read_text())
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def _compare_command(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from pssnet_core.evaluation.compare import CompareConfig, markdown, paired_differences, read_per_observation
    from pssnet_core.evaluation.report import write_csv

    config = CompareConfig(metric=args.metric, confidence=args.confidence, resamples=args.resamples, seed=args.seed,
                           references=args.references)
    rows = read_per_observation(p.strip() for p in args.per_observation.split(",") if p.strip())
    methods = [m for m in _models(args.methods) if m != args.baseline]
    differences = paired_differences(rows, methods, args.baseline, config)
    if not differences:
        raise EvaluationCliError(f"no observation was scored by both the baseline {args.baseline!r} and {methods}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = markdown(differences, config)
    out.write_text(text)
    table = write_csv(out.with_suffix(".csv"), [asdict(d) for d in differences])
    print(text)
    print(f"wrote {out}, {table}")
    return 0
