"""Parallel-jaw grasps chosen against many sampled completions: grasps that hold whatever the hidden side is.

One call from completions to ranked grasps::

    grasps = plan_grasps(occupancy, observation.pose, observation.points, GraspConfig())
    grasps.poses[0]        # (4, 4) best grasp in the camera frame
    grasps.scores[0]       # fraction of the completions it holds for
    position, quaternion = grasps.position_quaternions()   # (K, 3), (K, 4) xyzw, for geometry_msgs/Pose

Pose convention (that of ``pssnet_interfaces/srv/SampleCompletions``): the origin lies between the
fingertips, z is the approach direction (the hand moves along +z onto the object), y is the closing axis,
x = y cross z (right-handed, REP 103). Widths are the opening the grasp needs, in metres.

Everything internal works in *grid coordinates* (voxel units, z up; see :mod:`pssnet_core.geometry`).
The gripper, in its own frame (origin between the fingertips, lengths in voxels), is three kinds of box:

- closing region: the space between the fingers, ``|x| <= finger_width/2``, ``|y| <= width/2``,
  ``-finger_length <= z <= 0``;
- two fingers: ``|x| <= finger_width/2``, ``width/2 <= |y| <= width/2 + finger_thickness``, same z;
- palm: ``|x| <= finger_width/2``, ``|y| <= max_opening/2 + finger_thickness``,
  ``-finger_length - palm_depth <= z <= -finger_length`` (the palm spans the open hand whatever the width).

How a grasp is judged against one completion (:func:`score_grasps`). A grasp *holds* for completion s when
  1. its opening fits the gripper (``width <= max_opening``),
  2. no part of the gripper reaches below the support plane (analytic, from the boxes' corners),
  3. the closing region contains at least ``min_object_width`` of object along the closing axis, and
  4. neither finger nor the palm overlaps an occupied voxel of s.
Volumes are tested on lattices of sample points (spacing at most one voxel along every axis, faces
included) transformed into the grid; a part "overlaps" s when any of its sample points falls in an
occupied voxel of s, i.e. the part overlaps the occupied voxel cubes to within the lattice resolution.
All completions are tested at once: the S occupancy grids are packed into one bit word per voxel (bit s =
completion s), so each sample point costs one gather and a bitwise OR, whatever S.

Score = fraction of completions the grasp holds for. Ties are broken by the *secondary* term in [0, 1]:
``0.8 * pad contact + 0.2 * opening margin``. Pad contact is the mean, over the completions the grasp
holds for, of the fraction of the two finger pads (finger-width x finger-length faces, sampled on the
lattice) that touch the object when the fingers close on it: a pad cell touches when the object along its
line across the closing region lies within one voxel of the pad's first contact. Deep grasps on faces
square to the closing axis touch with the whole pad; fingertip grasps, and grasps across a box's corner or
on a slanted face, touch with a small part. Opening margin is ``(max_opening - width) / max_opening``:
spare opening tolerates pose error. Contact normals are not checked otherwise (voxel normals are coarse).

Candidates (:func:`generate_candidates`). Anchors are the surface voxels of the union of the completions
plus the observed points; orientations are a top approach (straight down, ``top_yaws`` closing axes about
the vertical) and side approaches (``side_yaws`` horizontal approach directions around the vertical, each
with the closing axis horizontal and/or vertical: ``side_rolls``). For each (anchor, orientation) pair the
hand slides along the approach until the palm would touch the union of the completions (one voxel short)
or, approaching downwards, until the fingertips would reach the support plane. Then the closing axis is
swept at full opening (half-voxel resolution): each completion's object extent along the closing axis is
swept over twice the opening (half-voxel resolution): in each completion, the run of object along the
closing axis through the anchor is measured; the completions whose run fits the gripper (with
``clearance`` on both sides) define the needed opening, ``width = their combined extent + 2 clearance``
(the widest completion's extent when the runs share a side), and the grasp is re-centred on it. A
completion whose run does not fit is not held by this grasp; a run stops at the first empty slice, so a
mug's rim is pinched wall by wall rather than across the whole cup. Near-duplicates are dropped; at most
``max_candidates`` are kept (a seeded random subset). Deterministic given the seed.

Support plane: the grid is gravity aligned, so the plane is the horizontal plane ``z = support_z`` (grid
voxel units). Unless given, :func:`estimate_support_height` takes the lower of (a) the lowest observed point
(or, without points, the bottom face of the lowest known-occupied layer) and (b) the median over completions
of the bottom face of each completion's lowest occupied layer: the object rests on the plane, so the plane
is at or below everything seen, and lower still where the completions say the hidden bottom reaches lower
(the median ignores a single stray sample).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from pssnet_core.geometry import GridPose

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "approach_orientations",
    "GraspConfig",
    "GraspError",
    "GraspSet",
    "GripperConfig",
    "GraspCandidates",
    "GraspChecks",
    "SingleCompletionChoice",
    "check_grasps",
    "estimate_support_height",
    "generate_candidates",
    "matrix_to_position_quaternion",
    "plan_grasps",
    "plot_grasps",
    "score_grasps",
    "single_completion_choice",
]

KIND_NAMES = ("top", "side")


class GraspError(ValueError):
    """Grasp planning input or configuration is invalid; the message says exactly what is wrong."""


# ------------------------------------------------------------------------------------------- configs


@dataclass(frozen=True)
class GripperConfig:
    """A parallel-jaw gripper (defaults: about a Franka Hand; a Robotiq 2F-85 opens 0.085 m).

    Attributes:
        max_opening: largest distance between the finger pads (metres).
        finger_length: how far the fingers reach from the palm to the fingertips along the approach (metres).
        finger_width: finger extent across the closing plane, along the gripper x axis (metres).
        finger_thickness: finger extent along the closing axis (metres).
        palm_depth: thickness of the palm (hand body) behind the fingers along the approach (metres).
        min_object_width: less object than this between the fingers along the closing axis is not held (metres).
    """

    max_opening: float = 0.08
    finger_length: float = 0.05
    finger_width: float = 0.02
    finger_thickness: float = 0.01
    palm_depth: float = 0.02
    min_object_width: float = 0.005

    def __post_init__(self) -> None:
        values = {"max_opening": self.max_opening, "finger_length": self.finger_length,
                  "finger_width": self.finger_width, "finger_thickness": self.finger_thickness,
                  "palm_depth": self.palm_depth, "min_object_width": self.min_object_width}
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise GraspError(f"gripper {name} must be a finite number of metres, got {value!r}")
        if not 0.005 <= self.max_opening <= 0.5:
            raise GraspError(f"gripper max_opening must be in [0.005, 0.5] m, got {self.max_opening}")
        for name in ("finger_length", "finger_width", "finger_thickness", "palm_depth"):
            if not 0.001 <= values[name] <= 0.5:
                raise GraspError(f"gripper {name} must be in [0.001, 0.5] m, got {values[name]}")
        if not 0.0 <= self.min_object_width < self.max_opening:
            raise GraspError(f"gripper min_object_width must be in [0, max_opening={self.max_opening}) m, "
                             f"got {self.min_object_width}")


@dataclass(frozen=True)
class GraspConfig:
    """Candidate generation and scoring options.

    Attributes:
        gripper: the gripper.
        max_candidates: at most this many candidates are scored.
        top_yaws: closing-axis angles of the top (straight-down) approach, evenly over 180 degrees; 0 = none.
        side_yaws: horizontal approach directions, evenly over 360 degrees; 0 = no side grasps.
        side_rolls: closing-axis angles (degrees) of side grasps about the approach: 0 = horizontal,
            90 = vertical.
        clearance: free space left between each finger pad and the widest completion (metres).
        plane_clearance: every gripper part stays at least this far above the support plane (metres).
        oversample: raw (anchor, orientation) pairs generated per kept candidate, before de-duplication.
        seed: seed of the anchor/orientation sampling and of the final subset.
    """

    gripper: GripperConfig = field(default_factory=GripperConfig)
    max_candidates: int = 500
    top_yaws: int = 8
    side_yaws: int = 12
    side_rolls: tuple[float, ...] = (0.0, 90.0)
    clearance: float = 0.005
    plane_clearance: float = 0.0
    oversample: float = 3.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.gripper, GripperConfig):
            raise GraspError(f"gripper must be a GripperConfig, got {type(self.gripper).__name__}")
        for name in ("max_candidates", "top_yaws", "side_yaws", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise GraspError(f"{name} must be an integer, got {value!r}")
        if not 1 <= self.max_candidates <= 100_000:
            raise GraspError(f"max_candidates must be in [1, 100000], got {self.max_candidates}")
        if not 0 <= self.top_yaws <= 180 or not 0 <= self.side_yaws <= 360:
            raise GraspError(f"top_yaws must be in [0, 180] and side_yaws in [0, 360], got {self.top_yaws} "
                             f"and {self.side_yaws}")
        rolls = tuple(float(r) for r in self.side_rolls)
        if not all(math.isfinite(r) for r in rolls):
            raise GraspError(f"side_rolls must be finite degrees, got {self.side_rolls}")
        if self.top_yaws == 0 and (self.side_yaws == 0 or not rolls):
            raise GraspError("no approach direction: set top_yaws > 0, or side_yaws > 0 with side_rolls")
        if not 0.0 <= self.clearance < self.gripper.max_opening / 2:
            raise GraspError(f"clearance must be in [0, max_opening/2) m, got {self.clearance}")
        if not 0.0 <= self.plane_clearance <= 0.1:
            raise GraspError(f"plane_clearance must be in [0, 0.1] m, got {self.plane_clearance}")
        if not 1.0 <= self.oversample <= 20.0:
            raise GraspError(f"oversample must be in [1, 20], got {self.oversample}")
        if self.seed < 0:
            raise GraspError(f"seed must be >= 0, got {self.seed}")


@dataclass(frozen=True)
class _Dims:
    """Gripper dimensions in voxels."""

    max_opening: float
    finger_length: float
    finger_width: float
    finger_thickness: float
    palm_depth: float
    min_object_width: float
    clearance: float
    plane_clearance: float

    @classmethod
    def of(cls, config: GraspConfig, voxel_size: float) -> _Dims:
        g = config.gripper
        return cls(g.max_opening / voxel_size, g.finger_length / voxel_size, g.finger_width / voxel_size,
                   g.finger_thickness / voxel_size, g.palm_depth / voxel_size, g.min_object_width / voxel_size,
                   config.clearance / voxel_size, config.plane_clearance / voxel_size)


# ------------------------------------------------------------------------------------------- results


@dataclass
class GraspCandidates:
    """Grasps in grid coordinates (voxel units, z up), before or after scoring.

    Attributes:
        origins: (K, 3) point between the fingertips.
        rotations: (K, 3, 3) columns are the gripper x, y (closing) and z (approach) axes in the grid frame.
        widths: (K,) opening needed, voxels.
        kinds: (K,) int8 index into :data:`KIND_NAMES` ("top", "side").
    """

    origins: np.ndarray
    rotations: np.ndarray
    widths: np.ndarray
    kinds: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)

    def subset(self, index: np.ndarray) -> GraspCandidates:
        return GraspCandidates(self.origins[index], self.rotations[index], self.widths[index], self.kinds[index])

    @classmethod
    def empty(cls) -> GraspCandidates:
        return cls(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int8))


@dataclass
class GraspSet:
    """Grasps ranked best first, scored against every completion. Camera-frame fields use metres.

    Attributes:
        poses: (K, 4, 4) camera-frame poses (origin between the fingertips, z approach, y closing axis).
        widths: (K,) opening needed (metres).
        scores: (K,) in [0, 1]: fraction of the completions the grasp holds for.
        holds: (K, S) whether grasp k holds for completion s.
        secondary: (K,) tie-break term in [0, 1] (see the module docstring).
        kinds: (K,) "top" or "side".
        grid: the same grasps in grid coordinates.
        support_z: height of the support plane in grid coordinates (voxels).
        voxel_size: voxel edge (metres).
    """

    poses: np.ndarray
    widths: np.ndarray
    scores: np.ndarray
    holds: np.ndarray
    secondary: np.ndarray
    kinds: np.ndarray
    grid: GraspCandidates
    support_z: float
    voxel_size: float

    def __len__(self) -> int:
        return len(self.scores)

    @property
    def num_completions(self) -> int:
        return int(self.holds.shape[1])

    def subset(self, index: np.ndarray | slice) -> GraspSet:
        """The grasps at ``index`` (keeps their order)."""
        index = np.arange(len(self))[index]
        return GraspSet(self.poses[index], self.widths[index], self.scores[index], self.holds[index],
                        self.secondary[index], self.kinds[index], self.grid.subset(index), self.support_z,
                        self.voxel_size)

    def top(self, k: int, min_score: float = 0.0) -> GraspSet:
        """The best ``k`` grasps whose score is at least ``min_score``."""
        if k < 0:
            raise GraspError(f"k must be >= 0, got {k}")
        keep = np.flatnonzero(self.scores >= min_score)[:k]
        return self.subset(keep)

    def position_quaternions(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3) positions and (K, 4) unit quaternions (x, y, z, w) of :attr:`poses`."""
        if len(self) == 0:
            return np.zeros((0, 3)), np.zeros((0, 4))
        return self.poses[:, :3, 3].copy(), Rotation.from_matrix(self.poses[:, :3, :3]).as_quat()


