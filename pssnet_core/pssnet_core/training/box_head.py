"""Fits a mixture box posterior (:class:`~pssnet_core.models.box_mixture.BoxMixtureHead`) onto a trained PSSNet.

The head is a density estimate of one thing: the flow code of the true box given the encoder's output. With
the encoder, decoder and flow of a trained model frozen, those pairs are computed once per training view
(encoder forward only, ~1 ms per view at 32^3 in bf16) and the head is fitted on them with large batches, much
as the paper fits its flow alone before the VAE. Why not fine-tune the whole model: at the training batch of
16 the head sees ~40x fewer pairs in the same time, and the rest of the model need not change (the decoder
already draws the handle where a box code puts it).

The result is an ordinary checkpoint (flow included) with ``box_components`` > 1: it exports, samples and
evaluates like any other PSSNet checkpoint, and ``pssnet train --init-from`` trains it further (with the same
L_flow, now the mixture's likelihood).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pssnet_core.data.store import DatasetReader
from pssnet_core.models import build_model
from pssnet_core.models.base import resolve_precision
from pssnet_core.models.checkpoint import LOAD_FACTS, CheckpointError, load_checkpoint, save_checkpoint
from pssnet_core.models.vae import PSSNet


@dataclass
class BoxHeadFitConfig:
    """Parameters of :func:`fit_box_head`.

    Attributes:
        checkpoint: a PSSNet checkpoint with its flow (which embeds the true boxes): a training checkpoint or
            an export written since exports keep it.
        data: training dataset directories (comma-joined, as ``pssnet train --data``).
        out: the checkpoint to write.
        components: K, the mixture's components (>= 2).
        hidden: width of the head's hidden layers.
        max_views: training views used (the first ones of a seeded shuffle; ``None`` = all).
        val_fraction: share of those views held out to report the fit.
        steps: optimiser steps; batch: pairs per step; lr: Adam's learning rate (cosine decay to 0).
        seed: shuffling, initialisation and batches.
        threads: torch threads.
    """

    checkpoint: str
    data: str
    out: str
    components: int = 16
    hidden: int = 256
    max_views: int | None = None
    val_fraction: float = 0.03
    steps: int = 4000
    batch: int = 512
    lr: float = 1e-3
    seed: int = 0
    threads: int = 2

    def __post_init__(self) -> None:
        if self.components < 2:
            raise ValueError(f"components must be >= 2 (1 is the paper's Gaussian), got {self.components}")
        if self.hidden < 1 or self.steps < 1 or self.batch < 2 or not self.lr > 0:
            raise ValueError("hidden, steps must be >= 1, batch >= 2 and lr > 0")
        if not 0.0 < self.val_fraction < 0.5:
            raise ValueError(f"val_fraction must lie in (0, 0.5), got {self.val_fraction}")
        if self.max_views is not None and self.max_views < 10:
            raise ValueError(f"max_views must be >= 10, got {self.max_views}")


@torch.no_grad()
def encoder_pairs(model: PSSNet, data: str, max_views: int | None, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(features (V, 2 x latent_dim), true box codes (V, box_dim)) of training views, frozen model."""
    reader = DatasetReader(data)
    dtype = resolve_precision(model.device)
    features, codes, seen = [], [], 0
    for batch in reader.iter_batches(128, shuffle=True, seed=seed, keys=("known_occupied", "known_free", "box")):
        x = torch.from_numpy(np.stack([batch["known_occupied"], batch["known_free"]], 1).astype(np.float32))
        with torch.autocast(model.device.type, dtype=dtype, enabled=dtype is not None):
            mu, logvar = model.encode(model.check_input(x.to(model.device)))
        box = torch.from_numpy(np.asarray(batch["box"], dtype=np.float32)).to(model.device)
        features.append(torch.cat([mu, logvar], 1).float().cpu())
        codes.append(model.embed_box(model.normalise_box(box)).cpu())
        seen += len(x)
        if max_views is not None and seen >= max_views:
            break
    f, c = torch.cat(features), torch.cat(codes)
    return (f, c) if max_views is None else (f[:max_views], c[:max_views])


def fit_box_head(config: BoxHeadFitConfig, log: Any = print) -> dict[str, Any]:
    """Fits the head, writes ``config.out``; returns the fit's summary (also stored in the checkpoint)."""
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    base, base_config, extra = load_checkpoint(config.checkpoint)
    if not isinstance(base, PSSNet):
        raise CheckpointError(f"{config.checkpoint} is a {base_config.model} checkpoint; a box head needs PSSNet")
    if "flow." in extra["missing_modules"]:
        raise CheckpointError(f"{config.checkpoint} is an export written without the flow; fit the head on the "
                              f"training checkpoint (runs/<name>/best.pt)")
    t0 = time.perf_counter()
    features, codes = encoder_pairs(base, config.data, config.max_views, config.seed)
    seconds_pairs = time.perf_counter() - t0
    n_val = max(1, int(round(config.val_fraction * len(codes))))
    order = torch.randperm(len(codes), generator=torch.Generator().manual_seed(config.seed))
    val, train = order[:n_val], order[n_val:]
    log(f"{len(codes)} views encoded in {seconds_pairs:.0f} s; fitting on {len(train)}, validating on {n_val}")

    new_config = dataclasses.replace(base_config, box_components=config.components, box_head_hidden=config.hidden)
    model = build_model(new_config)
    missing, unexpected = model.load_state_dict(base.state_dict(), strict=False)
    if unexpected or any(not k.startswith("box_head.") for k in missing):
        raise CheckpointError(f"{config.checkpoint}: weights do not carry over (missing {missing[:5]}, "
                              f"unexpected {unexpected[:5]})")
    head = model.box_head
    assert head is not None  # components >= 2
    optimizer = torch.optim.Adam(head.parameters(), lr=config.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, config.steps)
    rng = torch.Generator().manual_seed(config.seed + 1)
    head.train()
    t1 = time.perf_counter()
    for step in range(config.steps):
        rows = train[torch.randint(len(train), (config.batch,), generator=rng)]
        loss = head.nll(features[rows], codes[rows]).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        if step % 1000 == 0 or step == config.steps - 1:
            log(f"step {step}: train NLL {loss.item():.2f} nats per box")
    head.eval()
    model.eval()
    with torch.no_grad():
        mixture_val = float(head.nll(features[val], codes[val]).mean())
        gaussian_val = float(base.box_nll(features[val, :base.latent_dim], features[val, base.latent_dim:],
                                          codes[val]).mean())
    summary = {"components": config.components, "hidden": config.hidden, "views": len(codes),
               "val_views": n_val, "steps": config.steps, "batch": config.batch, "lr": config.lr,
               "seed": config.seed, "data": config.data, "from": str(config.checkpoint),
               "val_nll_mixture": mixture_val, "val_nll_gaussian": gaussian_val,
               "seconds_pairs": seconds_pairs, "seconds_fit": time.perf_counter() - t1}
    if not math.isfinite(mixture_val):
        raise RuntimeError(f"the box head's validation NLL is {mixture_val}: the fit diverged")
    log(f"validation NLL of the true box codes: mixture {mixture_val:.2f}, the Gaussian it replaces "
        f"{gaussian_val:.2f} nats per box")
    kept = {k: v for k, v in extra.items() if k not in ("optimizers", "rng", "train_state", *LOAD_FACTS)}
    kept["box_head_fit"] = summary
    save_checkpoint(Path(config.out), model, new_config, kept)
    return summary
