"""Data-parallel training across processes and machines: torch.distributed, launched by torchrun.

``torchrun --nproc-per-node K -m pssnet_core train ...`` starts K copies of ``pssnet train``; torchrun's
environment (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT) turns this module on when WORLD_SIZE > 1.
What the trainer does with it, and why:

- Backend from the device: gloo for ``--device cpu``, NCCL for ``--device cuda`` (rank on a node takes
  ``cuda:LOCAL_RANK``).
- Gradients: each sub-network trained by gradient (``CompletionModel.networks()``: encoder, decoder, flow,
  box head, discriminator, generator) gets its own DistributedDataParallel, not the model as a whole: a training
  step runs several optimiser steps (PSSNet: flow then VAE; the GANs: discriminator then generator), and each
  backward pass then all-reduces only the gradients it produced. Gradients are averaged over ranks.
- Batch: ``--batch-size`` is per rank; one step trains on K x batch views, and ``--lr`` is the learning rate of
  that global batch's mean loss (no automatic scaling: raise it yourself if you raise K). The flow's
  pre-training batch (``flow_pretrain_batch``) is per rank too.
- Data: every epoch the shards are permuted by the seed (the same permutation on every rank) and dealt to the
  ranks round robin; each rank decodes only its own shards and shuffles them as a single process does. An epoch
  ends for all ranks when the first runs out of full batches (up to about one shard per rank goes unused in that
  epoch; a different one each epoch).
- Batch norm (the flow's, the box head's): per-rank batch statistics, as with one process at the per-rank batch;
  running statistics are averaged over ranks after every step, so all ranks hold identical state.
- Seeds: every rank builds the model from ``--seed`` (and DDP copies rank 0's weights); afterwards each rank
  draws its own noise (rank 0 continues the single-process stream).
- Rank 0 alone writes logs, validates and saves checkpoints; the others wait for it at the next step.
- Stopping: one small all-reduce per step agrees on the end of the epoch, the time budget, non-finite losses and
  SIGINT/SIGTERM, so every rank stops after the same step and rank 0 saves last.pt consistently.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from types import FrameType

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from pssnet_core.data.store import DatasetReader
from pssnet_core.models.base import CompletionModel

#: Rank 0 validates and saves while the others wait in the next collective: allow a long validation.
COLLECTIVE_TIMEOUT = datetime.timedelta(minutes=30)


class DistributedError(ValueError):
    """A distributed run is misconfigured (its device or the launcher's environment)."""


@dataclass(frozen=True)
class DistributedRun:
    """Where this process stands in a run: rank, world size, its device. One process: rank 0 of 1."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def any(self, *flags: bool) -> list[bool]:
        """Each flag OR-ed over the ranks (one all-reduce): how ranks agree to stop after the same step."""
        if not self.enabled:
            return list(flags)
        t = torch.tensor([float(f) for f in flags], device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return [bool(v) for v in t.tolist()]

    def mean(self, values: dict[str, float]) -> dict[str, float]:
        """Each value averaged over the ranks (same keys on every rank): logged losses of the global batch."""
        if not self.enabled or not values:
            return values
        keys = sorted(values)
        t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=self.device)
        dist.all_reduce(t)
        return dict(zip(keys, (t / self.world_size).tolist(), strict=True))

    def average_buffers(self, model: nn.Module) -> None:
        """Averages floating-point buffers (batch-norm running statistics) over the ranks, in place.

        A running average is linear in the batch statistics, so the average of the ranks' running averages is
        the running average of the ranks' mean statistics, whatever the number of ranks.
        """
        buffers = [b for b in model.buffers() if b.is_floating_point()]
        if not self.enabled or not buffers:
            return
        flat = torch.cat([b.detach().reshape(-1).double() for b in buffers])
        dist.all_reduce(flat)
        flat /= self.world_size
        for b, part in zip(buffers, flat.split([b.numel() for b in buffers]), strict=True):
            b.copy_(part.view_as(b))

    def wrap(self, model: CompletionModel) -> dict[str, nn.Module]:
        """One DistributedDataParallel per sub-network (see the module docstring); rank 0's weights win."""
        device_ids = [self.device.index] if self.device.type == "cuda" else None
        # No buffer broadcast before each forward: average_buffers averages them instead of taking rank 0's.
        return {name: DistributedDataParallel(net, device_ids=device_ids, forward_sync_buffers=False,
                                              gradient_as_bucket_view=True)
                for name, net in model.networks().items()}


def run_from_env() -> tuple[int, int, int]:
    """(rank, world size, local rank) from torchrun's environment; (0, 1, 0) outside torchrun."""
    try:
        return (int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)),
                int(os.environ.get("LOCAL_RANK", 0)))
    except ValueError as error:
        raise DistributedError(f"bad RANK/WORLD_SIZE/LOCAL_RANK in the environment: {error}") from error


