"""Completions drawn as surfaces, so that a person sees at a glance where samples differ.

Voxel-centre clouds (what the node publishes) are put back on their lattice, closed into a surface with
marching cubes (scikit-image) and drawn with matplotlib as lit triangles: one colour per sample, the observed
part in its own colour. Points are expected in gravity-aligned axes (x the horizontal viewing direction away
from the camera, y to its left, z up), where the node's grid axes are the coordinate axes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pssnet_core.spread import BitRows, farthest_point_selection

#: Light direction for the shading (from above, behind the viewer's left shoulder when seen from the camera).
LIGHT = np.array([-0.4, 0.3, 0.85]) / np.linalg.norm([-0.4, 0.3, 0.85])


@dataclass(frozen=True)
class SurfaceMesh:
    """A triangle mesh: (V, 3) vertices, (F, 3) vertex indices."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def empty(self) -> bool:
        return len(self.faces) == 0


def lattice_occupancy(points: np.ndarray, voxel_size: float, origin: np.ndarray) -> np.ndarray:
    """Voxel centres on a common lattice -> a padded boolean grid whose voxel (i, j, k) has its centre at
    ``origin + (i, j, k) * voxel_size`` (``origin`` = the lowest centre over every cloud drawn together)."""
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    index = np.rint((np.asarray(points, np.float64) - origin) / voxel_size).astype(np.int64)
    if len(index) and index.min() < 0:
        raise ValueError("points lie below the lattice origin")
    shape = (index.max(axis=0) + 3) if len(index) else np.array([3, 3, 3])
    grid = np.zeros(tuple(shape), dtype=bool)
    grid[tuple((index + 1).T)] = True  # +1: one empty voxel of padding below, so the surface closes
    return grid


def surface_of(points: np.ndarray, voxel_size: float, origin: np.ndarray) -> SurfaceMesh:
    """The closed surface around the voxels whose centres are ``points`` (marching cubes at level 0.5)."""
    from skimage.measure import marching_cubes

    grid = lattice_occupancy(points, voxel_size, origin)
    if not grid.any():
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    vertices, faces, _, _ = marching_cubes(grid.astype(np.float32), level=0.5)
    return SurfaceMesh((vertices - 1.0) * voxel_size + origin, faces)


def draw_surface(ax: Any, mesh: SurfaceMesh, colour: Any, alpha: float = 1.0) -> None:
    """Adds the mesh to a matplotlib 3-D axis as flat-lit triangles, all in ``colour`` or one (F, 3) RGB per face."""
    from matplotlib.colors import to_rgb
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if mesh.empty:
        return
    triangles = mesh.vertices[mesh.faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # Two-sided lighting: marching cubes orients faces consistently, but the viewer may see either side.
    shade = 0.35 + 0.65 * np.abs(normals @ LIGHT)
    base = np.asarray(colour, np.float64) if np.ndim(colour) == 2 else np.asarray(to_rgb(colour))[None, :]
    colours = np.clip(base[:, :3] * shade[:, None], 0.0, 1.0)
    ax.add_collection3d(Poly3DCollection(triangles, facecolors=colours, edgecolors="none", alpha=alpha))


def sample_agreement(samples: list[np.ndarray], voxel_size: float, origin: np.ndarray
                     ) -> tuple[SurfaceMesh, np.ndarray]:
    """The surface of the union of the samples, and per face the fraction of samples that occupy it.

    Where every sample has the voxel behind a face (fraction 1) the completions agree; where few do, the shape
    there is what only some samples imagine: the ambiguity of the view, seen at a glance.
    """
    grids = [lattice_occupancy(c, voxel_size, origin) for c in samples]
    shape = np.max([g.shape for g in grids], axis=0)
    counts = np.zeros(tuple(shape), np.int32)
    for g in grids:
        counts[:g.shape[0], :g.shape[1], :g.shape[2]] += g
    union = surface_of(np.concatenate(samples), voxel_size, origin)
    if union.empty:
        return union, np.zeros(0)
    # Each face borders one occupied voxel of the union: the voxel half a voxel inside along its normal.
    triangles = union.vertices[union.faces]
    centroids = triangles.mean(axis=1)
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    best = np.zeros(len(centroids), np.int32)
    for sign in (-1.0, 1.0):  # the inside is on one side of the face; take the side with the samples
        index = np.rint((centroids + sign * 0.5 * voxel_size * normals - origin) / voxel_size).astype(np.int64) + 1
        index = np.clip(index, 0, np.array(counts.shape) - 1)
        best = np.maximum(best, counts[tuple(index.T)])
    return union, best / len(samples)


def most_different(samples: list[np.ndarray], count: int, voxel_size: float, origin: np.ndarray) -> list[int]:
    """Indices of ``count`` samples that differ most from each other (farthest-point order on the Jaccard
    distance of their voxel sets, starting from sample 0), for figures that must show the spread. When fewer
    distinct samples exist, the rest follow in index order."""
    if not samples:
        return []
    grids = [lattice_occupancy(c, voxel_size, origin) for c in samples]
    stacked = np.zeros((len(grids), *np.max([g.shape for g in grids], axis=0)), dtype=bool)
    for grid, g in zip(stacked, grids, strict=True):  # one lattice: each grid's corner is the origin
        grid[:g.shape[0], :g.shape[1], :g.shape[2]] = g
    picked = [int(i) for i in farthest_point_selection(BitRows.pack(stacked), count)[0]]
    rest = [i for i in range(len(samples)) if i not in picked]
    return (picked + rest)[:min(count, len(samples))]


def equal_box(ax: Any, points: np.ndarray, margin: float = 0.01) -> None:
    """Same scale on all three axes, framing ``points`` (matplotlib 3-D axes stretch each axis otherwise)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2 + margin
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
