"""Common interface of the completion models and the precision/device helpers they share.

Interface (what the trainer and the inference facade call):

- ``model.make_optimizers(lr) -> dict[str, Optimizer]``: every model owns how its parameters are split
  (the GAN models return a generator and a discriminator optimiser, PSSNet a VAE and a flow one).
- ``model.training_step(batch, optimizers, ctx) -> dict[str, float]``: one full update (forward, backward,
  optimiser steps) on a batch with keys ``input`` (B,2,N,N,N), ``target`` (B,1,N,N,N) float and ``box``
  (B,24); returns the loss terms for logging. ``ctx`` says how to autocast.
- ``model.pretrain(box_source, ctx) -> dict[str, float]``: optional warm-up before the main loop (PSSNet
  trains its flow there); the default does nothing.
- ``model.reconstruct(input) -> logits`` (B,1,N,N,N): one deterministic completion (posterior mean), for
  validation loss and IoU.
- ``model.sample(input, num_samples, generator) -> probabilities``: see :meth:`CompletionModel.sample`.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import ClassVar

import torch
from torch import nn

from pssnet_core.models.config import ModelConfig


class ModelInputError(ValueError):
    """A tensor given to a model has the wrong shape or type."""


@lru_cache(maxsize=1)
def cpu_has_fast_bf16() -> bool:
    """True when this CPU has native bf16 matrix instructions (AVX512-BF16 or AMX-BF16).

    Without them oneDNN emulates bf16 and it is slower than fp32, so precision "auto" falls back to fp32.
    Read from /proc/cpuinfo (Linux); anywhere else we assume no.
    """
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    flags: set[str] = set()
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    return bool({"avx512_bf16", "amx_bf16"} & flags)


#: The precision settings that inference, training, the benchmarks and the node share: "fp32", "bf16", or
#: "auto" = bf16 where the hardware runs it natively (AVX512-BF16 / AMX CPUs, bf16 GPUs), else fp32.
PRECISIONS = ("auto", "fp32", "bf16")


def resolve_precision(device: torch.device | str, precision: str = "auto") -> torch.dtype | None:
    """The autocast dtype of ``precision`` on ``device``: ``torch.bfloat16``, or None for plain fp32.

    "bf16" is honoured on any CPU (where it is emulated it is slow but numerically real: how an AVX2 machine
    tests the bf16 path); only a GPU without bf16 refuses it.

    Raises:
        ValueError: ``precision`` is not one of :data:`PRECISIONS`, or "bf16" on a GPU without bf16.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    device = torch.device(device)
    if precision == "fp32":
        return None
    if device.type == "cuda":
        if precision == "bf16" and not torch.cuda.is_bf16_supported():
            raise ValueError("this GPU does not support bf16; use precision fp32")
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    if precision == "bf16":
        return torch.bfloat16
    return torch.bfloat16 if device.type == "cpu" and cpu_has_fast_bf16() else None


@dataclass(frozen=True)
class StepContext:
    """How a step runs: the device and the autocast dtype (``None`` = plain fp32)."""

    device: torch.device
    autocast_dtype: torch.dtype | None = None

    def autocast(self) -> contextlib.AbstractContextManager:
        """Autocast context for forward passes (backward runs outside it)."""
        if self.autocast_dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=self.autocast_dtype)

    @property
    def precision(self) -> str:
        """The precision setting this context runs: "fp32" or "bf16" (see :data:`PRECISIONS`)."""
        return {None: "fp32", torch.bfloat16: "bf16"}.get(self.autocast_dtype, str(self.autocast_dtype))


def fp32_region(device: torch.device) -> contextlib.AbstractContextManager:
    """Disables autocast (small numerically delicate parts: flow, KL, losses)."""
    return torch.autocast(device_type=device.type, enabled=False)


