"""The paper's VAE, PSSNet (VAE + box flow) and VAE-GAN.

Losses follow the authors' TensorFlow code (the TF "CVAE" tutorial scale): L_rec is the voxel BCE summed
over the grid, L_VAE the *single-sample* KL estimate log q(z|x) - log p(z) at the drawn z, both averaged
over the batch, weighted 1:1.

PSSNet specifics (paper sec. 4, DESIGN.md):

- The first ``box_dim`` = 24 latent dims are the box part. During training the decoder gets
  ``[flow(box), z_rest]``: the encoder's box sample is *replaced* by the flow embedding of the true box.
- L_flow = -log N(flow(box); mu_box, sigma_box) trains the encoder's box posterior to predict that
  embedding. The flow output is detached there: the flow itself is fitted only by maximum likelihood
  (boxes -> N(0, I)); letting L_flow move it would pull the embedding towards the encoder instead of
  keeping it a normalised code of the box.
- The flow is first pre-trained alone on the training boxes (``flow_pretrain_steps`` = 1000 batches of
  1024 at ``flow_pretrain_lr`` = 1e-4, like the authors' separate flow training with batch 1500), then
  keeps training at ``flow_lr`` (1e-5, the authors' value) alongside the VAE. Why 1e-4 for the
  pre-training: at 1e-5 the flow needs ~3x the steps to reach the same held-out likelihood, and 1e-3 is
  unstable (numbers in :class:`~pssnet_core.models.config.PSSNetConfig`). The decoder sees the flow in
  eval mode (running batch-norm statistics), so a box has one embedding regardless of its batch.
- KL is computed on the non-box dims only.
- Inference is plain VAE sampling from the encoder's posterior over all 200 dims; the flow is not used.
- Beyond the paper (``twin_rate`` > 0): for that share of the batch the decoder gets the box code of a turned
  twin (the view's mug turned about its axis, :mod:`pssnet_core.data.twins`) and must reproduce the twin's grid,
  while the rest of the latent still comes from the view; the posterior, KL, L_flow and the flow's own fit keep
  the view's true box. Why: otherwise box code and rest always agree, and the rest learns to veto handles the
  box code puts at the edges of what the view allows.
- Beyond the paper (``box_components`` > 1): the box dims' posterior is a mixture of diagonal Gaussians
  (:mod:`pssnet_core.models.box_mixture`), fitted by the same L_flow (its negative log-likelihood of the true
  box's code); the other dims keep the Gaussian. With 1 component the model is the paper's.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator

import torch
from torch import nn

from pssnet_core.models.base import (
    CompletionModel,
    StepContext,
    bce_sum,
    check_box_temperature,
    check_num_samples,
    fp32_region,
)
from pssnet_core.models.box_mixture import BoxMixtureHead, mixture_nll
from pssnet_core.models.config import PSSNetConfig, VAEConfig, VAEGANConfig
from pssnet_core.models.flow import LOG_2PI, RealNVP, log_prob_from
from pssnet_core.models.networks import Decoder3D, Discriminator3D, Encoder3D, single_thread


def single_sample_kl(z: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """log q(z|x) - log N(z; 0, I) at the drawn z, summed over dims, mean over the batch."""
    log_q = -0.5 * ((z - mu).pow(2) * torch.exp(-logvar) + logvar + LOG_2PI)
    log_p = -0.5 * (z.pow(2) + LOG_2PI)
    return (log_q - log_p).sum(1).mean()


class VAE(CompletionModel):
    """Encoder (stride-2 convs, dense to mean and log-variance) and mirrored decoder."""

    name = "vae"
    fuses_sampling = True  # Encoder3D and Decoder3D.probabilities

    def __init__(self, config: VAEConfig) -> None:
        super().__init__(config)
        self.config: VAEConfig = config
        self.latent_dim = config.latent_dim
        self.encoder = Encoder3D(2, config.channels, config.grid_size, 2 * config.latent_dim)
        self.decoder = Decoder3D(config.latent_dim, config.channels, config.grid_size)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, logvar), each (B, latent_dim), in fp32."""
        return self._posterior(self.encoder(x))

    @staticmethod
    def _posterior(encoded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, logvar = encoded.float().chunk(2, dim=1)
        # Clamp: a runaway log-variance early in training would give inf/NaN in exp().
        return mu, logvar.clamp(-30.0, 20.0)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Occupancy logits (B,1,N,N,N)."""
        return self.decoder(z)

    def decode_probabilities(self, z: torch.Tensor, spatial: bool = True) -> torch.Tensor:
        """Occupancy probabilities (B,1,N,N,N), fp32: sigmoid(decode(z)), fused without autograd on the CPU; with
        ``spatial`` False (B, N^3) in the decoder's block order (:meth:`Decoder3D.probabilities`)."""
        return self.decoder.probabilities(z, spatial)

    def _vae_forward(self, x: torch.Tensor, ctx: StepContext
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        with ctx.autocast():
            mu, logvar = self._posterior(self.wrapped("encoder")(x))
        eps = torch.randn_like(mu)
        z = mu + torch.exp(0.5 * logvar) * eps
        return z, mu, logvar, eps

    def training_step(self, batch: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer],
                      ctx: StepContext) -> dict[str, float]:
        x, y = self.check_input(batch["input"]), batch["target"].to(ctx.device)
        z, mu, logvar, _ = self._vae_forward(x, ctx)
        with ctx.autocast():
            logits = self.wrapped("decoder")(z)
        rec = bce_sum(logits, y)
        kl = single_sample_kl(z, mu, logvar)
        loss = rec + self.config.kl_weight * kl
        opt = optimizers["main"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": loss.item(), "rec": rec.item(), "kl": kl.item()}

    def reconstruct(self, x: torch.Tensor) -> torch.Tensor:
        mu, _ = self.encode(self.check_input(x))
        return self.decode(mu)

    def sample(self, x: torch.Tensor, num_samples: int, generator: torch.Generator | None = None,
               box_temperature: float = 1.0) -> torch.Tensor:
        check_num_samples(num_samples)
        t = check_box_temperature(box_temperature, self.has_box_latent)
        # One input's encoder and latent draws are ~60 MMAC of small ops: on one thread none of them waits for a
        # second thread to be scheduled, which on a busy 2-core machine costs more than the parallel GEMMs save
        # (encoder 9 vs 60 ms median, 3.9 vs 5.0 ms best; BENCHMARKS.md "Inference").
        with single_thread() if x.shape[0] == 1 else contextlib.nullcontext():
            mu, logvar = self.encode(self.check_input(x))  # encoder once
            z = self.sample_latents(mu, logvar, num_samples, generator, t)
        return self.decode_probabilities(z)  # decoder on all latents in one batch

    def sample_latents(self, mu: torch.Tensor, logvar: torch.Tensor, num_samples: int,
                       generator: torch.Generator | None, box_temperature: float) -> torch.Tensor:
        """(B * num_samples, latent_dim) draws from the diagonal Gaussian posterior, box sigma times the
        temperature."""
        b = mu.shape[0]
        eps = torch.randn(b * num_samples, self.latent_dim, generator=generator).to(mu.device)
        if box_temperature != 1.0:
            eps[:, :self.box_dim] *= box_temperature
        return mu.repeat_interleave(num_samples, 0) + torch.exp(0.5 * logvar).repeat_interleave(num_samples, 0) * eps


class PSSNet(VAE):
    """VAE whose first ``box_dim`` latent dims encode the object's bounding box through a RealNVP flow."""

    name = "pssnet"
    # Exports keep the flow (0.5 MB; fp16 half that): it maps boxes to the codes the decoder reads, which box-code
    # diagnosis, box-head fits, turned twins and fine-tunes from an export need. The exports written before
    # 2026-11-27 (the shipped model among them) dropped it: they load and sample, without it.
    export_optional_prefixes = ("flow.",)

    def __init__(self, config: PSSNetConfig) -> None:
        super().__init__(config)
        self.config: PSSNetConfig = config
        self.box_dim = config.box_dim
        self.flow = RealNVP(config.box_dim, config.flow_couplings, config.flow_hidden,
                            config.flow_hidden_layers, config.flow_batchnorm_every)
        # The box posterior: the encoder's diagonal Gaussian (the paper, 1 component) or a mixture head.
        self.box_head = (BoxMixtureHead(2 * config.latent_dim, config.box_dim, config.box_components,
                                        config.box_head_hidden) if config.box_components > 1 else None)

    def box_nll(self, mu: torch.Tensor, logvar: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """-log q(code | view) of box codes under the box posterior, (B,): L_flow per view."""
        k = self.box_dim
        if self.box_head is not None:
            return mixture_nll(*self.wrapped("box_head")(torch.cat([mu, logvar], 1)), code)
        return (0.5 * ((code - mu[:, :k]).pow(2) * torch.exp(-logvar[:, :k]) + logvar[:, :k] + LOG_2PI)).sum(1)

    def box_spread(self, mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
        """(B, box_dim) standard deviation of the box posterior per dim, in flow units (prior: 1)."""
        if self.box_head is not None:
            return self.box_head.spread(torch.cat([mu, logvar], 1))
        return torch.exp(0.5 * logvar[:, :self.box_dim])

    def sample_latents(self, mu: torch.Tensor, logvar: torch.Tensor, num_samples: int,
                       generator: torch.Generator | None, box_temperature: float) -> torch.Tensor:
        z = super().sample_latents(mu, logvar, num_samples, generator, box_temperature)
        if self.box_head is not None:
            # The mixture's temperature scales each component's sigma: the weights and centres stay.
            z[:, :self.box_dim] = self.box_head.sample(torch.cat([mu, logvar], 1), num_samples, generator,
                                                       box_temperature)
        return z

    def reconstruct(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.mode_latent(*self.encode(self.check_input(x))))

    def mode_latent(self, mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
        """The posterior's most likely latent: ``mu``, with the box part at the heaviest mixture component's centre
        (the mixture's mean can be the code of no box at all)."""
        if self.box_head is None:
            return mu
        return torch.cat([self.box_head.mode(torch.cat([mu, logvar], 1)), mu[:, self.box_dim:]], 1)

    def turn_box_codes(self, codes: torch.Tensor, axis: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
        """The box codes of the same boxes turned about the grid's vertical axis (z: the grid is gravity-aligned)
        through ``axis`` (grid x, y in voxels) by ``angles`` (radians, one per code), through the flow: boxes
        out of it, turned, back in. Needs the flow the decoder was trained against (exports keep it)."""
        # fp32 under any autocast: a bf16 coupling stack would move the boxes by more than the turn's precision.
        with torch.no_grad(), fp32_region(codes.device):
            corners = self.box_of_code(codes).view(-1, 8, 3)
            # Angles drawn by a CPU generator turn codes on a GPU: everything meets on the codes' device.
            axis, angles = axis.to(corners), angles.to(corners)
            cos, sin = torch.cos(angles)[:, None], torch.sin(angles)[:, None]
            dx, dy = corners[..., 0] - axis[0], corners[..., 1] - axis[1]
            turned = torch.stack([axis[0] + cos * dx - sin * dy, axis[1] + sin * dx + cos * dy, corners[..., 2]], -1)
            return self.embed_box(self.normalise_box(turned.reshape(len(codes), -1)))

    def box_of_code(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, box_dim) grid coordinates of the boxes whose codes are ``codes``: the inverse of
        ``embed_box(normalise_box(box))``, with running batch-norm statistics, no gradient."""
        was_training = self.flow.training
        self.flow.eval()  # the batch norms invert with their running statistics
        with torch.no_grad():
            box = self.flow.inverse(codes.float()) * self.config.box_scale + self.config.box_offset
        self.flow.train(was_training)
        return box

    def normalise_box(self, box: torch.Tensor) -> torch.Tensor:
        """Grid coordinates (0..N) -> roughly [-1, 1]."""
        if box.ndim != 2 or box.shape[1] != self.box_dim:
            raise ValueError(f"box must have shape (B, {self.box_dim}), got {tuple(box.shape)}")
        return (box.float() - self.config.box_offset) / self.config.box_scale

    def flow_nll(self, box: torch.Tensor) -> torch.Tensor:
        """Mean negative log-likelihood of normalised boxes under the flow (nats per box)."""
        return -log_prob_from(*self.wrapped("flow")(box)).mean()

    def embed_box(self, box_n: torch.Tensor) -> torch.Tensor:
        """flow(box) with running batch-norm statistics, no gradient: the decoder's box code."""
        was_training = self.flow.training
        self.flow.eval()
        with torch.no_grad():
            z_box, _ = self.flow(box_n)
        self.flow.train(was_training)
        return z_box

    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        return {"main": torch.optim.Adam(self.parameters_except("flow."), lr=lr),
                "flow": torch.optim.Adam(self.flow.parameters(), lr=self.config.flow_lr)}

    def pretrain(self, box_source: Callable[[int], Iterator[torch.Tensor]], ctx: StepContext) -> dict[str, float]:
        """Fits the flow alone on training boxes for ``flow_pretrain_steps`` (fp32, own Adam).

        ``box_source(batch_size)`` yields (B, 24) box batches in grid coordinates, endlessly.
        """
        steps = self.config.flow_pretrain_steps
        if steps == 0:
            return {}
        opt = torch.optim.Adam(self.flow.parameters(), lr=self.config.flow_pretrain_lr)
        self.flow.train()
        nll = torch.tensor(math.nan)
        done = 0
        for box in box_source(self.config.flow_pretrain_batch):
            with fp32_region(ctx.device):
                nll = self.flow_nll(self.normalise_box(box.to(ctx.device)))
            opt.zero_grad(set_to_none=True)
            nll.backward()
            opt.step()
            done += 1
            if done >= steps:
                break
        return {"flow_pretrain_nll": float(nll.item()), "flow_pretrain_steps": float(done)}

    def training_step(self, batch: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer],
                      ctx: StepContext) -> dict[str, float]:
        x, y = self.check_input(batch["input"]), batch["target"].to(ctx.device)
        box_n = self.normalise_box(batch["box"].to(ctx.device))
        # Flow: maximum likelihood at flow_lr (fp32; 24-D, cheap).
        with fp32_region(ctx.device):
            self.flow.train()
            flow_nll = self.flow_nll(box_n)
        optimizers["flow"].zero_grad(set_to_none=True)
        flow_nll.backward()
        optimizers["flow"].step()
        z_box = self.embed_box(box_n)
        z_box_dec, y, turned = self._twin_swap(batch, z_box, y, ctx)

        z, mu, logvar, _ = self._vae_forward(x, ctx)
        k = self.box_dim
        z_dec = torch.cat([z_box_dec, z[:, k:]], dim=1)  # box replacement
        with ctx.autocast():
            logits = self.wrapped("decoder")(z_dec)
        rec = bce_sum(logits, y)
        kl = single_sample_kl(z[:, k:], mu[:, k:], logvar[:, k:])
        l_flow = self.box_nll(mu, logvar, z_box).mean()
        loss = rec + self.config.kl_weight * kl + self.config.flow_weight * l_flow
        opt = optimizers["main"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        out = {"loss": loss.item(), "rec": rec.item(), "kl": kl.item(), "flow": l_flow.item(),
               "flow_nll": flow_nll.item()}
        if turned is not None:
            out["twins"] = float(turned.float().mean())
        return out

    def _twin_swap(self, batch: dict[str, torch.Tensor], z_box: torch.Tensor, target: torch.Tensor,
                   ctx: StepContext) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The decoder's box codes and targets: a Bernoulli(``twin_rate``) subset of the rows takes its twin's.

        Returns ``(box codes, targets, which rows)``; the inputs unchanged and None with ``twin_rate`` 0.
        """
        if not self.config.twin_rate:
            return z_box, target, None
        if "twin_box" not in batch or "twin_target" not in batch:
            raise ValueError("twin_rate > 0 needs twin_box and twin_target in the batch (DatasetReader's TWIN_KEYS "
                             "of a dataset with twins: `pssnet dataset twins`)")
        # Drawn by torch's CPU generator, whatever the device: the seed alone fixes which rows turn.
        turned = (torch.rand(len(z_box)) < self.config.twin_rate).to(ctx.device)
        twin_code = self.embed_box(self.normalise_box(batch["twin_box"].to(ctx.device)))
        twin_target = batch["twin_target"].to(ctx.device)
        return (torch.where(turned[:, None], twin_code, z_box),
                torch.where(turned.view(-1, *([1] * (target.ndim - 1))), twin_target, target), turned)


class VAEGAN(VAE):
    """VAE plus an unconditional 3-D discriminator on decoded occupancy probabilities (non-saturating GAN).

    Simplification (documented): the classic VAE-GAN (Larsen et al.) also swaps the voxel loss for a
    discriminator-feature loss; we keep the voxel BCE and add the adversarial term, the form used as a
    baseline in the PSSNet paper's framework.
    """

    name = "vae_gan"
    training_only_prefixes = ("discriminator.",)

    def __init__(self, config: VAEGANConfig) -> None:
        super().__init__(config)
        self.config: VAEGANConfig = config
        self.discriminator = Discriminator3D(1, config.disc_channels, config.grid_size)

    def make_optimizers(self, lr: float) -> dict[str, torch.optim.Optimizer]:
        return {"main": torch.optim.Adam(self.parameters_except("discriminator."), lr=lr),
                "disc": torch.optim.Adam(self.discriminator.parameters(), lr=self.config.disc_lr,
                                         betas=(0.5, 0.999))}

    def training_step(self, batch: dict[str, torch.Tensor], optimizers: dict[str, torch.optim.Optimizer],
                      ctx: StepContext) -> dict[str, float]:
        x, y = self.check_input(batch["input"]), batch["target"].to(ctx.device)
        if self.uses_channels_last():
            y = y.contiguous(memory_format=torch.channels_last_3d)
        z, mu, logvar, _ = self._vae_forward(x, ctx)
        with ctx.autocast():
            logits = self.wrapped("decoder")(z)
        fake = torch.sigmoid(logits.float())
        return _gan_update(self, optimizers, ctx, logits, y, fake, y, extra_loss=self.config.kl_weight
                           * single_sample_kl(z, mu, logvar), extra_name="kl", pos_weight=None,
                           adv_weight=self.config.adv_weight)


def _gan_update(model: CompletionModel, optimizers: dict[str, torch.optim.Optimizer], ctx: StepContext,
                logits: torch.Tensor, target: torch.Tensor, fake_disc_in: torch.Tensor,
                real_disc_in: torch.Tensor, extra_loss: torch.Tensor | None, extra_name: str,
                pos_weight: float | None, adv_weight: float) -> dict[str, float]:
    """Discriminator step (real vs detached fake), then generator step (reconstruction + adversarial).

    Real and fake go through the discriminator as one batch: the same numbers as two passes (it has no batch
    norm), and one forward per backward, which a data-parallel wrapper needs.
    """
    disc: nn.Module = model.discriminator  # type: ignore[assignment]
    bce = nn.functional.binary_cross_entropy_with_logits
    with ctx.autocast():
        d_real, d_fake = model.wrapped("discriminator")(torch.cat([real_disc_in, fake_disc_in.detach()])).float() \
            .split([len(real_disc_in), len(fake_disc_in)])
    loss_d = bce(d_real, torch.ones_like(d_real)) + bce(d_fake, torch.zeros_like(d_fake))
    optimizers["disc"].zero_grad(set_to_none=True)
    loss_d.backward()
    optimizers["disc"].step()

    # The generator step needs gradients through D, not into it: the bare D, whose wrapper (if any) would wait
    # for gradients of its own parameters.
    disc.requires_grad_(False)
    try:
        with ctx.autocast():
            d_gen = disc(fake_disc_in).float()
    finally:
        disc.requires_grad_(True)
    adv = bce(d_gen, torch.ones_like(d_gen))
    rec = bce_sum(logits, target, pos_weight=pos_weight)
    loss = rec + adv_weight * model.grid_size**3 * adv
    if extra_loss is not None:
        loss = loss + extra_loss
    optimizers["main"].zero_grad(set_to_none=True)
    loss.backward()
    optimizers["main"].step()
    out = {"loss": loss.item(), "rec": rec.item(), "adv": adv.item(), "disc": loss_d.item()}
    if extra_loss is not None:
        out[extra_name] = extra_loss.item()
    return out
