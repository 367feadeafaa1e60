"""Many trials: every strategy on the same scenes, success rates with 95 % intervals, causes, filmstrips.

Scene ``i`` of a scenario is drawn from ``(seed, scenario, i)`` and shown to every strategy, so the
strategies are compared on identical views (paired). Each record is appended to ``records.jsonl`` as soon
as it is done; a run started again with the same settings skips the (scene, strategy) pairs already there.
"""

from __future__ import annotations

import gzip
import json
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pssnet_core.grasps import KIND_NAMES, GraspConfig, GripperConfig
from pssnet_core.provenance import invocation
from pssnet_core.trials import DEFAULT_STRATEGIES, LOOK_MIN_SEPARABILITY, SCENARIOS
from pssnet_core.trials.collision import Faithfulness
from pssnet_core.trials.physics import OUTCOMES, PhysicsConfig, PhysicsScene, TrialOutcome, build_model, run_trial
from pssnet_core.trials.scenarios import ScenarioConfig, SceneFactory
from pssnet_core.trials.strategies import Choice, Strategist

if TYPE_CHECKING:
    from pssnet_core.inference import Completer

SHIPPED_CHECKPOINT = "shipped default"  # how a run's settings name the shipped PSSNet (no --pssnet-checkpoint)
CAUSES = ("no_grasp", *OUTCOMES[1:])  # every failure cause, in report order
FRAME_SIZE = (240, 320)  # filmstrip frame height, width (pixels)


@dataclass(frozen=True)
class TrialsConfig:
    """One run of trials.

    Attributes:
        scenarios: scenarios to run.
        strategies: strategies to compare.
        trials: scenes per scenario (every strategy gets each scene).
        seed: master seed of the scenes, latent noise and candidate sampling.
        num_samples: completions per view for PSSNet and the VAE (the node's default is 20).
        sampler: how PSSNet and the VAE draw them (the pipeline's ``sampler``; the node's default: checked).
        sampler_options: ``NAME=VALUE`` settings of the checked sampler's other parameters (the pipeline's
            ``sampler_options``; none = the node's).
        look_threshold: the second look's strategies look again when some place tells two samples apart with at
            least this probability.
        filmstrip_scenes: scenes per scenario drawn in the filmstrip (the first ones).
        grasps: grasp candidate and scoring options: the node's defaults, but 10 raw (anchor, orientation)
            pairs per kept candidate instead of 3 (the clutter filter drops most of them: in the cupboard ~95 %)
            and fingers kept 3 mm above the (known) table.
        scenario: scene options.
        physics: simulation options.
        checkpoints: which model files the strategies used (recorded with the results; a resumed run must
            use the same).
    """

    scenarios: tuple[str, ...] = SCENARIOS
    strategies: tuple[str, ...] = DEFAULT_STRATEGIES
    trials: int = 200
    seed: int = 0
    num_samples: int = 20
    sampler: str = "checked"
    sampler_options: tuple[str, ...] = ()
    look_threshold: float = LOOK_MIN_SEPARABILITY
    filmstrip_scenes: int = 2
    grasps: GraspConfig = field(default_factory=lambda: GraspConfig(oversample=10.0, plane_clearance=0.003))
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    checkpoints: dict[str, str] = field(default_factory=dict)

    def fingerprint(self) -> dict[str, Any]:
        """What decides the records (the scene count and cache location may change between runs)."""
        data = asdict(self)
        data.pop("trials")
        data.pop("filmstrip_scenes")
        data["scenario"].pop("cache_dir")
        if not data["sampler_options"]:  # the node's sampler: as runs made before the option existed recorded it
            data.pop("sampler_options")
        if data["look_threshold"] == LOOK_MIN_SEPARABILITY:  # likewise for runs made before the threshold was set
            data.pop("look_threshold")
        return json.loads(json.dumps(data, default=str))


def scene_seed(seed: int, index: int) -> int:
    """The seed of scene ``index``'s latent noise, candidates and random pick in a run with master ``seed``: what
    a script that makes a run's choices again must pass to ``Strategist.choose``."""
    return int(np.random.default_rng([seed, index]).integers(2**31 - 1))


#: Planner switches added after runs were made with them absent (off): a run's settings.json without one ran without it.
PREDATED_SWITCHES = {"observed_points_check": False, "surface_at_voxel_centres": False}