class CompletionModel(nn.Module):
    """Base class of the registry's models; see the module docstring for the interface."""

    name: ClassVar[str] = ""
    #: parameter-name prefixes used only for training; an inference export drops them.
    training_only_prefixes: ClassVar[tuple[str, ...]] = ()
    #: parameter-name prefixes an inference export may lack because older exports dropped them; a model loaded
    #: without them samples, and the load lists them in ``extra["missing_modules"]``.
    export_optional_prefixes: ClassVar[tuple[str, ...]] = ()
    #: whether :meth:`sample` runs the fused CPU inference path of :mod:`pssnet_core.models.networks`.
    fuses_sampling: ClassVar[bool] = False
    #: leading latent dims that encode the object's box (PSSNet sets it from its config; 0 = no box part).
    box_dim: int = 0

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.grid_size = config.grid_size
        # Data-parallel wrappers of the sub-networks while a distributed run trains (see :meth:`wrapped`). A
        # plain dict, so neither state_dict() nor .to() sees them: checkpoints stay those of the bare model.
        self._wrappers: dict[str, nn.Module] = {}

    # ----------------------------------------------------------------------------------------- helpers
    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    @property
    def has_box_latent(self) -> bool:
        """Whether the model has a box part (``box_dim`` > 0), the dims a box temperature widens."""
        return self.box_dim > 0

    def check_input(self, x: torch.Tensor) -> torch.Tensor:
        """Validates a (B,2,N,N,N) network input and moves it to the model's device and memory format."""
        n = self.grid_size
        if not isinstance(x, torch.Tensor):
            raise ModelInputError(f"network input must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim != 5 or x.shape[1:] != (2, n, n, n) or x.shape[0] < 1:
            raise ModelInputError(f"network input must have shape (B, 2, {n}, {n}, {n}), got {tuple(x.shape)}")
        x = x.to(self.device, dtype=torch.float32)
        if self.uses_channels_last():
            x = x.contiguous(memory_format=torch.channels_last_3d)
        return x

    def uses_channels_last(self) -> bool:
        for p in self.parameters():
            if p.ndim == 5:
                return p.is_contiguous(memory_format=torch.channels_last_3d) and not p.is_contiguous()
        return False

    def to_fast_layout(self) -> CompletionModel:
        """channels_last_3d weights: the fast conv layout for oneDNN (CPU) and cuDNN."""
        return self.to(memory_format=torch.channels_last_3d)

    def parameters_except(self, *prefixes: str) -> Iterator[nn.Parameter]:
        """Parameters whose names start with none of ``prefixes``."""
        for name, p in self.named_parameters():
            if not name.startswith(prefixes):
                yield p

    # ------------------------------------------------------------------------------- data parallelism
    def networks(self) -> dict[str, nn.Module]:
        """The sub-networks trained by gradient, by attribute name (encoder, decoder, flow, discriminator...).

        A distributed run wraps each in its own DistributedDataParallel rather than the whole model: every
        optimiser step of a training step (flow, VAE, discriminator, generator) then reduces only the gradients
        of the networks its own backward pass reached.
        """
        return {name: m for name, m in self.named_children() if any(p.requires_grad for p in m.parameters())}

    def set_wrappers(self, wrappers: dict[str, nn.Module]) -> None:
        """Routes the training forward passes of ``networks()`` through these wrappers; ``{}`` removes them."""
        if unknown := set(wrappers) - set(self.networks()):
            raise ValueError(f"no sub-networks named {sorted(unknown)}; known: {sorted(self.networks())}")
        self._wrappers = dict(wrappers)

    def wrapped(self, name: str) -> nn.Module:
        """Sub-network ``name`` as a training step calls it: its data-parallel wrapper in a distributed run.

        Only training steps go through the wrappers: a wrapper's forward with gradients on prepares a gradient
        reduction that every rank must then join, and inference or validation runs on one rank.
        """
        return self._wrappers[name] if name in self._wrappers else getattr(self, name)

    # -------------------------------------------------------------------------------------- interface
    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        return {"main": torch.optim.Adam(self.parameters(), lr=lr)}

    def pretrain(self, box_source: Callable[[int], Iterator[torch.Tensor]], ctx: StepContext
                 ) -> dict[str, float]:
        """Optional warm-up before the main loop; ``box_source(batch_size)`` yields box batches endlessly.

        The default does nothing."""
        del box_source, ctx
        return {}

    def training_step(self, batch: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer],
                      ctx: StepContext) -> dict[str, float]:
        raise NotImplementedError

    def reconstruct(self, x: torch.Tensor) -> torch.Tensor:
        """Deterministic completion logits (B,1,N,N,N)."""
        raise NotImplementedError

    def sample(self, x: torch.Tensor, num_samples: int, generator: torch.Generator | None = None,
               box_temperature: float = 1.0) -> torch.Tensor:
        """Samples completions.

        Args:
            x: network input (B,2,N,N,N); usually B = 1.
            num_samples: completions per input.
            generator: CPU generator for the latent noise (drawn on the CPU, then moved, so that a seed gives
                the same samples on every device).
            box_temperature: factor on the posterior standard deviation of the box latent dims (PSSNet only;
                models without a box part accept only 1.0). See :func:`check_box_temperature`.

        Returns:
            float32 occupancy probabilities (B * num_samples, 1, N, N, N); rows ``b * num_samples`` to
            ``(b + 1) * num_samples - 1`` belong to input ``b``.
        """
        raise NotImplementedError


def bce_sum(logits: torch.Tensor, target: torch.Tensor, pos_weight: float | None = None) -> torch.Tensor:
    """Binary cross-entropy summed over voxels, mean over the batch (the per-sample ELBO scale).

    With ``pos_weight`` = alpha: alpha * BCE on occupied voxels + (1 - alpha) * BCE on empty ones.
    """
    logits = logits.float()
    if pos_weight is None:
        loss = nn.functional.binary_cross_entropy_with_logits(logits, target, reduction="none")
    else:
        pos = nn.functional.softplus(-logits)  # -log sigmoid(l)
        neg = nn.functional.softplus(logits)  # -log(1 - sigmoid(l))
        loss = pos_weight * target * pos + (1.0 - pos_weight) * (1.0 - target) * neg
    return loss.flatten(1).sum(1).mean()


MAX_BOX_TEMPERATURE = 10.0


def check_box_temperature(box_temperature: float, has_box: bool) -> float:
    """Validates a box temperature: finite, in (0, MAX_BOX_TEMPERATURE], and 1.0 for models without a box part.

    Why a temperature: a posterior that is too narrow on ambiguous views can be widened along the box
    dims alone (the decoder moves hidden parts, e.g. a handle, with z_box) without deforming the rest.
    """
    t = float(box_temperature)
    if not math.isfinite(t) or not 0.0 < t <= MAX_BOX_TEMPERATURE:
        raise ModelInputError(f"box_temperature must lie in (0, {MAX_BOX_TEMPERATURE}], got {box_temperature!r}")
    if not has_box and t != 1.0:
        raise ModelInputError(f"this model has no box latent; box_temperature must be 1.0, got {t}")
    return t


def check_num_samples(num_samples: int) -> int:
    if not isinstance(num_samples, int) or isinstance(num_samples, bool) or num_samples < 1:
        raise ModelInputError(f"num_samples must be a positive int, got {num_samples!r}")
    return num_samples
