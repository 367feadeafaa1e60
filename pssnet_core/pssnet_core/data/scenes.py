"""Rendering one object on a support plane with a pinhole depth camera, and the ground truth of the view.

World frame: z up, the support plane is z = 0 and infinite, the object stands on it. The camera is a
perspective pinhole (default 640x480, Kinect-like) in the optical frame of REP 103 (x right, y down,
z forward), placed on an orbit around the object: ``distance`` metres from an aim point near the object's
centre, looking down ``tilt_deg`` degrees, from azimuth ``azimuth_deg`` (180 = on the -x side, looking
along +x, so a mug at yaw 0 turns its handle, which points along +x, away from the camera).

How a view is rendered (:func:`render_view`, or :class:`ObjectScene` to reuse one object across views):
rays are cast in the *object* frame against an open3d ``RaycastingScene`` built once per object, the
plane is intersected analytically, and the nearer hit wins. Depth is distance along the optical axis,
rounded to whole millimetres like a 16UC1 sensor image (so the stored uint16 image reproduces the
observation bit for bit); 0 means "no reading". The mask marks pixels whose nearest hit is the object.
A vertical slit (:class:`Slit`) blanks every column outside it: depth 0 and mask 0, i.e. unknown.
Optional sensor imperfections (:class:`SensorNoise`) are off unless asked for.

Ground truth (:func:`ground_truth_occupancy`) follows the project's one occupancy definition
(:func:`pssnet_core.geometry.solid_occupancy`): a voxel is occupied when its centre lies inside the watertight
object mesh (open3d ``compute_occupancy``) or the mesh surface passes through it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import trimesh

from pssnet_core.geometry import (
    CameraIntrinsics,
    GridConfig,
    GridPose,
    Observation,
    observe,
    solid_occupancy,
    surface_samples,
)
from pssnet_core.shapes import Shape


class SceneError(ValueError):
    """A rendering request is invalid (bad camera, slit or pose); the message says which."""


# Area of the handle's visible surface (summed pixel footprints, m^2) above which a mug's handle counts as
# visible: 0.5 cm^2 is about 25 pixels of a 640x480 Kinect-like image at 0.75 m (see the data README).
HANDLE_VISIBLE_AREA_M2: float = 0.5e-4
# A handle pixel is visible when the handle-alone depth equals the scene depth within this (m).
HANDLE_DEPTH_TOLERANCE: float = 0.001
# Pixels beyond the projected grid kept in a stored crop: the widest min-filter footprint of
# geometry.carve_free_space (8 px) plus one for rounding, so the crop reproduces the observation exactly.
CROP_MARGIN_PX: int = 10


@dataclass(frozen=True)
class SensorNoise:
    """Depth-sensor imperfections, all optional (a view rendered without a SensorNoise is exact).

    Attributes:
        sigma_base: axial noise standard deviation at 0.4 m (m); Kinect model of Nguyen et al. 2012,
            sigma(z) = sigma_base + sigma_quadratic * (z - 0.4)^2.
        sigma_quadratic: growth of the axial noise with distance (1/m).
        edge_threshold: a pixel whose depth differs from a 4-neighbour by more than this (m) lies on a
            depth discontinuity.
        edge_dropout: probability that a discontinuity pixel has no reading (boundary dropout).
        pixel_dropout: probability that any pixel has no reading.
    """

    sigma_base: float = 0.0012
    sigma_quadratic: float = 0.0019
    edge_threshold: float = 0.01
    edge_dropout: float = 0.5
    pixel_dropout: float = 0.0

    def __post_init__(self) -> None:
        if self.sigma_base < 0 or self.sigma_quadratic < 0 or self.edge_threshold <= 0:
            raise SceneError("noise sigmas must be >= 0 and edge_threshold > 0")
        if not (0 <= self.edge_dropout <= 1 and 0 <= self.pixel_dropout <= 1):
            raise SceneError("dropout probabilities must be in [0, 1]")

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy copy of a float depth image (metres, 0 = no reading)."""
        valid = depth > 0
        sigma = self.sigma_base + self.sigma_quadratic * (depth - 0.4) ** 2
        noisy = np.where(valid, depth + rng.standard_normal(depth.shape) * sigma, 0.0)
        edge = np.zeros(depth.shape, dtype=bool)
        jump_x = np.abs(np.diff(depth, axis=1)) > self.edge_threshold
        jump_y = np.abs(np.diff(depth, axis=0)) > self.edge_threshold
        edge[:, 1:] |= jump_x
        edge[:, :-1] |= jump_x
        edge[1:, :] |= jump_y
        edge[:-1, :] |= jump_y
        drop = (edge & (rng.random(depth.shape) < self.edge_dropout)) | (rng.random(depth.shape) < self.pixel_dropout)
        return np.where(drop | ~valid, 0.0, np.maximum(noisy, 0.0))