def config_of_run(directory: Path) -> TrialsConfig:
    """The :class:`TrialsConfig` a run's ``settings.json`` records (the default scene cache; one scene count), for
    scripts that make a run's choices again. A planner switch the run predates is off (:data:`PREDATED_SWITCHES`).

    Raises:
        ValueError: the settings hold something this rebuild does not reproduce (a scenario, physics or other
            setting changed from its default), named in the message.
    """
    settings = json.loads((directory / "settings.json").read_text())
    try:
        grasps = {**PREDATED_SWITCHES, **settings["grasps"]}
        gripper = GripperConfig(**grasps.pop("gripper"))
        grasps = GraspConfig(gripper=gripper, **{k: tuple(v) if isinstance(v, list) else v for k, v in grasps.items()})
        config = TrialsConfig(scenarios=tuple(settings["scenarios"]), strategies=tuple(settings["strategies"]),
                              seed=settings["seed"], num_samples=settings["num_samples"], sampler=settings["sampler"],
                              sampler_options=tuple(settings.get("sampler_options", ())),
                              look_threshold=settings.get("look_threshold", LOOK_MIN_SEPARABILITY), grasps=grasps,
                              scenario=ScenarioConfig(objects=settings["scenario"]["objects"]),
                              checkpoints=settings["checkpoints"])
    except (KeyError, TypeError) as error:  # a setting the run predates, or one the code no longer has
        raise ValueError(f"{directory}: settings.json from another version of the trials ({error})") from None
    rebuilt = config.fingerprint()
    for name in PREDATED_SWITCHES:
        if name not in settings["grasps"]:
            rebuilt["grasps"].pop(name)
    differing = []
    for key in sorted(set(rebuilt) | set(settings)):
        mine, theirs = rebuilt.get(key), settings.get(key)
        if isinstance(mine, dict) and isinstance(theirs, dict):
            differing += [f"{key}.{k}" for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]
        elif mine != theirs:
            differing.append(key)
    if differing:
        raise ValueError(f"{directory}: settings {', '.join(differing)} are not the defaults this rebuild assumes")
    return config


def pssnet_checkpoint_of(config: TrialsConfig) -> str | None:
    """The PSSNet checkpoint a run's settings name, as :meth:`Completer.from_checkpoint` takes it (None: the
    shipped model)."""
    named = config.checkpoints.get("pssnet", "")
    return None if named in ("", SHIPPED_CHECKPOINT) else named


def strategist_of(config: TrialsConfig, pssnet: Completer, vae: Completer | None = None) -> Strategist:
    """The :class:`Strategist` a run of ``config`` plans with (its grasps, samples, sampler, sampler options and
    look threshold): the one `pssnet grasp-trials` makes, and the one scripts replaying a run must make."""
    return Strategist(pssnet, vae, config.grasps, config.num_samples, config.physics, config.scenario.clutter_margin,
                      config.sampler, config.sampler_options, config.look_threshold)


@dataclass
class TrialRecord:
    """One strategy on one scene."""

    scenario: str
    index: int
    strategy: str
    outcome: str
    score: float
    kind: str
    width: float
    candidates: int
    lift: float
    followed: float
    contact: str
    notes: dict[str, Any]

    @property
    def success(self) -> bool:
        return self.outcome == "success"


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion (sensible at 0 %, 100 % and small n)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass
class Summary:
    """Success rate and failure causes of one strategy in one scenario."""

    scenario: str
    strategy: str
    n: int
    successes: int
    causes: dict[str, int]

    @property
    def rate(self) -> float:
        return self.successes / self.n if self.n else float("nan")

    @property
    def interval(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.n)


def summarise(records: Iterable[TrialRecord], scenarios: tuple[str, ...], strategies: tuple[str, ...]
              ) -> list[Summary]:
    """One :class:`Summary` per (scenario, strategy), in the given orders."""
    table = {(s, g): Summary(s, g, 0, 0, dict.fromkeys(CAUSES, 0)) for s in scenarios for g in strategies}
    for r in records:
        entry = table.get((r.scenario, r.strategy))
        if entry is None:
            continue
        entry.n += 1
        if r.success:
            entry.successes += 1
        else:
            entry.causes[r.outcome] += 1
    return list(table.values())


