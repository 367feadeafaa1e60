"""Dataclass configurations of the completion models, serialisable to plain dicts and YAML.

Every checkpoint stores ``config.to_dict()``, so :func:`config_from_dict` alone rebuilds the model.

Grid sizes: the paper's network (64^3) has four Conv3d(kernel 2, stride 2) stages, so the decoder starts
from a 4x4x4x512 tensor. At 32^3 we keep the same four stride-2 stages and channels [64, 128, 256, 512]
and let the bottleneck shrink to 2x2x2x512. Why not three stages to keep 4x4x4: the dense layers then see
32768 features instead of 4096, 13 M extra parameters (encoder 32768 -> 400, decoder 200 -> 32768), which
breaks the 15 MB budget of the shipped 32^3 model, and each bottleneck voxel would see only an 8^3 patch
of the object instead of 16^3. The rule for any size is ``bottleneck = grid_size / 2**len(channels)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import yaml


class ConfigError(ValueError):
    """A model configuration is invalid or cannot be parsed."""


def _default_channels() -> list[int]:
    return [64, 128, 256, 512]


@dataclass
class ModelConfig:
    """Fields shared by every model.

    Attributes:
        grid_size: voxels along each axis of the (cubic) observation grid.
        channels: encoder channels per stride-2 stage; the decoder mirrors them.
    """

    model: ClassVar[str] = ""
    grid_size: int = 32
    channels: list[int] = field(default_factory=_default_channels)

    def __post_init__(self) -> None:
        self.channels = [int(c) for c in self.channels]
        if not self.channels or any(c < 1 for c in self.channels):
            raise ConfigError(f"channels must be a non-empty list of positive ints, got {self.channels}")
        stages = 2 ** len(self.channels)
        if self.grid_size < stages or self.grid_size % stages:
            raise ConfigError(f"grid_size {self.grid_size} must be a positive multiple of 2**len(channels) "
                              f"= {stages}")

    @property
    def bottleneck(self) -> int:
        """Spatial size of the innermost feature grid."""
        return self.grid_size // 2 ** len(self.channels)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (lists, numbers, strings) including the registry name under ``model``."""
        return {"model": self.model, **dataclasses.asdict(self)}

    def to_yaml(self, path: str | Path | None = None) -> str:
        """YAML text of :meth:`to_dict`; also written to ``path`` when given."""
        text = yaml.safe_dump(self.to_dict(), sort_keys=False)
        if path is not None:
            Path(path).write_text(text)
        return text


@dataclass
class VAEConfig(ModelConfig):
    """Plain VAE (the paper's baseline): stride-2 conv encoder, dense to mean/log-variance, mirrored decoder.

    Attributes:
        latent_dim: size of the latent vector (the paper: 200).
        kl_weight: weight of the single-sample KL term relative to the summed voxel BCE.
    """

    model: ClassVar[str] = "vae"
    latent_dim: int = 200
    kl_weight: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.latent_dim < 1:
            raise ConfigError(f"latent_dim must be positive, got {self.latent_dim}")


@dataclass
class PSSNetConfig(VAEConfig):
    """PSSNet: a VAE whose first ``box_dim`` latent dims are tied to the object's box through a RealNVP flow.

    Attributes:
        box_dim: 24 = 8 box corners x (x, y, z).
        box_offset: box normalisation, ``(box - box_offset) / box_scale``; grid coordinates (0..N voxels)
            become roughly [-1, 1]. ``None`` means ``grid_size / 2``.
        box_scale: see ``box_offset``; ``None`` means ``grid_size / 2``.
        flow_couplings: number of affine coupling layers (paper: 8).
        flow_hidden: width of each coupling's hidden layers (paper: 512).
        flow_hidden_layers: hidden layers per coupling network (paper: 2).
        flow_batchnorm_every: a batch-norm bijection after every this many couplings (paper: 2).
        flow_lr: learning rate of the flow while the VAE trains (the authors' code: 1e-5).
        flow_pretrain_steps: flow-only maximum-likelihood steps on the training boxes before the VAE starts.
        flow_pretrain_lr: learning rate of that pre-training. Measured (H100, 20k yaw-rotated boxes, batch
            1024, held-out NLL in nats/box after 300/1000/3000 steps): 1e-5 (paper) -13.5/-45.4/-65.0,
            1e-4 -53.1/-65.4/-62.3, 1e-3 -45.4/-30.3/-29.1 (unstable). So 1e-4 reaches in 1000 steps what
            1e-5 needs 3000 for, and 1e-3 is too high; after pre-training the paper's 1e-5 takes over.
        flow_pretrain_batch: batch size of that pre-training (the authors': 1500).
        flow_weight: weight of L_flow (the paper: 1, same as the VAE loss).
        box_components: components of the box posterior: 1 = the paper's diagonal Gaussian (the encoder's
            first ``box_dim`` outputs), K > 1 = a mixture head over the encoder's output
            (:class:`~pssnet_core.models.box_mixture.BoxMixtureHead`; why: ``results/box_mixture/``).
        box_head_hidden: width of the mixture head's two hidden layers.
        twin_rate: share of each training batch decoded from a turned twin's box code (the same mug turned about
            its axis, :mod:`pssnet_core.data.twins`) against the twin's grid, the rest of the latent still from
            the view: teaches the decoder to follow the box code where the rest would veto a handle. 0 = the
            paper's training; needs a dataset with twins (``pssnet dataset twins``).
    """

    model: ClassVar[str] = "pssnet"
    box_dim: int = 24
    box_offset: float | None = None
    box_scale: float | None = None
    flow_couplings: int = 8
    flow_hidden: int = 512
    flow_hidden_layers: int = 2
    flow_batchnorm_every: int = 2
    flow_lr: float = 1e-5
    flow_pretrain_steps: int = 1000
    flow_pretrain_lr: float = 1e-4
    flow_pretrain_batch: int = 1024
    flow_weight: float = 1.0
    box_components: int = 1
    box_head_hidden: int = 256
    twin_rate: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.twin_rate <= 1.0:
            raise ConfigError(f"twin_rate must lie in [0, 1], got {self.twin_rate}")
        if self.box_components < 1 or self.box_head_hidden < 1:
            raise ConfigError(f"box_components and box_head_hidden must be >= 1, got {self.box_components}, "
                              f"{self.box_head_hidden}")
        if not 0 < self.box_dim < self.latent_dim or self.box_dim % 2:
            raise ConfigError(f"box_dim must be even and in (0, latent_dim={self.latent_dim}), got {self.box_dim}")
        if self.box_offset is None:
            self.box_offset = self.grid_size / 2
        if self.box_scale is None:
            self.box_scale = self.grid_size / 2
        if self.box_scale <= 0:
            raise ConfigError(f"box_scale must be positive, got {self.box_scale}")
        if self.flow_couplings < 1 or self.flow_hidden < 1 or self.flow_hidden_layers < 1:
            raise ConfigError("flow_couplings, flow_hidden and flow_hidden_layers must be positive")
        if self.flow_pretrain_steps < 0 or self.flow_pretrain_batch < 2:
            raise ConfigError("flow_pretrain_steps must be >= 0 and flow_pretrain_batch >= 2")