@dataclass(frozen=True)
class Slit:
    """A vertical slit in the image: only columns inside it are seen (the rest is unknown).

    Attributes:
        width_m: slit width at the object's depth (metres); converted to pixels with fx / depth.
        offset_m: horizontal offset of the slit's centre from the centre of the object's (unoccluded)
            mask columns, at the object's depth (metres; positive = towards image right).
        offset_fraction: further offset, as a fraction of the object's visible width (the extent of its
            unoccluded mask columns at the object's depth).
        max_offset_fraction: if set, the total offset is clipped to this fraction of the visible width, so
            the slit stays over the object's central part.
    """

    width_m: float
    offset_m: float = 0.0
    offset_fraction: float = 0.0
    max_offset_fraction: float | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.width_m) or self.width_m <= 0:
            raise SceneError(f"slit width must be positive, got {self.width_m}")
        if not (np.isfinite(self.offset_m) and np.isfinite(self.offset_fraction)):
            raise SceneError(f"slit offsets must be finite, got {self.offset_m}, {self.offset_fraction}")
        if self.max_offset_fraction is not None and not self.max_offset_fraction >= 0:
            raise SceneError(f"max_offset_fraction must be >= 0, got {self.max_offset_fraction}")

    def offset(self, visible_width_m: float) -> float:
        """Offset (m) of the slit's centre from the object's centre, given the object's visible width (m)."""
        offset = self.offset_m + self.offset_fraction * visible_width_m
        if self.max_offset_fraction is not None:
            limit = self.max_offset_fraction * visible_width_m
            offset = float(np.clip(offset, -limit, limit))
        return offset


@dataclass
class RenderedView:
    """One rendered view of an object standing on the support plane.

    Attributes:
        depth: (H, W) float32 depth along the optical axis in metres (whole millimetres unless rendered
            with ``quantize_mm=False``); 0 = no reading (nothing hit, dropped out or outside the slit).
        mask: (H, W) uint8, 1 where the object is seen.
        intrinsics: the camera's pinhole intrinsics.
        camera_pose: (4, 4) world <- camera (optical frame).
        object_pose: (4, 4) world <- object.
        up: (3,) world z (against gravity) in the camera frame: what ``observe`` needs.
        handle_visible: for mugs with a handle, whether enough of the handle is seen; None otherwise.
        handle_area_m2: visible handle surface (sum of pixel footprints, m^2); None without a handle.
        slit_columns: ``(u0, u1)`` half-open range of visible columns, or None without a slit.
        object_depth: depth of the object's centre along the optical axis (m), used to size the slit.
    """

    depth: np.ndarray
    mask: np.ndarray
    intrinsics: CameraIntrinsics
    camera_pose: np.ndarray
    object_pose: np.ndarray
    up: np.ndarray
    handle_visible: bool | None = None
    handle_area_m2: float | None = None
    slit_columns: tuple[int, int] | None = None
    object_depth: float = field(default=0.0)

    def observe(self, config: GridConfig) -> Observation:
        """The observation grid of this view: exactly what the node computes from the same images."""
        return observe(self.depth, self.mask, self.intrinsics, self.up, config)


# ------------------------------------------------------------------------------------------- poses


