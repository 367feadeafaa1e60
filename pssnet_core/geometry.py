"""Observation geometry: from one depth image of an object to what the network sees.

The single code path shared by dataset generation and the ROS node:

    depth (metres) + mask + intrinsics + up vector
      -> masked points in the camera (optical) frame            :func:`masked_points`
      -> gravity-aligned grid placed from those points          :func:`place_grid`
      -> known-occupied / known-free voxel grids                :func:`observe`

Frames: the camera frame is the optical frame of REP 103 (x right, y down, z forward). The grid frame is
gravity aligned: its z axis is "up", its x axis the horizontal viewing direction (the optical axis
projected on the horizontal plane), y = z x x. Grid coordinates are continuous voxel units: voxel
(i, j, k) spans [i, i + 1) x [j, j + 1) x [k, k + 1) and its centre is (i + 0.5, j + 0.5, k + 0.5).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np


class ObservationError(ValueError):
    """The input cannot be turned into an observation; the message says exactly why."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a depth image (no distortion: depth images are usually rectified)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ObservationError(f"image size must be positive, got {self.width}x{self.height}")
        values = np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise ObservationError(
                f"intrinsics must be finite, got fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if self.fx <= 0 or self.fy <= 0:
            raise ObservationError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy} (zero intrinsics?)")

    @classmethod
    def from_k(cls, k: np.ndarray | list[float], width: int, height: int) -> CameraIntrinsics:
        """Builds intrinsics from a row-major 3x3 camera matrix (as in sensor_msgs/CameraInfo.k)."""
        k = np.asarray(k, dtype=np.float64).reshape(3, 3)
        return cls(width=int(width), height=int(height), fx=float(k[0, 0]), fy=float(k[1, 1]),
                   cx=float(k[0, 2]), cy=float(k[1, 2]))

    @classmethod
    def kinect_like(cls, width: int = 640, height: int = 480) -> CameraIntrinsics:
        """Intrinsics of a Kinect/PrimeSense-like depth camera (about 58 x 45 degrees field of view)."""
        scale = width / 640.0
        return cls(width=width, height=height, fx=525.0 * scale, fy=525.0 * scale,
                   cx=(width - 1) / 2.0, cy=(height - 1) / 2.0)

    def matrix(self) -> np.ndarray:
        """Returns the 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def backproject(self, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates and depths (metres along the optical axis) -> (M, 3) camera-frame points."""
        z = np.asarray(depth, dtype=np.float64)
        x = (np.asarray(u, dtype=np.float64) - self.cx) * z / self.fx
        y = (np.asarray(v, dtype=np.float64) - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=-1)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, 3) camera-frame points -> pixel coordinates u, v (floats) and depth z."""
        points = np.asarray(points, dtype=np.float64)
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * points[:, 0] / z + self.cx
            v = self.fy * points[:, 1] / z + self.cy
        return u, v, z


def validate_depth_and_mask(depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics) -> None:
    """Raises ObservationError if depth/mask do not match each other and the intrinsics."""
    if depth.ndim != 2:
        raise ObservationError(f"depth must be a 2-D image, got shape {depth.shape}")
    if mask.shape != depth.shape:
        raise ObservationError(f"mask shape {mask.shape} differs from depth shape {depth.shape}")
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ObservationError(
            f"depth is {depth.shape[1]}x{depth.shape[0]} but camera_info says {intrinsics.width}x{intrinsics.height}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise ObservationError(f"depth must be float metres, got dtype {depth.dtype}")


def valid_depth(depth: np.ndarray, min_depth: float = 0.1, max_depth: float = 5.0) -> np.ndarray:
    """Boolean image of usable readings: finite and within [min_depth, max_depth] metres (0/NaN = none)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth)


def masked_points(depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
                  min_depth: float = 0.1, max_depth: float = 5.0, min_points: int = 1) -> np.ndarray:
    """Camera-frame points of the valid depth readings inside the mask.

    Args:
        depth: (H, W) float depth in metres along the optical axis; 0, NaN, Inf or out of range = no reading.
        mask: (H, W) array, non-zero = target object.
        intrinsics: pinhole intrinsics of the depth image.
        min_depth: readings closer than this (metres) are ignored.
        max_depth: readings farther than this (metres) are ignored.
        min_points: fewer valid masked readings than this is an error.

    Returns:
        (M, 3) float64 points in the camera frame.

    Raises:
        ObservationError: shapes disagree, the mask is empty, or no masked pixel has a valid reading.
    """
    validate_depth_and_mask(depth, mask, intrinsics)
    object_pixels = mask != 0
    n_mask = int(object_pixels.sum())
    if n_mask == 0:
        raise ObservationError("mask is empty: no pixel marks the target object")
    usable = object_pixels & valid_depth(depth, min_depth, max_depth)
    n_usable = int(usable.sum())
    if n_usable < min_points:
        raise ObservationError(
            f"only {n_usable} of {n_mask} masked pixels have a valid depth in [{min_depth}, {max_depth}] m "
            f"(need at least {min_points})")
    v, u = np.nonzero(usable)
    return intrinsics.backproject(u, v, depth[v, u])


