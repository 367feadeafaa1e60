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

from collections.abc import Callable, Sequence
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


@dataclass(frozen=True)
class CameraLimits:
    """Calibrations that no real depth camera has: a CameraInfo outside these is corrupt, not a camera.

    Attributes:
        min_fov_deg: smallest field of view along either image axis (a 64 px crop of a 525 px focal-length
            camera still sees 7 degrees).
        max_fov_deg: largest field of view along either image axis (a pinhole model cannot hold 180 degrees).
        max_pixel_aspect: largest ratio of fx and fy (pixels are square, or binned 2:1).
        max_skew_shift_px: the skew K[0,1], which the pinhole model here ignores, may shift no pixel further.
        matrix_tolerance: how far the fixed entries of K and P (zeros, the 1) and R's orthonormality may be off.
        projection_tolerance: relative difference allowed between P's and K's focal lengths and principal
            points when the camera needs no rectification (no distortion and R = identity), where they must
            agree.
    """

    min_fov_deg: float = 1.0
    max_fov_deg: float = 160.0
    max_pixel_aspect: float = 2.0
    max_skew_shift_px: float = 0.5
    matrix_tolerance: float = 1e-3
    projection_tolerance: float = 0.01


def check_intrinsics(intrinsics: CameraIntrinsics, limits: CameraLimits | None = None, matrix: str = "K") -> None:
    """Raises ObservationError, naming the value, when no real camera has these pinhole intrinsics.

    Checks the field of view along each axis, the pixel aspect ratio, and that the principal point lies
    inside the image.

    Args:
        intrinsics: the intrinsics to check.
        limits: what real cameras have (default :class:`CameraLimits`).
        matrix: name of the matrix they come from, for the message ("K", "P").
    """
    limits = limits or CameraLimits()
    k = intrinsics
    for name, focal, size, direction in (("fx", k.fx, k.width, "horizontal"), ("fy", k.fy, k.height, "vertical")):
        fov = float(np.degrees(2.0 * np.arctan(size / (2.0 * focal))))
        if not limits.min_fov_deg <= fov <= limits.max_fov_deg:
            raise ObservationError(
                f"{matrix} {name} = {focal:g} px gives a {direction} field of view of {fov:.3g} deg over {size} px; "
                f"real cameras have {limits.min_fov_deg:g} to {limits.max_fov_deg:g} deg (corrupt calibration?)")
    aspect = max(k.fx / k.fy, k.fy / k.fx)
    if aspect > limits.max_pixel_aspect:
        raise ObservationError(f"{matrix} fx = {k.fx:g} px and fy = {k.fy:g} px differ by a factor of {aspect:.3g}; "
                               f"real pixels are square to within {limits.max_pixel_aspect:g}x")
    for name, centre, size, side in (("cx", k.cx, k.width, "wide"), ("cy", k.cy, k.height, "high")):
        if not 0.0 <= centre <= size:
            raise ObservationError(f"{matrix} principal point {name} = {centre:g} px lies outside the {size} px "
                                   f"{side} image")


def check_skew(matrix: np.ndarray, intrinsics: CameraIntrinsics, limits: CameraLimits, name: str = "K") -> None:
    """Raises ObservationError when the skew ``matrix[0, 1]``, which the pinhole model here drops, shears the
    image by more than ``limits.max_skew_shift_px``."""
    skew = float(matrix[0, 1])
    # Ignoring the skew moves a pixel in row v by skew * (v - cy) / fy: bound that over the image.
    rows = max(intrinsics.cy, intrinsics.height - intrinsics.cy)
    max_skew = limits.max_skew_shift_px * intrinsics.fy / rows
    if not abs(skew) <= max_skew:
        shift = abs(skew) * rows / intrinsics.fy
        raise ObservationError(f"{name} skew {name}[0,1] = {skew:g} shifts pixels by up to {shift:.3g} px, which a "
                               f"pinhole model without skew ignores; |skew| must be at most {max_skew:.3g} "
                               f"({limits.max_skew_shift_px:g} px)")