def paired_lines(records: list[TrialRecord], scenarios: tuple[str, ...], strategies: tuple[str, ...],
                 reference: str = "pssnet") -> list[str]:
    """Markdown lines comparing ``reference`` with every other strategy on the same scenes: scenes only it
    lifted, scenes only the other lifted, and the exact two-sided sign (McNemar) test of that split."""
    from scipy.stats import binomtest

    if reference not in strategies:
        return []
    success = {(r.scenario, r.index, r.strategy): r.success for r in records}
    lines = []
    for scenario in scenarios:
        parts = []
        for other in strategies:
            if other == reference:
                continue
            pairs = [(success[(scenario, i, reference)], success[(scenario, i, other)])
                     for (s, i, g) in success if s == scenario and g == reference and (s, i, other) in success]
            wins = sum(a and not b for a, b in pairs)
            losses = sum(b and not a for a, b in pairs)
            p = binomtest(wins, wins + losses).pvalue if wins + losses else 1.0
            parts.append(f"{other} +{wins}/-{losses} (p={p:.2g})")
        lines.append(f"- {scenario}: " + ", ".join(parts))
    return lines


def markdown_table(summaries: list[Summary]) -> str:
    """The results table: success rate with its 95 % interval and the failure causes."""
    lines = ["| scenario | strategy | trials | success | 95 % interval | " + " | ".join(CAUSES) + " |",
             "|---|---|---:|---:|---|" + "---:|" * len(CAUSES)]
    for s in summaries:
        lo, hi = s.interval
        rate = f"{100 * s.rate:.0f} %" if s.n else "-"
        lines.append(f"| {s.scenario} | {s.strategy} | {s.n} | {rate} | {100 * lo:.0f}-{100 * hi:.0f} % | "
                     + " | ".join(str(s.causes[c]) for c in CAUSES) + " |")
    return "\n".join(lines)


#: Bin edges of :func:`calibration_lines` (the last bin includes 1).
CALIBRATION_BINS = (0.0, 0.5, 0.7, 0.9, 1.0)
#: :func:`calibration_lines`' full-opening row: grasps opened to within this of the hand's maximum (m).
FULL_OPENING_MARGIN = 0.002


def calibration_lines(records: list[TrialRecord], scenario: str, strategy: str,
                      max_opening: float | None = None) -> list[str]:
    """A markdown table of how the chosen grasp's score and weight share foretold the outcome (one strategy in one
    scenario): its trials with a grasp binned by the grasp's score, then by its weight share (``notes.weight_share``,
    recorded since stop 47; those rows only where recorded), then by the grasp's kind (top, side, tilted), with how
    many lifted the object and how the rest failed. With ``max_opening`` (m, the hand's), one more row: the grasps
    opened to within :data:`FULL_OPENING_MARGIN` of it (a pinch of a body about as wide as the hand)."""
    chosen = [r for r in records if r.scenario == scenario and r.strategy == strategy and r.outcome != "no_grasp"]
    failures = tuple(c for c in CAUSES if c != "no_grasp")
    lines = [f"| {scenario}, {strategy}: bin | grasps | lifted | " + " | ".join(failures) + " |",
             "|---|---:|---:|" + "---:|" * len(failures)]

    def row(label: str, cell: list[TrialRecord]) -> str:
        lifted = sum(r.success for r in cell)
        rate = f" ({100 * lifted / len(cell):.0f} %)" if cell else ""
        return (f"| {label} | {len(cell)} | {lifted}{rate} | "
                + " | ".join(str(sum(r.outcome == c for r in cell)) for c in failures) + " |")

    shared = [r for r in chosen if "weight_share" in r.notes]
    for label, rated, value in (("score", chosen, lambda r: r.score),
                                ("weight share", shared, lambda r: float(r.notes["weight_share"]))):
        if not rated:
            continue
        for lo, hi in zip(CALIBRATION_BINS[:-1], CALIBRATION_BINS[1:], strict=True):
            top = hi == CALIBRATION_BINS[-1]
            lines.append(row(f"{label} {lo:g}-{hi:g}", [r for r in rated if lo <= value(r) < hi
                                                          or (top and value(r) == hi)]))
    for kind in [k for k in KIND_NAMES if any(r.kind == k for r in chosen)]:
        lines.append(row(f"kind {kind}", [r for r in chosen if r.kind == kind]))
    if max_opening is not None and chosen:
        lines.append(row(f"opened to within {1000 * FULL_OPENING_MARGIN:g} mm of the hand's {100 * max_opening:g} cm",
                         [r for r in chosen if r.width >= max_opening - FULL_OPENING_MARGIN]))
    return lines


