"""Input checks shared by candidate generation, scoring and planning, and the support plane."""

from __future__ import annotations

import math

import numpy as np

from pssnet_core.geometry import GridPose
from pssnet_core.grasps.config import GraspError


def check_occupancy(occupancy: np.ndarray, pose: GridPose) -> np.ndarray:
    occupancy = np.asarray(occupancy)
    if occupancy.ndim != 4 or len(set(occupancy.shape[1:])) != 1:
        raise GraspError(f"completions must be an (S, N, N, N) array, got shape {occupancy.shape}")
    if occupancy.shape[0] < 1:
        raise GraspError("completions are empty: need at least one (S >= 1)")
    if occupancy.shape[1] != pose.size:
        raise GraspError(f"completion grids are {occupancy.shape[1]}^3 but the grid pose says {pose.size}^3")
    if occupancy.dtype != bool:
        if not np.issubdtype(occupancy.dtype, np.number):
            raise GraspError(f"completions must be bool occupancy, got dtype {occupancy.dtype}")
        occupancy = occupancy > 0.5 if np.issubdtype(occupancy.dtype, np.floating) else occupancy != 0
    return occupancy


def check_points(points: np.ndarray | None) -> np.ndarray | None:
    if points is None:
        return None
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise GraspError(f"observed points must be an (M, 3) array, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise GraspError("observed points contain NaN or Inf")
    return points


def check_weights(weights: np.ndarray | None, count: int) -> np.ndarray | None:
    """Completion weights normalised to sum 1 (None stays None: equal weights)."""
    if weights is None:
        return None
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (count,):
        raise GraspError(f"weights must have one entry per completion ({count}), got shape {weights.shape}")
    if not np.all(np.isfinite(weights)) or weights.min() < 0 or weights.sum() <= 0:
        raise GraspError("weights must be finite, non-negative and not all zero")
    return weights / weights.sum()


def estimate_support_height(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None = None,
                            known_occupied: np.ndarray | None = None) -> float:
    """Height of the horizontal support plane in grid coordinates (voxels); see the package docstring.

    Args:
        occupancy: (S, N, N, N) bool completions.
        pose: the grid pose.
        points: (M, 3) observed points in the camera frame, or None.
        known_occupied: (N, N, N) bool, used when ``points`` is None.

    Raises:
        GraspError: nothing to estimate from (no points, no known-occupied voxel, every completion empty).
    """
    return support_height_of(check_occupancy(occupancy, pose), pose, check_points(points), known_occupied)


def support_height_of(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None,
                      known_occupied: np.ndarray | None) -> float:
    """:func:`estimate_support_height` on input already checked by :func:`check_occupancy` and :func:`check_points`."""
    observed = math.inf
    if points is not None and len(points):
        observed = float(pose.camera_to_grid(points)[:, 2].min())
    elif known_occupied is not None and np.any(known_occupied):
        observed = float(np.flatnonzero(np.asarray(known_occupied).any(axis=(0, 1)))[0])
    layers = occupancy.any(axis=(1, 2))  # (S, N): which z layers each completion occupies
    has = layers.any(axis=1)
    completed = float(np.median(np.argmax(layers[has], axis=1))) if has.any() else math.inf
    height = min(observed, completed)
    if not math.isfinite(height):
        raise GraspError("cannot place the support plane: no observed point, no known-occupied voxel and "
                         "every completion is empty")
    return height