def resolve_device(device: str, world_size: int, local_rank: int) -> torch.device:
    """The device of this rank: ``cuda`` becomes ``cuda:LOCAL_RANK`` in a distributed run."""
    dev = torch.device(device)
    if world_size > 1 and dev.type == "cuda":
        if dev.index is not None:
            raise DistributedError(f"--device {device} under torchrun: pass --device cuda, each rank takes the "
                                   f"GPU of its LOCAL_RANK (CUDA_VISIBLE_DEVICES chooses which GPUs)")
        if local_rank >= torch.cuda.device_count():
            raise DistributedError(f"LOCAL_RANK {local_rank} but this node has {torch.cuda.device_count()} "
                                   f"GPUs: start at most that many processes per node")
        return torch.device("cuda", local_rank)
    return dev


@contextlib.contextmanager
def session(device: str) -> Iterator[DistributedRun]:
    """This process's part in a run: joins the process group when WORLD_SIZE > 1 and leaves it afterwards.

    A process group that already exists (a caller that set it up) is used as it is and left to its owner.
    """
    owned = False
    if dist.is_available() and dist.is_initialized():
        rank, world, local = dist.get_rank(), dist.get_world_size(), run_from_env()[2]
    else:
        rank, world, local = run_from_env()
    dev = resolve_device(device, world, local)
    if world > 1 and not dist.is_initialized():
        if dev.type == "cuda":
            torch.cuda.set_device(dev)
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", timeout=COLLECTIVE_TIMEOUT,
                                device_id=dev if dev.type == "cuda" else None)
        owned = True
    try:
        yield DistributedRun(rank, world, local, dev)
    finally:
        if owned:
            dist.destroy_process_group()


class StopFlag:
    """``signals`` (default SIGINT and SIGTERM) set a flag instead of interrupting; the training loop stops at the
    next step boundary.

    A distributed run: raising KeyboardInterrupt at once would leave the other ranks waiting in a collective;
    torchrun forwards a signal to every worker (and kills them 30 s later), so each sees the flag at the next
    step. A second signal only sets the flag again: torchrun's forwarded copy must not cut the saving short.
    ``pssnet train`` takes SIGTERM this way in every run: raised at once, the interrupt can land inside an import or
    a file write and surface as another error (matplotlib's import during a validation failed with ImportError).
    """

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self._event = threading.Event()
        self._signals = signals
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopFlag:
        for sig in self._signals:
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()


def rank_seed(seed: int, rank: int, step: int) -> int:
    """Seed of rank ``rank``'s own noise (rank > 0) from ``step`` on: distinct per rank, reproducible."""
    return int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0])


def shard_spans(reader: DatasetReader) -> list[tuple[int, int]]:
    """(first sample number, sample count) of every shard of ``reader``, in its shard order."""
    # DatasetReader keeps its shard table private; it is the index's shard list with global sample numbers.
    return [(int(s["first"]), int(s["count"])) for s in reader._shards]


def rank_shards(num_shards: int, seed: int, rank: int, world_size: int) -> list[int]:
    """The shards rank ``rank`` reads in the epoch seeded ``seed``: a seeded permutation dealt round robin."""
    return [int(s) for s in np.random.default_rng(seed).permutation(num_shards)[rank::world_size]]


def min_rank_samples(reader: DatasetReader, world_size: int) -> int:
    """The fewest samples any rank can be dealt in an epoch (the smallest shards, as many as the fewest dealt)."""
    counts = sorted(count for _, count in shard_spans(reader))
    return sum(counts[:len(counts) // world_size])


def rank_batches(reader: DatasetReader, batch_size: int, seed: int, rank: int, world_size: int,
                 keys: Sequence[str] | None) -> Iterator[dict[str, np.ndarray]]:
    """Full batches from this rank's shards of the epoch seeded ``seed`` (what a DistributedSampler does for
    an indexable dataset, for a stream of shards): two-shard windows, shuffled within, as
    ``DatasetReader.iter_batches`` does for one process. Disjoint across ranks; the partial last batch is
    dropped, so every rank's batches weigh the same in the averaged gradient.
    """
    spans = shard_spans(reader)
    shards = rank_shards(len(spans), seed, rank, world_size)
    rng = np.random.default_rng([seed, rank])
    pending: dict[str, np.ndarray] = {}
    for start in range(0, len(shards), 2):
        parts = []
        for shard in shards[start:start + 2]:
            arrays = reader.load_shard(shard, keys=keys, twin_seed=seed)
            first, count = spans[shard]
            arrays["index"] = np.arange(first, first + count, dtype=np.int64)
            parts.append(arrays)
        window = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        perm = rng.permutation(len(window["index"]))
        window = {k: np.concatenate([pending[k], v[perm]]) if pending else v[perm] for k, v in window.items()}
        n = len(window["index"])
        for lo in range(0, n - batch_size + 1, batch_size):
            yield {k: v[lo:lo + batch_size] for k, v in window.items()}
        pending = {k: v[n - n % batch_size:] for k, v in window.items()}
