"""Grasp candidates from the completions and the observed points (see the package docstring)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from pssnet_core.geometry import GridPose
from pssnet_core.grasps.config import GraspConfig, VoxelDims
from pssnet_core.grasps.inputs import check_occupancy, check_points, estimate_support_height
from pssnet_core.grasps.lattice import PackedGrids, box_or, lattice_count, lowest_point, voxel_box_rows
from pssnet_core.grasps.results import GraspCandidates


def approach_orientations(config: GraspConfig) -> tuple[np.ndarray, np.ndarray]:
    """The candidate orientations: (O, 3, 3) gripper axes (columns x, y, z) in the grid frame, (O,) kinds."""
    rotations, kinds = _orientations(config.top_yaws, config.side_yaws, tuple(config.side_rolls),
                                     tuple(config.tilted_pitches))
    return rotations.copy(), kinds.copy()


@functools.lru_cache(maxsize=8)
def _orientations(top_yaws: int, side_yaws: int, side_rolls: tuple[float, ...],
                  tilted_pitches: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`approach_orientations`, computed once per option set (read-only arrays: the cache shares them)."""
    rotations, kinds = [], []
    down = np.array([0.0, 0.0, -1.0])
    for i in range(top_yaws):
        phi = math.pi * i / top_yaws
        y = np.array([math.cos(phi), math.sin(phi), 0.0])
        rotations.append(np.stack([np.cross(y, down), y, down], axis=1))
        kinds.append(0)
    for kind, pitch in [(1, 0.0)] + [(2, float(p)) for p in tilted_pitches]:
        for j in range(side_yaws):
            theta = 2.0 * math.pi * j / side_yaws
            beta = math.radians(pitch)
            a = np.array([math.cos(theta) * math.cos(beta), math.sin(theta) * math.cos(beta), -math.sin(beta)])
            h = np.array([-math.sin(theta), math.cos(theta), 0.0])  # horizontal, across the approach
            v = np.cross(a, h)  # across the approach in its vertical plane (straight up for a level approach)
            for roll in side_rolls:
                psi = math.radians(float(roll))
                y = math.cos(psi) * h + math.sin(psi) * v
                rotations.append(np.stack([np.cross(y, a), y, a], axis=1))
                kinds.append(kind)
    rotations, kinds = np.asarray(rotations, dtype=np.float64), np.asarray(kinds, dtype=np.int8)
    rotations.flags.writeable = kinds.flags.writeable = False
    return rotations, kinds


def _anchors(union: np.ndarray, points_grid: np.ndarray | None) -> np.ndarray:
    """Surface voxel centres of the union of completions, and observed points inside the grid."""
    surface = union & ~ndimage.binary_erosion(union, border_value=0)
    anchors = [np.argwhere(surface).astype(np.float64) + 0.5]
    if points_grid is not None and len(points_grid):
        n = union.shape[0]
        voxels = np.floor(points_grid).astype(np.int64)
        voxels = voxels[np.all((voxels >= 0) & (voxels < n), axis=1)]
        # Distinct voxels in x, y, z lexicographic order: unique flat indices (row-wise unique is far slower).
        flat = np.unique(np.ravel_multi_index(tuple(voxels.T), union.shape))
        flat = flat[~surface.ravel()[flat]]
        anchors.append(np.stack(np.unravel_index(flat, union.shape), axis=1).astype(np.float64) + 0.5)
    return np.concatenate(anchors, axis=0)


def _anchor_weights(union: np.ndarray, anchors: np.ndarray, bias: float) -> np.ndarray:
    """Draw probability of each anchor: ``density ** -bias`` (see ``GraspConfig.thin_anchor_bias``), summing to 1."""
    if bias == 0.0:
        return np.full(len(anchors), 1.0 / len(anchors))
    density = ndimage.uniform_filter(union.astype(np.float32), size=5, mode="constant")
    voxels = np.clip(np.floor(anchors).astype(np.int64), 0, union.shape[0] - 1)
    weights = np.maximum(density[tuple(voxels.T)].astype(np.float64), 1.0 / 125) ** -bias
    return weights / weights.sum()


