"""3D-RecGAN++ (Yang et al. 2018) without its super-resolution layers, as a baseline.

Generator: the U-Net of :class:`pssnet_core.models.networks.UNet3D`. Discriminator: conditional, it sees
the observation (2 channels) concatenated with a shape (1 channel), as in 3D-RecGAN++.

Deviations (documented): stride-2 k4 convolutions instead of k4 stride-1 conv + max-pool (about 8x fewer
FLOPs, in line with the stride-2 choice for the VAE); a non-saturating GAN loss instead of WGAN-GP (no
double backward through 3-D convs, which would triple the CPU step time); ``adv_weight`` relative to the
mean per-voxel loss.

Sampling: 3D-RecGAN++ is deterministic; it has no latent noise. :meth:`RecGAN.sample` therefore returns
the same completion ``num_samples`` times and ignores the generator. That is the honest baseline: its
diversity is zero, and the coverage metrics show what a single best guess achieves.
"""

from __future__ import annotations

import torch

from pssnet_core.models.base import CompletionModel, StepContext, check_box_temperature, check_num_samples
from pssnet_core.models.config import RecGANConfig
from pssnet_core.models.networks import Discriminator3D, UNet3D
from pssnet_core.models.vae import _gan_update


class RecGAN(CompletionModel):
    """3D-RecGAN++ generator (U-Net with dense bottleneck) and conditional discriminator."""

    name = "recgan"
    training_only_prefixes = ("discriminator.",)

    def __init__(self, config: RecGANConfig) -> None:
        super().__init__(config)
        self.config: RecGANConfig = config
        self.generator = UNet3D(2, config.channels, config.grid_size, config.bottleneck_dim)
        self.discriminator = Discriminator3D(3, config.disc_channels, config.grid_size)

    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        return {"main": torch.optim.Adam(self.generator.parameters(), lr=lr),
                "disc": torch.optim.Adam(self.discriminator.parameters(), lr=self.config.disc_lr,
                                         betas=(0.5, 0.999))}

    def training_step(self, batch: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer],
                      ctx: StepContext) -> dict[str, float]:
        x, y = self.check_input(batch["input"]), batch["target"].to(ctx.device)
        if self.uses_channels_last():
            y = y.contiguous(memory_format=torch.channels_last_3d)
        with ctx.autocast():
            logits = self.wrapped("generator")(x)
        fake = torch.sigmoid(logits.float())
        return _gan_update(self, optimizers, ctx, logits, y, torch.cat([x, fake], 1), torch.cat([x, y], 1),
                           extra_loss=None, extra_name="", pos_weight=self.config.bce_alpha,
                           adv_weight=self.config.adv_weight)

    def reconstruct(self, x: torch.Tensor) -> torch.Tensor:
        return self.generator(self.check_input(x))

    def sample(self, x: torch.Tensor, num_samples: int, generator: torch.Generator | None = None,
               box_temperature: float = 1.0) -> torch.Tensor:
        """The one deterministic completion, repeated ``num_samples`` times (``generator`` is unused)."""
        check_num_samples(num_samples)
        check_box_temperature(box_temperature, has_box=False)
        del generator
        probs = torch.sigmoid(self.generator(self.check_input(x)).float())
        return probs.repeat_interleave(num_samples, 0)