def rotation_z(angle_deg: float) -> np.ndarray:
    """3x3 rotation about z by ``angle_deg`` degrees."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_x(angle_deg: float) -> np.ndarray:
    """3x3 rotation about x by ``angle_deg`` degrees."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def object_pose(mesh: trimesh.Trimesh, yaw_deg: float = 0.0, tip_deg: float = 0.0,
                translation: tuple[float, float] | np.ndarray = (0.0, 0.0)) -> np.ndarray:
    """World <- object transform of an object resting on the plane.

    The object is first tipped by ``tip_deg`` about its own x axis (a horizontal axis), then turned by
    ``yaw_deg`` about the vertical, dropped so its lowest point touches z = 0 and moved by ``translation``
    (x, y metres) along the plane.
    """
    rotation = rotation_z(yaw_deg) @ rotation_x(tip_deg)
    lowest = float((np.asarray(mesh.vertices) @ rotation.T)[:, 2].min())
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:2, 3] = np.asarray(translation, dtype=np.float64).reshape(2)
    pose[2, 3] = -lowest
    return pose


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World <- camera pose (optical frame, no roll) of a camera at ``position`` looking at ``target``.

    Raises:
        SceneError: the camera looks straight up or down (no horizontal viewing direction to fix roll).
    """
    position = np.asarray(position, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - position
    norm = np.linalg.norm(forward)
    if norm < 1e-9:
        raise SceneError("camera position and target coincide")
    forward /= norm
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:
        raise SceneError("the camera looks straight up or down; tilt must be below 90 degrees")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = position
    return pose


def orbit_camera(target: np.ndarray, distance: float, tilt_deg: float, azimuth_deg: float = 180.0) -> np.ndarray:
    """World <- camera pose ``distance`` m from ``target``, looking down ``tilt_deg``, placed at ``azimuth_deg``."""
    if not distance > 0:
        raise SceneError(f"camera distance must be positive, got {distance}")
    if not -90.0 < tilt_deg < 90.0:
        raise SceneError(f"camera tilt must be in (-90, 90) degrees, got {tilt_deg}")
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    offset = distance * np.array([np.cos(t) * np.cos(a), np.cos(t) * np.sin(a), np.sin(t)])
    return look_at(np.asarray(target, dtype=np.float64) + offset, target)


def posed_box_corners(shape: Shape, pose: np.ndarray) -> np.ndarray:
    """(8, 3) world corners of the shape's object-frame bounding box at ``pose`` (fixed corner order)."""
    return shape.box_corners() @ pose[:3, :3].T + pose[:3, 3]


# ------------------------------------------------------------------------------------------- scene


def _o3d_mesh(mesh: trimesh.Trimesh) -> o3d.t.geometry.TriangleMesh:
    return o3d.t.geometry.TriangleMesh(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.int32)))