@dataclass
class VAEGANConfig(VAEConfig):
    """VAE + 3-D discriminator on decoded shapes.

    Attributes:
        disc_channels: discriminator Conv3d(k4, s2) channels.
        adv_weight: weight of the generator's adversarial loss relative to the *mean per-voxel* BCE (the
            loss added is ``adv_weight * grid_size**3 * L_adv``, so it keeps its meaning across grid sizes).
        disc_lr: discriminator learning rate.
    """

    model: ClassVar[str] = "vae_gan"
    disc_channels: list[int] = field(default_factory=lambda: [32, 64, 128, 256])
    adv_weight: float = 0.01
    disc_lr: float = 1e-4


@dataclass
class RecGANConfig(ModelConfig):
    """3D-RecGAN++ without its super-resolution layers (a deterministic baseline).

    U-Net: Conv3d(k4, s2, p1) + LeakyReLU stages, two dense layers through a ``bottleneck_dim`` code, then
    ConvTranspose3d(k4, s2, p1) + ReLU stages, each fed the concatenation of the previous stage and the
    encoder stage of the same size (skip connections); sigmoid output. Loss: the paper's modified
    cross-entropy (``bce_alpha`` on occupied voxels, ``1 - bce_alpha`` on empty) plus a conditional
    discriminator (observation + shape). ``channels`` ``None`` means five stages ending at 512 for 64^3
    (as in 3D-RecGAN++) and four for 32^3, so the dense layers always see 2x2x2x512.

    Attributes:
        bottleneck_dim: width of the dense code.
        bce_alpha: weight of occupied voxels in the modified cross-entropy (3D-RecGAN++: 0.85).
        disc_channels: discriminator channels.
        adv_weight: adversarial weight relative to the mean per-voxel loss (see :class:`VAEGANConfig`).
        disc_lr: discriminator learning rate.
    """

    model: ClassVar[str] = "recgan"
    channels: list[int] = None  # type: ignore[assignment]  # resolved from grid_size below
    bottleneck_dim: int = 2000
    bce_alpha: float = 0.85
    disc_channels: list[int] = field(default_factory=lambda: [32, 64, 128, 256])
    adv_weight: float = 0.01
    disc_lr: float = 1e-4

    def __post_init__(self) -> None:
        if self.channels is None:
            self.channels = [64, 128, 256, 512, 512] if self.grid_size >= 64 else [64, 128, 256, 512]
        super().__post_init__()
        if not 0.0 < self.bce_alpha < 1.0:
            raise ConfigError(f"bce_alpha must be in (0, 1), got {self.bce_alpha}")


CONFIG_CLASSES: dict[str, type[ModelConfig]] = {
    cls.model: cls for cls in (PSSNetConfig, VAEConfig, VAEGANConfig, RecGANConfig)
}


def config_class(name: str) -> type[ModelConfig]:
    """Config dataclass registered under model ``name``."""
    try:
        return CONFIG_CLASSES[name]
    except KeyError:
        raise ConfigError(f"unknown model {name!r}; known: {sorted(CONFIG_CLASSES)}") from None


def config_from_dict(data: dict[str, Any]) -> ModelConfig:
    """Inverse of :meth:`ModelConfig.to_dict`; unknown keys are an error (they are likely typos)."""
    if not isinstance(data, dict) or "model" not in data:
        raise ConfigError(f"a model config must be a dict with a 'model' key, got {data!r}")
    data = dict(data)
    cls = config_class(str(data.pop("model")))
    known = {f.name for f in dataclasses.fields(cls)}
    if unknown := sorted(set(data) - known):
        raise ConfigError(f"unknown fields for model {cls.model!r}: {unknown}; known: {sorted(known)}")
    try:
        return cls(**data)
    except TypeError as error:
        raise ConfigError(f"bad config for model {cls.model!r}: {error}") from error

