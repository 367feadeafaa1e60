"""Synthetic datasets: scenes, sharded storage, builds.

``SCALES`` and ``TWINS_PER_VIEW`` live here rather than in ``datasets`` and ``twins`` so that the command line can
offer them without importing the renderer (open3d) and the shape generators (manifold3d): ``pssnet train`` then runs
on a machine without them.
"""

#: Dataset scales of ``pssnet dataset build --scale`` (see :mod:`pssnet_core.data.datasets`).
SCALES: tuple[str, ...] = ("default", "large", "broad", "boxes", "slits")
#: Default turned twins per mug view of ``pssnet dataset twins`` (see :mod:`pssnet_core.data.twins`).
TWINS_PER_VIEW: int = 4