def check_camera_model(width: int, height: int, k: np.ndarray | Sequence[float], d: np.ndarray | Sequence[float] = (),
                       r: np.ndarray | Sequence[float] = (), p: np.ndarray | Sequence[float] = (),
                       limits: CameraLimits | None = None) -> CameraIntrinsics:
    """Pinhole intrinsics from a full calibration (as in sensor_msgs/CameraInfo), refusing one no camera has.

    sensor_msgs/CameraInfo: K is the camera matrix of the raw (distorted) image, P's left 3x3 that of the
    rectified image, and one CameraInfo accompanies both. The pinhole model here has no distortion, so it
    describes the rectified image (image_rect, what depth_image_proc takes), whose pixels image_geometry's
    PinholeCameraModel maps with P: the intrinsics are P's whenever P is given. Without distortion and
    rectification (D zero, R identity) the raw image is its own rectified image and P must equal K; a raw image
    of a distorted camera fits neither matrix and has to be rectified first (image_proc).

    Args:
        width: image width (pixels).
        height: image height (pixels).
        k: row-major 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
        d: distortion coefficients (empty or all zero: none).
        r: row-major 3x3 rectification rotation; empty or all zero: not given.
        p: row-major 3x4 projection matrix [[fx', s', cx', Tx], [0, fy', cy', Ty], [0, 0, 1, 0]]; empty or all
            zero: not given (then K's intrinsics are used). Tx and Ty (a stereo pair's second camera) place that
            camera in the first one's frame; the points here stay in the image's own frame, as in
            image_geometry's projectPixelTo3dRay.
        limits: what real cameras have (default :class:`CameraLimits`).

    Returns:
        The intrinsics of P when it is given, else of K (the skew, checked to be negligible, is dropped).

    Raises:
        ObservationError: the message names the matrix entry that is wrong.
    """
    limits = limits or CameraLimits()
    tol = limits.matrix_tolerance
    k = np.asarray(k, dtype=np.float64).reshape(3, 3)
    intrinsics = CameraIntrinsics.from_k(k, width, height)
    check_intrinsics(intrinsics, limits)
    fixed = np.array([k[1, 0], k[2, 0], k[2, 1], k[2, 2] - 1.0])
    if not np.all(np.isfinite(fixed)) or np.abs(fixed).max() > tol:
        raise ObservationError(f"K must have the form [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got rows 2-3 "
                               f"{k[1].tolist()} and {k[2].tolist()}")
    check_skew(k, intrinsics, limits)
    rotation = np.asarray(r, dtype=np.float64).reshape(-1)
    rotated = False
    if rotation.size and np.any(rotation):
        if rotation.size != 9 or not np.all(np.isfinite(rotation)):
            raise ObservationError(f"R must be 9 finite numbers, got {rotation.tolist()}")
        rotation = rotation.reshape(3, 3)
        error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
        if error > tol or np.linalg.det(rotation) < 0:
            raise ObservationError(f"R is not a rotation matrix (R R^T differs from I by {error:.3g}, det "
                                   f"{np.linalg.det(rotation):.3g}): {rotation.round(6).tolist()}")
        rotated = float(np.abs(rotation - np.eye(3)).max()) > tol
    projection = np.asarray(p, dtype=np.float64).reshape(-1)
    if not (projection.size and np.any(projection)):
        return intrinsics
    if projection.size != 12 or not np.all(np.isfinite(projection)):
        raise ObservationError(f"P must be 12 finite numbers, got {projection.tolist()}")
    projection = projection.reshape(3, 4)
    fixed = np.array([projection[1, 0], projection[2, 0], projection[2, 1], projection[2, 2] - 1.0,
                      projection[2, 3]])
    if np.abs(fixed).max() > tol:
        raise ObservationError(f"P must have the form [[fx', s', cx', Tx], [0, fy', cy', Ty], [0, 0, 1, 0]], "
                               f"got rows 2-3 {projection[1].tolist()} and {projection[2].tolist()}")
    rectified = CameraIntrinsics.from_k(projection[:, :3], width, height)
    check_intrinsics(rectified, limits, matrix="P")
    check_skew(projection, rectified, limits, name="P")
    distortion = np.asarray(d, dtype=np.float64).reshape(-1)
    if not rotated and not np.any(distortion):
        rel = limits.projection_tolerance
        for name, of_p, of_k, scale in (("fx", rectified.fx, intrinsics.fx, intrinsics.fx),
                                        ("fy", rectified.fy, intrinsics.fy, intrinsics.fy),
                                        ("cx", rectified.cx, intrinsics.cx, width),
                                        ("cy", rectified.cy, intrinsics.cy, height)):
            if abs(of_p - of_k) > rel * scale:
                raise ObservationError(f"P {name} = {of_p:g} but K {name} = {of_k:g}: without distortion and "
                                       "rectification (D zero, R identity) the two must agree")
    return rectified


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
    # flatnonzero + divmod: a third of the time of a 2-D nonzero on a VGA image.
    flat = np.flatnonzero(usable)
    v, u = np.divmod(flat, usable.shape[1])
    return intrinsics.backproject(u, v, depth.reshape(-1)[flat])


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

    def occupied_centres_per_grid(self, occupancy: np.ndarray) -> list[np.ndarray]:
        """Camera-frame centres of the occupied voxels of each grid of an (S, N, N, N) stack, as S float32 (M_s, 3)
        arrays, each in the order of :meth:`occupied_centres`.

        One pass over the stack (flat indices, one float32 product) instead of an argwhere per grid: for the
        node's 20 samples at 32^3 about a third of the time.
        """
        occupancy = np.asarray(occupancy, dtype=bool)
        count, n = occupancy.shape[0], self.size
        flat = np.flatnonzero(occupancy)
        grid, voxel = np.divmod(flat, n ** 3)
        ijk = np.empty((len(flat), 3), dtype=np.float32)
        ij, ijk[:, 2] = np.divmod(voxel, n)
        ijk[:, 0], ijk[:, 1] = np.divmod(ij, n)
        ijk += np.float32(0.5)
        centres = ijk @ (self.rotation.T * self.voxel_size).astype(np.float32)
        centres += self.origin.astype(np.float32)
        return np.split(centres, np.cumsum(np.bincount(grid, minlength=count))[:-1])

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
    local = rotation.T @ points.T  # (3, M) grid-axis coordinates (metres), origin at the camera: rows reduce fast
    lo = local.min(axis=1)
    hi = local.max(axis=1)
    extent = config.extent
    corner_local = np.array([
        lo[0] - config.front_margin * config.voxel_size,
        0.5 * (lo[1] + hi[1]) - 0.5 * extent,
        lo[2] - config.bottom_margin * config.voxel_size,
    ])
    return GridPose(rotation=rotation, origin=rotation @ corner_local, voxel_size=config.voxel_size,
                    size=config.size)