class FrameRenderer:
    """Render callback for :func:`run_trial`: the scene seen from ``view`` (distance m, azimuth and elevation
    degrees of MuJoCo's free camera) around ``lookat``.

    One offscreen context per trial model (creating one costs about as much as a frame); :meth:`close` it.
    """

    def __init__(self, lookat: np.ndarray, view: tuple[float, float, float]) -> None:
        self.lookat = np.asarray(lookat, dtype=np.float64)
        self.view = view
        self._model = None
        self._renderer = None

    def __call__(self, model, data) -> np.ndarray:
        import mujoco

        if model is not self._model:
            self.close()
            self._model, self._renderer = model, mujoco.Renderer(model, *FRAME_SIZE)
        camera = mujoco.MjvCamera()
        camera.lookat[:] = self.lookat
        camera.distance, camera.azimuth, camera.elevation = self.view
        self._renderer.update_scene(data, camera=camera)
        # Software GL here: shadows and reflections would double the cost of a frame and show nothing new.
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return self._renderer.render().copy()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._model = self._renderer = None


@dataclass
class SceneFilm:
    """What the filmstrip shows of one scene.

    Attributes:
        index: scene index.
        overview: the scene from the robot's side, without the hand.
        depth: (H, W) the depth image the strategies saw (m).
        mask: (H, W) its object mask.
        notes: what was drawn.
        trials: each strategy's record and frames (start, grasp or contact, end).
    """

    index: int
    overview: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    notes: dict[str, Any]
    trials: list[tuple[TrialRecord, list[np.ndarray]]] = field(default_factory=list)


def overview_frame(scene: PhysicsScene, renderer: FrameRenderer, config: TrialsConfig) -> np.ndarray:
    """The scene without the hand (it waits 2 m above, out of the picture)."""
    import mujoco

    away = np.eye(4)
    away[2, 3] = 2.0
    model = build_model(scene, away, config.grasps.gripper, config.physics)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return renderer(model, data)


def save_filmstrip(path: Path, scenario: str, films: list[SceneFilm]) -> None:
    """Per scene: the scene, the depth view and what was drawn; then one row per strategy that had a grasp,
    with its start, grasp and end frames and the outcome."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sum(1 + sum(r.outcome != "no_grasp" for r, _ in f.trials) for f in films)
    fig, axes = plt.subplots(rows, 3, figsize=(3 * 2.6, rows * 2.0 + 0.4), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    row = 0
    for film in films:
        axes[row, 0].imshow(film.overview)
        axes[row, 0].set_title(f"scene {film.index} (from the robot's side)", fontsize=7, loc="left")
        rows_px, cols_px = np.nonzero(film.mask)
        margin = 80  # pixels of surroundings (clutter, table) around the object
        v0, u0 = max(rows_px.min() - margin, 0), max(cols_px.min() - margin, 0)
        window = (slice(v0, rows_px.max() + margin), slice(u0, cols_px.max() + margin))
        axes[row, 1].imshow(np.where(film.depth > 0, film.depth, np.nan)[window], cmap="viridis")
        axes[row, 1].contour(film.mask[window], levels=[0.5], colors="r", linewidths=0.6)
        axes[row, 1].set_title("depth camera view (object mask in red)", fontsize=7, loc="left")
        none = [r.strategy for r, _ in film.trials if r.outcome == "no_grasp"]
        text = "\n".join([f"{k}: {v}" for k, v in film.notes.items()] + [f"no grasp: {', '.join(none) or '-'}"])
        axes[row, 2].text(0.0, 1.0, text, fontsize=6, va="top", family="monospace", transform=axes[row, 2].transAxes)
        row += 1
        for record, frames in film.trials:
            if record.outcome == "no_grasp":
                continue
            for col, frame in enumerate(frames[:3]):
                axes[row, col].imshow(frame)
            axes[row, 0].set_title(f"{record.strategy}: {record.outcome} ({record.kind}, score {record.score:.2f})",
                                   fontsize=7, loc="left")
            row += 1
    fig.suptitle(f"{scenario}: the first scenes; frames: pre-grasp, fingers closed (or first contact), end",
                 fontsize=9)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.5 / (rows * 2.0 + 0.4)))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def read_records(path: Path) -> list[TrialRecord]:
    """The records of a run's records.jsonl, or of a gzipped copy when ``path`` ends in .gz (none when the file
    does not exist)."""
    if not path.is_file():
        return []
    text = gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz" else path.read_text()
    return [TrialRecord(**json.loads(line)) for line in text.splitlines() if line.strip()]


def read_run_records(directory: Path) -> list[TrialRecord]:
    """A run directory's records: its records.jsonl, or records.jsonl.gz as committed under results/."""
    plain = directory / "records.jsonl"
    return read_records(plain if plain.is_file() else directory / "records.jsonl.gz")