@dataclass(frozen=True)
class GridConfig:
    """Size and placement of the observation grid.

    The grid spans ``size * voxel_size`` metres along each axis (0.20 m by default, which holds every
    object of the training families in any orientation). Placement is a deterministic function of the
    observed points: the grid starts ``front_margin`` voxels in front of the nearest observed point along
    the viewing direction (the hidden side extends away from the camera), ``bottom_margin`` voxels below
    the lowest observed point (objects stand on a support surface), and is centred sideways on the
    observed points' extent.
    """

    size: int = 32
    voxel_size: float = 0.00625
    front_margin: float = 1.0
    bottom_margin: float = 1.0

    def __post_init__(self) -> None:
        if not 4 <= self.size <= 256:
            raise ObservationError(f"grid size must be in [4, 256], got {self.size}")
        if not 1e-4 <= self.voxel_size <= 1.0:
            raise ObservationError(f"voxel_size must be in [1e-4, 1] m, got {self.voxel_size}")
        if not 0.0 <= self.front_margin < self.size / 2 or not 0.0 <= self.bottom_margin < self.size / 2:
            raise ObservationError("grid margins must be in [0, size/2) voxels")

    @property
    def extent(self) -> float:
        """Edge length of the grid in metres."""
        return self.size * self.voxel_size

    @classmethod
    def for_size(cls, size: int, extent: float = 0.20) -> GridConfig:
        """A grid of ``size`` voxels per edge spanning ``extent`` metres."""
        return cls(size=size, voxel_size=extent / size)