def check_object_scale(points: np.ndarray, pose: GridPose, config: GridConfig, min_voxels: float,
                       outliers: float = 0.01) -> None:
    """Raises ObservationError when the observed object is implausibly large or small for the grid.

    The central part of the points (without the ``outliers`` fraction at each end of every grid axis: stray
    mask pixels) must fit in the room the grid's placement leaves along each axis, and must span at least
    ``min_voxels`` along one. Wrong depth units (a 16-bit image in 0.1 mm read as mm) or a wrong focal
    length scale the object by the same factor and fail here.
    """
    grid = np.ascontiguousarray(pose.camera_to_grid(points).T)  # (3, M): quantiles along rows are faster
    lo, hi = np.quantile(grid, [outliers, 1.0 - outliers], axis=1)
    extent = hi - lo
    room = np.array([config.size - config.front_margin, config.size, config.size - config.bottom_margin])
    voxel = config.voxel_size
    hint = "for this model, or the depth units (depth_scale of 16-bit images) or the intrinsics are wrong"
    axis = int(np.argmax(extent / room))
    if extent[axis] > room[axis]:
        name = ("along the view", "across the view", "upwards")[axis]
        raise ObservationError(f"the observed object spans {extent[axis] * voxel:.3g} m {name}, more than the "
                               f"{room[axis] * voxel:.3g} m the {config.size}^3 grid of {voxel * 1000:.3g} mm voxels "
                               f"holds: too large {hint}")
    if extent.max() < min_voxels:
        raise ObservationError(f"the observed object spans only {extent.max() * voxel * 1000:.3g} mm, less than "
                               f"{min_voxels:g} voxels ({min_voxels * voxel * 1000:.3g} mm) of the grid: too small "
                               f"{hint}")


