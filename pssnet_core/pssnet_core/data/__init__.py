"""Synthetic datasets: scenes, sharded storage, builds.

``SCALES`` lives here rather than in ``datasets`` so that the command line can offer it without importing the
renderer (open3d) and the shape generators (manifold3d): ``pssnet train`` then runs on a machine without them.
"""

#: Dataset scales of ``pssnet dataset build --scale`` (see :mod:`pssnet_core.data.datasets`).
SCALES: tuple[str, ...] = ("default", "large", "broad")
