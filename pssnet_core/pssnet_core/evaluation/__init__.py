"""The paper's evaluation: observation model (Alg. 1), plausible sets (Alg. 2), plausible-diversity metrics, and
the experiments built on them.

Shared pieces: :mod:`observation_model`, :mod:`plausible`, :mod:`metrics`, :mod:`testsets` (dataset loading),
:mod:`experiment` (the completer protocol, report files and their writer), :mod:`figures`.
Experiments, each a config, a ``run_*`` and a report: :mod:`evaluate` + :mod:`report` (``pssnet evaluate``),
:mod:`handles` + :mod:`handles_report`, :mod:`ambiguity` (with :mod:`ambiguity_sets`, :mod:`ambiguity_cache`,
:mod:`ambiguity_report`, :mod:`ambiguity_plots`), :mod:`memorisation` (with :mod:`memorisation_search`,
:mod:`memorisation_report`); :mod:`compare` pairs methods of an evaluation. :mod:`cli` turns arguments into
configs. The metrics need only numpy/scipy; the rest needs open3d.
"""
