"""Grasp trials in physics: do grasps chosen across PSSNet's completions pick up more real objects?

``pssnet grasp-trials`` (see :mod:`pssnet_core.trials.cli`) runs every strategy
(:mod:`~pssnet_core.trials.strategies`) on randomised scenes (:mod:`~pssnet_core.trials.scenarios`) in
MuJoCo (:mod:`~pssnet_core.trials.physics`, collision shapes from :mod:`~pssnet_core.trials.collision`) and
reports success rates (:mod:`~pssnet_core.trials.run`).
"""

import os

# MuJoCo picks its GL backend when first imported; offscreen frames on a headless machine need EGL
# (osmesa does not work here). A caller's own choice wins.
os.environ.setdefault("MUJOCO_GL", "egl")

#: the scenes (:mod:`pssnet_core.trials.scenarios`)
SCENARIOS = ("mug_hidden_handle", "box_slit", "control")
#: where the scenes' objects come from (``ScenarioConfig.objects``): the training data's generator, or the
#: out-of-family generator (:mod:`pssnet_core.shapes.independent`)
OBJECT_SOURCES = ("procedural", "independent")
#: the grasp-choosing strategies (:mod:`pssnet_core.trials.strategies`)
STRATEGIES = ("pssnet", "pssnet_confident", "vae", "one_completion", "observed", "oracle", "random")