def scene_set_of_run(directory: Path) -> str:
    """What decides a run's scenes and how they play out, as one string: its master seed and its scenario and
    physics settings (as :meth:`TrialsConfig.fingerprint` recorded them, without the scene cache's location). Runs
    with the same string showed their strategies the same scene at each index; :func:`pooled_records` pairs them by
    it."""
    settings = json.loads((directory / "settings.json").read_text())
    return json.dumps({key: settings[key] for key in ("seed", "scenario", "physics")}, sort_keys=True)


def pooled_records(comparisons: Sequence[tuple[str, str, Sequence[Path]]]) -> list[TrialRecord]:
    """The records of several runs per compared strategy, as one set of scenes.

    Each comparison is (label, strategy, run directories): the records of ``strategy`` in those runs, relabelled
    ``label``. Every scene is numbered anew by its scene set (:func:`scene_set_of_run`) and index, one numbering for
    all comparisons, so that records of the same scene pair (:func:`paired_lines`) and scenes of different sets
    (other seeds, other objects) add up instead of pairing by index alone.

    Raises:
        ValueError: a comparison has a scene twice (two runs of one scene set) or no record of its strategy.
    """
    keyed: list[tuple[tuple[str, str, int], TrialRecord]] = []
    for label, strategy, directories in comparisons:
        seen: set[tuple[str, str, int]] = set()
        for directory in directories:
            scenes = scene_set_of_run(directory)
            for record in read_run_records(directory):
                if record.strategy != strategy:
                    continue
                key = (scenes, record.scenario, record.index)
                if key in seen:
                    raise ValueError(f"{label}: scene {record.index} of {record.scenario} is in two of its runs "
                                     f"({directory} repeats a scene set)")
                seen.add(key)
                keyed.append((key, replace(record, strategy=label)))
        if not seen:
            raise ValueError(f"{label}: no records of {strategy!r} in {', '.join(map(str, directories))}")
    numbers = {key: number for number, key in enumerate(sorted({key for key, _ in keyed}))}
    return [replace(record, index=numbers[key]) for key, record in keyed]


def run_trials(config: TrialsConfig, strategist: Strategist, out: Path, progress: bool = True) -> list[TrialRecord]:
    """Runs (or resumes) every (scene, strategy) trial; writes records, filmstrips and the summary to ``out``.

    Raises:
        ValueError: ``out`` holds records made with different settings.
    """
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    settings = out / "settings.json"
    fingerprint = config.fingerprint()
    if settings.is_file() and json.loads(settings.read_text()) != fingerprint:
        raise ValueError(f"{out} holds trials made with other settings; use another --out or remove it")
    settings.write_text(json.dumps(fingerprint, indent=1))
    records_path = out / "records.jsonl"
    records = read_records(records_path)
    done = {(r.scenario, r.index, r.strategy) for r in records}
    with (out / "provenance.jsonl").open("a") as log:  # one line per invocation: a resumed run says what it mixed
        log.write(json.dumps(invocation(records_before=len(records), sampler=config.sampler,
                                        checked_sampler=asdict(strategist.sampler_config)
                                        if config.sampler == "checked" else None)) + "\n")
    factory = SceneFactory(config.scenario, config.grasps.gripper)
    bar = tqdm(total=len(config.scenarios) * config.trials * len(config.strategies), unit="trial",
               disable=not progress, file=sys.stderr)
    bar.update(sum(1 for s in config.scenarios for i in range(config.trials) for g in config.strategies
                   if (s, i, g) in done))
    with records_path.open("a") as sink:
        for scenario in config.scenarios:
            films: list[SceneFilm] = []
            for index in range(config.trials):
                film = index < config.filmstrip_scenes
                todo = tuple(g for g in config.strategies if (scenario, index, g) not in done)
                if not todo and not film:
                    continue
                scene = factory.scene(scenario, index, config.seed)
                seed = scene_seed(config.seed, index)
                choices = strategist.choose(scene, config.strategies if film else todo, seed)
                renderer = None
                if film:
                    renderer = FrameRenderer(scene.physics.object_pose[:3, 3] + np.array([0.0, 0.0, 0.08]),
                                             scene.film_view)
                    films.append(SceneFilm(index, overview_frame(scene.physics, renderer, config), scene.view.depth,
                                           scene.view.mask, scene.notes))
                for name, choice in choices.items():
                    outcome = _attempt(scene.physics, choice, config, renderer)
                    record = TrialRecord(scenario, index, name, outcome.outcome, choice.score, choice.kind,
                                         choice.width, choice.candidates, outcome.lift, outcome.followed,
                                         outcome.contact, {**scene.notes, **choice.notes})
                    if film:
                        films[-1].trials.append((record, outcome.frames))
                    if (scenario, index, name) not in done:
                        records.append(record)
                        done.add((scenario, index, name))
                        sink.write(json.dumps(asdict(record)) + "\n")
                        sink.flush()
                        bar.update(1)
                if renderer is not None:
                    renderer.close()
                bar.set_postfix_str(f"{scenario} scene {index}")
            if films:
                save_filmstrip(out / f"filmstrip_{scenario}.png", scenario, films)
    bar.close()
    used = {str(r.notes["object"]) for r in records}
    faithfulness = {name: f for name, f in factory.faithfulness.items() if name in used}
    write_summary(out / "summary.md", config, records, faithfulness, factory.rejected)
    return records


