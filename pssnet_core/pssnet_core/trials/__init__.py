"""Grasp trials in physics: do grasps chosen across PSSNet's completions pick up more real objects?

``pssnet grasp-trials`` (see :mod:`pssnet_core.trials.cli`) runs every strategy
(:mod:`~pssnet_core.trials.strategies`) on randomised scenes (:mod:`~pssnet_core.trials.scenarios`) in
MuJoCo (:mod:`~pssnet_core.trials.physics`, collision shapes from :mod:`~pssnet_core.trials.collision`) and
reports success rates (:mod:`~pssnet_core.trials.run`).
"""

#: MuJoCo's GL backend for the filmstrips' offscreen frames on a headless machine (osmesa does not work here).
#: MuJoCo reads ``MUJOCO_GL`` when it is first imported, so the command line sets it (unless the caller did)
#: before it imports the trial modules; a program that imports :mod:`pssnet_core.trials.physics` itself sets it first.
HEADLESS_GL = "egl"

#: the scenes (:mod:`pssnet_core.trials.scenarios`) a run takes by default
SCENARIOS = ("mug_hidden_handle", "box_slit", "control")
#: run only when asked for: a mug behind the box's slit (no training set of the shipped model shows a mug behind one)
EXTRA_SCENARIOS = ("mug_slit",)
#: every scene a run can be asked for
ALL_SCENARIOS = SCENARIOS + EXTRA_SCENARIOS
#: where the scenes' objects come from (``ScenarioConfig.objects``): the training data's generator, or the
#: out-of-family generator (:mod:`pssnet_core.shapes.independent`)
OBJECT_SOURCES = ("procedural", "independent")
#: the grasp-choosing strategies (:mod:`pssnet_core.trials.strategies`)
STRATEGIES = ("pssnet", "pssnet_confident", "pssnet_second_look", "vae", "vae_second_look", "one_completion",
              "one_completion_second_look", "observed", "oracle", "plausible", "scene_posterior", "random")
#: run only when asked for: yardsticks that plan on variants of the true object (hundreds voxelised per scene)
REFERENCE_STRATEGIES = ("plausible", "scene_posterior")
#: run only when asked for: strategies that see more than the one view the others share
ACTIVE_STRATEGIES = ("pssnet_second_look", "one_completion_second_look", "vae_second_look")
#: by default the second look's strategies look again when some place tells two samples apart at least this likely
LOOK_MIN_SEPARABILITY = 0.5
#: the strategies that need a VAE checkpoint
VAE_STRATEGIES = ("vae", "vae_second_look")
#: what a run compares unless told otherwise (the VAE too when a VAE checkpoint is given)
DEFAULT_STRATEGIES = tuple(s for s in STRATEGIES if s not in (*REFERENCE_STRATEGIES, *ACTIVE_STRATEGIES, "vae"))
