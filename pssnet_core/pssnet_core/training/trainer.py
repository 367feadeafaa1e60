"""Training loop for every registry model: epochs over a shard dataset, validation, logs, checkpoints.

Output directory::

    last.pt            full state (weights, optimisers, RNG, position in the epoch): ``--resume`` continues it,
                       also with another number of ranks (nothing in it depends on the world size)
    best.pt            weights of the best validation ``best_metric`` so far (no optimiser state)
    train_log.csv      averaged loss terms every ``log_every`` steps
    val_log.csv        validation: val_bce (mean per-voxel BCE of the posterior-mean completion), val_iou
                       (IoU at 0.5), val_best_acc_mm (quick best accuracy: min over ``val_num_samples``
                       samples of the chamfer distance to the ground truth, mean over ``val_slice`` inputs)
    loss_curves.png    both logs plotted
    model_config.yaml, train_config.yaml, summary.json
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import queue
import threading
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from scipy.spatial import cKDTree
from tqdm import tqdm

from pssnet_core.data.store import GRID_KEYS, TRAINING_KEYS, TWIN_KEYS, DatasetReader
from pssnet_core.models.base import PRECISIONS, CompletionModel, StepContext, resolve_precision
from pssnet_core.models.checkpoint import CheckpointError, load_checkpoint, read_checkpoint, save_checkpoint
from pssnet_core.models.config import ModelConfig, PSSNetConfig, config_from_dict
from pssnet_core.models.registry import default_config, get_model_class
from pssnet_core.training import distributed
from pssnet_core.training.distributed import DistributedRun
from pssnet_core.training.logs import TRAIN_LOG, VAL_LOG, CsvLog, plot_curves, truncate_after_step

BEST_METRICS = {"val_bce": min, "val_iou": max, "val_best_acc_mm": min}


class TrainingError(ValueError):
    """Training cannot start or continue (bad arguments, mismatching data or checkpoint)."""


@dataclass
class TrainConfig:
    """Everything a training run needs; the CLI fills it from its arguments.

    Attributes:
        model: registry name.
        data: training dataset directory.
        out: output directory.
        val_data: validation dataset; None validates on the first ``val_max_samples`` training samples.
        epochs: passes over the training data.
        max_minutes: wall-clock budget (training + validation); None = no limit.
        max_steps: optimiser-step budget of the whole run (counted across --resume); None = no limit. The fair
            budget when runs share a loaded machine, where minutes buy different numbers of steps.
        batch_size: samples per step and rank (paper: 16); a distributed step trains on world size x this.
        lr: learning rate of the main optimiser (paper: Adam 1e-3) for the mean loss of the step's whole batch
            (all ranks: DDP averages their gradients); not scaled with the number of ranks.
        device: "cpu" or "cuda" (or "cuda:1"; under torchrun "cuda", and each rank takes cuda:LOCAL_RANK).
        precision: "auto" (bf16 autocast where the hardware runs it natively, else fp32), "fp32", "bf16".
        threads: torch CPU threads (None: torch's default).
        seed: seeds weights, noise and shuffling.
        resume: continue from ``out/last.pt``.
        init_from: warm start: a new run (step 0, fresh logs, fresh best) whose weights come from this
            checkpoint, e.g. to fine-tune on rebuilt data. A checkpoint that carries the training-only modules
            (another run's last.pt or best.pt) keeps its PSSNet flow, which its decoder was trained against: the
            flow is not pre-trained again; last.pt also brings its optimiser states. An inference-only export (the
            shipped model) brings its weights only, and the flow it lacks is pre-trained. The model config is the
            checkpoint's; ``model_config`` must be unset.
        val_every: validate every this many steps; 0 = at the end of every epoch.
        val_max_samples: validation loss and IoU on at most this many validation samples.
        val_slice: inputs used for the quick best-accuracy.
        val_num_samples: samples per input for the quick best-accuracy.
        best_metric: which validation number selects best.pt.
        log_every: steps per train_log.csv row.
        model_config: YAML with model config overrides (e.g. channels, latent_dim, flow_lr).
        twin_rate: PSSNet's ``twin_rate`` for this run (None: the model config's), overriding that of
            ``model_config``, ``init_from`` or the resumed checkpoint; > 0 needs turned twins in ``data``.
        half_checkpoint: store best.pt in float16 (last.pt stays float32 to resume exactly).
        progress: show tqdm bars.
    """

    model: str
    data: str
    out: str
    val_data: str | None = None
    epochs: int = 10
    max_minutes: float | None = None
    max_steps: int | None = None
    batch_size: int = 16
    lr: float = 1e-3
    device: str = "cpu"
    precision: str = "auto"
    threads: int | None = None
    seed: int = 0
    resume: bool = False
    init_from: str | None = None
    val_every: int = 0
    val_max_samples: int = 512
    val_slice: int = 16
    val_num_samples: int = 8
    best_metric: str = "val_bce"
    log_every: int = 10
    model_config: str | None = None
    twin_rate: float | None = None
    half_checkpoint: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0:
            raise TrainingError("epochs and batch_size must be >= 1 and lr > 0")
        if self.precision not in PRECISIONS:
            raise TrainingError(f"precision must be auto, fp32 or bf16, got {self.precision!r}")
        if self.best_metric not in BEST_METRICS:
            raise TrainingError(f"best_metric must be one of {sorted(BEST_METRICS)}, got {self.best_metric!r}")
        if self.max_minutes is not None and self.max_minutes <= 0:
            raise TrainingError(f"max_minutes must be positive, got {self.max_minutes}")
        if self.max_steps is not None and self.max_steps < 1:
            raise TrainingError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.init_from is not None and (self.resume or self.model_config is not None):
            raise TrainingError("init_from starts a new run from a checkpoint's weights and config: it cannot be "
                                "combined with resume or model_config")
        if self.val_every < 0 or self.log_every < 1 or self.val_num_samples < 1 or self.val_slice < 0:
            raise TrainingError("val_every >= 0, log_every >= 1, val_num_samples >= 1, val_slice >= 0")
        if self.twin_rate is not None and not 0.0 <= self.twin_rate <= 1.0:
            raise TrainingError(f"twin_rate must lie in [0, 1], got {self.twin_rate}")
        if self.twin_rate and self.model != "pssnet":
            raise TrainingError(f"twin_rate is PSSNet's (turned twins replace its box code); --model is "
                                f"{self.model!r}")


def resolve_context(device: str, precision: str) -> StepContext:
    """Device + autocast dtype (:func:`resolve_precision`); an unusable device or precision is a TrainingError."""
    try:
        dev = torch.device(device)
    except RuntimeError as error:
        raise TrainingError(f"bad device {device!r}: {error}") from error
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise TrainingError("--device cuda requested but torch sees no CUDA device")
    if dev.type not in ("cpu", "cuda"):
        raise TrainingError(f"device must be cpu or cuda, got {device!r}")
    try:
        return StepContext(dev, resolve_precision(dev, precision))
    except ValueError as error:
        raise TrainingError(str(error)) from error


def batch_to_tensors(batch: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Store batch -> model batch: ``input`` (B,2,N,N,N), ``target`` (B,1,N,N,N) float32, ``box``, ``index``, and
    with the twin keys ``twin_target`` (B,1,N,N,N) float32 and ``twin_box``."""
    out = {"input": torch.from_numpy(np.stack([batch["known_occupied"], batch["known_free"]], 1)
                                     .astype(np.float32)),
           "index": torch.from_numpy(batch["index"])}
    if "occupancy" in batch:
        out["target"] = torch.from_numpy(batch["occupancy"][:, None].astype(np.float32))
    if "box" in batch:
        out["box"] = torch.from_numpy(np.asarray(batch["box"], dtype=np.float32))
    if "twin_occupancy" in batch:
        out["twin_target"] = torch.from_numpy(batch["twin_occupancy"][:, None].astype(np.float32))
    if "twin_box" in batch:
        out["twin_box"] = torch.from_numpy(np.asarray(batch["twin_box"], dtype=np.float32))
    return out


def prefetch(iterator: Iterator[Any], depth: int = 2) -> Generator[Any, None, None]:
    """Runs ``iterator`` in a background thread (shard decoding overlaps compute); re-raises its errors.

    Closing the generator (``contextlib.closing``, or its last reference dropped) stops the thread and waits for
    it. Why wait: a daemon thread still inside torch code (``torch.from_numpy`` of the next batch) when the
    interpreter exits is unwound through C++ frames that must not unwind, and the process aborts ("terminate
    called without an active exception"): rank 1 of a distributed run, which leaves right after its last step,
    did that now and then.
    """
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def offer(item: Any) -> bool:
        """Queues ``item`` unless the consumer has stopped (then False): the thread never blocks for good."""
        while not stop.is_set():
            try:
                items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for item in iterator:
                if not offer(item):
                    return
            offer(done)
        except BaseException as error:  # handed to the consumer
            offer(error)

    thread = threading.Thread(target=work, name="prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item = items.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join()  # at most the time of the item being made


def chamfer_mm(a: np.ndarray, b: np.ndarray, voxel_size: float) -> float:
    """Symmetric chamfer distance between two sets of voxel indices (M,3)/(K,3), in millimetres:
    0.5 * (mean nearest distance a->b + mean nearest distance b->a) between voxel centres; inf if one is empty."""
    if len(a) == 0 or len(b) == 0:
        return math.inf
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return 0.5 * (float(d_ab.mean()) + float(d_ba.mean())) * voxel_size * 1000.0


@torch.inference_mode()
def reconstruction_scores(logits: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view BCE per voxel and IoU (occupied = logit > 0; two empty grids count as IoU 1) of (B,1,N,N,N)."""
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, target, reduction="none").flatten(1).mean(1)
    pred, gt = (logits > 0).flatten(1), target.bool().flatten(1)
    inter, union = (pred & gt).sum(1).float(), (pred | gt).sum(1).float()
    return bce, torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(union))


def validate(model: CompletionModel, reader: DatasetReader, ctx: StepContext, max_samples: int,
             slice_size: int, num_samples: int, batch_size: int, seed: int) -> dict[str, float]:
    """Validation numbers (see the module docstring). Leaves the model in train mode."""
    model.eval()
    try:
        indices = list(range(min(len(reader), max_samples)))
        bce_sum, iou_sum, count = 0.0, 0.0, 0
        for batch in reader.iter_batches(batch_size, shuffle=False, keys=GRID_KEYS, indices=indices):
            t = batch_to_tensors(batch)
            with ctx.autocast():
                logits = model.reconstruct(t["input"]).float()
            bce, iou = reconstruction_scores(logits, t["target"].to(logits.device))
            bce_sum += float(bce.sum())
            iou_sum += float(iou.sum())
            count += len(logits)
        best = []
        if slice_size:
            generator = torch.Generator().manual_seed(seed)
            for batch in reader.iter_batches(1, shuffle=False, keys=GRID_KEYS,
                                             indices=indices[:slice_size]):
                t = batch_to_tensors(batch)
                with ctx.autocast():
                    probs = model.sample(t["input"], num_samples, generator=generator)
                gt = np.argwhere(batch["occupancy"][0])
                occupied = (probs[:, 0] > 0.5).cpu().numpy()
                best.append(min(chamfer_mm(np.argwhere(o), gt, reader.voxel_size) for o in occupied))
        finite = [b for b in best if math.isfinite(b)]
        return {"val_bce": bce_sum / max(count, 1), "val_iou": iou_sum / max(count, 1),
                "val_best_acc_mm": float(np.mean(finite)) if finite else math.nan, "val_n": float(count)}
    finally:
        model.train()


class Trainer:
    """Runs one training job described by a :class:`TrainConfig`."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.ctx = resolve_context(cfg.device, cfg.precision)
        self.train_reader = DatasetReader(cfg.data)
        self.val_reader = DatasetReader(cfg.val_data) if cfg.val_data else self.train_reader
        if self.val_reader.grid_size != self.train_reader.grid_size:
            raise TrainingError(f"validation grid {self.val_reader.grid_size} != training grid "
                                f"{self.train_reader.grid_size}")
        if len(self.train_reader) < 2:
            raise TrainingError(f"{cfg.data} has {len(self.train_reader)} samples; need at least 2")

    # ------------------------------------------------------------------------------------------ setup
    def _model_config(self) -> ModelConfig:
        overrides: dict[str, Any] = _read_yaml(self.cfg.model_config) if self.cfg.model_config else {}
        if overrides.get("model", self.cfg.model) != self.cfg.model:
            raise TrainingError(f"{self.cfg.model_config} is a config for {overrides['model']!r}, "
                                f"not --model {self.cfg.model!r}")
        overrides.pop("model", None)
        grid = self.train_reader.grid_size
        if overrides.get("grid_size", grid) != grid:
            raise TrainingError(f"model config grid_size {overrides['grid_size']} != dataset grid {grid}")
        overrides["grid_size"] = grid
        get_model_class(self.cfg.model)  # clear error for an unknown name
        return default_config(self.cfg.model, **overrides)

    def _box_source(self, run: DistributedRun) -> Callable[[int], Iterator[torch.Tensor]]:
        reader, seed = self.train_reader, self.cfg.seed

        def boxes(batch_size: int) -> Iterator[torch.Tensor]:
            available = distributed.min_rank_samples(reader, run.world_size) if run.enabled else len(reader)
            batch_size = min(batch_size, available)
            epoch = 0
            while True:
                for batch in self._batches(run, batch_size, seed + 7919 * (epoch + 1), True, ("box",)):
                    yield torch.from_numpy(np.asarray(batch["box"], dtype=np.float32))
                epoch += 1

        return boxes

    def _batches(self, run: DistributedRun, batch_size: int, seed: int, drop_last: bool,
                 keys: tuple[str, ...]) -> Iterator[dict[str, np.ndarray]]:
        """One epoch of this rank's batches: the whole shuffled stream for one process, else its shards."""
        if not run.enabled:
            return self.train_reader.iter_batches(batch_size, shuffle=True, seed=seed, drop_last=drop_last,
                                                  keys=keys)
        return distributed.rank_batches(self.train_reader, batch_size, seed, run.rank, run.world_size, keys)

    # -------------------------------------------------------------------------------------------- run
    def fit(self, stop: distributed.StopFlag | None = None) -> dict[str, Any]:
        """Trains; returns the summary also written to ``summary.json``.

        Under torchrun (WORLD_SIZE > 1) this process is one rank of a data-parallel run
        (:mod:`pssnet_core.training.distributed`); only rank 0 writes to ``out``. ``stop``: a flag whose signal
        ends a single-process run at the next step boundary (last.pt saved, KeyboardInterrupt raised); a
        distributed run sets its own.
        """
        with distributed.session(self.cfg.device) as run:
            if not run.enabled:
                return self._fit(run, stop)
            self.ctx = resolve_context(str(run.device), self.cfg.precision)
            with distributed.StopFlag() as stop:
                return self._fit(run, stop)

    def _fit(self, run: DistributedRun, stop: distributed.StopFlag | None) -> dict[str, Any]:
        cfg, ctx, main = self.cfg, self.ctx, run.is_main

        def say(message: str) -> None:
            if main:
                tqdm.write(message)

        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        if run.enabled and (fewest := distributed.min_rank_samples(self.train_reader, run.world_size)) \
                < cfg.batch_size:
            raise TrainingError(f"{run.world_size} ranks x batch {cfg.batch_size}: a rank may be dealt only "
                                f"{fewest} samples of {cfg.data} ({self.train_reader.num_shards} shards) in an "
                                f"epoch; use fewer ranks or a smaller --batch-size")
        last_path = self.out / "last.pt"
        if main:
            self.out.mkdir(parents=True, exist_ok=True)
        if run.enabled:
            self._check_ranks_see_files(run, last_path)
        state: dict[str, Any] = {"epoch": 0, "batch_in_epoch": 0, "samples_in_epoch": 0, "step": 0,
                                 "elapsed_s": 0.0, "best": None}
        opt_states: dict[str, Any] | None = None
        if cfg.resume and last_path.exists():
            model, config, extra = load_checkpoint(last_path)
            if extra.get("inference_only"):
                raise TrainingError(f"{last_path} is an inference-only export; it cannot resume training")
            if config.model != cfg.model:
                raise TrainingError(f"{last_path} holds a {config.model!r} model, not {cfg.model!r}")
            state.update(extra.get("train_state", {}))
            # Checkpoints from before distributed training count batches of the same size, one rank.
            state.setdefault("samples_in_epoch", state["batch_in_epoch"] * cfg.batch_size)
            opt_states = extra.get("optimizers")
            if "rng" in extra:
                torch.set_rng_state(extra["rng"])
            if main:
                truncate_after_step(self.out / TRAIN_LOG, state["step"])
                truncate_after_step(self.out / VAL_LOG, state["step"])
        else:
            if cfg.resume:
                say(f"--resume: no {last_path}; starting a new run")
            torch.manual_seed(cfg.seed)  # the same weights on every rank
            if cfg.init_from is not None:
                model, config, extra = load_checkpoint(cfg.init_from)
                if config.model != cfg.model:
                    raise TrainingError(f"{cfg.init_from} holds a {config.model!r} model, not {cfg.model!r}")
                # PSSNet's flow, which the decoder was trained against, is kept (pre-training a new one would change
                # every box code the decoder reads); last.pt also brings its optimiser states. An export brings
                # weights only (fresh optimisers); one written without the flow (before exports kept it, e.g. the
                # shipped model) gets a new flow pre-trained below.
                opt_states = extra.get("optimizers")
                state["init_from"] = str(cfg.init_from)
                state["init_pretrain"] = "flow." in extra["missing_modules"]
            else:
                config = self._model_config()
                model = get_model_class(config.model)(config)
            if main:
                for name in ("train_log.csv", "val_log.csv"):
                    (self.out / name).unlink(missing_ok=True)
        if run.rank:
            # Each rank its own noise (rank 0 keeps the stream a single process has, saved in last.pt).
            torch.manual_seed(distributed.rank_seed(cfg.seed, run.rank, state["step"]))
        if config.grid_size != self.train_reader.grid_size:
            raise TrainingError(f"model grid {config.grid_size} != dataset grid {self.train_reader.grid_size}")
        config = self._apply_twin_rate(model, config)
        if main:
            config.to_yaml(self.out / "model_config.yaml")
            (self.out / "train_config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))

        model.to(ctx.device).to_fast_layout().train()
        if run.enabled:
            model.set_wrappers(run.wrap(model))
        try:
            return self._train(run, stop, model, config, state, opt_states, say)
        finally:
            model.set_wrappers({})

    def _apply_twin_rate(self, model: CompletionModel, config: ModelConfig) -> ModelConfig:
        """The run's model config with ``--twin-rate`` applied (also to ``model``); checks the data has twins."""
        if self.cfg.twin_rate is not None and isinstance(config, PSSNetConfig):
            config = dataclasses.replace(config, twin_rate=self.cfg.twin_rate)
            model.config = config
        twin_rate = getattr(config, "twin_rate", 0.0)
        if twin_rate > 0 and not self.train_reader.has_twins:
            raise TrainingError(f"twin_rate {twin_rate} needs turned twins, but no dataset directory of "
                                f"{self.cfg.data} has them: build them with `pssnet dataset twins --data DIR`")
        return config

    def _check_ranks_see_files(self, run: DistributedRun, last_path: Path) -> None:
        """Every rank reads last.pt / --init-from itself: they must all see the same files."""
        cfg = self.cfg
        has_last = cfg.resume and last_path.exists()
        lacks_init = cfg.init_from is not None and not Path(cfg.init_from).exists()
        some_have, some_lack, init_missing = run.any(has_last, cfg.resume and not has_last, lacks_init)
        if some_have and some_lack:
            raise TrainingError(f"{last_path} exists for some ranks only: --out must be a directory every rank "
                                f"sees (a shared filesystem)")
        if init_missing:
            raise TrainingError(f"--init-from {cfg.init_from} is missing for some ranks: it must be readable by "
                                f"every rank")

    def _train(self, run: DistributedRun, stop: distributed.StopFlag | None, model: CompletionModel,
               config: ModelConfig, state: dict[str, Any], opt_states: dict[str, Any] | None,
               say: Callable[[str], None]) -> dict[str, Any]:
        cfg, ctx, main = self.cfg, self.ctx, run.is_main
        last_path = self.out / "last.pt"
        keys = TRAINING_KEYS + TWIN_KEYS if getattr(config, "twin_rate", 0.0) > 0 else TRAINING_KEYS
        optimizers = model.make_optimizers(cfg.lr)
        if opt_states:
            for name, opt in optimizers.items():
                if name in opt_states:
                    opt.load_state_dict(opt_states[name])

        fresh_run = state["step"] == 0 and state["batch_in_epoch"] == 0 and state["epoch"] == 0
        if fresh_run and (not cfg.init_from or state.get("init_pretrain")):
            t0 = time.perf_counter()
            pre = model.pretrain(self._box_source(run), ctx)
            run.average_buffers(model)
            if pre:
                say(f"pretrain: {pre} in {time.perf_counter() - t0:.1f} s")
                state["pretrain"] = pre

        train_log, val_log = CsvLog(self.out / TRAIN_LOG), CsvLog(self.out / VAL_LOG)
        better = BEST_METRICS[cfg.best_metric]
        global_batch = cfg.batch_size * run.world_size
        if run.enabled:
            steps_per_epoch, drop_last = max(len(self.train_reader) // global_batch, 1), True
        else:
            drop_last = len(self.train_reader) > cfg.batch_size
            steps_per_epoch = len(self.train_reader) // cfg.batch_size if drop_last else 1
        start = time.perf_counter() - state["elapsed_s"]
        invocation_start = time.perf_counter()  # --max-minutes limits this invocation (also on --resume)
        budget_s = cfg.max_minutes * 60 if cfg.max_minutes else math.inf
        last_val: dict[str, float] = {}
        stopped_by = "epochs"

        def elapsed() -> float:
            return time.perf_counter() - start

        saved_at = [-1]

        def checkpoint(candidate: dict[str, float] | None) -> None:
            state["elapsed_s"] = elapsed()
            state["world_size"] = run.world_size  # for the record: nothing saved depends on it
            improved = False
            if candidate is not None and math.isfinite(value := candidate[cfg.best_metric]):
                best = state["best"]
                improved = best is None or (value < best if better is min else value > best)
                if improved:
                    state["best"] = value
            extra = {"train_state": dict(state), "train_config": dataclasses.asdict(cfg),
                     "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                     "rng": torch.get_rng_state()}
            save_checkpoint(last_path, model, config, extra)
            saved_at[0] = state["step"]
            if improved:
                meta = {"train_state": dict(state), "train_config": dataclasses.asdict(cfg), "val": candidate,
                        "data": str(cfg.data), "precision": ctx.precision}
                save_checkpoint(self.out / "best.pt", model, config, meta, half=cfg.half_checkpoint)

        def run_validation() -> dict[str, float]:
            if not main:
                return {}  # rank 0 validates; the others wait for it in the next collective
            t0 = time.perf_counter()
            result = validate(model, self.val_reader, ctx, cfg.val_max_samples, cfg.val_slice,
                              cfg.val_num_samples, max(cfg.batch_size, 8), cfg.seed)
            row = {"step": state["step"], "epoch": state["epoch"], "elapsed_s": elapsed(), **result}
            val_log.write(row)
            say(f"[val] step {state['step']} epoch {state['epoch']}: bce {result['val_bce']:.4f} "
                f"iou {result['val_iou']:.3f} best-acc {result['val_best_acc_mm']:.2f} mm "
                f"({time.perf_counter() - t0:.1f} s)")
            checkpoint(result)
            plot_curves(self.out, title=f"{config.model} {config.grid_size}^3")
            return result

        if cfg.max_steps is not None and state["step"] >= cfg.max_steps:
            stopped_by = "max_steps"  # resumed a finished run: validate and summarise only
        try:
            while state["epoch"] < cfg.epochs and stopped_by == "epochs":
                epoch = state["epoch"]
                # Where a resumed epoch continues: exact with the same ranks and batch; else at the same fraction.
                done = state["samples_in_epoch"] // global_batch
                # Closed on every way out of the epoch (its end, a stop, an exception): see prefetch.
                with contextlib.closing(prefetch(map(batch_to_tensors, self._batches(
                        run, cfg.batch_size, cfg.seed + epoch, drop_last, keys)))) as stream:
                    bar = tqdm(total=steps_per_epoch, initial=done, desc=f"epoch {epoch}",
                               disable=not (cfg.progress and main), dynamic_ncols=True, leave=False)
                    sums: dict[str, float] = {}
                    n_logged, t_log = 0, time.perf_counter()
                    for _ in range(done):
                        next(stream, None)
                    batch = next(stream, None)
                    (epoch_over,) = run.any(batch is None)
                    while not epoch_over:
                        losses = model.training_step(batch, optimizers, ctx)
                        run.average_buffers(model)
                        batch = next(stream, None)
                        # One agreement per step: every rank leaves the loop after the same step.
                        non_finite, signalled, time_up, epoch_over = run.any(
                            not all(math.isfinite(v) for v in losses.values()), stop is not None and stop.is_set(),
                            time.perf_counter() - invocation_start > budget_s, batch is None)
                        if non_finite:
                            raise TrainingError(f"non-finite loss at step {state['step']}: {losses}"
                                                f"{' (on some rank)' if run.enabled else ''}; lower --lr or use "
                                                f"--precision fp32")
                        done += 1
                        state.update(step=state["step"] + 1, batch_in_epoch=done, samples_in_epoch=done * global_batch)
                        if signalled:
                            raise KeyboardInterrupt
                        for k, v in losses.items():
                            sums[k] = sums.get(k, 0.0) + v
                        n_logged += 1
                        bar.update(1)
                        bar.set_postfix(loss=f"{losses['loss']:.1f}", rec=f"{losses['rec']:.1f}")
                        if state["step"] % cfg.log_every == 0:
                            now = time.perf_counter()
                            means = run.mean({k: v / n_logged for k, v in sums.items()})
                            if main:
                                train_log.write({"step": state["step"], "epoch": epoch, "elapsed_s": elapsed(),
                                                 "samples_per_s": n_logged * global_batch / (now - t_log), **means})
                            sums, n_logged, t_log = {}, 0, now
                        if cfg.val_every and state["step"] % cfg.val_every == 0:
                            last_val = run_validation()
                        if time_up:
                            stopped_by = "max_minutes"
                        elif cfg.max_steps is not None and state["step"] >= cfg.max_steps:
                            stopped_by = "max_steps"
                        if stopped_by != "epochs":
                            break
                bar.close()
                if stopped_by == "epochs":
                    state.update(epoch=state["epoch"] + 1, batch_in_epoch=0, samples_in_epoch=0)
                if not cfg.val_every or stopped_by != "epochs":
                    last_val = run_validation()
        except KeyboardInterrupt:
            if main:
                say("interrupted: saving last.pt (continue with --resume)")
                checkpoint(None)
            raise
        if not last_val:
            last_val = run_validation()
        if main and saved_at[0] != state["step"]:
            checkpoint(None)
        summary = {"model": config.model, "grid_size": config.grid_size, "steps": state["step"],
                   "epochs_completed": state["epoch"], "elapsed_s": elapsed(), "stopped_by": stopped_by,
                   "precision": ctx.precision, "device": str(ctx.device), "best_" + cfg.best_metric: state["best"],
                   "last_validation": last_val, "pretrain": state.get("pretrain"),
                   "init_from": state.get("init_from"), "rank": run.rank, "world_size": run.world_size,
                   "global_batch": global_batch,
                   "train_samples": len(self.train_reader), "data": cfg.data, "val_data": cfg.val_data}
        if main:
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2))
            plot_curves(self.out, title=f"{config.model} {config.grid_size}^3")
        return summary


def _read_yaml(path: str) -> dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as error:
        raise TrainingError(f"cannot read model config {path}: {error}") from error
    if not isinstance(data, dict):
        raise TrainingError(f"{path} must hold a mapping of model config fields")
    return data


__all__ = ["BEST_METRICS", "CheckpointError", "TrainConfig", "Trainer", "TrainingError", "chamfer_mm",
           "config_from_dict", "read_checkpoint", "resolve_context", "validate"]
