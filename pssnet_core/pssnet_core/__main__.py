"""``python -m pssnet_core``: the ``pssnet`` command line, also as torchrun runs it.

``torchrun --nproc-per-node K -m pssnet_core train ...`` starts K ranks of a data-parallel ``pssnet train``
(see :mod:`pssnet_core.training.distributed`).
"""

import sys

from pssnet_core.cli import main

if __name__ == "__main__":  # not when a spawned worker process re-imports the main module
    sys.exit(main())