@dataclass(frozen=True)
class ViewEvidence:
    """What one camera of a fused observation saw, in the observation grid.

    Attributes:
        known_occupied: (N, N, N) bool, voxels holding this view's surface points.
        known_free: (N, N, N) bool, voxels this view saw through.
        camera: (3,) this camera's centre in the first camera's frame (metres).
    """

    known_occupied: np.ndarray = field(repr=False)
    known_free: np.ndarray = field(repr=False)
    camera: np.ndarray


@dataclass
class Observation:
    """What the network sees of one view (or of several fused), and where it lies in the first camera's frame.

    Attributes:
        known_occupied: (N, N, N) bool, voxels holding observed surface points.
        known_free: (N, N, N) bool, voxels seen through (between the camera and a valid reading).
        pose: where the grid lies in the (first) camera frame.
        points: (M, 3) observed object points in the (first) camera frame.
        views: for an observation fused from several views (:func:`fuse_view`), each view's own evidence, the
            first view's first; empty for one view (then the grids above are that view's, camera at the origin).
    """

    known_occupied: np.ndarray
    known_free: np.ndarray
    pose: GridPose
    points: np.ndarray = field(repr=False)
    views: tuple[ViewEvidence, ...] = ()

    def evidence(self) -> tuple[ViewEvidence, ...]:
        """Each view's own evidence (one entry, camera at the origin, for a single view)."""
        if self.views:
            return self.views
        return (ViewEvidence(self.known_occupied, self.known_free, np.zeros(3)),)

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
    in_front = z > 1e-3
    inv_z = np.float32(1.0) / np.where(in_front, z, np.float32(1.0))
    u = np.rint(np.float32(intrinsics.fx) * x * inv_z + np.float32(intrinsics.cx))
    v = np.rint(np.float32(intrinsics.fy) * y * inv_z + np.float32(intrinsics.cy))
    in_image = in_front & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    if not in_image.any():
        return np.zeros((pose.size,) * 3, dtype=bool)
    # The windowed minimum only where voxels project, plus the window's reach: every window of a projected pixel
    # lies inside this crop, so the crop's edges never enter a result (where they are the image's own edges,
    # the replicated border is the same as on the whole image).
    u0 = max(int(np.min(u, where=in_image, initial=np.inf)) - radius, 0)
    u1 = min(int(np.max(u, where=in_image, initial=-np.inf)) + radius + 1, intrinsics.width)
    v0 = max(int(np.min(v, where=in_image, initial=np.inf)) - radius, 0)
    v1 = min(int(np.max(v, where=in_image, initial=-np.inf)) + radius + 1, intrinsics.height)
    blocked = np.where(usable[v0:v1, u0:u1], depth[v0:v1, u0:u1], 0.0).astype(np.float32)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    nearest_reading = cv2.erode(blocked, kernel, borderType=cv2.BORDER_REPLICATE)  # windowed minimum
    # The pixel index in int64: float32 holds integers exactly only up to 2**24, fewer pixels than a 4200 x 4200 image.
    flat = np.where(in_image, (v.astype(np.int64) - v0) * (u1 - u0) + (u.astype(np.int64) - u0), 0)
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


