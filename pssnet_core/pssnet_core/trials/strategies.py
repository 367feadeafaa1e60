"""The strategies: each chooses one grasp from the same view, through the node's own code path.

Every strategy turns a set of shapes into ranked grasps with :func:`pssnet_core.grasps.plan_grasps`, called
on the :class:`~pssnet_core.pipeline.CompletionPipeline`'s output as the node calls it (the observation
grid, observed points and known-occupied grid, the grasp config with the call's seed), plus what a robot
knows of its surroundings: the scenario's clutter (the ``allowed`` filter) and the table's height (the
support plane, instead of the node's estimate from the view, which may lie a voxel below the table). It
takes the best-ranked grasp unless that holds for none of its shapes (then it has none):

- ``pssnet``: PSSNet's samples (the node's default sampler); a grasp's score is the weighted fraction of the samples it
  holds for (the product);
- ``pssnet_confident``: the same grasps, chosen risk-averse (:meth:`GraspSet.confident_choice`: the firmest
  grip among those holding for >= 90 % of the samples' weight, else no grasp);
- ``pssnet_second_look``: the robot looks again before it grasps when a place round the object
  (:func:`~pssnet_core.trials.scenarios.look_cameras`) would tell two of its samples apart with probability >=
  ``look_threshold`` (:mod:`pssnet_core.next_view`, the known clutter in front): from the place that
  tells them apart best, it completes both views fused (``CompletionPipeline.run(more_views=...)``) and takes the
  best-ranked grasp on those samples; else PSSNet's grasp. The only strategy that sees more than one view. (Looking
  only when no grasp held for >= 90 % of the samples was tried first: the samples' agreement on a grasp proved a
  poor sign of a safe one, ``results/second_look/``);
- ``one_completion_second_look``: the same look (where PSSNet's samples say, when they say so), then PSSNet's
  posterior mean of both views fused, one shape: what the samples add once the robot has looked;
- ``vae``: the VAE's samples, scored the same way;
- ``vae_second_look``: ``pssnet_second_look`` with the VAE in PSSNet's place: the VAE's own samples of the first
  view decide whether and from where to look, the VAE completes both views (the active strategies compared under
  one policy);
- ``one_completion``: PSSNet's posterior mean alone (``decode(mu) > 0.5``), one shape;
- ``observed``: the observed voxels alone (the known-occupied grid);
- ``oracle``: the true shape in the same grid (an upper bound: the planner's own limits remain);
- ``plausible``: the true object changed only where the view cannot see, checked, chosen and weighted as the
  node's checked sampler does (:mod:`~pssnet_core.trials.plausible`): what a sampler that draws exactly what the
  view allows would lift: every image-consistent sampler that spans what the view allows, under this planner;
- ``scene_posterior``: a mug's turns within the handle directions the scenario draws (the exact posterior of the
  hidden handle given the view: the ceiling of a sampler that learned the mugs' distribution, under this planner), or
  the scenario's own boxes at every sideways place the view allows (a posterior under that stated prior; the
  scenario's own would read the box's place from the camera's aim);
- ``random``: a uniformly random candidate among PSSNet's that hold for at least one sample (a lower bound).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from pssnet_core.grasps import GraspConfig, GraspSet, plan_grasps
from pssnet_core.inference import Completer
from pssnet_core.next_view import NextViewConfig, rank_views, scaled_intrinsics
from pssnet_core.pipeline import CompletionPipeline, MoreView, PipelineConfig, PipelineInputError, PipelineResult
from pssnet_core.trials import LOOK_MIN_SEPARABILITY, STRATEGIES, VAE_STRATEGIES
from pssnet_core.trials.physics import PhysicsConfig
from pssnet_core.trials.plausible import PlausibleVariantsConfig, VariantJudge, plausible_shapes, posterior_shapes
from pssnet_core.trials.scenarios import TrialScene, allowed_by_clutter, clutter_depth, look_cameras, render_look


@dataclass
class SecondLook:
    """Both views completed by PSSNet (None when no look was taken), and where the look came from, for the records."""

    result: PipelineResult | None
    notes: dict[str, float | str]


@dataclass
class Choice:
    """One strategy's grasp for one scene.

    Attributes:
        strategy: the strategy's name.
        pose: (4, 4) world <- gripper at the grasp, or None when the strategy found no grasp.
        width: planned opening (m).
        score: fraction of the strategy's shapes the grasp holds for (0 without a grasp).
        kind: "top" or "side" ("" without a grasp).
        candidates: candidates the strategy ranked (after the clutter filter).
        notes: what else the strategy did, for the records: the grasp's ``weight_share``
            (``GraspSet.weight_shares``), where a second look came from.
    """

    strategy: str
    pose: np.ndarray | None
    width: float = 0.0
    score: float = 0.0
    kind: str = ""
    candidates: int = 0
    notes: dict[str, float | str] = field(default_factory=dict)


def posterior_mean(completer: Completer, result: PipelineResult) -> np.ndarray:
    """(1, N, N, N) bool: the model's posterior-mean completion of the pipeline's observation."""
    x = torch.from_numpy(result.observation.network_input())[None]
    with torch.inference_mode(), completer.ctx.autocast():
        logits = completer.model.reconstruct(x)
    return (torch.sigmoid(logits.float())[0, 0] > 0.5).cpu().numpy()[None]


class Strategist:
    """Runs the strategies on a scene.

    Args:
        pssnet: the PSSNet completer (also the posterior mean and the random baseline's candidates).
        vae: the VAE completer, or None (then the ``vae`` strategy cannot be asked for).
        grasps: grasp candidate and scoring options (the node's).
        num_samples: completions drawn per view for PSSNet and the VAE.
        sampler: how they are drawn (``PipelineConfig.sampler``).
        sampler_options: the checked sampler's other settings (``PipelineConfig.sampler_options``).
        physics: for the pre-grasp distance the clutter filter checks.
        clutter_margin: clearance the planner keeps from the clutter (m).
        look_threshold: the second look's strategies look again when some place tells two samples apart with at
            least this probability (and above 0).
    """

    def __init__(self, pssnet: Completer, vae: Completer | None, grasps: GraspConfig, num_samples: int,
                 physics: PhysicsConfig, clutter_margin: float, sampler: str = "checked",
                 sampler_options: tuple[str, ...] = (), look_threshold: float = LOOK_MIN_SEPARABILITY) -> None:
        if not 0.0 <= look_threshold <= 1.0:
            raise ValueError(f"look_threshold must lie in [0, 1], got {look_threshold}")
        self.look_threshold = look_threshold
        config = PipelineConfig(num_samples=num_samples, grasps=grasps, sampler=sampler,
                                sampler_options=tuple(sampler_options))
        self.pipelines = {"pssnet": CompletionPipeline(pssnet, config)}
        self.num_samples = num_samples
        self.sampler_config = config.checked_sampler_config()
        if vae is not None:
            self.pipelines["vae"] = CompletionPipeline(vae, config)
        self.pssnet = pssnet
        self.grasps = grasps
        self.physics = physics
        self.clutter_margin = clutter_margin

    def _complete(self, name: str, scene: TrialScene, seed: int, more_views: tuple[MoreView, ...] = ()
                  ) -> PipelineResult:
        pipeline = self.pipelines[name]
        pipeline.config = pipeline.with_config(up_vector=tuple(float(u) for u in scene.view.up), seed=seed)
        view = scene.view
        return pipeline.run(view.depth, view.mask, view.intrinsics, compute_grasps=False, more_views=more_views)

    def _plan(self, occupancy: np.ndarray, result: PipelineResult, scene: TrialScene, seed: int,
              weights: np.ndarray | None = None) -> GraspSet:
        """Ranked grasps on ``occupancy``; ``weights``: the sampler's weights of its samples (None: equal)."""
        observation = result.observation
        allowed = allowed_by_clutter(scene, observation.pose, self.grasps.gripper, self.physics, self.clutter_margin)
        return plan_grasps(occupancy, observation.pose, observation.points, replace(self.grasps, seed=seed),
                           known_occupied=observation.known_occupied, allowed=allowed,
                           support_z=scene.table_height(observation.pose), weights=weights)

    @staticmethod
    def _choice(name: str, grasps: GraspSet, index: int | None, camera_pose: np.ndarray) -> Choice:
        if index is None or len(grasps) == 0 or grasps.scores[index] <= 0.0:
            return Choice(name, None, candidates=len(grasps))
        return Choice(name, camera_pose @ grasps.poses[index], float(grasps.widths[index]),
                      float(grasps.scores[index]), str(grasps.kinds[index]), len(grasps),
                      {"weight_share": round(float(grasps.weight_shares[index]), 3)})

    def _second_look(self, model: str, scene: TrialScene, result: PipelineResult, seed: int) -> SecondLook:
        """Where ``model``'s samples of the first view (``result``) say to look from, and both views completed by it
        (no look when no place tells two samples apart with probability >= ``look_threshold``)."""
        camera = scene.view.camera_pose
        cameras = look_cameras(scene)
        config = NextViewConfig(delta=self.sampler_config.delta)
        small = scaled_intrinsics(scene.view.intrinsics, config.scale)
        scores = rank_views(result.occupancy, result.weights, result.observation.pose,
                            [np.linalg.inv(c.pose) @ camera for c in cameras], scene.view.intrinsics,
                            [clutter_depth(scene.physics.clutter, c.pose, small) for c in cameras], config)
        for pick in np.argsort(-scores, kind="stable"):
            if scores[pick] < self.look_threshold or scores[pick] <= 0.0:
                break
            look, view = cameras[pick], render_look(scene, cameras[pick].pose)
            if view is None or int(view.mask.sum()) < self.pipelines[model].config.min_mask_pixels:
                continue
            more = MoreView(view.depth, view.mask, view.intrinsics, np.linalg.inv(camera) @ look.pose)
            try:
                both = self._complete(model, scene, seed, (more,))
            except PipelineInputError:  # too little of the object in that view: the next best place
                continue
            notes = {"look_azimuth_deg": look.azimuth_deg, "look_elevation_deg": look.elevation_deg,
                     "look_separability": round(float(scores[pick]), 3)}
            return SecondLook(both, notes)
        return SecondLook(None, {"look_separability": round(float(scores.max(initial=0.0)), 3)})

    def choose(self, scene: TrialScene, strategies: tuple[str, ...], seed: int) -> dict[str, Choice]:
        """Each strategy's grasp for ``scene``; ``seed`` seeds the latent noise, candidates and the random pick."""
        unknown = set(strategies) - set(STRATEGIES)
        if unknown:
            raise ValueError(f"unknown strategies {sorted(unknown)}; expected some of {STRATEGIES}")
        if set(VAE_STRATEGIES) & set(strategies) and "vae" not in self.pipelines:
            raise ValueError(f"the strategies {', '.join(VAE_STRATEGIES)} need a VAE checkpoint")
        camera = scene.view.camera_pose
        result = self._complete("pssnet", scene, seed)
        observation = result.observation
        choices: dict[str, Choice] = {}
        pssnet_grasps = None
        if {"pssnet", "pssnet_confident", "pssnet_second_look", "random"} & set(strategies):
            pssnet_grasps = self._plan(result.occupancy, result, scene, seed, result.weights)
        look = None
        if {"pssnet_second_look", "one_completion_second_look"} & set(strategies):
            look = self._second_look("pssnet", scene, result, seed)
        vae = vae_grasps = None
        if set(VAE_STRATEGIES) & set(strategies):
            vae = self._complete("vae", scene, seed)
            vae_grasps = self._plan(vae.occupancy, vae, scene, seed, vae.weights)
        for name in strategies:
            if name == "pssnet":
                choices[name] = self._choice(name, pssnet_grasps, 0, camera)
            elif name == "pssnet_confident":
                choices[name] = self._choice(name, pssnet_grasps, pssnet_grasps.confident_choice(), camera)
            elif name in ("pssnet_second_look", "vae_second_look"):
                if name == "pssnet_second_look":
                    first_grasps, model_look = pssnet_grasps, look
                else:
                    first_grasps, model_look = vae_grasps, self._second_look("vae", scene, vae, seed)
                first_score = round(float(first_grasps.scores[0]) if len(first_grasps) else 0.0, 3)
                if model_look.result is None:
                    choice = self._choice(name, first_grasps, 0, camera)
                else:
                    both = model_look.result
                    choice = self._choice(name, self._plan(both.occupancy, both, scene, seed, both.weights), 0, camera)
                choices[name] = replace(choice, notes={**choice.notes, **model_look.notes, "first_score": first_score})
            elif name == "one_completion_second_look":
                seen = look.result if look.result is not None else result
                choice = self._choice(name, self._plan(posterior_mean(self.pssnet, seen), seen, scene, seed), 0, camera)
                choices[name] = replace(choice, notes={**choice.notes, **look.notes})
            elif name == "random":
                holding = np.flatnonzero(pssnet_grasps.scores > 0.0)
                rng = np.random.default_rng([seed, zlib.crc32(b"random")])
                pick = int(rng.choice(holding)) if len(holding) else None
                choices[name] = self._choice(name, pssnet_grasps, pick, camera)
            elif name in ("plausible", "scene_posterior"):
                judge = VariantJudge(scene.physics.shape, scene.physics.object_pose, camera,
                                     observation.known_occupied, observation.known_free, observation.pose,
                                     self.sampler_config)
                if name == "plausible":
                    shapes = plausible_shapes(judge, self.num_samples, PlausibleVariantsConfig(), seed)
                else:
                    observed = observation.points @ camera[:3, :3].T + camera[:3, 3]
                    shapes = posterior_shapes(judge, self.num_samples, float(scene.notes.get("yaw_deg", 0.0)),
                                              scene.yaw_range_deg, scene.pool, observed)
                choices[name] = self._choice(name, self._plan(shapes.occupancy, result, scene, seed, shapes.weights),
                                             0, camera)
            elif name == "vae":
                choices[name] = self._choice(name, vae_grasps, 0, camera)
            else:
                shapes = {"one_completion": lambda: posterior_mean(self.pssnet, result),
                          "observed": lambda: observation.known_occupied[None],
                          "oracle": lambda: scene.ground_truth(observation.pose)[None]}[name]()
                choices[name] = self._choice(name, self._plan(shapes, result, scene, seed), 0, camera)
        return choices
