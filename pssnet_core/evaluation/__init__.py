"""The paper's evaluation: observation model (Alg. 1), plausible sets (Alg. 2), plausible-diversity metrics.

Modules: :mod:`observation_model`, :mod:`plausible`, :mod:`metrics`, :mod:`evaluate` (runs completers),
:mod:`report` (tables, plots), :mod:`testsets` (dataset loading), :mod:`cli` (``pssnet plausible``,
``pssnet evaluate``). The metrics need only numpy/scipy; the rest needs open3d.
"""
