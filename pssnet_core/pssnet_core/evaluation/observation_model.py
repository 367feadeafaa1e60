"""Observation model (the paper's Alg. 1): does a candidate shape explain an observed depth image?

A candidate (a watertight mesh at a pose in the test camera's frame) is rendered from the test camera into an
*expected* depth image, only over a window that holds the observed object and the candidate's projection (plus
a margin); outside that window the candidate casts no ray, so nothing is lost. Each observed pixel is then:

- **excluded** when it has no reading (depth 0 or NaN: slit-occluded pixels, holes), or lies outside the
  stored crop;
- **unreliable** when the observed depth gradient there exceeds ``delta`` (forward differences, as
  ``tf.image.image_gradients`` in the authors' code), inflated by one pixel (3x3 dilation): silhouette and
  self-occlusion edges, where a sub-pixel misalignment makes an arbitrarily large depth difference;
- otherwise **compared**:

  * an object pixel (mask on, valid reading ``O``) is violated when ``|E - O| > delta`` (a candidate with no
    surface there, ``E = inf``, violates);
  * a non-object pixel with a valid reading (support, background) is violated when the candidate lies in front
    of that reading by more than ``delta`` (``O - E > delta``): the camera saw through the place the candidate
    occupies. A candidate *behind* a non-object reading is hidden by it and so consistent. ``+inf`` depth
    means "saw nothing up to infinity": any candidate surface there violates.

The candidate is plausible iff the number of violations is at most the outlier allowance
(``outlier_count + floor(outlier_fraction * number of valid object pixels)``; 0 by default, as in the paper).

With a background that is far and uniform (the paper's object-only images) this is exactly "every reliable
pixel differs by at most delta"; the non-object rule generalises it to scenes with a support surface and an
occluder: the expected image of a scene where the candidate replaces the object is ``min(E, O)`` at pixels
that do not show the object, whose difference to ``O`` is ``max(0, O - E)``.

Gradient source: the paper says "depth gradient"; the authors' code takes the gradient of the expected image.
We take the observed image's gradient by default (``gradient="observed"``: the unreliable set is then a property
of the observation alone, which makes the plausible-set prefilter provably safe); ``"expected"`` and ``"both"``
are available.

Depth convention: depth is metres along the optical axis; pixel (u, v) looks along ``((u + o - cx) / fx,
(v + o - cy) / fy, 1)`` where ``o = pixel_offset`` (0 matches :func:`pssnet_core.geometry.CameraIntrinsics.backproject`;
0.5 matches open3d's ``create_rays_pinhole``). Use the convention the test images were rendered with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage

from pssnet_core.geometry import CameraIntrinsics, GridPose, solid_occupancy, surface_samples


class ObservationModelError(ValueError):
    """Bad input to the observation model (shapes, poses, parameters)."""


GRADIENT_SOURCES = ("observed", "expected", "both")


@dataclass(frozen=True)
class ObservationModelConfig:
    """Parameters of the observation model.

    Attributes:
        delta: depth tolerance in metres (paper: 0.04; about 0.01 plays its role for real-size mugs).
        outlier_count: violations always allowed.
        outlier_fraction: further violations allowed, as a fraction of the view's valid object pixels.
        gradient: which image's depth gradient marks unreliable pixels: "observed", "expected" or "both".
        inflate: unreliable pixels are dilated by this many pixels (paper: 1).
        margin_px: extra pixels rendered around the window (>= inflate + 1 so edges are seen).
        pixel_offset: 0.0 if integer pixel coordinates are pixel centres, 0.5 for open3d's pinhole rays.
        min_depth: readings closer than this (metres) count as no reading.
        max_depth: finite readings farther than this count as no reading.
    """

    delta: float = 0.04
    outlier_count: int = 0
    outlier_fraction: float = 0.0
    gradient: str = "observed"
    inflate: int = 1
    margin_px: int = 3
    pixel_offset: float = 0.0
    min_depth: float = 0.05
    max_depth: float = 20.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.delta) and self.delta > 0):
            raise ObservationModelError(f"delta must be a positive number of metres, got {self.delta}")
        if self.outlier_count < 0:
            raise ObservationModelError(f"outlier_count must be >= 0, got {self.outlier_count}")
        if not 0.0 <= self.outlier_fraction < 1.0:
            raise ObservationModelError(f"outlier_fraction must be in [0, 1), got {self.outlier_fraction}")
        if self.gradient not in GRADIENT_SOURCES:
            raise ObservationModelError(f"gradient must be one of {GRADIENT_SOURCES}, got {self.gradient!r}")
        if self.inflate < 0 or self.margin_px < self.inflate + 1:
            raise ObservationModelError(
                f"need inflate >= 0 and margin_px >= inflate + 1, got inflate={self.inflate} "
                f"margin_px={self.margin_px}")

    def with_delta(self, delta: float) -> ObservationModelConfig:
        """A copy with another delta."""
        return ObservationModelConfig(delta=delta, outlier_count=self.outlier_count,
                                      outlier_fraction=self.outlier_fraction, gradient=self.gradient,
                                      inflate=self.inflate, margin_px=self.margin_px,
                                      pixel_offset=self.pixel_offset, min_depth=self.min_depth,
                                      max_depth=self.max_depth)

    @property
    def has_allowance(self) -> bool:
        return self.outlier_count > 0 or self.outlier_fraction > 0


def _as_pose(matrix: np.ndarray, name: str) -> np.ndarray:
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ObservationModelError(f"{name} must be a finite 4x4 transform, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5) or np.linalg.det(rotation) < 0:
        raise ObservationModelError(f"{name} must be a rigid transform (rotation part not orthonormal)")
    return matrix


@dataclass(frozen=True)
class DepthView:
    """One observed depth image (or a crop of one) of the test object.

    Attributes:
        depth: (h, w) float metres; 0/NaN/out of range = no reading (excluded), +inf = saw nothing.
        mask: (h, w), non-zero = the test object.
        intrinsics: pinhole intrinsics of the *full* image.
        offset: (u0, v0): the full-image pixel of the crop's top-left pixel.
    """

    depth: np.ndarray
    mask: np.ndarray
    intrinsics: CameraIntrinsics
    offset: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        depth = np.asarray(self.depth)
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise ObservationModelError(f"depth must be a 2-D float image, got {depth.shape} {depth.dtype}")
        if np.shape(self.mask) != depth.shape:
            raise ObservationModelError(f"mask shape {np.shape(self.mask)} differs from depth shape {depth.shape}")
        u0, v0 = self.offset
        if u0 < 0 or v0 < 0 or u0 + depth.shape[1] > self.intrinsics.width or \
                v0 + depth.shape[0] > self.intrinsics.height:
            raise ObservationModelError(
                f"crop {depth.shape[1]}x{depth.shape[0]} at offset {self.offset} does not fit the "
                f"{self.intrinsics.width}x{self.intrinsics.height} image")

    def object_points(self, pixel_offset: float = 0.0, min_depth: float = 0.05, max_depth: float = 20.0) -> np.ndarray:
        """(M, 3) camera-frame points of the object pixels with a finite reading."""
        depth = np.asarray(self.depth, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ok = (np.asarray(self.mask) != 0) & np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth)
        rows, cols = np.nonzero(ok)
        z = depth[rows, cols]
        k = self.intrinsics
        u0, v0 = self.offset
        return np.stack([(cols + u0 + pixel_offset - k.cx) * z / k.fx, (rows + v0 + pixel_offset - k.cy) * z / k.fy,
                         z], axis=1)


def depth_gradient_mask(depth: np.ndarray, delta: float, inflate: int = 1) -> np.ndarray:
    """Pixels whose depth gradient exceeds ``delta``, dilated by ``inflate`` pixels.

    The gradient is the larger absolute forward difference along rows and columns. Differences involving a
    no-reading pixel (NaN) do not count; a finite/inf pair counts as an edge (infinite difference).
    """
    d = np.asarray(depth, dtype=np.float64)
    edge = np.zeros(d.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        dx = np.abs(d[:, 1:] - d[:, :-1])
        dy = np.abs(d[1:, :] - d[:-1, :])
        edge[:, :-1] |= dx > delta
        edge[:-1, :] |= dy > delta
    if inflate > 0 and edge.any():
        edge = ndimage.binary_dilation(edge, structure=np.ones((3, 3), dtype=bool), iterations=inflate)
    return edge


class PreparedView:
    """A view with the per-view parts of the observation model computed once (for many candidates).

    Args:
        view: the observed depth view.
        config: observation-model parameters.
    """

    def __init__(self, view: DepthView, config: ObservationModelConfig) -> None:
        self.view = view
        self.config = config
        depth = np.asarray(view.depth, dtype=np.float64)
        finite = np.isfinite(depth) & (depth >= config.min_depth) & (depth <= config.max_depth)
        infinite = np.isposinf(depth)
        self.valid = finite | infinite
        self.object = (np.asarray(view.mask) != 0) & finite
        # Observed depth with no-reading pixels as NaN, "saw nothing" as +inf.
        self.observed = np.where(finite, depth, np.where(infinite, np.inf, np.nan))
        if config.gradient in ("observed", "both"):
            self.unreliable = depth_gradient_mask(self.observed, config.delta, config.inflate)
        else:
            self.unreliable = np.zeros(depth.shape, dtype=bool)
        self.num_object_pixels = int(self.object.sum())
        self.allowance = config.outlier_count + int(math.floor(config.outlier_fraction * self.num_object_pixels))
        rows, cols = np.nonzero(self.object)
        self.object_box = None if len(rows) == 0 else (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)

    @cached_property
    def reliable_object_points(self) -> np.ndarray:
        """(M, 3) camera-frame points of the reliable (compared) object pixels."""
        rows, cols = np.nonzero(self.object & ~self.unreliable)
        u0, v0 = self.view.offset
        k = self.view.intrinsics
        o = self.config.pixel_offset
        z = self.observed[rows, cols]
        return np.stack([(cols + u0 + o - k.cx) * z / k.fx, (rows + v0 + o - k.cy) * z / k.fy, z], axis=1)

    @cached_property
    def max_ray_scale(self) -> float:
        """Largest ``|(x/z, y/z, 1)|`` over the reliable object pixels: converts a depth gap to a 3-D distance."""
        p = self.reliable_object_points
        if len(p) == 0:
            return 1.0
        return float(np.sqrt(1.0 + ((p[:, 0] / p[:, 2]) ** 2 + (p[:, 1] / p[:, 2]) ** 2).max()))


@dataclass(frozen=True)
class PlausibilityResult:
    """Outcome of one candidate check.

    Attributes:
        plausible: the candidate explains the view (violations <= allowance).
        violations: compared pixels that differ by more than delta.
        compared: pixels compared (valid reading, reliable, inside the rendered window).
        allowance: violations allowed.
        max_object_error: largest |E - O| over compared object pixels (metres; inf if the candidate misses one).
    """

    plausible: bool
    violations: int
    compared: int
    allowance: int
    max_object_error: float


class MeshRaycaster:
    """Renders expected depth of one mesh at any pose (one open3d scene per mesh, rays moved into its frame).

    Args:
        vertices: (V, 3) mesh vertices in the object frame (metres).
        faces: (F, 3) triangle indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import open3d as o3d  # local: the metrics run without open3d

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(faces, dtype=np.uint32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or len(self.faces) == 0:
            raise ObservationModelError("a candidate mesh needs (V, 3) vertices and at least one face")
        self._o3d = o3d
        self._surface: dict[float, np.ndarray] = {}
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.faces))

    @classmethod
    def from_trimesh(cls, mesh: object) -> MeshRaycaster:
        """From a ``trimesh.Trimesh`` (anything with ``vertices`` and ``faces``)."""
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces))

    @cached_property
    def diameter(self) -> float:
        """Largest distance between two points of the mesh (metres), from its convex hull."""
        from scipy.spatial import ConvexHull

        pts = self.vertices.astype(np.float64)
        try:
            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # degenerate (flat) meshes: use all vertices
            pass
        if len(pts) > 4000:
            pts = pts[:: int(np.ceil(len(pts) / 4000))]
        diff = pts[:, None, :] - pts[None, :, :]
        return float(np.sqrt((diff**2).sum(-1).max()))

    def project_box(self, camera_from_object: np.ndarray, intrinsics: CameraIntrinsics,
                    pixel_offset: float) -> tuple[float, float, float, float] | None:
        """Pixel bounds (u_min, u_max, v_min, v_max) of the projected vertices; None if any is behind the camera."""
        pose = np.asarray(camera_from_object, dtype=np.float32)
        p = self.vertices @ pose[:3, :3].T + pose[:3, 3]
        if (p[:, 2] <= 1e-6).any():
            return None
        u = intrinsics.fx * p[:, 0] / p[:, 2] + intrinsics.cx - pixel_offset
        v = intrinsics.fy * p[:, 1] / p[:, 2] + intrinsics.cy - pixel_offset
        return float(u.min()), float(u.max()), float(v.min()), float(v.max())

    def depth(self, camera_from_object: np.ndarray, intrinsics: CameraIntrinsics, us: np.ndarray,
              vs: np.ndarray, pixel_offset: float = 0.0) -> np.ndarray:
        """Expected depth (metres along the optical axis, inf = no hit) at full-image pixel grid ``vs x us``.

        Args:
            camera_from_object: 4x4 pose of the mesh in the camera frame.
            intrinsics: full-image intrinsics.
            us: (w,) pixel columns; vs: (h,) pixel rows.
            pixel_offset: see :class:`ObservationModelConfig`.

        Returns:
            (h, w) float64.
        """
        uu, vv = np.meshgrid(np.asarray(us, dtype=np.float64), np.asarray(vs, dtype=np.float64))
        return self.depth_at(camera_from_object, intrinsics, uu.reshape(-1), vv.reshape(-1),
                             pixel_offset).reshape(uu.shape)

    def depth_at(self, camera_from_object: np.ndarray, intrinsics: CameraIntrinsics, u: np.ndarray, v: np.ndarray,
                 pixel_offset: float = 0.0) -> np.ndarray:
        """Expected depth at the listed full-image pixels ``(u[k], v[k])``; (K,) float64, inf = no hit."""
        o3d = self._o3d
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        # Directions with unit z in the camera frame: the hit distance is then the depth along the optical axis,
        # and a rigid motion of the rays keeps it.
        d_cam = np.stack([(u + pixel_offset - intrinsics.cx) / intrinsics.fx,
                          (v + pixel_offset - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], axis=-1)
        rotation = camera_from_object[:3, :3]
        origin = -rotation.T @ camera_from_object[:3, 3]  # camera centre in the object frame
        rays = np.empty((len(d_cam), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = d_cam @ rotation  # rows are R^T d
        return self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)

    def inside(self, points_object: np.ndarray) -> np.ndarray:
        """Which object-frame points (M, 3) lie inside the watertight mesh."""
        query = self._o3d.core.Tensor(np.ascontiguousarray(points_object, dtype=np.float32))
        return self.scene.compute_occupancy(query).numpy().astype(bool)

    def surface(self, voxel_size: float) -> np.ndarray:
        """Object-frame surface samples dense enough for ``voxel_size`` (cached per voxel size)."""
        if voxel_size not in self._surface:
            self._surface[voxel_size] = surface_samples(self.vertices, self.faces, voxel_size)
        return self._surface[voxel_size]

    def occupancy_grid(self, pose: GridPose, camera_from_object: np.ndarray) -> np.ndarray:
        """The mesh at ``camera_from_object`` voxelised in ``pose``'s grid (the project's one definition,
        :func:`pssnet_core.geometry.solid_occupancy`)."""
        return solid_occupancy(pose, camera_from_object, self.surface(pose.voxel_size), self.inside)


def render_window(prepared: PreparedView, raycaster: MeshRaycaster,
                  camera_from_object: np.ndarray) -> tuple[tuple[int, int, int, int], np.ndarray]:
    """Renders the candidate over the crop window it can influence.

    The window is the union of the observed object's box and the candidate's projected box, grown by
    ``margin_px`` and clipped to the crop. Returns ((r0, r1, c0, c1) in crop pixels, expected depth (r1-r0, c1-c0)).
    """
    view, cfg = prepared.view, prepared.config
    h, w = view.depth.shape
    u0, v0 = view.offset
    boxes = []
    if prepared.object_box is not None:
        boxes.append(prepared.object_box)
    proj = raycaster.project_box(camera_from_object, view.intrinsics, 0.0)
    if proj is None:
        boxes.append((0, h, 0, w))  # part of the candidate behind the camera: render the whole crop
    else:
        pu0, pu1, pv0, pv1 = proj
        boxes.append((int(math.floor(pv0)) - v0, int(math.ceil(pv1)) + 1 - v0,
                      int(math.floor(pu0)) - u0, int(math.ceil(pu1)) + 1 - u0))
    m = cfg.margin_px
    r0 = max(0, min(b[0] for b in boxes) - m)
    r1 = min(h, max(b[1] for b in boxes) + m)
    c0 = max(0, min(b[2] for b in boxes) - m)
    c1 = min(w, max(b[3] for b in boxes) + m)
    if r1 <= r0 or c1 <= c0:
        return (0, 0, 0, 0), np.zeros((0, 0))
    expected = raycaster.depth(camera_from_object, view.intrinsics, np.arange(c0, c1) + u0,
                               np.arange(r0, r1) + v0, cfg.pixel_offset)
    return (r0, r1, c0, c1), expected


def compare_depth(prepared: PreparedView, window: tuple[int, int, int, int], expected: np.ndarray,
                  delta: float | None = None) -> PlausibilityResult:
    """Applies the pixel rules to an expected depth window (see the module docstring).

    Args:
        prepared: the observed view.
        window: (r0, r1, c0, c1) crop pixels of ``expected``.
        expected: expected depth over the window (inf = no surface).
        delta: overrides the config's delta (the unreliable set must have been prepared with the same delta
            when the gradient comes from the observation; see :class:`MultiDeltaView`).
    """
    cfg = prepared.config
    delta = cfg.delta if delta is None else delta
    r0, r1, c0, c1 = window
    observed = prepared.observed[r0:r1, c0:c1]
    valid = prepared.valid[r0:r1, c0:c1]
    obj = prepared.object[r0:r1, c0:c1]
    unreliable = prepared.unreliable[r0:r1, c0:c1]
    if cfg.gradient in ("expected", "both") and expected.size:
        unreliable = unreliable | depth_gradient_mask(expected, delta, cfg.inflate)
    compared = valid & ~unreliable
    with np.errstate(invalid="ignore"):
        obj_error = np.abs(expected - observed)
        obj_error = np.where(np.isnan(obj_error), np.inf, obj_error)  # inf - inf: candidate absent where nothing seen
        obj_viol = compared & obj & (obj_error > delta)
        # Candidate in front of a non-object reading: it would have hidden what the camera saw.
        bg_viol = compared & ~obj & np.isfinite(expected) & (observed - expected > delta)
    violations = int(obj_viol.sum() + bg_viol.sum())
    obj_compared = compared & obj
    max_err = float(obj_error[obj_compared].max()) if obj_compared.any() else 0.0
    return PlausibilityResult(plausible=violations <= prepared.allowance, violations=violations,
                              compared=int(compared.sum()), allowance=prepared.allowance,
                              max_object_error=max_err)


class MultiDeltaView:
    """One view prepared for several deltas: render each candidate once, judge it at every delta.

    With ``early_reject`` (only with the observed-gradient rule, where the reliable object pixels do not depend
    on the candidate), a candidate is first checked on a sparse, fixed sample of reliable object pixels; if it
    already has more violations there than allowed at every delta it is rejected without the full render.
    This is exact, not an approximation: those pixels are compared in the full check too, so violations found
    among them are violations of the full check.

    Args:
        view: the observed view.
        config: base parameters (its delta is ignored).
        deltas: the deltas to judge at.
        sparse_pixels: size of the sparse sample (0 disables the early check).
    """

    def __init__(self, view: DepthView, config: ObservationModelConfig, deltas: tuple[float, ...],
                 sparse_pixels: int = 96) -> None:
        if not deltas:
            raise ObservationModelError("need at least one delta")
        self.deltas = tuple(float(d) for d in deltas)
        self.prepared = {d: PreparedView(view, config.with_delta(d)) for d in self.deltas}
        # The rendered window depends only on the object box and the candidate: the same for every delta.
        self.any = self.prepared[self.deltas[0]]
        self.sparse: tuple[np.ndarray, np.ndarray] | None = None
        if sparse_pixels > 0 and config.gradient == "observed":
            reliable = np.logical_and.reduce([p.object & ~p.unreliable for p in self.prepared.values()])
            rows, cols = np.nonzero(reliable)
            if len(rows):
                pick = np.linspace(0, len(rows) - 1, min(sparse_pixels, len(rows))).round().astype(np.int64)
                self.sparse = (rows[pick], cols[pick])

    def _sparse_rejects(self, raycaster: MeshRaycaster, camera_from_object: np.ndarray) -> bool:
        rows, cols = self.sparse
        view, cfg = self.any.view, self.any.config
        u0, v0 = view.offset
        expected = raycaster.depth_at(camera_from_object, view.intrinsics, cols + u0, rows + v0, cfg.pixel_offset)
        error = np.abs(expected - self.any.observed[rows, cols])
        return all(int((error > d).sum()) > p.allowance for d, p in self.prepared.items())

    def judge(self, raycaster: MeshRaycaster, camera_from_object: np.ndarray) -> dict[float, PlausibilityResult] | None:
        """Results per delta for the candidate mesh at ``camera_from_object`` (rendered once).

        Returns None when the sparse check already rejects it at every delta.
        """
        camera_from_object = _as_pose(camera_from_object, "camera_from_object")
        if self.sparse is not None and self._sparse_rejects(raycaster, camera_from_object):
            return None
        window, expected = render_window(self.any, raycaster, camera_from_object)
        return {d: compare_depth(p, window, expected) for d, p in self.prepared.items()}
