"""Inference facade used by the ROS node and the evaluation: checkpoint in, sampled completions out.

    completer = Completer.from_checkpoint(None)          # the shipped default 32^3 PSSNet
    result = completer.complete(observation, num_samples=20, seed=0)
    result.occupancy                                      # (20, N, N, N) bool

The encoder runs once per call and the decoder once on all latents in one batch, under
``torch.inference_mode``, with channels_last_3d weights. ``precision`` ("auto", "fp32" or "bf16", the setting
training, the benchmarks and the node share) chooses the number format: "auto" is bf16 where the hardware runs
it natively (AVX512-BF16 / AMX CPUs, bf16 GPUs), else fp32. On the CPU the VAE family's sampling runs fused
matmuls on weights packed once (``Decoder3D.probabilities``): in fp32 equal to the plain layers up to fp32
rounding, in bf16 the same occupancy in >= 99.5 % of voxels (``inference_path`` says which path runs).

This module imports only torch/numpy (+ PyYAML via the configs): no open3d, cv2, trimesh or rclpy, so it
also runs on the GPU training machine. Observations are taken by duck typing (``.network_input()``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from pssnet_core.models.base import (
    CompletionModel,
    ModelInputError,
    StepContext,
    check_box_temperature,
    resolve_precision,
)
from pssnet_core.models.checkpoint import CheckpointError, load_verified
from pssnet_core.models.config import ModelConfig
from pssnet_core.models.networks import onednn_runs

if TYPE_CHECKING:
    from pssnet_core.geometry import Observation

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "default_pssnet_32.pt"

__all__ = ["DEFAULT_CHECKPOINT", "CheckpointError", "Completer", "CompletionInputError", "CompletionResult"]


class CompletionInputError(ValueError):
    """The observation or network input given to :meth:`Completer.complete` is unusable."""


@dataclass(frozen=True)
class CompletionResult:
    """Sampled completions of one observation.

    Attributes:
        probabilities: (n, N, N, N) float32 occupancy probabilities.
        occupancy: (n, N, N, N) bool, ``probabilities > 0.5``.
        grid_size: N.
        seed: the seed used for the latent noise.
        model: registry name of the model that produced them.
        elapsed_s: wall time of the network part.
    """

    probabilities: np.ndarray
    occupancy: np.ndarray
    grid_size: int
    seed: int
    model: str
    elapsed_s: float

    @property
    def num_samples(self) -> int:
        return int(self.probabilities.shape[0])


class Completer:
    """Holds a loaded model and samples completions from observations.

    Args:
        model: a registry model (eval mode is set here).
        config: its config.
        device: "cpu" or "cuda".
        threads: torch CPU threads to use (process-wide setting); None leaves torch's default.
        precision: "auto" (bf16 where the hardware runs it natively, else fp32), "fp32" or "bf16" (honoured on
            any CPU; emulated on AVX2-only ones, slow but numerically real). See :data:`PRECISIONS`.
        info: checkpoint metadata (``extra``), kept for callers.
        box_temperature: default factor on the posterior sigma of the box latent dims (PSSNet; 1.0 = the
            trained posterior); :meth:`complete` may override it per call. :meth:`from_checkpoint` takes the
            value calibrated with the model (recorded by ``pssnet export-model --box-temperature``).
    """

    def __init__(self, model: CompletionModel, config: ModelConfig, device: str | torch.device = "cpu",
                 threads: int | None = None, precision: str = "auto", info: dict[str, Any] | None = None,
                 box_temperature: float = 1.0) -> None:
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device cuda requested but torch sees no CUDA device")
        if threads is not None:
            if threads < 1:
                raise ValueError(f"threads must be >= 1, got {threads}")
            torch.set_num_threads(threads)
        autocast_dtype = resolve_precision(self.device, precision)  # ValueError on a bad setting
        self.config = config
        self.info = dict(info or {})
        # channels_last_3d: the fast conv layout (oneDNN, cuDNN) and a free first permute of the block layers.
        self.model = model.to(self.device).eval().to_fast_layout()
        try:
            self.box_temperature = check_box_temperature(box_temperature, model.has_box_latent)
        except ModelInputError as error:
            raise ValueError(str(error)) from error
        self.ctx = StepContext(self.device, autocast_dtype)

    @classmethod
    def from_checkpoint(cls, path: str | Path | None = None, device: str | torch.device = "cpu",
                        threads: int | None = None, precision: str = "auto",
                        box_temperature: float | None = None, for_serving: bool = False) -> Completer:
        """Loads a checkpoint (``weights_only``); ``path`` None loads the shipped default 32^3 PSSNet.

        Its weights are checked and its self-test run (:func:`pssnet_core.models.checkpoint.load_verified`;
        ``for_serving`` adds the checks that only a model that completes shapes passes); the self-test's result
        is ``info["self_test"]``.

        Raises:
            CheckpointError: the file is missing, corrupt or not a model checkpoint, or fails its self-test.
        """
        if path is None:
            path = DEFAULT_CHECKPOINT
            if not path.is_file():
                raise CheckpointError(
                    f"the default model {path} is missing from this installation. Train one with "
                    "`pssnet train --model pssnet --data DATA --out runs/pssnet32`, then "
                    f"`pssnet export-model runs/pssnet32/best.pt {path}`, or pass a checkpoint path")
        loaded = load_verified(path, map_location="cpu", for_serving=for_serving)
        model, config, extra = loaded.model, loaded.config, loaded.extra
        extra["path"] = str(path)
        extra["self_test"] = loaded.self_test
        if box_temperature is None:  # the temperature calibrated with the model, else the trained posterior
            box_temperature = float(extra.get("box_temperature", 1.0))
        return cls(model, config, device=device, threads=threads, precision=precision, info=extra,
                   box_temperature=box_temperature)

    @property
    def grid_size(self) -> int:
        return self.config.grid_size

    @property
    def model_name(self) -> str:
        return self.config.model

    @property
    def has_box_latent(self) -> bool:
        """Whether the model has a box part that a box temperature widens (PSSNet)."""
        return self.model.has_box_latent

    @property
    def precision(self) -> str:
        """"fp32" or "bf16": what the network actually runs in ("auto" resolved)."""
        return self.ctx.precision

    @property
    def inference_path(self) -> str:
        """Which network path :meth:`complete` runs: "fused fp32" or "fused bf16" (fused oneDNN matmuls on weights
        packed once; "fused bf16 (torch.addmm)" where this CPU's oneDNN has no bf16 linear and torch emulates
        it), or "unfused" (torch's layers, under autocast in bf16: other models, other devices)."""
        if self.device.type != "cpu" or not torch.backends.mkldnn.is_available() or not self.model.fuses_sampling:
            return "unfused"
        path = f"fused {self.precision}"
        return path if onednn_runs(self.ctx.autocast_dtype or torch.float32) else path + " (torch.addmm)"

    def network_input(self, observation: Observation | np.ndarray | torch.Tensor) -> torch.Tensor:
        """The checked (1, 2, N, N, N) float32 network input of an observation or its array.

        Raises:
            CompletionInputError: wrong type or shape, or NaN/inf values.
        """
        if hasattr(observation, "network_input"):
            observation = observation.network_input()
        if isinstance(observation, torch.Tensor):
            array = observation.detach().to("cpu", torch.float32)
        elif isinstance(observation, np.ndarray):
            array = torch.from_numpy(np.ascontiguousarray(observation, dtype=np.float32))
        else:
            raise CompletionInputError(f"expected an Observation or a (2, N, N, N) array, got "
                                       f"{type(observation).__name__}")
        n = self.grid_size
        if array.ndim == 5 and array.shape[0] == 1:
            array = array[0]
        if tuple(array.shape) != (2, n, n, n):
            raise CompletionInputError(f"network input must have shape (2, {n}, {n}, {n}) for this "
                                       f"{n}^3 model, got {tuple(array.shape)}")
        # numpy: one serial pass; torch's isfinite().all() is five parallel ones (~0.1 vs 35 ms median when busy).
        if not np.isfinite(array.numpy()).all():
            raise CompletionInputError("network input contains NaN or inf")
        return array[None]

    def complete(self, observation: Observation | np.ndarray | torch.Tensor, num_samples: int = 20,
                 seed: int = 0, box_temperature: float | None = None) -> CompletionResult:
        """Samples ``num_samples`` completions of one observation.

        Args:
            observation: an ``Observation`` (anything with ``network_input()``) or its (2, N, N, N) array
                (channel 0 known occupied, channel 1 known free), numpy or torch.
            num_samples: number of completions (>= 1).
            seed: seed of the latent noise; the same seed gives the same samples.
            box_temperature: overrides the completer's ``box_temperature`` for this call.

        Returns:
            A :class:`CompletionResult`.
        """
        if isinstance(num_samples, bool) or not isinstance(num_samples, int | np.integer) or num_samples < 1:
            raise CompletionInputError(f"num_samples must be a positive int, got {num_samples!r}")
        x = self.network_input(observation)
        temperature = self.box_temperature if box_temperature is None else box_temperature
        try:
            temperature = check_box_temperature(temperature, self.has_box_latent)
        except ModelInputError as error:
            raise CompletionInputError(str(error)) from error
        generator = torch.Generator().manual_seed(int(seed))
        t0 = time.perf_counter()
        with torch.inference_mode(), self.ctx.autocast():
            probs = self.model.sample(x, int(num_samples), generator=generator, box_temperature=temperature)
        probs_np = probs[:, 0].float().cpu().numpy()
        elapsed = time.perf_counter() - t0
        return CompletionResult(probabilities=probs_np, occupancy=probs_np > 0.5, grid_size=self.grid_size,
                                seed=int(seed), model=self.model_name, elapsed_s=elapsed)