def _run_through(bits: PackedGrids, slices: np.ndarray, centre: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(W, n, K) occupied-slice words -> first and last slice of each completion's run through slice ``centre``.

    Returns lo, hi (K, S) and whether the centre slice is occupied (K, S); lo/hi are meaningless where not.
    """
    # Bit s of the running AND outwards from the centre stays set while completion s's run lasts.
    left = bits.count(np.bitwise_and.accumulate(slices[:, centre::-1], axis=1))
    right = bits.count(np.bitwise_and.accumulate(slices[:, centre:], axis=1))
    return centre + 1 - left, centre - 1 + right, bits.unpack(slices[:, centre])


def generate_candidates(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None = None,
                        config: GraspConfig | None = None, support_z: float | None = None,
                        known_occupied: np.ndarray | None = None,
                        allowed: Callable[[GraspCandidates], np.ndarray] | None = None) -> GraspCandidates:
    """Grasp candidates from the completions (and the observed points); see the package docstring.

    Args:
        occupancy: (S, N, N, N) bool completions.
        pose: grid pose (grid -> camera).
        points: (M, 3) observed points in the camera frame (more anchors; support plane), or None.
        config: options (default :class:`GraspConfig`).
        support_z: support-plane height in grid voxels; None = :func:`estimate_support_height`.
        known_occupied: (N, N, N) observed voxels, for the support plane when ``points`` is None.
        allowed: candidates (grid coordinates, final widths) -> (K,) bool, the ones the surroundings allow
            (e.g. approaches clear of known clutter); applied before the ``max_candidates`` subset, drawing
            up to ``config.draw_rounds`` rounds of raw pairs until that many pass.

    Returns:
        At most ``config.max_candidates`` candidates in grid coordinates, in a deterministic order.
    """
    config = config or GraspConfig()
    occupancy = check_occupancy(occupancy, pose)
    points = check_points(points)
    if support_z is None:
        support_z = estimate_support_height(occupancy, pose, points, known_occupied)
    return candidates_from_packed(PackedGrids(occupancy), occupancy.any(axis=0), pose, points, config, support_z,
                                  allowed)


def candidates_from_packed(bits: PackedGrids, union: np.ndarray, pose: GridPose, points: np.ndarray | None,
                           config: GraspConfig, support_z: float,
                           allowed: Callable[[GraspCandidates], np.ndarray] | None = None) -> GraspCandidates:
    """:func:`generate_candidates` on checked input and completions packed once (the planner scores on them too).

    Args:
        bits: the completions, packed.
        union: (N, N, N) bool, voxels occupied in any completion.
        pose, points, config, support_z, allowed: as :func:`generate_candidates` (points checked, or None).
    """
    points_grid = pose.camera_to_grid(points) if points is not None else None
    anchors = _anchors(union, points_grid)
    rotations_all, kinds_all = _orientations(config.top_yaws, config.side_yaws, tuple(config.side_rolls),
                                             tuple(config.tilted_pitches))
    if len(anchors) == 0:
        return GraspCandidates.empty()
    rng = np.random.default_rng(config.seed)
    total = len(anchors) * len(rotations_all)
    raw = int(min(total, math.ceil(config.oversample * config.max_candidates)))
    if raw == total:
        anchor_id, orient_id = np.divmod(np.arange(total), len(rotations_all))
        (origins, rot, widths, orient_id), _ = _placed(bits, union, anchors[anchor_id], orient_id, rotations_all,
                                                       kinds_all, pose, config, support_z, allowed)
    else:
        anchor_p = _anchor_weights(union, anchors, config.thin_anchor_bias)
        found: list[tuple[np.ndarray, ...]] = []
        # Where ``allowed`` rejects candidates (a hand in a cupboard may come in from one side only), draw again
        # until max_candidates distinct ones pass: a filter must not leave the planner the handful of candidates
        # it happened to draw first (in the grasp trials' cupboard 19 of 500 remained, and the true shape's best
        # handle pinch was often not among them). A round the filter takes nothing from ends the draws.
        for _ in range(config.draw_rounds if allowed is not None else 1):
            anchor_id = rng.choice(len(anchors), size=raw, p=anchor_p)
            orient_id = rng.integers(len(rotations_all), size=raw)
            anchor_id, orient_id = np.divmod(np.unique(anchor_id * len(rotations_all) + orient_id),
                                             len(rotations_all))
            placed, rejected = _placed(bits, union, anchors[anchor_id], orient_id, rotations_all, kinds_all, pose,
                                       config, support_z, allowed)
            found.append(placed)
            origins, rot, widths, orient_id = (np.concatenate(parts) for parts in zip(*found, strict=True))
            if not rejected or len(_distinct(origins, orient_id)) >= config.max_candidates:
                break

    # 3. Drop near-duplicates (same orientation, origin within half a voxel), keep a seeded subset.
    index = _distinct(origins, orient_id)
    if len(index) > config.max_candidates:
        index = np.sort(rng.choice(index, size=config.max_candidates, replace=False))
    return GraspCandidates(origins[index], rot[index], widths[index], kinds_all[orient_id[index]])


def _distinct(origins: np.ndarray, orient_id: np.ndarray) -> np.ndarray:
    """Indices of the first of each group of near-duplicates (same orientation, origin within half a voxel), sorted."""
    key = np.concatenate([orient_id[:, None], np.round(origins * 2.0).astype(np.int64)], axis=1)
    _, first_index = np.unique(key, axis=0, return_index=True)
    return np.sort(first_index)


def _placed(bits: PackedGrids, union: np.ndarray, p: np.ndarray, orient_id: np.ndarray, rotations_all: np.ndarray,
            kinds_all: np.ndarray, pose: GridPose, config: GraspConfig, support_z: float,
            allowed: Callable[[GraspCandidates], np.ndarray] | None) -> tuple[tuple[np.ndarray, ...], int]:
    """Anchors ``p`` (K, 3) with orientations ``orient_id`` -> the grasps placed on them that fit and ``allowed``
    accepts (origins, rotations, widths, orientation ids), and how many fitting ones ``allowed`` rejected."""
    dims = VoxelDims.of(config, pose.voxel_size)
    rot = rotations_all[orient_id]
    approach = rot[:, :, 2]

    # 1. Slide along the approach until the palm (one voxel short) meets the union of the completions.
    fl, fw, ft, wmax = dims.finger_length, dims.finger_width, dims.finger_thickness, dims.max_opening
    reach = fl + dims.palm_depth
    n_u = lattice_count(reach, 1.0)
    counts = (lattice_count(fw, 1.0), lattice_count(wmax + 2 * ft, 1.0), n_u)
    # Anchors are voxel centres: the palm's column reads voxels at offsets fixed per orientation.
    hit_rows = voxel_box_rows(union, np.floor(p).astype(np.int64), rotations_all, orient_id,
                              np.array([0.0, 0.0, -reach / 2]), np.array([fw / 2, wmax / 2 + ft, reach / 2]),
                              counts)  # (n_u, K)
    u_values = np.linspace(-reach, 0.0, n_u)  # rows: u from -reach (far behind) to 0 (anchor)
    first = np.where(hit_rows.any(axis=0), u_values[np.argmax(hit_rows, axis=0)], 0.0)
    t = first + fl - 1.0
    # Approaching downwards: stop where the lowest gripper part would reach the support plane.
    low0 = lowest_point(p, rot, np.full(len(p), wmax), dims) - p[:, 2]  # lowest z relative to the origin
    az = approach[:, 2]
    going_down = az < -1e-6
    limit = (p[:, 2] + low0 - (support_z + dims.plane_clearance)) / np.where(going_down, -az, 1.0)
    t = np.where(going_down, np.minimum(t, limit), t)
    # Shallow variants: fingertips only this far past the first contact (distinct from the deepest grasp).
    depths = [t]
    pair_of_depth = [np.arange(len(t))]
    for depth in config.shallow_depths:
        shallow = first + depth / pose.voxel_size
        distinct = shallow < t - 0.5
        depths.append(shallow[distinct])
        pair_of_depth.append(np.flatnonzero(distinct))
    pick = np.concatenate(pair_of_depth)
    p, rot, orient_id, t = p[pick], rot[pick], orient_id[pick], np.concatenate(depths)
    keep = t > 0.0
    p, rot, t, orient_id = p[keep], rot[keep], t[keep], orient_id[keep]
    origins = p + t[:, None] * rot[:, :, 2]

    # 2. Sweep the closing axis (twice the opening, half-voxel steps); the completions whose run of object
    # through the anchor fits the gripper set the width and the centre.
    half_n = int(math.floor(wmax / 0.5 + 1e-6))
    n_y = 2 * half_n + 1
    # Exact half-voxel spacing (extents come in half voxels), offset by a quarter voxel so that, along grid
    # axes, samples never sit on voxel faces (anchors are voxel centres): edges are then found to +-0.25.
    ys = (np.arange(n_y) - half_n) * 0.5 + 0.25
    slices = box_or(bits.data, bits.padded, origins, rot, np.array([0.0, 0.25, -fl / 2]),
                    np.array([fw / 2, half_n * 0.5, fl / 2]), (lattice_count(fw, 1.0), n_y, lattice_count(fl, 1.0)),
                    keep=(1,))  # (W, n_y, K)
    lo, hi, has = _run_through(bits, slices, half_n)
    extent = ys[hi] - ys[lo] + 0.5
    # Gap left between each pad and the run's outer voxel faces (``GraspConfig.surface_at_voxel_centres``).
    gap = max(dims.clearance - 0.5, 0.0) if config.surface_at_voxel_centres else dims.clearance
    fits = has & (lo > 0) & (hi < n_y - 1) & (extent + 2 * gap <= wmax + 1e-9)
    ok = fits.any(axis=1)
    lo_u = np.where(ok, np.where(fits, lo, n_y).min(axis=1), 0)
    hi_u = np.where(ok, np.where(fits, hi, -1).max(axis=1), 0)
    widths = ys[hi_u] - ys[lo_u] + 0.5 + 2 * gap
    ok &= widths <= wmax + 1e-9
    origins = origins + (0.5 * (ys[lo_u] + ys[hi_u]))[:, None] * rot[:, :, 1]
    origins, rot, widths, orient_id = origins[ok], rot[ok], widths[ok], orient_id[ok]
    if allowed is None:
        return (origins, rot, widths, orient_id), 0
    keep = np.asarray(allowed(GraspCandidates(origins, rot, widths, kinds_all[orient_id])), dtype=bool)
    return (origins[keep], rot[keep], widths[keep], orient_id[keep]), int(np.count_nonzero(~keep))
