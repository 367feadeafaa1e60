"""A PNG contact sheet of shapes (matplotlib 3-D surface plots), for looking at generated or loaded objects."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pssnet_core.shapes.procedural import Shape


def save_gallery(shapes: Sequence[Shape], path: str | Path, columns: int = 6, elevation: float = 25.0,
                 azimuth: float = -60.0, cell_inches: float = 2.6) -> Path:
    """Draws each shape's mesh in its object frame and saves one PNG.

    All panels share one metric scale (the largest shape sets it), so relative sizes are visible.

    Args:
        shapes: the shapes to draw.
        path: output PNG path (parent folders are created).
        columns: panels per row.
        elevation, azimuth: view angles in degrees (matplotlib convention).
        cell_inches: size of one panel.

    Returns:
        The written path.

    Raises:
        ValueError: no shapes or ``columns`` < 1.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not shapes:
        raise ValueError("save_gallery needs at least one shape")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = (len(shapes) + columns - 1) // columns
    half = max(float(np.max(s.mesh.extents)) for s in shapes) / 2
    fig = plt.figure(figsize=(columns * cell_inches, rows * cell_inches))
    for i, shape in enumerate(shapes):
        ax = fig.add_subplot(rows, columns, i + 1, projection="3d")
        v = np.asarray(shape.mesh.vertices)
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=np.asarray(shape.mesh.faces), color="#8fa9c9",
                        linewidth=0.0, antialiased=False, shade=True)
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_zlim(0.0, 2 * half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elevation, azim=azimuth)
        ax.set_axis_off()
        label = str(shape.identity)
        extra = shape.attributes.get("handle_style") or shape.attributes.get("kind") or shape.attributes.get("name")
        ax.set_title(f"{label}\n{extra}" if extra else label, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