def _pixel_rays(intrinsics: CameraIntrinsics, u0: int, u1: int, v0: int, v1: int) -> np.ndarray:
    """(h, w, 3) camera-frame ray directions with unit z (ray parameter = depth) for a pixel window."""
    u = (np.arange(u0, u1, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(v0, v1, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    dirs = np.empty((v1 - v0, u1 - u0, 3))
    dirs[..., 0] = u[None, :]
    dirs[..., 1] = v[:, None]
    dirs[..., 2] = 1.0
    return dirs


class ObjectScene:
    """Ray-casting scenes of one shape in its object frame, built once and reused for every view.

    Holds the object (and, for mugs, the handle alone) so that rendering a view, deciding handle
    visibility and computing ground-truth occupancy cost no scene rebuild.
    """

    def __init__(self, shape: Shape, threads: int = 0) -> None:
        """Args: shape: the object. threads: open3d threads per call (0 = all cores; 1 in dataset workers)."""
        self.shape = shape
        self.threads = int(threads)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(_o3d_mesh(shape.mesh))
        self._handle_scene: o3d.t.geometry.RaycastingScene | None = None
        if shape.handle is not None:
            self._handle_scene = o3d.t.geometry.RaycastingScene()
            self._handle_scene.add_triangles(_o3d_mesh(shape.handle))
        self.vertices = np.asarray(shape.mesh.vertices, dtype=np.float64)
        self._surface: dict[float, np.ndarray] = {}  # surface samples by voxel size

    def surface(self, voxel_size: float) -> np.ndarray:
        """Object-frame surface samples dense enough for ``voxel_size`` (cached: one set per grid resolution)."""
        if voxel_size not in self._surface:
            self._surface[voxel_size] = surface_samples(self.vertices, np.asarray(self.shape.mesh.faces), voxel_size)
        return self._surface[voxel_size]

    def _cast(self, scene: o3d.t.geometry.RaycastingScene, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = np.empty((*dirs.shape[:-1], 6), dtype=np.float32)
        rays[..., :3] = origin
        rays[..., 3:] = dirs
        return scene.cast_rays(o3d.core.Tensor(rays), nthreads=self.threads)["t_hit"].numpy()

    def occupancy(self, points_object: np.ndarray) -> np.ndarray:
        """Bool per point: inside the solid (object-frame points, (M, 3))."""
        if len(points_object) == 0:
            return np.zeros(0, dtype=bool)
        query = o3d.core.Tensor(np.ascontiguousarray(points_object, dtype=np.float32))
        return self._scene.compute_occupancy(query, nthreads=self.threads).numpy().astype(bool)

    def render(self, object_pose: np.ndarray, camera_pose: np.ndarray, intrinsics: CameraIntrinsics,
               slit: Slit | None = None, noise: SensorNoise | None = None, noise_seed: int = 0,
               quantize_mm: bool = True) -> RenderedView:
        """Renders the object at ``object_pose`` on the plane, seen from ``camera_pose``.

        Args:
            object_pose: (4, 4) world <- object; the object should rest on z = 0 (see :func:`object_pose`).
            camera_pose: (4, 4) world <- camera (optical frame).
            intrinsics: pinhole intrinsics (image size included).
            slit: optional vertical slit; columns outside it become unknown (depth 0, mask 0).
            noise: optional sensor imperfections (applied before the slit); None renders exact depth.
            noise_seed: seed of the noise (ignored without noise).
            quantize_mm: round depth to whole millimetres, as a 16UC1 sensor image stores it.

        Raises:
            SceneError: the object is not in front of the camera or not in the image.
        """
        object_pose = np.asarray(object_pose, dtype=np.float64)
        camera_pose = np.asarray(camera_pose, dtype=np.float64)
        h, w = intrinsics.height, intrinsics.width
        r_wc, position = camera_pose[:3, :3], camera_pose[:3, 3]
        if position[2] <= 0:
            raise SceneError(f"the camera is at or below the support plane (z = {position[2]:.3f} m)")
        cam_to_obj = np.linalg.inv(object_pose) @ camera_pose
        # Support plane z = 0, analytically: depth = -height / (world z of the unit-z ray).
        dirs = _pixel_rays(intrinsics, 0, w, 0, h)
        dz_world = dirs @ r_wc[2]
        with np.errstate(divide="ignore"):
            depth = np.where(dz_world < -1e-9, -position[2] / dz_world, np.inf)
        # The object only where its posed bounding box projects.
        corners_cam = (posed_box_corners(self.shape, object_pose) - position) @ r_wc
        if np.any(corners_cam[:, 2] <= 1e-3):
            raise SceneError("the object is not entirely in front of the camera")
        u, v, _ = intrinsics.project(corners_cam)
        u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, w)
        v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, h)
        if u0 >= u1 or v0 >= v1:
            raise SceneError("the object is outside the image")
        window = dirs[v0:v1, u0:u1] @ cam_to_obj[:3, :3].T
        origin = cam_to_obj[:3, 3]
        t_obj = self._cast(self._scene, origin, window)
        mask = np.zeros((h, w), dtype=np.uint8)
        hit = t_obj < depth[v0:v1, u0:u1]
        mask[v0:v1, u0:u1] = hit
        depth[v0:v1, u0:u1] = np.where(hit, t_obj, depth[v0:v1, u0:u1])
        depth = np.where(np.isfinite(depth), depth, 0.0)
        if not mask.any():
            raise SceneError("the object is hidden: no pixel sees it")
        centre_cam = (object_pose[:3, :3] @ self.shape.bounds.mean(axis=0) + object_pose[:3, 3] - position) @ r_wc
        object_depth = float(centre_cam[2])

        handle_visible = handle_area = None
        clean = depth
        if noise is not None:
            depth = noise.apply(depth, np.random.default_rng(noise_seed))
        slit_columns = None
        if slit is not None:
            slit_columns = self._slit_columns(slit, mask, intrinsics, object_depth)
            outside = np.ones(w, dtype=bool)
            outside[slit_columns[0]:slit_columns[1]] = False
            depth = depth.copy()
            depth[:, outside] = 0.0
            mask[:, outside] = 0
        if self._handle_scene is not None:
            t_handle = self._cast(self._handle_scene, origin, window)
            seen = (np.abs(t_handle - clean[v0:v1, u0:u1]) <= HANDLE_DEPTH_TOLERANCE) & (mask[v0:v1, u0:u1] != 0)
            handle_area = float(np.sum(t_obj[seen] ** 2) / (intrinsics.fx * intrinsics.fy))
            handle_visible = handle_area >= HANDLE_VISIBLE_AREA_M2
        if quantize_mm:
            depth = np.round(depth * 1000.0) / 1000.0
            depth[depth > 65.535] = 0.0  # beyond what a uint16 millimetre image holds
        return RenderedView(depth=depth.astype(np.float32), mask=mask, intrinsics=intrinsics,
                            camera_pose=camera_pose, object_pose=object_pose, up=r_wc.T @ np.array([0.0, 0.0, 1.0]),
                            handle_visible=handle_visible, handle_area_m2=handle_area, slit_columns=slit_columns,
                            object_depth=object_depth)

    @staticmethod
    def _slit_columns(slit: Slit, mask: np.ndarray, intrinsics: CameraIntrinsics,
                      object_depth: float) -> tuple[int, int]:
        columns = np.flatnonzero(mask.any(axis=0))
        visible_width = (columns[-1] + 1 - columns[0]) * object_depth / intrinsics.fx
        centre = 0.5 * (columns[0] + columns[-1]) + slit.offset(visible_width) * intrinsics.fx / object_depth
        half = 0.5 * slit.width_m * intrinsics.fx / object_depth
        u0 = int(np.clip(np.round(centre - half), 0, intrinsics.width))
        u1 = int(np.clip(np.round(centre + half), 0, intrinsics.width))
        if u1 <= u0:
            raise SceneError(f"the slit (width {slit.width_m} m, offset {slit.offset_m} m) lies outside the image")
        return u0, u1

    def ground_truth(self, object_pose: np.ndarray, grid_pose: GridPose, camera_pose: np.ndarray) -> np.ndarray:
        """(N, N, N) bool ground-truth occupancy; see :func:`ground_truth_occupancy`."""
        camera_from_object = np.linalg.inv(camera_pose) @ object_pose
        return solid_occupancy(grid_pose, camera_from_object, self.surface(grid_pose.voxel_size), self.occupancy)

    @staticmethod
    def _object_to_grid(points: np.ndarray, grid_to_object: np.ndarray, voxel_size: float) -> np.ndarray:
        return (points - grid_to_object[:3, 3]) @ grid_to_object[:3, :3] / voxel_size

    def grid_overshoot(self, object_pose: np.ndarray, grid_pose: GridPose, camera_pose: np.ndarray) -> float:
        """How far (in voxels) the object reaches beyond the grid; 0 when it lies entirely inside."""
        grid_to_object = np.linalg.inv(object_pose) @ camera_pose @ grid_pose.to_matrix()
        g = self._object_to_grid(self.vertices, grid_to_object, grid_pose.voxel_size)
        return float(max(0.0, -g.min(), g.max() - grid_pose.size))


def ground_truth_occupancy(shape: Shape, object_pose: np.ndarray, grid_pose: GridPose, camera_pose: np.ndarray,
                           scene: ObjectScene | None = None) -> np.ndarray:
    """The ground-truth solid occupancy of an object in an observation grid.

    The project's one definition (:func:`pssnet_core.geometry.solid_occupancy`): voxel (i, j, k) is occupied
    when its centre lies inside the watertight object mesh (open3d ``RaycastingScene.compute_occupancy``,
    ray-parity test) or the mesh surface passes through it.

    Args:
        shape: the object.
        object_pose: (4, 4) world <- object.
        grid_pose: the grid in the camera frame (``Observation.pose``).
        camera_pose: (4, 4) world <- camera.
        scene: an :class:`ObjectScene` of ``shape`` to reuse (built on the fly when None).

    Returns:
        (N, N, N) bool.
    """
    scene = scene if scene is not None else ObjectScene(shape)
    return scene.ground_truth(object_pose, grid_pose, camera_pose)


def box_in_grid(shape: Shape, object_pose: np.ndarray, grid_pose: GridPose, camera_pose: np.ndarray) -> np.ndarray:
    """The 24-D box: the 8 corners of the shape's object-frame bounding box, in grid coordinates.

    Corner order is :meth:`Shape.box_corners` (binary counting, x fastest); the result is the (8, 3)
    corners flattened row by row to (24,) float32, in voxel units.
    """
    world = posed_box_corners(shape, np.asarray(object_pose, dtype=np.float64))
    camera_pose = np.asarray(camera_pose, dtype=np.float64)
    camera = (world - camera_pose[:3, 3]) @ camera_pose[:3, :3]
    return grid_pose.camera_to_grid(camera).reshape(24).astype(np.float32)


def render_view(shape: Shape, yaw_deg: float = 0.0, distance: float = 0.7, tilt_deg: float = 30.0, *,
                tip_deg: float = 0.0, translation: tuple[float, float] = (0.0, 0.0), azimuth_deg: float = 180.0,
                aim_offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
                intrinsics: CameraIntrinsics | None = None, slit: Slit | None = None,
                noise: SensorNoise | None = None, noise_seed: int = 0, quantize_mm: bool = True,
                scene: ObjectScene | None = None) -> RenderedView:
    """Renders a shape standing on the support plane in one call.

    The object is posed by :func:`object_pose` (tip about x, yaw about z, dropped onto the plane, moved by
    ``translation``); the camera sits ``distance`` m from the centre of the posed object's bounding box
    (plus ``aim_offset``), looking down ``tilt_deg`` from ``azimuth_deg``. With the default azimuth, a mug
    at ``yaw_deg=0`` shows its back (handle hidden), at 180 its handle points at the camera, at 90 sideways.

    Example:
        >>> view = render_view(make_shape("mug", 3), yaw_deg=0.0, distance=0.6, tilt_deg=20.0)
        >>> obs = view.observe(GridConfig.for_size(32))

    Returns:
        The rendered view (depth in metres, mask, intrinsics, camera and object poses, up vector, handle flag).
    """
    intrinsics = intrinsics or CameraIntrinsics.kinect_like()
    scene = scene if scene is not None else ObjectScene(shape)
    pose = object_pose(shape.mesh, yaw_deg, tip_deg, translation)
    target = posed_box_corners(shape, pose).mean(axis=0) + np.asarray(aim_offset, dtype=np.float64)
    camera = orbit_camera(target, distance, tilt_deg, azimuth_deg)
    return scene.render(pose, camera, intrinsics, slit=slit, noise=noise, noise_seed=noise_seed,
                        quantize_mm=quantize_mm)


def crop_window(view: RenderedView, grid_pose: GridPose) -> tuple[int, int, int, int]:
    """Pixel window ``(v0, u0, v1, u1)`` that holds everything the observation of this view depends on.

    It covers the object's mask and the projection of the whole grid, widened by :data:`CROP_MARGIN_PX`
    (the free-space carving's largest min-filter footprint), so pasting the window into an otherwise
    empty image reproduces the observation exactly (see :func:`pssnet_core.data.samples.full_images`).
    """
    n = grid_pose.size
    corners = np.array([[i, j, k] for i in (0, n) for j in (0, n) for k in (0, n)], dtype=np.float64)
    cam = grid_pose.grid_to_camera(corners)
    rows, cols = np.nonzero(view.mask)
    h, w = view.depth.shape
    if np.all(cam[:, 2] > 1e-3):
        u, v, _ = view.intrinsics.project(cam)
        u_lo, u_hi, v_lo, v_hi = u.min(), u.max(), v.min(), v.max()
    else:  # part of the grid behind the camera: keep the whole image
        u_lo, u_hi, v_lo, v_hi = 0, w, 0, h
    if len(rows):
        u_lo, u_hi = min(u_lo, cols.min()), max(u_hi, cols.max())
        v_lo, v_hi = min(v_lo, rows.min()), max(v_hi, rows.max())
    m = CROP_MARGIN_PX
    v0 = int(np.clip(np.floor(v_lo) - m, 0, h))
    v1 = int(np.clip(np.ceil(v_hi) + m + 1, 0, h))
    u0 = int(np.clip(np.floor(u_lo) - m, 0, w))
    u1 = int(np.clip(np.ceil(u_hi) + m + 1, 0, w))
    return v0, u0, v1, u1