def _attempt(physics_scene, choice: Choice, config: TrialsConfig, render) -> TrialOutcome:
    if choice.pose is None:
        return TrialOutcome("no_grasp", 0.0, 0.0)
    return run_trial(physics_scene, choice.pose, choice.width, config.grasps.gripper, config.physics, render=render)


def faithfulness_lines(faithfulness: dict[str, Faithfulness]) -> list[str]:
    """Markdown lines: how faithful the collision shapes of the objects used were, per family."""
    lines = []
    for family in sorted({name.split("-")[0] for name in faithfulness}):
        items = [f for name, f in faithfulness.items() if name.split("-")[0] == family]
        volume = np.array([100 * f.volume_error for f in items])
        extra = np.array([100 * f.extra for f in items])
        missing = np.array([100 * f.missing for f in items])
        parts = np.array([f.parts for f in items])
        line = (f"- {family} ({len(items)} objects): {int(np.median(parts))} convex parts (median; "
                f"{parts.min()}-{parts.max()}), union volume {np.median(volume):+.1f} % of the true volume "
                f"(median; {volume.min():+.1f} to {volume.max():+.1f} %), of which extra {extra.max():.1f} % "
                f"and missing {missing.max():.2f} % at most")
        holes = [f for f in items if f.hole_kept is not None]
        if holes:
            gap_true = np.array([1000 * f.hole_gap_true for f in holes])
            gap_parts = np.array([1000 * f.hole_gap_parts for f in holes])
            line += (f"; handle hole kept in {sum(f.hole_kept for f in holes)}/{len(holes)}, clear gap body to "
                     f"handle {np.median(gap_parts):.1f} mm in the parts vs {np.median(gap_true):.1f} mm true "
                     f"(median; largest loss {np.max(gap_true - gap_parts):.1f} mm)")
        lines.append(line)
    return lines


def write_summary(path: Path, config: TrialsConfig, records: list[TrialRecord],
                  faithfulness: dict[str, Faithfulness], rejected: list[str]) -> None:
    """The results table, the collision shapes' faithfulness and the run's settings as markdown."""
    summaries = summarise(records, config.scenarios, config.strategies)
    text = [f"# Grasp trials ({config.trials} scenes per scenario, seed {config.seed})", "",
            markdown_table(summaries), "",
            "Failure causes: no_grasp (the strategy found no grasp holding for any of its shapes), collision "
            "(the hand touched something before closing), missed (the fingers closed without both touching the "
            "object), slipped (held after closing, lost by the end of the exit and shake).", "",
            "Paired on the same scenes, PSSNet against each strategy: +scenes only PSSNet lifted / -scenes only "
            "the other lifted (exact sign test of that split):", "",
            *paired_lines(records, config.scenarios, config.strategies), "",
            "What the chosen grasp's score (the share of the strategy's shapes it holds for) and weight share (the "
            "share of the weight its pads hold, over those shapes) said of the outcome, scenes with a grasp:", "",
            *[line for scenario in config.scenarios for strategy in config.strategies
              for line in (*calibration_lines(records, scenario, strategy, config.grasps.gripper.max_opening), "")],
            f"Collision shapes (CoACD, threshold {config.scenario.decomposition.threshold}) of the objects used:", "",
            *faithfulness_lines(faithfulness),
            f"- left out of the object pools for an unfaithful collision shape (volume off by more than "
            f"{100 * config.scenario.max_volume_error:.0f} % or the handle hole closed): "
            f"{', '.join(rejected) or 'none'}",
            "",
            "Settings:", "", "```json", json.dumps(config.fingerprint(), indent=1), "```", ""]
    path.write_text("\n".join(text))