def gravity_aligned_rotation(up: np.ndarray) -> np.ndarray:
    """Rotation whose columns are the grid axes (x = horizontal viewing direction, y, z = up) in the camera frame.

    Raises:
        ObservationError: the up vector is not finite/non-zero, or the camera looks (almost) straight along it.
    """
    up = np.asarray(up, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(up)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ObservationError(f"up vector must be finite and non-zero, got {up.tolist()}")
    z_axis = up / norm
    optical_axis = np.array([0.0, 0.0, 1.0])
    horizontal = optical_axis - z_axis * (optical_axis @ z_axis)
    h_norm = np.linalg.norm(horizontal)
    # Looking within ~8 degrees of straight down or up leaves no usable horizontal viewing direction.
    if h_norm < 0.14:
        raise ObservationError(
            "the camera looks (almost) straight along the up vector; the gravity-aligned grid needs a viewing "
            f"direction with a horizontal component (up in camera frame = {z_axis.round(3).tolist()})")
    x_axis = horizontal / h_norm
    y_axis = np.cross(z_axis, x_axis)
    return np.stack([x_axis, y_axis, z_axis], axis=1)


@dataclass(frozen=True)
class GridPose:
    """Where a voxel grid lies in the camera frame.

    Attributes:
        rotation: (3, 3) columns are the grid x, y, z axes expressed in the camera frame.
        origin: (3,) camera-frame position of the grid corner (grid coordinate 0, 0, 0).
        voxel_size: edge of one voxel in metres.
        size: voxels per edge.
    """

    rotation: np.ndarray
    origin: np.ndarray
    voxel_size: float
    size: int

    def grid_to_camera(self, grid_coords: np.ndarray) -> np.ndarray:
        """(M, 3) continuous grid coordinates (voxel units) -> (M, 3) camera-frame points."""
        return np.asarray(grid_coords, dtype=np.float64) * self.voxel_size @ self.rotation.T + self.origin

    def camera_to_grid(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) camera-frame points -> (M, 3) continuous grid coordinates (voxel units)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation / self.voxel_size

    def voxel_indices(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer voxel indices of camera-frame points, and a mask of those inside the grid."""
        ijk = np.floor(self.camera_to_grid(points)).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < self.size), axis=1)
        return ijk, inside

    def occupied_centres(self, occupancy: np.ndarray) -> np.ndarray:
        """Camera-frame centres of the occupied voxels of an (N, N, N) grid, as (M, 3) float64."""
        ijk = np.argwhere(occupancy)
        return self.grid_to_camera(ijk + 0.5)

    def all_centres(self) -> np.ndarray:
        """Camera-frame centres of every voxel, (N^3, 3) in C order of (i, j, k)."""
        axis = np.arange(self.size) + 0.5
        grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
        return self.grid_to_camera(grid)

    def to_matrix(self) -> np.ndarray:
        """4x4 transform from grid coordinates scaled to metres to the camera frame."""
        t = np.eye(4)
        t[:3, :3] = self.rotation
        t[:3, 3] = self.origin
        return t

    def to_dict(self) -> dict[str, object]:
        """Plain-data form for storage."""
        return {"rotation": self.rotation.tolist(), "origin": self.origin.tolist(),
                "voxel_size": float(self.voxel_size), "size": int(self.size)}

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> GridPose:
        """Inverse of :meth:`to_dict`."""
        return cls(rotation=np.asarray(data["rotation"], dtype=np.float64).reshape(3, 3),
                   origin=np.asarray(data["origin"], dtype=np.float64).reshape(3),
                   voxel_size=float(data["voxel_size"]), size=int(data["size"]))


# Surface samples per voxel edge for :func:`surface_samples`: 25 samples per voxel-sized patch of surface,
# so a voxel the surface crosses with a fifth of a voxel face of area or more holds one with P > 99 %.
SURFACE_SAMPLES_PER_VOXEL_EDGE: int = 5


def surface_samples(vertices: np.ndarray, faces: np.ndarray, voxel_size: float, seed: int = 0) -> np.ndarray:
    """Seeded uniform samples of a mesh surface, dense for voxels of ``voxel_size`` ((M, 3) float64, mesh frame)."""
    import trimesh  # local: only ground-truth voxelisation needs it

    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
    spacing = voxel_size / SURFACE_SAMPLES_PER_VOXEL_EDGE
    count = max(1, int(np.ceil(mesh.area / spacing**2)))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64)


def solid_occupancy(pose: GridPose, camera_from_object: np.ndarray, surface: np.ndarray,
                    inside: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The project's one ground-truth occupancy of an object in a grid.

    A voxel is occupied when its centre lies inside the solid *or* the object's surface passes through it
    (binvox-style: a surface plus its filled interior). Centres alone are not enough: a mug wall or handle
    thinner than a voxel falls between centres, leaving a ground truth with holes that misses about half of
    the voxels the camera sees (measured on the 32^3 mug test set); with the surface voxels every observed
    point lies in a ground-truth voxel.

    Args:
        pose: the grid.
        camera_from_object: (4, 4) camera <- object.
        surface: dense object-frame surface samples (:func:`surface_samples` at ``pose.voxel_size``).
        inside: object-frame points (M, 3) -> bool (M,), inside the watertight solid.

    Returns:
        (N, N, N) bool.
    """
    n = pose.size
    rotation, translation = camera_from_object[:3, :3], camera_from_object[:3, 3]
    grid = pose.camera_to_grid(np.asarray(surface, dtype=np.float64) @ rotation.T + translation)
    occupancy = np.zeros((n, n, n), dtype=bool)
    if len(grid) == 0:
        return occupancy
    # Only voxels within the surface's bounds can have an inside centre: query that block alone.
    lo = np.clip(np.floor(grid.min(axis=0)).astype(int), 0, n)
    hi = np.clip(np.floor(grid.max(axis=0)).astype(int) + 1, 0, n)
    if np.all(hi > lo):
        axes = [np.arange(lo[c], hi[c]) + 0.5 for c in range(3)]
        centres = pose.grid_to_camera(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3))
        occupancy[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = inside((centres - translation) @ rotation).reshape(
            tuple(hi - lo))
    ijk = np.floor(grid).astype(np.int64)
    ijk = ijk[np.all((ijk >= 0) & (ijk < n), axis=1)]
    occupancy[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return occupancy


def place_grid(points: np.ndarray, up: np.ndarray, config: GridConfig) -> GridPose:
    """Places the gravity-aligned grid from the observed points (see :class:`GridConfig`)."""
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ObservationError(f"need a non-empty (M, 3) point array to place the grid, got {points.shape}")
    rotation = gravity_aligned_rotation(up)
    local = points @ rotation  # points in grid-axis coordinates (metres), origin at the camera
    lo = local.min(axis=0)
    hi = local.max(axis=0)
    extent = config.extent
    corner_local = np.array([
        lo[0] - config.front_margin * config.voxel_size,
        0.5 * (lo[1] + hi[1]) - 0.5 * extent,
        lo[2] - config.bottom_margin * config.voxel_size,
    ])
    return GridPose(rotation=rotation, origin=rotation @ corner_local, voxel_size=config.voxel_size,
                    size=config.size)


@dataclass
class Observation:
    """What the network sees of one view, and where it lies in the camera frame.

    Attributes:
        known_occupied: (N, N, N) bool, voxels holding observed surface points.
        known_free: (N, N, N) bool, voxels seen through (between the camera and a valid reading).
        pose: where the grid lies in the camera frame.
        points: (M, 3) observed object points in the camera frame.
    """

    known_occupied: np.ndarray
    known_free: np.ndarray
    pose: GridPose
    points: np.ndarray = field(repr=False)

    def network_input(self) -> np.ndarray:
        """(2, N, N, N) float32: channel 0 known occupied, channel 1 known free."""
        return np.stack([self.known_occupied, self.known_free]).astype(np.float32)


def carve_free_space(depth: np.ndarray, usable: np.ndarray, intrinsics: CameraIntrinsics,
                     pose: GridPose) -> np.ndarray:
    """Voxels that lie in front of a valid reading: the camera saw through them.

    A voxel is free when its centre projects into the image and lies, with a margin of half a voxel
    diagonal, in front of the smallest valid reading within its projected footprint. Taking the minimum
    over the footprint (and treating missing readings as distance 0) keeps voxels at silhouette edges and
    next to holes unknown rather than wrongly free. Readings of any pixel count, inside the mask or beside
    it: rays that pass the object and hit the support or background also cross free space.

    Returns:
        (N, N, N) bool.
    """
    # Camera coordinates of every voxel centre by broadcasting the per-axis offsets: much cheaper than an
    # (N^3, 3) matrix product, and float32 is ample for millimetre voxels.
    steps = (np.arange(pose.size, dtype=np.float32) + 0.5) * np.float32(pose.voxel_size)
    axes = pose.rotation.astype(np.float32)
    origin = pose.origin.astype(np.float32)
    x, y, z = ((origin[c] + steps[:, None, None] * axes[c, 0] + steps[None, :, None] * axes[c, 1]
                + steps[None, None, :] * axes[c, 2]).reshape(-1) for c in range(3))
    half_diagonal = 0.5 * np.sqrt(3.0) * pose.voxel_size
    nearest = max(float(z.min()), 1e-3)
    radius = int(np.ceil(intrinsics.fx * half_diagonal / nearest))
    radius = min(radius, 8)  # the footprint of a voxel closer than ~fx*r/8 m; bounded to keep this cheap
    blocked = np.where(usable, depth, 0.0).astype(np.float32)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    nearest_reading = cv2.erode(blocked, kernel, borderType=cv2.BORDER_REPLICATE)  # windowed minimum
    in_front = z > 1e-3
    inv_z = np.float32(1.0) / np.where(in_front, z, np.float32(1.0))
    u = np.rint(np.float32(intrinsics.fx) * x * inv_z + np.float32(intrinsics.cx))
    v = np.rint(np.float32(intrinsics.fy) * y * inv_z + np.float32(intrinsics.cy))
    in_image = in_front & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    flat = np.where(in_image, v * intrinsics.width + u, 0).astype(np.int64)
    free = in_image & (z + np.float32(half_diagonal) < nearest_reading.reshape(-1)[flat])
    return free.reshape(pose.size, pose.size, pose.size)


def observe(depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, up: np.ndarray,
            config: GridConfig, min_depth: float = 0.1, max_depth: float = 5.0,
            min_points: int = 10) -> Observation:
    """Turns one depth image and object mask into the observation grid the network sees.

    This is the only implementation: the dataset generator and the ROS node both call it.

    Args:
        depth: (H, W) float depth in metres; 0/NaN/Inf or out-of-range pixels are "no reading" (unknown).
        mask: (H, W), non-zero = target object.
        intrinsics: pinhole intrinsics of the depth image.
        up: (3,) the up direction (against gravity) in the camera frame.
        config: grid size, voxel size and placement margins.
        min_depth: readings closer than this are ignored (metres).
        max_depth: readings farther than this are ignored (metres).
        min_points: fewer valid masked readings than this is an error.

    Returns:
        The observation (known-occupied and known-free grids, grid pose, observed points).

    Raises:
        ObservationError: with a message saying what is wrong with the input.
    """
    points = masked_points(depth, mask, intrinsics, min_depth, max_depth, min_points)
    pose = place_grid(points, up, config)
    ijk, inside = pose.voxel_indices(points)
    known_occupied = np.zeros((config.size,) * 3, dtype=bool)
    known_occupied[tuple(ijk[inside].T)] = True
    usable = valid_depth(depth, min_depth, max_depth)
    known_free = carve_free_space(depth, usable, intrinsics, pose)
    known_free &= ~known_occupied  # a voxel holding observed surface is never free
    return Observation(known_occupied=known_occupied, known_free=known_free, pose=pose, points=points)