def checked_rigid(transform: np.ndarray, name: str) -> np.ndarray:
    """``transform`` as a (4, 4) float64 array, checked to be a rigid transform (rotation and translation).

    Raises:
        ObservationError: naming ``name``, when it is not a finite 4x4 matrix or its rotation part is not a rotation.
    """
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ObservationError(f"{name} must be a finite 4x4 transform, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        raise ObservationError(f"{name}'s rotation is not a rotation (orthonormal, determinant +1)")
    return matrix


def rigid_inverse(transform: np.ndarray, name: str) -> np.ndarray:
    """The inverse of a rigid (4, 4) transform (:func:`checked_rigid` first)."""
    matrix = checked_rigid(transform, name)
    inverse = np.eye(4)
    inverse[:3, :3] = matrix[:3, :3].T
    inverse[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return inverse


#: :func:`fuse_view`'s checks of a further view's pose: most of its object points lie in the first view's grid, and it
#: sees through little of the surface the views before saw (the true poses of the trials' looks: none; an inverted
#: pose: 7-53 % of it, or its points outside the grid).
MIN_POINTS_IN_GRID, MAX_SEEN_THROUGH = 0.5, 0.05


def fuse_view(observation: Observation, depth: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics,
              first_from_camera: np.ndarray, min_depth: float = 0.1, max_depth: float = 5.0,
              min_points: int = 10) -> Observation:
    """Adds a second look at the same object to an observation: the union of what both saw, in the first grid.

    The grid keeps the first view's placement (the network was trained on grids placed so); the new view's
    surface points inside it become known occupied, the voxels it saw through known free (never where either
    view saw surface), and its evidence is kept apart (:attr:`Observation.views`) so that a check of a shape
    against the observation follows each camera's own rays.

    Args:
        observation: the observation so far (one view or already fused).
        depth, mask, intrinsics: the new view, as for :func:`observe`.
        first_from_camera: (4, 4) the new camera's pose in the first camera's frame (first <- new).
        min_depth, max_depth, min_points: as for :func:`observe`.

    Raises:
        ObservationError: the new view has too few masked readings, ``first_from_camera`` is not a rigid
            transform, or the view does not fit the observation at that pose (less than half of its object points
            in the grid, or it sees through more than 5 % of the surface seen before: a wrong or inverted pose).
    """
    transform = checked_rigid(first_from_camera, "first_from_camera")
    rotation, translation = transform[:3, :3], transform[:3, 3]
    points = masked_points(depth, mask, intrinsics, min_depth, max_depth, min_points)
    pose = observation.pose
    # The grid as the new camera sees it: the same voxels, expressed in the new camera's frame.
    pose_here = GridPose(rotation=rotation.T @ pose.rotation, origin=rotation.T @ (pose.origin - translation),
                         voxel_size=pose.voxel_size, size=pose.size)
    ijk, inside = pose_here.voxel_indices(points)
    hint = "is first_from_camera this camera's pose in the first camera's frame (not its inverse), in metres?"
    if inside.mean() < MIN_POINTS_IN_GRID:
        raise ObservationError(f"only {inside.mean():.0%} of this view's object points fall in the first view's grid "
                               f"(need {MIN_POINTS_IN_GRID:.0%}): {hint}")
    occupied = np.zeros((pose.size,) * 3, dtype=bool)
    occupied[tuple(ijk[inside].T)] = True
    free = carve_free_space(depth, valid_depth(depth, min_depth, max_depth), intrinsics, pose_here)
    seen_through, surface = (int(np.count_nonzero(g)) for g in (free & observation.known_occupied,
                                                                 observation.known_occupied))
    if seen_through > MAX_SEEN_THROUGH * max(surface, 1):
        raise ObservationError(f"this view sees through {seen_through} of the {surface} voxels where the views before "
                               f"saw surface (at most {MAX_SEEN_THROUGH:.0%}): {hint}")
    known_occupied = observation.known_occupied | occupied
    new = ViewEvidence(occupied, free & ~occupied, translation.copy())
    return Observation(known_occupied=known_occupied, known_free=(observation.known_free | free) & ~known_occupied,
                       pose=pose, points=np.concatenate([observation.points, points @ rotation.T + translation]),
                       views=(*observation.evidence(), new))
