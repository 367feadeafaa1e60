"""Figure helpers the experiments' plots share: voxel grids in 3D axes, and writing a figure."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _surface(grid: np.ndarray) -> np.ndarray:
    """Indices of occupied voxels with at least one empty 6-neighbour (what a voxel picture shows)."""
    padded = np.pad(grid, 1)
    inner = padded[1:-1, 1:-1, 1:-1]
    interior = inner.copy()
    for axis in range(3):
        for shift in (-1, 1):
            interior &= np.roll(padded, shift, axis=axis)[1:-1, 1:-1, 1:-1]
    return np.argwhere(grid & ~interior)


def save_figure(fig: Any, path: str | Path, dpi: int = 100) -> Path:
    """Lays out, writes (creating the folder) and closes a matplotlib figure; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def draw_voxels(ax: Any, grid: np.ndarray, title: str, color: str) -> None:
    """Draws the surface voxels of ``grid`` into the 3D axes ``ax`` (no ticks, equal aspect)."""
    pts = _surface(grid)
    n = grid.shape[0]
    if len(pts):
        # grid x = viewing direction, z = up: show the camera's side on the left
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=2, c=color, depthshade=True, linewidths=0)
    ax.set_xlim(0, n)
    ax.set_ylim(0, n)
    ax.set_zlim(0, n)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=20, azim=-60)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])
    ax.set_title(title, fontsize=7)
