"""The plausibility-checked diverse sampler: propose many completions, keep those the view allows, return a
spread of them with weights.

Why: the posterior of a VAE (PSSNet included) is trained to explain the training views, not to span every
shape a view allows; on objects made elsewhere its samples bunch up (handles drawn near straight behind, boxes
behind a slit all narrower than the truth). The view itself says what is allowed, so the sampler asks it:

1. **Propose** ``proposals_per_sample`` x the requested number of latents from up to four sources: the trained
   posterior, the posterior with its box dims widened (``widened_temperature``), and, for models with a box part
   (PSSNet), box codes from the prior N(0, I) of the flow space (every training box width and handle azimuth)
   with the rest of the latent from the posterior, and **turned boxes**: posterior draws whose box is turned about
   the vertical axis through the posterior mode's centre by a uniform angle (a mug's handle to every azimuth, its
   body where it was), with the rest of the latent scaled towards the prior's mean by a factor drawn from
   [``turned_rest_low``, 1]. Why turned boxes and a weaker rest: a prior box code also redraws the body's box,
   so most prior proposals whose handle lies where the view allows fail the check on their bodies; and the rest
   of the posterior latent, which encodes what the camera saw, vetoes handles the box puts far from straight
   behind (``results/reach/README.md``). Turning needs the flow (exports keep it; models exported without it
   draw those proposals from the prior instead). All are decoded in one batch.
2. **Check** each proposal against the observation with the observation model of Alg. 1 on the grid
   (:class:`GridCheck`): a proposal is rejected when it leaves observed surface unexplained (no occupied voxel
   within ``delta`` behind an observed voxel, along its camera ray: the expected depth would differ by more than
   delta) on more than ``max_missed_fraction`` of the observed voxels (silhouette voxels are where a sub-voxel
   shift decides, the grid's analogue of Alg. 1's unreliable pixels), or when it occupies more than
   ``max_free_voxels`` voxels lying more than ``delta`` in front of what the camera saw (it saw through them).
3. **Refine** (``refine_steps`` > 0) ``refine_misses`` rejected proposals, those of the three times as many least
   violating that differ most from the accepted ones (``refine_novel_misses``), or the ``short_pool_refine_misses``
   least violating where fewer proposals than requested pass: a few gradient
   steps on the rest of each one's latent (its box code, which places the handle and the hidden extent, held
   fixed) towards occupying the observed voxels and leaving seen-through space empty, then check them again.
   Why: a proposal that reaches a hidden handle the posterior does not draw (a turned box) mostly fails on its
   body, moved a voxel or two off what the camera saw; the view can put the body back without taking the handle
   away. Gradient steps on the latent are the model's own way to explain the view (as an auto-decoder infers a
   code); nothing else here knows what the decoder can draw.
4. **Select** the requested number among the accepted proposals by farthest-point selection on the Jaccard
   distance of their occupancy (1 - IoU), starting from the first accepted posterior proposal; each selected
   sample's **weight** is the share of accepted proposals nearest to it (sums to 1), which the grasp score uses.

When fewer proposals (refined ones included) are accepted than requested, the least-violating rejected ones make
up the number (``fill_with_nearest_misses``; without it the accepted ones are repeated, their weight split among
the copies); when none is, the least-violating proposals are returned; the result's ``note`` says which.

The check runs in the grid, not in the image: the grid is what the network saw, and a proposal is only known
at voxel resolution. Rendering each of hundreds of voxel grids into the depth image would cost more than the
decoder itself; along-ray lookups in the grid cost a few milliseconds for all of them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from pssnet_core.geometry import GridPose, ViewEvidence
from pssnet_core.inference import CompletionInputError, CompletionResult
from pssnet_core.options import config_with
from pssnet_core.spread import BitRows, farthest_point_selection

SAMPLERS: tuple[str, ...] = ("posterior", "checked")

# Proposal sources, in the order their latents are drawn and decoded.
SOURCES: tuple[str, ...] = ("posterior", "widened", "prior_box", "turned_box")
# The refined nearest misses, counted beside the sources in a result's ``accepted_by_source``.
REFINED = "refined"


@dataclass(frozen=True)
class CheckedSamplerConfig:
    """Parameters of the checked sampler.

    Attributes:
        proposals_per_sample: proposals decoded per requested sample (the issue asks for >= 10).
        source_shares: shares of the proposals drawn from (posterior, widened posterior, prior box codes, turned
            boxes); models without a box part draw every proposal from the posterior, models without their flow
            draw the turned share from the prior box codes.
        widened_temperature: factor on the box dims' posterior sigma of the widened source.
        turned_rest_low: the turned boxes' rest of the latent is scaled by a factor drawn from [this, 1].
        delta: depth tolerance of the check (metres), Alg. 1's delta.
        max_missed_fraction: observed voxels a proposal may leave unexplained (the silhouette's share).
        missed_margin: a proposal may also leave unexplained this much more than the median posterior proposal
            (the model's own accuracy on this view); the larger of the two limits applies.
        max_free_voxels: voxels a proposal may occupy deeper than ``delta`` inside seen-through space.
        max_proposals: upper bound on proposals per call (memory: one float32 grid each).
        fill_with_nearest_misses: when fewer proposals than requested samples pass the check, make the pool up with
            the least-violating rejected ones (as when none passes) instead of repeating the accepted ones: no jump
            from twenty nearest misses when nothing passes to twenty copies of one when one does (mugs behind a
            slit: arc coverage 0.47 -> 0.58, nothing worse measured; results/shipped_with_flow/README.md).
        refine_misses: least-violating rejected proposals refined per call.
        short_pool_refine_misses: least-violating rejected proposals refined instead when fewer proposals than
            requested samples pass the check (at most the rejected ones; the cost is paid where the pool falls
            short: mugs behind a narrow slit, whose proposals mostly miss the few voxels seen through it).
        refine_steps: Adam steps of the refinement (0: no refinement).
        refine_rate: Adam's learning rate on the latent (prior units).
        refine_anchor: weight of the squared distance from the proposal's own latent (keeps the refined proposal
            what it was where the view says nothing).
        refine_only_short_pools: refine only when fewer proposals than requested samples pass the check (the
            cost is then paid where the pool falls short, not on every call).
        refine_novel_misses: where the pool is full, refine the ``refine_misses`` of the 3 x ``refine_misses``
            least-violating rejected proposals farthest (Jaccard) from the accepted ones' farthest-point spread,
            instead of the least violating: a miss like an accepted proposal adds nothing when refined (hidden
            arc coverage out of family 0.79 -> 0.82, results/novel_misses/README.md).
    """

    proposals_per_sample: int = 10
    source_shares: tuple[float, float, float, float] = (0.4, 0.2, 0.0, 0.4)
    widened_temperature: float = 2.0
    turned_rest_low: float = 0.5
    delta: float = 0.01
    max_missed_fraction: float = 0.02
    missed_margin: float = 0.0
    max_free_voxels: int = 2
    max_proposals: int = 2000
    fill_with_nearest_misses: bool = True
    refine_misses: int = 20
    short_pool_refine_misses: int = 60
    refine_steps: int = 3
    refine_rate: float = 0.2
    refine_anchor: float = 0.01
    refine_only_short_pools: bool = False
    refine_novel_misses: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.proposals_per_sample <= 100:
            raise ValueError(f"proposals_per_sample must lie in [1, 100], got {self.proposals_per_sample}")
        shares = np.asarray(self.source_shares, dtype=np.float64)
        if shares.shape != (len(SOURCES),) or not np.all(np.isfinite(shares)) or shares.min() < 0 or shares.sum() <= 0:
            raise ValueError(f"source_shares must be {len(SOURCES)} non-negative numbers ({', '.join(SOURCES)}), not "
                             f"all zero, got {self.source_shares}")
        if not (math.isfinite(self.widened_temperature) and 0 < self.widened_temperature <= 10):
            raise ValueError(f"widened_temperature must lie in (0, 10], got {self.widened_temperature}")
        if not 0.0 <= self.turned_rest_low <= 1.0:
            raise ValueError(f"turned_rest_low must lie in [0, 1], got {self.turned_rest_low}")
        if not (math.isfinite(self.delta) and 0 < self.delta <= 0.2):
            raise ValueError(f"delta must lie in (0, 0.2] metres, got {self.delta}")
        if not (0.0 <= self.max_missed_fraction < 1.0 and 0.0 <= self.missed_margin < 1.0):
            raise ValueError(f"max_missed_fraction and missed_margin must lie in [0, 1), got "
                             f"{self.max_missed_fraction}, {self.missed_margin}")
        if not (0 <= self.refine_misses <= self.max_proposals and self.short_pool_refine_misses >= 0
                and 0 <= self.refine_steps <= 100):
            raise ValueError(f"refine_misses must lie in [0, max_proposals], short_pool_refine_misses be >= 0 and "
                             f"refine_steps lie in [0, 100], got {self.refine_misses}, "
                             f"{self.short_pool_refine_misses}, {self.refine_steps}")
        if not (math.isfinite(self.refine_rate) and 0 < self.refine_rate <= 10
                and math.isfinite(self.refine_anchor) and self.refine_anchor >= 0):
            raise ValueError(f"refine_rate must lie in (0, 10] and refine_anchor be >= 0, got {self.refine_rate}, "
                             f"{self.refine_anchor}")
        if self.max_free_voxels < 0 or self.max_proposals < 1:
            raise ValueError(f"max_free_voxels must be >= 0 and max_proposals >= 1, got {self.max_free_voxels}, "
                             f"{self.max_proposals}")

    def accepts(self, missed: np.ndarray, free: np.ndarray, posterior: np.ndarray) -> np.ndarray:
        """(P,) bool: the proposals the check keeps, from their :meth:`GridCheck.violations` (``missed`` share of
        the observed voxels, ``free`` voxels); ``posterior`` marks the posterior source's proposals, whose median
        ``missed`` sets the ``missed_margin`` limit."""
        limit = self.max_missed_fraction
        if self.missed_margin > 0:
            limit = max(limit, float(np.median(missed[posterior])) + self.missed_margin)
        return (missed <= limit) & (free <= self.max_free_voxels)

    def proposal_counts(self, num_samples: int, has_box: bool, has_flow: bool = True) -> dict[str, int]:
        """Proposals per source for ``num_samples`` requested samples (at least ``num_samples`` in all)."""
        total = min(max(num_samples * self.proposals_per_sample, num_samples), max(self.max_proposals, num_samples))
        shares = np.asarray(self.source_shares, dtype=np.float64)
        if not has_box:
            shares = np.eye(len(SOURCES))[0]
        elif not has_flow:  # no boxes to turn: the turned share is drawn from the prior's box codes
            shares = shares.copy()
            shares[SOURCES.index("prior_box")] += shares[SOURCES.index("turned_box")]
            shares[SOURCES.index("turned_box")] = 0.0
        shares = shares / shares.sum()
        counts = np.floor(shares * total).astype(int)
        counts[int(np.argmax(shares))] += total - int(counts.sum())
        return {name: int(c) for name, c in zip(SOURCES, counts, strict=True)}


def checked_config_with(options: Sequence[str], base: CheckedSamplerConfig | None = None) -> CheckedSamplerConfig:
    """``base`` (default: the defaults) with ``NAME=VALUE`` overrides of its fields, as command lines give them
    (``--sampler-option turned_rest_low=0.75``, ``--sampler-option source_shares=0.5,0,0,0.5``): each value is
    parsed as its field's type (a tuple as comma-separated numbers, :func:`pssnet_core.options.config_with`), and the
    result is checked as any config is.

    Raises:
        ValueError: an unknown name, a value of the wrong form, or values the config refuses.
    """
    return config_with(base or CheckedSamplerConfig(), options, "sampler option")


def _grid_parts(observation: Any) -> tuple[np.ndarray, np.ndarray, GridPose]:
    """Known-occupied, known-free and grid pose of an ``Observation`` or an evaluation view."""
    pose = getattr(observation, "pose", None)
    if not isinstance(pose, GridPose):
        pose = getattr(observation, "grid_pose", None)
    known_free = getattr(observation, "known_free", None)
    if not isinstance(pose, GridPose) or known_free is None or getattr(observation, "known_occupied", None) is None:
        raise CompletionInputError("the checked sampler needs an observation with known_occupied, known_free and "
                                   "its grid pose (an Observation or an evaluation view), not a bare network input")
    return np.asarray(observation.known_occupied, bool), np.asarray(known_free, bool), pose


@dataclass(frozen=True)
class GridCheck:
    """Alg. 1's observation model on the grid, prepared once per observation.

    Attributes:
        observed_rays: (K, S) flat voxel indices along each observed voxel's camera ray, from the voxel to
            ``delta`` behind it (-1 past the grid: a ray leaving the grid there cannot be checked, counts as met).
        deep_free: (N^3,) bool, seen-through voxels whose point ``delta`` further along the ray is seen through
            too (or outside the grid): a proposal there lies more than delta in front of what the camera saw.
    """

    observed_rays: np.ndarray
    deep_free: np.ndarray

    @classmethod
    def prepare(cls, known_occupied: np.ndarray, known_free: np.ndarray, pose: GridPose, delta: float,
                views: tuple[ViewEvidence, ...] = ()) -> GridCheck:
        """The check of one view (camera at the origin of ``pose``'s frame), or of each of ``views`` (a fused
        observation's, :attr:`Observation.views`): every observed voxel along its own camera's ray, and a
        proposal in front of any camera's readings by more than delta is in deep-free space."""
        if not views:
            views = (ViewEvidence(known_occupied, known_free, np.zeros(3)),)
        parts = [cls._prepare_view(v, known_free, pose, delta) for v in views]
        return cls(observed_rays=np.concatenate([p.observed_rays for p in parts]),
                   deep_free=np.logical_or.reduce([p.deep_free for p in parts]))

    @classmethod
    def _prepare_view(cls, view: ViewEvidence, all_free: np.ndarray, pose: GridPose, delta: float) -> GridCheck:
        n = pose.size
        camera = pose.camera_to_grid(np.asarray(view.camera, np.float64)[None])[0]  # in grid coordinates (voxels)
        reach = delta / pose.voxel_size  # voxels
        steps = np.linspace(0.0, reach, max(2, int(math.ceil(reach * 2)) + 1))  # half-voxel spacing

        def along_rays(ijk: np.ndarray, offsets: np.ndarray) -> np.ndarray:
            centres = ijk + 0.5
            direction = centres - camera
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            points = centres[:, None, :] + offsets[None, :, None] * direction[:, None, :]
            index = np.floor(points).astype(np.int64)
            inside = np.all((index >= 0) & (index < n), axis=2)
            flat = np.ravel_multi_index(tuple(np.clip(index, 0, n - 1).transpose(2, 0, 1)), (n, n, n))
            return np.where(inside, flat, -1)

        observed = along_rays(np.argwhere(view.known_occupied).astype(np.float64), steps).reshape(-1, len(steps))
        free_ijk = np.argwhere(view.known_free)
        behind = along_rays(free_ijk.astype(np.float64), np.array([reach]))[:, 0]
        # Seen free delta further along this camera's ray by any view: a proposal here lies in front of a reading.
        free_flat = all_free.reshape(-1)
        deep = np.zeros(n ** 3, dtype=bool)
        deep[np.ravel_multi_index(tuple(free_ijk.T), (n, n, n))] = (behind < 0) | free_flat[np.maximum(behind, 0)]
        return cls(observed_rays=observed, deep_free=deep)

    def reordered(self, order: np.ndarray) -> GridCheck:
        """The same check of grids whose voxels are stored in another order: ``order[v]`` is where spatial voxel
        ``v`` lies (the decoder's block order, :meth:`Decoder3D.block_order`)."""
        deep_free = np.zeros_like(self.deep_free)
        deep_free[order] = self.deep_free
        rays = self.observed_rays
        return GridCheck(observed_rays=np.where(rays < 0, -1, order[np.maximum(rays, 0)]), deep_free=deep_free)

    def violations(self, occupancy: np.ndarray, packed: BitRows) -> tuple[np.ndarray, np.ndarray]:
        """Per proposal of a (P, N^3) bool array (and the same packed): the fraction of observed voxels left
        unexplained, and the number of occupied deep-free voxels."""
        if len(self.observed_rays):
            rays = self.observed_rays
            met = occupancy[:, np.maximum(rays, 0).reshape(-1)].reshape(len(occupancy), *rays.shape) | (rays < 0)
            missed = 1.0 - met.any(axis=2).mean(axis=1)
        else:
            missed = np.zeros(occupancy.shape[0])
        return missed.astype(np.float64), packed.count_within(self.deep_free)

    def badness(self, missed: np.ndarray, free: np.ndarray) -> np.ndarray:
        """How badly each proposal violates the view: its :meth:`violations`, missed observed voxels and occupied
        deep-free voxels, on one scale (voxels)."""
        return missed * max(len(self.observed_rays), 1) + free


def spread_selection(packed: BitRows, ok: np.ndarray, badness: np.ndarray, count: int, fill: bool = False
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The checked sampler's choice among judged proposals (``packed``): up to ``count`` of the accepted ones
    (``ok``), spread by farthest-point selection on Jaccard distance, or of the ``count`` least violating
    (``badness``) when none is accepted; with ``fill``, also when fewer than ``count`` are accepted (the accepted
    ones and the least-violating rejected ones up to ``count``). Returns the chosen proposals' indices and their
    weights, the share of the pool in each one's cell (summing to 1)."""
    pool = np.flatnonzero(ok)
    if len(pool) == 0 or (fill and len(pool) < count):
        rejected = np.argsort(np.where(ok, np.inf, badness), kind="stable")[:count - len(pool)]
        pool = np.concatenate([pool, rejected])
    picked, cell = farthest_point_selection(packed.subset(pool), count)
    weights = np.bincount(cell, minlength=len(picked)).astype(np.float64)
    return pool[picked], weights / weights.sum()


@dataclass(frozen=True)
class CheckedResult(CompletionResult):
    """A :class:`CompletionResult` of the checked sampler.

    Attributes:
        weights: (n,) share of the accepted proposals each sample stands for (sums to 1).
        proposals: proposals decoded (refined nearest misses included).
        accepted: proposals the check accepted.
        accepted_by_source: accepted proposals per source (``SOURCES``, then ``REFINED``: refined nearest misses).
        note: "" when at least ``n`` distinct proposals were accepted, else what happened.
        check_s: seconds spent checking and selecting (inside ``elapsed_s``).
        refine_s: seconds spent refining nearest misses (inside ``elapsed_s``).
    """

    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    proposals: int = 0
    accepted: int = 0
    accepted_by_source: dict[str, int] = field(default_factory=dict)
    note: str = ""
    check_s: float = 0.0
    refine_s: float = 0.0


class CheckedSampler:
    """Wraps a :class:`pssnet_core.inference.Completer`; :meth:`complete` has the completer's signature, and the
    evaluation and the pipeline use a sampler wherever they take a completer.

    Args:
        completer: a loaded completer of a latent-variable model (VAE, VAE-GAN, PSSNet).
        config: sampler parameters.
    """

    def __init__(self, completer: Any, config: CheckedSamplerConfig | None = None) -> None:
        if not self.applies_to(completer):
            raise ValueError(f"the checked sampler needs a latent-variable model; {completer.model_name} has none "
                             "(use the posterior sampler)")
        self.completer = completer
        self.sampler_config = config or CheckedSamplerConfig()

    @staticmethod
    def applies_to(completer: Any) -> bool:
        """Whether ``completer``'s model has a latent to propose from (VAE, VAE-GAN, PSSNet; not 3D-RecGAN++)."""
        model = getattr(completer, "model", None)
        return all(hasattr(model, name) for name in ("encode", "sample_latents", "decode_probabilities"))

    @property
    def model(self) -> Any:
        return self.completer.model

    @property
    def has_box_latent(self) -> bool:
        return self.completer.has_box_latent

    @property
    def has_flow(self) -> bool:
        """Whether the model's box codes can be turned: a box part and the flow it was trained against (models
        exported before exports kept the flow load without it)."""
        return self.has_box_latent and "flow." not in self.completer.info.get("missing_modules", ())

    @property
    def grid_size(self) -> int:
        return int(self.completer.grid_size)

    @property
    def model_name(self) -> str:
        return str(self.completer.model_name)

    @property
    def box_temperature(self) -> float:
        return float(self.completer.box_temperature)

    @property
    def precision(self) -> str:
        return str(self.completer.precision)

    @property
    def info(self) -> dict[str, Any]:
        return self.completer.info

    def propose(self, x: torch.Tensor, counts: dict[str, int], generator: torch.Generator,
                box_temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The proposals of each source, in ``SOURCES`` order: (P, latent_dim) latents and (P, N^3) float32
        occupancy probabilities in the decoder's block order (``model.decoder.block_order()``: the check and the
        selection run in that order; only the chosen samples are put in spatial order)."""
        model = self.completer.model
        box = model.box_dim
        with torch.inference_mode(), self.completer.ctx.autocast():
            mu, logvar = model.encode(model.check_input(x))
            latents = []
            if counts["posterior"]:
                latents.append(model.sample_latents(mu, logvar, counts["posterior"], generator, box_temperature))
            if counts["widened"]:
                latents.append(model.sample_latents(mu, logvar, counts["widened"], generator,
                                                    box_temperature * self.sampler_config.widened_temperature))
            if counts["prior_box"]:
                z = model.sample_latents(mu, logvar, counts["prior_box"], generator, 1.0)
                z[:, :box] = torch.randn(counts["prior_box"], box, generator=generator).to(z)
                latents.append(z)
            if counts["turned_box"]:
                latents.append(self._turned_latents(mu, logvar, counts["turned_box"], generator, box_temperature))
            z = torch.cat(latents)
            probs = model.decode_probabilities(z, spatial=False)
        return z, probs

    def refine(self, latents: torch.Tensor, observed: np.ndarray, check: GridCheck) -> torch.Tensor:
        """(R, N^3) float32 occupancy probabilities of ``latents`` after ``refine_steps`` Adam steps on the rest of
        each latent (the box code, where the model has one, held fixed) minimising, per proposal, the mean
        -log p over the observed voxels plus the sum of -log(1 - p) over the deep-free ones (on the observed
        voxels' scale), plus ``refine_anchor`` times the squared distance from where it started. ``observed``
        (N^3 bool), ``check`` and the result are in the decoder's block order (:meth:`GridCheck.reordered`)."""
        model = self.completer.model
        config = self.sampler_config
        box = model.box_dim if self.has_box_latent else 0
        device = latents.device
        dtype = self.completer.ctx.autocast_dtype or torch.float32
        # The loss's gradient with respect to each logit is weight * sigmoid(sign * logit): sign -1 and weight
        # -1 / n on the n observed voxels (d/dl of softplus(-l) / n), sign +1 and weight 1 / n on the deep-free
        # ones, 0 elsewhere.
        seen = torch.as_tensor(observed, device=device)
        scale = 1.0 / max(int(seen.sum()), 1)
        sign = torch.where(seen, -1.0, 1.0)
        seen_through = torch.as_tensor(check.deep_free, device=device) & ~seen
        weight = torch.where(seen, -scale, torch.where(seen_through, scale, 0.0))
        # No autograd: the decoder's pullback gives the latent's gradient (Decoder3D.logits_and_pullback), in
        # inference mode whether or not the caller is in it.
        with torch.inference_mode():
            start = latents.float()
            rest = start[:, box:].clone()
            optimizer = torch.optim.Adam([rest], lr=config.refine_rate)
            for _ in range(config.refine_steps):
                logits, pullback = model.decoder.logits_and_pullback(torch.cat([start[:, :box], rest], 1), dtype)
                rest.grad = (pullback(weight * torch.sigmoid(sign * logits))[:, box:]
                             + 2 * config.refine_anchor * (rest - start[:, box:]))
                optimizer.step()
            with self.completer.ctx.autocast():
                return model.decode_probabilities(torch.cat([start[:, :box], rest], 1), spatial=False)

    def _turned_latents(self, mu: torch.Tensor, logvar: torch.Tensor, count: int, generator: torch.Generator,
                        box_temperature: float) -> torch.Tensor:
        """Posterior draws with the box turned about the vertical axis through the centre (grid x, y) of the
        posterior mode's shape by uniform angles, the rest of the latent scaled by U(``turned_rest_low``, 1)."""
        model = self.completer.model
        box = model.box_dim
        mode = model.decode_probabilities(model.mode_latent(mu, logvar))[0, 0] > 0.5
        occupied = torch.nonzero(mode).float() + 0.5
        # An empty mode (an untrained model) turns about the grid's centre.
        axis = occupied[:, :2].mean(0) if len(occupied) else torch.full((2,), mode.shape[0] / 2.0)
        z = model.sample_latents(mu, logvar, count, generator, box_temperature)
        angles = (2 * torch.rand(count, generator=generator) - 1) * math.pi
        z[:, :box] = model.turn_box_codes(z[:, :box], axis, angles).to(z)
        low = self.sampler_config.turned_rest_low
        z[:, box:] *= low + (1 - low) * torch.rand(count, 1, generator=generator).to(z)
        return z

    def complete(self, observation: Any, num_samples: int = 20, seed: int = 0,
                 box_temperature: float | None = None) -> CheckedResult:
        """Samples ``num_samples`` completions the view allows, spread over what it allows, with weights.

        Args and errors as :meth:`pssnet_core.inference.Completer.complete`; ``observation`` must carry its
        known-free grid and grid pose (an ``Observation`` or an evaluation view).
        """
        if isinstance(num_samples, bool) or not isinstance(num_samples, int | np.integer) or num_samples < 1:
            raise CompletionInputError(f"num_samples must be a positive int, got {num_samples!r}")
        known_occupied, known_free, pose = _grid_parts(observation)
        x = self.completer.network_input(observation)
        temperature = self.completer.box_temperature if box_temperature is None else box_temperature
        counts = self.sampler_config.proposal_counts(int(num_samples), self.has_box_latent, self.has_flow)
        generator = torch.Generator().manual_seed(int(seed))
        t0 = time.perf_counter()
        latents, probs = self.propose(x, counts, generator, float(temperature))
        # Only the occupancy leaves the model's device for the check (a quarter of the bytes of the probabilities
        # on a GPU), in the decoder's block order as the check; the chosen samples' probabilities follow at the end.
        occupancy = (probs > 0.5).cpu().numpy()
        t1 = time.perf_counter()
        config = self.sampler_config
        block_order = self.model.decoder.block_order()
        order = block_order.numpy()
        check = GridCheck.prepare(known_occupied, known_free, pose, config.delta,
                                  getattr(observation, "views", ())).reordered(order)
        observed = np.zeros(len(order), bool)
        observed[order] = known_occupied.reshape(-1)
        packed = BitRows.pack(occupancy)
        missed, free = check.violations(occupancy, packed)
        source = np.repeat(np.arange(len(SOURCES)), [counts[s] for s in SOURCES])
        ok = config.accepts(missed, free, source == 0)
        refine_s = 0.0
        short = int(ok.sum()) < num_samples
        count = config.short_pool_refine_misses if short else config.refine_misses
        novel = config.refine_novel_misses and not short
        misses = np.argsort(np.where(ok, np.inf, check.badness(missed, free)), kind="stable")[
            :count * (3 if novel else 1)]
        misses = misses[~ok[misses]]
        if novel and len(misses) > count:  # of the 3 x count least violating, the count least like the accepted
            accepted_rows = np.flatnonzero(ok)
            spread, _ = farthest_point_selection(packed.subset(accepted_rows), int(num_samples))
            novelty = packed.subset(misses).nearest_jaccard(packed.subset(accepted_rows[spread]))
            misses = misses[np.sort(np.argsort(-novelty, kind="stable")[:count])]
        if config.refine_steps and len(misses) and (short or not config.refine_only_short_pools):
            t_refine = time.perf_counter()
            refined = self.refine(latents[torch.as_tensor(misses, device=latents.device)], observed, check)
            refined_occupancy = (refined > 0.5).cpu().numpy()
            refined_packed = BitRows.pack(refined_occupancy)
            refined_missed, refined_free = check.violations(refined_occupancy, refined_packed)
            # The same limits as the proposals' (the posterior's median miss set on those).
            limit_source = np.concatenate([source == 0, np.zeros(len(misses), bool)])
            missed, free = np.concatenate([missed, refined_missed]), np.concatenate([free, refined_free])
            ok = config.accepts(missed, free, limit_source)
            probs = torch.cat([probs, refined])
            occupancy = np.concatenate([occupancy, refined_occupancy])
            packed = BitRows(np.concatenate([packed.words, refined_packed.words]))  # the proposals' rows as packed
            source = np.concatenate([source, np.full(len(misses), len(SOURCES))])
            refine_s = time.perf_counter() - t_refine
        accepted = np.flatnonzero(ok)
        refined_count = int(np.sum(source == len(SOURCES)))
        proposed = f"{len(ok)}" + (f" ({refined_count} of them refined)" if refined_count else "")
        note = ""
        if len(accepted) == 0:
            note = (f"no proposal of {proposed} agrees with the view (delta {self.sampler_config.delta:g} m); "
                    f"returning the {min(int(num_samples), len(ok))} least-violating ones")
        elif len(accepted) < num_samples and self.sampler_config.fill_with_nearest_misses:
            note = (f"only {len(accepted)} of {proposed} proposals agree with the view (delta "
                    f"{self.sampler_config.delta:g} m); the least-violating others make up the {int(num_samples)}")
        chosen, weights = spread_selection(packed, ok, check.badness(missed, free), int(num_samples),
                                           fill=self.sampler_config.fill_with_nearest_misses)
        distinct = len(chosen)
        if len(chosen) < num_samples:  # repeat the heaviest; each copy carries an equal part of its weight
            order = np.argsort(-weights, kind="stable")
            extra = order[np.arange(int(num_samples) - len(chosen)) % len(order)]
            positions = np.concatenate([np.arange(len(chosen)), extra])
            copies = np.bincount(positions, minlength=len(chosen))
            weights = (weights / copies)[positions]
            chosen = chosen[positions]
            if not note:
                note = (f"only {distinct} distinct completions among {len(accepted)} of {len(ok)} proposals agree "
                        "with the view; some are repeated")
        n = self.completer.grid_size
        chosen_probs = probs[torch.as_tensor(chosen, device=probs.device)][:, block_order.to(probs.device)]
        chosen_probs = chosen_probs.cpu().numpy().reshape(-1, n, n, n)
        t2 = time.perf_counter()
        return CheckedResult(probabilities=chosen_probs, occupancy=chosen_probs > 0.5, grid_size=n, seed=int(seed),
                             model=self.completer.model_name, elapsed_s=t2 - t0, weights=weights.astype(np.float32),
                             proposals=len(ok), accepted=len(accepted),
                             accepted_by_source={s: int(np.sum(ok & (source == i)))
                                                 for i, s in enumerate((*SOURCES, REFINED))},
                             note=note, check_s=t2 - t1 - refine_s, refine_s=refine_s)