@dataclass
class SingleCompletionChoice:
    """The grasp one completion alone would choose, and how it fares against all completions.

    Attributes:
        index: the completion that chose.
        grasp: that grasp (a GraspSet of length 0 or 1) scored against *all* completions.
        score_alone: its score against completion ``index`` alone (1.0 when a grasp was found).
        score_all: its score against all completions (0.0 when none was found).
    """

    index: int
    grasp: GraspSet
    score_alone: float
    score_all: float


def matrix_to_position_quaternion(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 rigid transform -> ((3,) position, (4,) unit quaternion x, y, z, w) as geometry_msgs/Pose wants.

    Raises:
        GraspError: not a finite 4x4 matrix with a rotation block.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise GraspError(f"pose must be a finite 4x4 matrix, got shape {matrix.shape}")
    r = matrix[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise GraspError("pose rotation block is not a proper rotation")
    return matrix[:3, 3].copy(), Rotation.from_matrix(r).as_quat()


# ------------------------------------------------------------------------------------- bit-packed grids


class _Bits:
    """S occupancy grids packed into one little-endian bit word per voxel (bit s = completion s).

    The grid is padded by one empty voxel on every side; lattice points are clipped into the padded grid,
    so every point outside the grid reads as empty.
    """

    def __init__(self, occupancy: np.ndarray) -> None:
        s, n = occupancy.shape[0], occupancy.shape[1]
        self.num = s
        self.size = n
        self.padded = n + 2
        nbytes = (s + 7) // 8
        packed = np.packbits(np.moveaxis(occupancy, 0, -1), axis=-1, bitorder="little")  # (n, n, n, nbytes)
        if nbytes <= 8:
            width = next(b for b in (1, 2, 4, 8) if b >= nbytes)
            self.words = 1
        else:
            width = 8 * ((nbytes + 7) // 8)
            self.words = width // 8
        self.nbytes = width
        data = np.zeros((self.padded,) * 3 + (width,), dtype=np.uint8)
        data[1:-1, 1:-1, 1:-1, :nbytes] = packed
        dtype = np.dtype(f"<u{min(width, 8)}")
        flat = data.reshape(-1, width).view(dtype)  # (P^3, words)
        self.data = flat[:, 0].copy() if self.words == 1 else flat.copy()

    def gather(self, index: np.ndarray) -> np.ndarray:
        """Words at flat padded-grid indices: shape (...) or (..., words)."""
        return self.data[index]

    def reduce_or(self, words: np.ndarray, axis: int | tuple[int, ...]) -> np.ndarray:
        return np.bitwise_or.reduce(words, axis=axis)

    def bit_at(self, words: np.ndarray, slice_index: np.ndarray) -> np.ndarray:
        """Bit s of ``words[k, :, slice_index[k, s], :]`` for every completion s.

        Args:
            words: (K, nx, ny, nz) or (K, nx, ny, nz, W) words.
            slice_index: (K, S) index along axis 2 per completion.

        Returns:
            (K, S, nx, nz) bool.
        """
        k = words.shape[0]
        s = np.arange(self.num)
        picked = words[np.arange(k)[:, None], :, slice_index]  # (K, S, nx, nz[, W])
        if self.words > 1:
            picked = np.take_along_axis(picked, (s // 64)[None, :, None, None, None], axis=-1)[..., 0]
            shift = (s % 64).astype(np.uint64)
        else:
            shift = s.astype(picked.dtype)
        return ((picked >> shift[None, :, None, None]) & 1).astype(bool)

    def unpack(self, words: np.ndarray) -> np.ndarray:
        """Words (...) or (..., words) -> (..., S) bool."""
        words = np.ascontiguousarray(words)
        if self.words == 1:
            words = words[..., None]
        raw = words.view(np.uint8)
        return np.unpackbits(raw, axis=-1, bitorder="little")[..., :self.num].astype(bool)


def _lattice(n: int) -> np.ndarray:
    """n evenly spaced values in [-1, 1] (both ends included); [0] when n == 1."""
    return np.zeros(1, np.float32) if n <= 1 else np.linspace(-1.0, 1.0, n, dtype=np.float32)


def _count(extent: float, step: float) -> int:
    """Points covering ``extent`` (both ends) with spacing at most ``step``."""
    return int(math.ceil(extent / step - 1e-6)) + 1 if extent > 0 else 1


def _box_index(bits: _Bits, origins: np.ndarray, rotations: np.ndarray, centre: np.ndarray, half: np.ndarray,
               counts: tuple[int, int, int]) -> np.ndarray:
    """Flat padded-grid indices of a box's lattice points (per candidate centre/half extents, gripper frame).

    Args:
        bits: the packed grids (for the padded size).
        origins: (K, 3) gripper origins (grid).
        rotations: (K, 3, 3) gripper axes as columns (grid).
        centre: (K, 3) or (3,) box centre in the gripper frame.
        half: (K, 3) or (3,) half extents in the gripper frame.
        counts: lattice points along the gripper x, y, z.

    Returns:
        (K, nx, ny, nz) int32 indices; points outside the grid map to an empty padding voxel.
    """
    k = len(origins)
    centre = np.broadcast_to(np.asarray(centre, np.float32), (k, 3))
    half = np.broadcast_to(np.asarray(half, np.float32), (k, 3))
    rot = rotations.astype(np.float32)
    # +1: the padding layer, so that floor == truncation for every point inside the padded grid.
    base = origins.astype(np.float32) + np.float32(1.0)
    local = [centre[:, a, None] + _lattice(counts[a])[None, :] * half[:, a, None] for a in range(3)]  # (K, n_a)
    p = bits.padded
    hi = np.float32(p - 1)
    index = np.zeros((k, *counts), dtype=np.int32)
    coord = np.empty((k, *counts), dtype=np.float32)
    for c, stride in enumerate((p * p, p, 1)):
        tx = local[0] * rot[:, c, 0, None]
        ty = local[1] * rot[:, c, 1, None]
        tz = local[2] * rot[:, c, 2, None] + base[:, c, None]
        np.add(tx[:, :, None, None], ty[:, None, :, None], out=coord)
        coord += tz[:, None, None, :]
        np.clip(coord, np.float32(0.0), hi, out=coord)
        index += coord.astype(np.int32) * np.int32(stride)
    return index


def _lowest_point(origins: np.ndarray, rotations: np.ndarray, widths: np.ndarray, dims: _Dims) -> np.ndarray:
    """(K,) lowest grid z reached by any gripper part (fingers at ``widths``, palm), analytically."""
    k = len(origins)
    fl, fw, ft = dims.finger_length, dims.finger_width, dims.finger_thickness
    centres, halves = [], []
    for sign in (-1.0, 1.0):
        centres.append(np.stack([np.zeros(k), sign * (widths / 2 + ft / 2), np.full(k, -fl / 2)], axis=1))
        halves.append(np.broadcast_to([fw / 2, ft / 2, fl / 2], (k, 3)))
    centres.append(np.broadcast_to([0.0, 0.0, -fl - dims.palm_depth / 2], (k, 3)))
    halves.append(np.broadcast_to([fw / 2, dims.max_opening / 2 + ft, dims.palm_depth / 2], (k, 3)))
    zrow = rotations[:, 2, :]  # (K, 3): grid z of each gripper axis
    lows = [np.einsum("kj,kj->k", zrow, c) - np.einsum("kj,kj->k", np.abs(zrow), h)
            for c, h in zip(centres, halves, strict=True)]
    return origins[:, 2] + np.min(np.stack(lows, axis=1), axis=1)


# ------------------------------------------------------------------------------------------ inputs


def _check_occupancy(occupancy: np.ndarray, pose: GridPose) -> np.ndarray:
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


def _check_points(points: np.ndarray | None) -> np.ndarray | None:
    if points is None:
        return None
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise GraspError(f"observed points must be an (M, 3) array, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise GraspError("observed points contain NaN or Inf")
    return points


def estimate_support_height(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None = None,
                            known_occupied: np.ndarray | None = None) -> float:
    """Height of the horizontal support plane in grid coordinates (voxels); see the module docstring.

    Args:
        occupancy: (S, N, N, N) bool completions.
        pose: the grid pose.
        points: (M, 3) observed points in the camera frame, or None.
        known_occupied: (N, N, N) bool, used when ``points`` is None.

    Raises:
        GraspError: nothing to estimate from (no points, no known-occupied voxel, every completion empty).
    """
    occupancy = _check_occupancy(occupancy, pose)
    points = _check_points(points)
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


# ------------------------------------------------------------------------------------- orientations


def approach_orientations(config: GraspConfig) -> tuple[np.ndarray, np.ndarray]:
    """The candidate orientations: (O, 3, 3) gripper axes (columns x, y, z) in the grid frame, (O,) kinds."""
    rotations, kinds = [], []
    down = np.array([0.0, 0.0, -1.0])
    for i in range(config.top_yaws):
        phi = math.pi * i / config.top_yaws
        y = np.array([math.cos(phi), math.sin(phi), 0.0])
        rotations.append(np.stack([np.cross(y, down), y, down], axis=1))
        kinds.append(0)
    up = np.array([0.0, 0.0, 1.0])
    for j in range(config.side_yaws):
        theta = 2.0 * math.pi * j / config.side_yaws
        a = np.array([math.cos(theta), math.sin(theta), 0.0])
        h = np.cross(up, a)
        for roll in config.side_rolls:
            psi = math.radians(float(roll))
            y = math.cos(psi) * h + math.sin(psi) * up
            rotations.append(np.stack([np.cross(y, a), y, a], axis=1))
            kinds.append(1)
    return np.asarray(rotations, dtype=np.float64), np.asarray(kinds, dtype=np.int8)


# -------------------------------------------------------------------------------------- candidates


def _anchors(union: np.ndarray, points_grid: np.ndarray | None) -> np.ndarray:
    """Surface voxel centres of the union of completions, and observed points inside the grid."""
    surface = union & ~ndimage.binary_erosion(union, border_value=0)
    anchors = [np.argwhere(surface).astype(np.float64) + 0.5]
    if points_grid is not None and len(points_grid):
        n = union.shape[0]
        voxels = np.unique(np.floor(points_grid).astype(np.int64), axis=0)
        voxels = voxels[np.all((voxels >= 0) & (voxels < n), axis=1)]
        extra = voxels[~surface[tuple(voxels.T)]] if len(voxels) else voxels
        anchors.append(extra.astype(np.float64) + 0.5)
    return np.concatenate(anchors, axis=0)


def _extents(slices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., n, S) occupied slices -> first, last occupied slice and whether any, each (..., S)."""
    has = slices.any(axis=-2)
    n = slices.shape[-2]
    lo = np.argmax(slices, axis=-2)
    hi = n - 1 - np.argmax(slices[..., ::-1, :], axis=-2)
    return lo, hi, has


def _run_through(slices: np.ndarray, centre: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, n, S) occupied slices -> first and last slice of each completion's run through slice ``centre``.

    Returns lo, hi (K, S) and whether the centre slice is occupied (K, S); lo/hi are meaningless where not.
    """
    n = slices.shape[1]
    empty = ~slices
    left = empty[:, :centre + 1][:, ::-1]  # from the centre outwards to the left
    lo = np.where(left.any(axis=1), centre + 1 - np.argmax(left, axis=1), 0)
    right = empty[:, centre:]
    hi = np.where(right.any(axis=1), centre + np.argmax(right, axis=1) - 1, n - 1)
    return lo, hi, slices[:, centre]


def generate_candidates(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None = None,
                        config: GraspConfig | None = None, support_z: float | None = None,
                        known_occupied: np.ndarray | None = None,
                        allowed: Callable[[GraspCandidates], np.ndarray] | None = None) -> GraspCandidates:
    """Grasp candidates from the completions (and the observed points); see the module docstring.

    Args:
        occupancy: (S, N, N, N) bool completions.
        pose: grid pose (grid -> camera).
        points: (M, 3) observed points in the camera frame (more anchors; support plane), or None.
        config: options (default :class:`GraspConfig`).
        support_z: support-plane height in grid voxels; None = :func:`estimate_support_height`.
        known_occupied: (N, N, N) observed voxels, for the support plane when ``points`` is None.
        allowed: candidates (grid coordinates, final widths) -> (K,) bool, the ones the surroundings allow
            (e.g. approaches clear of known clutter); applied before the ``max_candidates`` subset.

    Returns:
        At most ``config.max_candidates`` candidates in grid coordinates, in a deterministic order.
    """
    config = config or GraspConfig()
    occupancy = _check_occupancy(occupancy, pose)
    points = _check_points(points)
    if support_z is None:
        support_z = estimate_support_height(occupancy, pose, points, known_occupied)
    dims = _Dims.of(config, pose.voxel_size)
    union = occupancy.any(axis=0)
    points_grid = pose.camera_to_grid(points) if points is not None else None
    anchors = _anchors(union, points_grid)
    rotations_all, kinds_all = approach_orientations(config)
    if len(anchors) == 0:
        return GraspCandidates.empty()
    rng = np.random.default_rng(config.seed)
    total = len(anchors) * len(rotations_all)
    raw = int(min(total, math.ceil(config.oversample * config.max_candidates)))
    pairs = np.arange(total) if raw == total else np.sort(rng.choice(total, size=raw, replace=False))
    anchor_id, orient_id = np.divmod(pairs, len(rotations_all))
    p = anchors[anchor_id]
    rot = rotations_all[orient_id]
    approach = rot[:, :, 2]

    # 1. Slide along the approach until the palm (one voxel short) meets the union of the completions.
    union_bits = _Bits(union[None])
    fl, fw, ft, wmax = dims.finger_length, dims.finger_width, dims.finger_thickness, dims.max_opening
    reach = fl + dims.palm_depth
    n_u = _count(reach, 1.0)
    counts = (_count(fw, 1.0), _count(wmax + 2 * ft, 1.0), n_u)
    column = _box_index(union_bits, p, rot, np.array([0.0, 0.0, -reach / 2]),
                        np.array([fw / 2, wmax / 2 + ft, reach / 2]), counts)
    hit_rows = union_bits.gather(column).any(axis=(1, 2))  # (K, n_u): u from -reach (far behind) to 0 (anchor)
    u_values = np.linspace(-reach, 0.0, n_u)
    first = np.where(hit_rows.any(axis=1), u_values[np.argmax(hit_rows, axis=1)], 0.0)
    t = first + fl - 1.0
    # Approaching downwards: stop where the lowest gripper part would reach the support plane.
    low0 = _lowest_point(p, rot, np.full(len(p), wmax), dims) - p[:, 2]  # lowest z relative to the origin
    az = approach[:, 2]
    going_down = az < -1e-6
    limit = (p[:, 2] + low0 - (support_z + dims.plane_clearance)) / np.where(going_down, -az, 1.0)
    t = np.where(going_down, np.minimum(t, limit), t)
    keep = t > 0.0
    p, rot, t, orient_id = p[keep], rot[keep], t[keep], orient_id[keep]
    origins = p + t[:, None] * rot[:, :, 2]

    # 2. Sweep the closing axis (twice the opening, half-voxel steps); the completions whose run of object
    # through the anchor fits the gripper set the width and the centre.
    bits = _Bits(occupancy)
    half_n = int(math.floor(wmax / 0.5 + 1e-6))
    n_y = 2 * half_n + 1
    # Exact half-voxel spacing (extents come in half voxels), offset by a quarter voxel so that, along grid
    # axes, samples never sit on voxel faces (anchors are voxel centres): edges are then found to +-0.25.
    ys = (np.arange(n_y) - half_n) * 0.5 + 0.25
    sweep = _box_index(bits, origins, rot, np.array([0.0, 0.25, -fl / 2]),
                       np.array([fw / 2, half_n * 0.5, fl / 2]), (_count(fw, 1.0), n_y, _count(fl, 1.0)))
    slices = bits.unpack(bits.reduce_or(bits.gather(sweep), axis=(1, 3)))  # (K, n_y, S)
    lo, hi, has = _run_through(slices, half_n)
    extent = ys[hi] - ys[lo] + 0.5
    fits = has & (lo > 0) & (hi < n_y - 1) & (extent + 2 * dims.clearance <= wmax + 1e-9)
    ok = fits.any(axis=1)
    lo_u = np.where(ok, np.where(fits, lo, n_y).min(axis=1), 0)
    hi_u = np.where(ok, np.where(fits, hi, -1).max(axis=1), 0)
    widths = ys[hi_u] - ys[lo_u] + 0.5 + 2 * dims.clearance
    ok &= widths <= wmax + 1e-9
    origins = origins + (0.5 * (ys[lo_u] + ys[hi_u]))[:, None] * rot[:, :, 1]
    origins, rot, widths, orient_id = origins[ok], rot[ok], widths[ok], orient_id[ok]
    if allowed is not None:
        keep = np.asarray(allowed(GraspCandidates(origins, rot, widths, kinds_all[orient_id])), dtype=bool)
        origins, rot, widths, orient_id = origins[keep], rot[keep], widths[keep], orient_id[keep]

    # 3. Drop near-duplicates (same orientation, origin within half a voxel), keep a seeded subset.
    key = np.concatenate([orient_id[:, None], np.round(origins * 2.0).astype(np.int64)], axis=1)
    _, first_index = np.unique(key, axis=0, return_index=True)
    index = np.sort(first_index)
    if len(index) > config.max_candidates:
        index = np.sort(rng.choice(index, size=config.max_candidates, replace=False))
    return GraspCandidates(origins[index], rot[index], widths[index], kinds_all[orient_id[index]])


# -------------------------------------------------------------------------------------------- scoring


@dataclass
class GraspChecks:
    """Why each grasp holds or not, per completion (see the module docstring for the rules).

    Attributes:
        fits: (K,) the opening fits the gripper.
        above: (K,) no gripper part reaches below the support plane.
        contains: (K, S) the closing region holds at least ``min_object_width`` of object.
        finger_hit: (K, S) a finger overlaps the completion.
        palm_hit: (K, S) the palm overlaps the completion.
        coverage: (K, S) fraction of the finger pads touching the object when the fingers close (0 if none).
    """

    fits: np.ndarray
    above: np.ndarray
    contains: np.ndarray
    finger_hit: np.ndarray
    palm_hit: np.ndarray
    coverage: np.ndarray

    @property
    def holds(self) -> np.ndarray:
        """(K, S) the grasp holds for the completion."""
        return (self.fits & self.above)[:, None] & self.contains & ~self.finger_hit & ~self.palm_hit


def check_grasps(candidates: GraspCandidates, occupancy: np.ndarray, pose: GridPose, support_z: float,
                 config: GraspConfig | None = None) -> GraspChecks:
    """Every test of every grasp against every completion, vectorised over grasps x completions.

    Args:
        candidates: grasps in grid coordinates (widths in voxels).
        occupancy: (S, N, N, N) bool completions.
        pose: the grid pose (for the voxel size).
        support_z: support-plane height (grid voxels).
        config: gripper and clearances.
    """
    config = config or GraspConfig()
    occupancy = _check_occupancy(occupancy, pose)
    k, s = len(candidates), occupancy.shape[0]
    if k == 0:
        none = np.zeros((0, s), dtype=bool)
        return GraspChecks(np.zeros(0, bool), np.zeros(0, bool), none, none, none, np.zeros((0, s)))
    dims = _Dims.of(config, pose.voxel_size)
    fl, fw, ft, wmax = dims.finger_length, dims.finger_width, dims.finger_thickness, dims.max_opening
    origins = np.asarray(candidates.origins, dtype=np.float64)
    rot = np.asarray(candidates.rotations, dtype=np.float64)
    widths = np.asarray(candidates.widths, dtype=np.float64)
    bits = _Bits(occupancy)
    nx, nz = _count(fw, 1.0), _count(fl, 1.0)

    fits = widths <= wmax + 1e-9
    above = _lowest_point(origins, rot, widths, dims) >= support_z + dims.plane_clearance - 1e-6

    # Closing region: the object's extent along the closing axis, and which pad cells face object.
    n_y = _count(wmax, 1.0)
    closing = bits.gather(_box_index(bits, origins, rot, np.array([0.0, 0.0, -fl / 2]),
                                     np.stack([np.full(k, fw / 2), widths / 2, np.full(k, fl / 2)], axis=1),
                                     (nx, n_y, nz)))
    slices = bits.unpack(bits.reduce_or(closing, axis=(1, 3)))  # (K, n_y, S)
    lo, hi, has = _extents(slices)
    extent = (hi - lo + 1) * (widths / (n_y - 1))[:, None]
    contains = has & (extent >= dims.min_object_width - 1e-9)
    # Pad contact: closing each finger until it touches completion s (slice lo / hi), the pad cells whose
    # column meets object within one voxel of that first touch. Prefix ORs along y give "object at or before
    # this slice" per cell for all completions at once; then bit s is read at completion s's touch slice.
    tol = np.ceil(1.0 / (widths / (n_y - 1)) - 1e-9).astype(np.int64)[:, None]  # slices in one voxel
    coverage = np.zeros((k, s))
    for words, touch in ((closing, lo), (closing[:, :, ::-1], n_y - 1 - hi)):
        prefix = np.bitwise_or.accumulate(words, axis=2)
        coverage += bits.bit_at(prefix, np.clip(touch + tol, 0, n_y - 1)).mean(axis=(2, 3))
    coverage = np.where(has, coverage / 2.0, 0.0)

    # Fingers and palm.
    finger_hit = np.zeros((k, s), dtype=bool)
    for sign in (-1.0, 1.0):
        centre = np.stack([np.zeros(k), sign * (widths / 2 + ft / 2), np.full(k, -fl / 2)], axis=1)
        words = bits.gather(_box_index(bits, origins, rot, centre, np.array([fw / 2, ft / 2, fl / 2]),
                                       (nx, _count(ft, 1.0), nz)))
        finger_hit |= bits.unpack(bits.reduce_or(words, axis=(1, 2, 3)))
    palm = bits.gather(_box_index(bits, origins, rot, np.array([0.0, 0.0, -fl - dims.palm_depth / 2]),
                                  np.array([fw / 2, wmax / 2 + ft, dims.palm_depth / 2]),
                                  (nx, _count(wmax + 2 * ft, 1.0), _count(dims.palm_depth, 1.0))))
    palm_hit = bits.unpack(bits.reduce_or(palm, axis=(1, 2, 3)))
    return GraspChecks(fits, above, contains, finger_hit, palm_hit, coverage)


def score_grasps(candidates: GraspCandidates, occupancy: np.ndarray, pose: GridPose, support_z: float,
                 config: GraspConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Whether each grasp holds for each completion, vectorised over grasps x completions.

    Args:
        candidates: grasps in grid coordinates (widths in voxels).
        occupancy: (S, N, N, N) bool completions.
        pose: the grid pose (for the voxel size).
        support_z: support-plane height (grid voxels).
        config: gripper and clearances.

    Returns:
        holds (K, S) bool, and the secondary tie-break term (K,) in [0, 1] (see the module docstring).
    """
    config = config or GraspConfig()
    checks = check_grasps(candidates, occupancy, pose, support_z, config)
    holds = checks.holds
    n_held = holds.sum(axis=1)
    coverage = np.where(n_held > 0, (checks.coverage * holds).sum(axis=1) / np.maximum(n_held, 1), 0.0)
    wmax = config.gripper.max_opening / pose.voxel_size
    margin = np.clip((wmax - np.asarray(candidates.widths, dtype=np.float64)) / wmax, 0.0, 1.0)
    return holds, 0.8 * coverage + 0.2 * margin


# ------------------------------------------------------------------------------------------ planning


def _to_grasp_set(candidates: GraspCandidates, holds: np.ndarray, secondary: np.ndarray, pose: GridPose,
                  support_z: float) -> GraspSet:
    scores = holds.mean(axis=1) if holds.shape[1] else np.zeros(len(candidates))
    order = np.lexsort((-secondary, -scores))  # score first, then the secondary term; stable
    c = candidates.subset(order)
    poses = np.tile(np.eye(4), (len(c), 1, 1))
    poses[:, :3, :3] = np.einsum("ij,kjl->kil", pose.rotation, c.rotations)
    poses[:, :3, 3] = pose.grid_to_camera(c.origins) if len(c) else np.zeros((0, 3))
    kinds = np.array([KIND_NAMES[i] for i in c.kinds], dtype=object)
    return GraspSet(poses=poses, widths=c.widths * pose.voxel_size, scores=scores[order], holds=holds[order],
                    secondary=secondary[order], kinds=kinds, grid=c, support_z=float(support_z),
                    voxel_size=float(pose.voxel_size))


def plan_grasps(occupancy: np.ndarray, pose: GridPose, points: np.ndarray | None = None,
                config: GraspConfig | None = None, known_occupied: np.ndarray | None = None,
                support_z: float | None = None,
                allowed: Callable[[GraspCandidates], np.ndarray] | None = None) -> GraspSet:
    """Completions in, grasps ranked by the fraction of completions they hold for out.

    Args:
        occupancy: (S, N, N, N) bool sampled completions (floats are thresholded at 0.5).
        pose: grid pose of the completions (grid -> camera frame), e.g. ``Observation.pose``.
        points: (M, 3) observed object points in the camera frame (``Observation.points``), or None.
        config: gripper, candidate and scoring options (default :class:`GraspConfig`).
        known_occupied: (N, N, N) observed voxels; places the support plane when ``points`` is None.
        support_z: support-plane height in grid voxels; None = :func:`estimate_support_height`.
        allowed: restricts the candidates (see :func:`generate_candidates`).

    Returns:
        The scored candidates, best first (possibly empty when no completion has any voxel the gripper fits).

    Raises:
        GraspError: malformed input (the message says what is wrong).
    """
    config = config or GraspConfig()
    occupancy = _check_occupancy(occupancy, pose)
    points = _check_points(points)
    if support_z is None:
        support_z = estimate_support_height(occupancy, pose, points, known_occupied)
    candidates = generate_candidates(occupancy, pose, points, config, support_z, allowed=allowed)
    holds, secondary = score_grasps(candidates, occupancy, pose, support_z, config)
    return _to_grasp_set(candidates, holds, secondary, pose, support_z)


def single_completion_choice(occupancy: np.ndarray, pose: GridPose, index: int, points: np.ndarray | None = None,
                             config: GraspConfig | None = None, known_occupied: np.ndarray | None = None,
                             support_z: float | None = None) -> SingleCompletionChoice:
    """The grasp that completion ``index`` alone would choose, re-scored against all the completions.

    Candidates are generated and ranked from that one completion (and the observed points), exactly as
    :func:`plan_grasps` would if the network had returned only it; the support plane is the one estimated
    from all completions, so the two choices are judged alike.
    """
    config = config or GraspConfig()
    occupancy = _check_occupancy(occupancy, pose)
    if not 0 <= index < occupancy.shape[0]:
        raise GraspError(f"completion index {index} is out of range [0, {occupancy.shape[0]})")
    points = _check_points(points)
    if support_z is None:
        support_z = estimate_support_height(occupancy, pose, points, known_occupied)
    alone = plan_grasps(occupancy[index:index + 1], pose, points, config, support_z=support_z)
    if len(alone) == 0 or alone.scores[0] <= 0.0:
        empty = _to_grasp_set(GraspCandidates.empty(), np.zeros((0, occupancy.shape[0]), bool), np.zeros(0),
                              pose, support_z)
        return SingleCompletionChoice(index=index, grasp=empty, score_alone=0.0, score_all=0.0)
    best = alone.grid.subset(np.array([0]))
    holds, secondary = score_grasps(best, occupancy, pose, support_z, config)
    grasp = _to_grasp_set(best, holds, secondary, pose, support_z)
    return SingleCompletionChoice(index=index, grasp=grasp, score_alone=float(alone.scores[0]),
                                  score_all=float(grasp.scores[0]))


# ------------------------------------------------------------------------------------------ plotting


def gripper_lines(grasps: GraspSet, config: GraspConfig | None = None) -> np.ndarray:
    """(K, 4, 2, 3) camera-frame line segments drawing each gripper: two fingers, the palm bar, the stem."""
    config = config or GraspConfig()
    g = config.gripper
    lines = np.zeros((len(grasps), 4, 2, 3))
    for k in range(len(grasps)):
        half = grasps.widths[k] / 2
        local = np.array([
            [[0, -half, 0], [0, -half, -g.finger_length]],
            [[0, half, 0], [0, half, -g.finger_length]],
            [[0, -half, -g.finger_length], [0, half, -g.finger_length]],
            [[0, 0, -g.finger_length], [0, 0, -g.finger_length - max(g.palm_depth, 0.03)]],
        ])
        lines[k] = local @ grasps.poses[k, :3, :3].T + grasps.poses[k, :3, 3]
    return lines


def plot_grasps(grasps: GraspSet, occupancy: np.ndarray, pose: GridPose, top_k: int = 5,
                config: GraspConfig | None = None, path: str | Path | None = None, max_completions: int = 6,
                observed: np.ndarray | None = None, title: str = "") -> Figure:
    """Draws the best grasps over the completions' voxel-centre clouds (camera-frame positions).

    Positions are the camera-frame points, drawn in gravity-aligned axes through the camera's origin (right,
    forward = the horizontal viewing direction, up), so the support plane is level. Two views: from the
    camera and from the side. Grasps are drawn as gripper outlines (fingers, palm, stem), coloured by rank
    (best = thick dark green) and labelled with rank and score.

    Args:
        grasps: ranked grasps.
        occupancy: (S, N, N, N) completions (at most ``max_completions`` are drawn, one colour each).
        pose: their grid pose.
        top_k: grasps drawn.
        config: the gripper used (finger length for the drawing).
        path: if given, the figure is also written there as a PNG.
        max_completions: completions drawn.
        observed: (M, 3) observed points (camera frame) drawn in black, or None.
        title: figure title.

    Returns:
        The matplotlib Figure (close it with ``matplotlib.pyplot.close(fig)`` when done).
    """
    import matplotlib.pyplot as plt

    occupancy = _check_occupancy(occupancy, pose)
    shown = grasps.top(top_k)
    lines = gripper_lines(shown, config)
    fig = plt.figure(figsize=(13, 6.5))
    cmap = plt.get_cmap("tab10")
    rank_colours = plt.get_cmap("RdYlGn_r")(np.linspace(0.0, 0.85, max(len(shown), 1)))
    axes_rows = pose.rotation  # columns: forward (grid x), left (grid y), up (grid z) in the camera frame

    def view(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = np.asarray(p) @ axes_rows
        return -g[..., 1], g[..., 0], g[..., 2]  # right, forward, up

    clouds = [pose.occupied_centres(occupancy[s]) for s in range(min(max_completions, occupancy.shape[0]))]
    for panel, (elev, azim) in enumerate(((25.0, -65.0), (15.0, 5.0))):
        ax = fig.add_subplot(1, 2, panel + 1, projection="3d")
        for s, c in enumerate(clouds):
            if len(c) > 2000:
                c = c[np.linspace(0, len(c) - 1, 2000).astype(int)]
            ax.scatter(*view(c), s=3, alpha=0.25, color=cmap(s % 10),
                       label=f"completion {s}" if panel == 0 else None)
        if observed is not None and len(observed):
            o = np.asarray(observed)[:: max(1, len(observed) // 1000)]
            ax.scatter(*view(o), s=1, color="k", alpha=0.35, label="observed" if panel == 0 else None)
        for k in range(len(shown) - 1, -1, -1):  # best drawn last, on top
            for seg in lines[k]:
                ax.plot(*view(seg), color=rank_colours[k], linewidth=3.5 if k == 0 else 1.8)
            ax.text(*view(shown.poses[k, :3, 3]), f"#{k + 1} {shown.scores[k]:.2f}", color=rank_colours[k],
                    fontsize=8)
        everything = np.concatenate([pose.occupied_centres(occupancy.any(axis=0)), lines.reshape(-1, 3)])
        if len(everything):
            v = np.stack(view(everything), axis=1)
            centre, radius = (v.min(axis=0) + v.max(axis=0)) / 2, float(np.ptp(v, axis=0).max()) / 2 + 0.01
            ax.set_xlim(centre[0] - radius, centre[0] + radius)
            ax.set_ylim(centre[1] - radius, centre[1] + radius)
            ax.set_zlim(centre[2] - radius, centre[2] + radius)
        ax.set_xlabel("right of camera (m)")
        ax.set_ylabel("ahead of camera, horizontal (m)")
        ax.set_zlabel("up from camera (m)")
        ax.view_init(elev=elev, azim=azim)
        if panel == 0:
            ax.legend(loc="upper left", fontsize=7, markerscale=3)
    summary = ", ".join(f"#{k + 1} {shown.kinds[k]} {shown.scores[k]:.2f} w={shown.widths[k] * 100:.1f}cm"
                        for k in range(len(shown)))
    fig.suptitle((title + "\n" if title else "") + (summary or "no grasps"), fontsize=9)
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig
