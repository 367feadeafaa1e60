"""``pssnet plausible`` (build/cache plausible sets), ``pssnet evaluate`` (the paper's table and figures),
``pssnet handles`` (where sampled mugs put a hidden or visible handle), ``pssnet ambiguity`` (samples against
what each view allows: plausible handle arcs, plausible box depths through a slit), ``pssnet memorisation``
(completions against the nearest training shape) and ``pssnet compare`` (paired differences between the methods
of an evaluation).

Each command turns its arguments into the experiment's config, loads the completers, runs the experiment and
writes its report (:mod:`pssnet_core.evaluation.experiment`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from pssnet_core.evaluation.evaluate import (
    PAPER_DELTA,
    SCALED_DELTA,
    EvaluateConfig,
    TestSetsConfig,
    load_test_sets,
    run_evaluation,
)
from pssnet_core.evaluation.experiment import Completer, Json, Report, write_report
from pssnet_core.evaluation.observation_model import ObservationModelConfig, ObservationModelError
from pssnet_core.evaluation.plausible import PlausibleSetError
from pssnet_core.evaluation.testsets import PAPER_TEST_SETS, TEST_SETS
from pssnet_core.ray_tasks import TaskRunner, add_ray_options, ray_config

if TYPE_CHECKING:  # the experiments' own modules load when their command runs
    from pssnet_core.evaluation.ambiguity import AmbiguityConfig
    from pssnet_core.evaluation.handles import HandlesConfig
    from pssnet_core.evaluation.memorisation import MemorisationConfig


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


def _add_model_options(p: argparse.ArgumentParser, default_models: str) -> None:
    p.add_argument("--models", default=default_models, help="method names (checkpoint order)")
    p.add_argument("--checkpoints", required=True,
                   help="a directory (DIR/<model>.pt or DIR/<model>/best.pt) or a comma list, one per model")


def _add_run_options(p: argparse.ArgumentParser, default_out: str, progress: bool = True) -> None:
    """--out, --device, --threads, --seed and (unless the command's other options add it) --no-progress."""
    p.add_argument("--out", default=default_out, help="output directory")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--seed", type=int, default=0)
    if progress:
        p.add_argument("--no-progress", action="store_true")


def _add_sampler_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samplers", type=_names, default=("posterior",),
                   help="posterior sampling only, or also each model behind the plausibility-checked sampler (method "
                        "<model>_checked): posterior, checked or posterior,checked")
    p.add_argument("--check-delta", type=float, default=None,
                   help="the checked sampler's depth tolerance in metres (default 0.01)")
    p.add_argument("--sampler-option", action="append", default=[], metavar="NAME=VALUE",
                   help="set another of the checked sampler's parameters (pssnet_core.sampling.CheckedSamplerConfig, "
                        "e.g. turned_rest_low=0.75 or source_shares=0.5,0,0,0.5); repeat for more")


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
    _add_model_options(e, "pssnet,vae,vae_gan,recgan")
    _add_plausible_options(e)
    e.add_argument("--samples", type=int, default=100, help="completions per observation (paper: 100)")
    _add_sampler_options(e)
    e.add_argument("--delta", type=float, default=PAPER_DELTA, help="the paper's delta (m)")
    e.add_argument("--scaled-delta", type=float, default=SCALED_DELTA,
                   help="the delta scaled to real-size objects (m); <= 0 to skip")
    _add_run_options(e, "results", progress=False)
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
    _add_model_options(h, "pssnet,vae")
    h.add_argument("--data", required=True, help="the mugs test set (or a directory holding test/mugs)")
    h.add_argument("--samples", type=int, default=20, help="completions per view")
    h.add_argument("--max-mugs", type=int, default=None, help="measure only the first K measurable mugs")
    _add_run_options(h, "results/handles")
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
    _add_model_options(a, "pssnet")
    a.add_argument("--data", required=True, help="directory holding the test sets (mugs, ycb_narrow)")
    a.add_argument("--sets", default="mugs,ycb_narrow",
                   help="one mug set and/or one narrow-slit set (default mugs,ycb_narrow; the out-of-family ones: "
                        "oof_mugs,oof_narrow; the mugs through the narrow slit: mugs_narrow, oof_mugs_narrow)")
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
    _add_run_options(a, "results/ambiguity")
    a.set_defaults(func=_guard(_ambiguity_command))

    m = subparsers.add_parser(
        "memorisation", help="distance of each completion to the nearest training shape and to the truth",
        description="The paper's appendix question: for every completion of the test views, the chamfer distance "
                    "(mm) to the nearest training ground truth (prefilter on block-averaged occupancy, exact "
                    "chamfer on the top-k) and to the view's truth. Writes OUT/memorisation.md, "
                    "OUT/memorisation.json, OUT/memorisation_per_completion.csv, OUT/memorisation_scatter.png "
                    "and OUT/memorisation_examples.png.")
    _add_model_options(m, "pssnet")
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
    _add_run_options(m, "results/memorisation")
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
            # (the experiments' own errors, CheckpointError and DatasetError are ValueErrors too)
            print(f"pssnet {args.command}: error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return 130
    return run


def _names(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _models(text: str) -> list[str]:
    models = list(_names(text))
    if not models:
        raise EvaluationCliError("--models is empty")
    if len(set(models)) != len(models):  # names key the results: a repeated one would hide a model
        raise EvaluationCliError(f"--models names must differ (they label the results), got {text!r}")
    return models


def _set_names(text: str) -> tuple[str, ...]:
    names = _names(text)
    unknown = [n for n in names if n not in TEST_SETS]
    if unknown:
        raise EvaluationCliError(f"unknown test sets {unknown}; known: {list(TEST_SETS)}")
    return names


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
                    box_temperatures: tuple[float, ...] | None = None,
                    sampler_options: tuple[str, ...] = ()) -> dict[str, Completer]:
    """Completers by method name (``pssnet_core.inference.Completer``).

    With ``samplers`` holding "checked", each latent-variable model also appears as ``<model>_checked``: the same
    checkpoint behind :class:`pssnet_core.sampling.CheckedSampler` (``check_delta`` metres, default its own; its
    other parameters from ``sampler_options``, ``NAME=VALUE`` each). A model without a latent (3D-RecGAN++) has no
    checked variant and is listed once, with a note on stderr.
    """
    from pssnet_core.inference import Completer as ModelCompleter
    from pssnet_core.models.base import check_box_temperature
    from pssnet_core.sampling import SAMPLERS, CheckedSampler, CheckedSamplerConfig, checked_config_with

    if not samplers or any(s not in SAMPLERS for s in samplers):
        raise EvaluationCliError(f"samplers must be a non-empty list of {', '.join(SAMPLERS)}, got {samplers}")
    temperatures = box_temperatures or (1.0,) * len(models)
    if len(temperatures) != len(models):
        raise EvaluationCliError(f"{len(temperatures)} box temperatures for {len(models)} models")
    try:
        config = CheckedSamplerConfig() if check_delta is None else CheckedSamplerConfig(delta=check_delta)
    except ValueError as error:
        raise EvaluationCliError(f"--check-delta: {error}") from error
    try:
        config = checked_config_with(sampler_options, config)
    except ValueError as error:
        raise EvaluationCliError(f"--sampler-option: {error}") from error
    out: dict[str, Completer] = {}
    for (model, path), temperature in zip(resolve_checkpoints(models, spec).items(), temperatures, strict=True):
        completer = ModelCompleter.from_checkpoint(path, device=device, threads=threads)
        try:
            completer.box_temperature = check_box_temperature(temperature, completer.has_box_latent)
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


def _write(report: Report, out: str, completers: dict[str, Completer]) -> dict[str, Path]:
    """Writes the report into ``out`` with ``methods.json`` (the code version, the machine and each method's
    settings: pssnet_core.provenance), prints its Markdown and the files written."""
    from pssnet_core.provenance import invocation, method_settings

    report = {**report, "methods": Json("methods.json", invocation(
        methods={name: method_settings(c) for name, c in completers.items()}), indent=1, strict=False)}
    files = write_report(report, out)
    print(files["markdown"].read_text())
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return files


# ------------------------------------------------------------------------------------------ plausible


def test_sets_config(args: argparse.Namespace) -> TestSetsConfig:
    """The test sets and plausible-set parameters of ``pssnet plausible`` / ``pssnet evaluate``."""
    return TestSetsConfig(
        data=args.data, sets=_set_names(args.sets), max_observations=args.max_observations,
        dense_mugs=args.dense_mugs, dense_step=args.dense_step, cache_dir=args.cache_dir, recompute=args.recompute,
        observation=ObservationModelConfig(outlier_fraction=args.outlier_fraction, outlier_count=args.outlier_count),
        record_fraction=args.record_fraction, progress=not args.no_progress)


def _plausible_command(args: argparse.Namespace) -> int:
    config = test_sets_config(args)
    with TaskRunner(ray_config(args)) as runner:
        load_test_sets(config, tuple(args.deltas), runner)
    return 0


# ------------------------------------------------------------------------------------------- evaluate


def evaluate_config(args: argparse.Namespace) -> EvaluateConfig:
    """The :class:`~pssnet_core.evaluation.evaluate.EvaluateConfig` of ``pssnet evaluate``'s arguments."""
    # Completers on a GPU take a whole GPU per Ray task.
    return EvaluateConfig(test_sets=test_sets_config(args), out=args.out, samples=args.samples, delta=args.delta,
                          scaled_delta=args.scaled_delta, seed=args.seed, plot_mugs=args.plot_mugs,
                          ray=ray_config(args), gpus_per_task=1.0 if str(args.device).startswith("cuda") else 0.0)


def _evaluate_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.report import evaluation_report

    config = evaluate_config(args)  # parameters checked before the models load
    completers = load_completers(_models(args.models), args.checkpoints, args.device, args.threads, args.samplers,
                                 args.check_delta, args.model_box_temperatures, tuple(args.sampler_option))
    command = " ".join(sys.argv[2:]) if sys.argv[1:2] == ["evaluate"] else ""
    _write(evaluation_report(run_evaluation(config, completers), command), config.out, completers)
    return 0


# -------------------------------------------------------------------------------------------- handles


def handles_config(args: argparse.Namespace) -> HandlesConfig:
    """The :class:`~pssnet_core.evaluation.handles.HandlesConfig` of ``pssnet handles``' arguments."""
    from pssnet_core.evaluation.handles import HandlesConfig

    return HandlesConfig(data=args.data, out=args.out, samples=args.samples, max_mugs=args.max_mugs, seed=args.seed,
                         progress=not args.no_progress)


def _handles_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.handles import run_handles
    from pssnet_core.evaluation.handles_report import handles_report

    config = handles_config(args)
    completers = load_completers(_models(args.models), args.checkpoints, args.device, args.threads)
    _write(handles_report(run_handles(config, completers)), config.out, completers)
    return 0


# ------------------------------------------------------------------------------------------ ambiguity


def ambiguity_config(args: argparse.Namespace) -> AmbiguityConfig:
    """The :class:`~pssnet_core.evaluation.ambiguity.AmbiguityConfig` of ``pssnet ambiguity``'s arguments."""
    from pssnet_core.evaluation.ambiguity import AmbiguityConfig
    from pssnet_core.evaluation.ambiguity_sets import AmbiguityMeasure

    measure = AmbiguityMeasure(
        deltas=tuple(args.deltas),
        observation=ObservationModelConfig(outlier_fraction=args.outlier_fraction, outlier_count=args.outlier_count),
        azimuth_step_deg=args.azimuth_step, arc_tolerance_deg=args.arc_tolerance, arc_margin_deg=args.arc_margin,
        extent_step_voxels=args.extent_step, extent_tolerance_voxels=args.extent_tolerance,
        extent_margin_voxels=args.extent_margin, rerender=not args.no_rerender)
    return AmbiguityConfig(data=args.data, out=args.out, sets=_set_names(args.sets), samples=args.samples,
                           box_temperatures=tuple(args.box_temperatures), max_views=args.max_views, seed=args.seed,
                           progress=not args.no_progress, figure_views=args.figure_views, cache_dir=args.cache_dir,
                           measure=measure)


def _ambiguity_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.ambiguity import run_ambiguity
    from pssnet_core.evaluation.ambiguity_report import ambiguity_report

    config = ambiguity_config(args)  # parameters checked before the models load
    completers = load_completers(_models(args.models), args.checkpoints, args.device, args.threads, args.samplers,
                                 args.check_delta, sampler_options=tuple(args.sampler_option))
    _write(ambiguity_report(run_ambiguity(config, completers)), config.out, completers)
    return 0


# --------------------------------------------------------------------------------------- memorisation


def memorisation_config(args: argparse.Namespace) -> MemorisationConfig:
    """The :class:`~pssnet_core.evaluation.memorisation.MemorisationConfig` of ``pssnet memorisation``'s
    arguments."""
    from pssnet_core.evaluation.memorisation import MemorisationConfig
    from pssnet_core.evaluation.memorisation_search import SearchConfig

    return MemorisationConfig(train_data=list(_names(args.train_data)), data=args.data, out=args.out,
                              sets=_set_names(args.sets), samples=args.samples, max_views=args.max_views,
                              seed=args.seed, verify=args.verify, progress=not args.no_progress,
                              search=SearchConfig(pool=args.pool, top_k=args.top_k))


def _memorisation_command(args: argparse.Namespace) -> int:
    from pssnet_core.evaluation.memorisation import run_memorisation
    from pssnet_core.evaluation.memorisation_report import memorisation_report

    config = memorisation_config(args)
    completers = load_completers(_models(args.models), args.checkpoints, args.device, args.threads)
    _write(memorisation_report(run_memorisation(config, completers)), config.out, completers)
    return 0


# -------------------------------------------------------------------------------------------- compare


def _compare_command(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from pssnet_core.evaluation.compare import CompareConfig, markdown, paired_differences, read_per_observation
    from pssnet_core.evaluation.experiment import write_csv

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
