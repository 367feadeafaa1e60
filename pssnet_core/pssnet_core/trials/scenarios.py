"""The trial scenes: the paper's two robot anecdotes, randomised, and an unambiguous control.

Every scene is built from held-out objects (test-split seeds, never in training; an object whose collision
shape is not faithful, :class:`ScenarioConfig` ``max_volume_error``, is left out) and rendered with the
project's own depth renderer (:class:`pssnet_core.data.scenes.ObjectScene`, the code that made the training
data), with the clutter boxes composited in by ray casting. World frame: z up, table at z = 0, the object
stands at the origin, the camera looks along +x from the -x side (azimuth 180, as in the training data).

- ``mug_hidden_handle`` (a mug in a cupboard): a mug whose body is wider than the gripper opens (no grasp
  across the body), its handle turned away so that the camera cannot see it (yaw drawn in +-80 degrees
  and redrawn until the renderer's handle-visibility test says hidden). A shelf 4 cm above the rim covers
  the body (no pinch of the rim from above: the hand needs 6.5 cm above it) and two blocks stand beside
  it, clear of the handle, so the far side is the only way in and the hidden handle the only thing to
  hold. The camera looks down 5-20 degrees so that the shelf hides none of the mug (checked per scene:
  the clutter may cover at most 1 % of the object's pixels). The way out is 2 cm up (the shelf leaves 4)
  and then 15 cm back out of the cupboard, instead of the plain 15 cm lift.
- ``box_slit``: a box standing behind two blocks that leave a 3.6 cm slit at the box's depth (the paper's
  narrow test slit), the camera looking horizontally from the height of the box's top (its top face is
  edge-on) and a wall 37 cm behind the box's front: its depth along the view is hidden (and, as in the
  training views, its width beyond the slit), while the space above it is seen free. Boxes are turned so
  that either their long or their short side runs along the view (+-10 degrees), so the hidden depth ranges
  over 2.4-12.6 cm, both sides of the gripper's 8 cm opening: a grasp that closes across the depth fails
  when the box is deeper than it.
- ``mug_slit`` (asked for by name): a mug of ``mug_hidden_handle``'s kind behind the same slit, blocks and wall as
  ``box_slit``, turned at random about its axis (the handle anywhere, mostly out of the slit's view), the camera
  level with its rim (so it does not see into it). Only the rim or the handle can be held. Why: the shipped model
  never saw a mug behind a slit in training (only YCB-like objects), so this asks whether a slit alone makes it
  complete a mug as something else.
- ``control``: the same objects in full view, without clutter, camera looking down 25-45 degrees: even scene
  indices show a box at a random yaw, odd ones a mug with its handle visible.

The planner may use only grasps whose whole hand motion (pre-grasp, approach, exit) stays clear of the
clutter by ``clutter_margin``: :func:`clear_of_clutter`, passed to ``plan_grasps(allowed=...)``.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import ConvexHull

from pssnet_core.data.scenes import (
    ObjectScene,
    RenderedView,
    SceneError,
    object_pose,
    orbit_camera,
    posed_box_corners,
)
from pssnet_core.geometry import CameraIntrinsics, GridPose
from pssnet_core.grasps import GraspCandidates, GripperConfig
from pssnet_core.next_view import RING_PLACES
from pssnet_core.shapes import Shape, make_shape, split_seeds
from pssnet_core.shapes.independent import make_independent_shape
from pssnet_core.trials import ALL_SCENARIOS, OBJECT_SOURCES
from pssnet_core.trials.collision import (
    DEFAULT_CACHE_DIR,
    ConvexPart,
    DecompositionConfig,
    Faithfulness,
    decompose,
    measure_faithfulness,
)
from pssnet_core.trials.physics import ClutterBox, PhysicsConfig, PhysicsScene

MAX_ATTEMPTS = 30


class ScenarioError(ValueError):
    """A scenario cannot be built as asked; the message says why."""


@dataclass(frozen=True)
class ScenarioConfig:
    """How scenes are drawn.

    Attributes:
        objects: where the objects come from: ``procedural`` (test-split objects of the generator the training
            data came from) or ``independent`` (the independently written generator of the out-of-family test
            set, :mod:`pssnet_core.shapes.independent`: objects no training view was made by).
        mugs: size of the held-out mug pool (the first test-split mugs that qualify).
        boxes: size of the held-out box pool.
        shelf_gap: shelf bottom above the mug's rim (m).
        slit_width: slit width at the box's depth (m).
        clutter_margin: the planner keeps the hand this far from the clutter (m).
        max_occlusion: largest fraction of the object's pixels the clutter may hide (mug scenes, control).
        max_volume_error: objects whose collision shape's volume is off by more than this fraction (or, mugs,
            whose handle hole it closes) are left out of the pools.
        intrinsics: the depth camera.
        decomposition: CoACD options of the collision shapes.
        cache_dir: where decompositions are cached (None: no cache).
    """

    objects: str = "procedural"
    mugs: int = 24
    boxes: int = 24
    shelf_gap: float = 0.04
    slit_width: float = 0.036
    clutter_margin: float = 0.005
    max_occlusion: float = 0.01
    max_volume_error: float = 0.05
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics.kinect_like)
    decomposition: DecompositionConfig = field(default_factory=DecompositionConfig)
    cache_dir: Path | None = DEFAULT_CACHE_DIR

    def __post_init__(self) -> None:
        if self.objects not in OBJECT_SOURCES:
            raise ScenarioError(f"objects must be one of {OBJECT_SOURCES}, got {self.objects!r}")


@dataclass
class TrialScene:
    """One scene: what the camera sees, and what the physics engine holds.

    Attributes:
        scenario: scenario name.
        index: scene index within the scenario.
        physics: object, collision parts, clutter and exit path.
        view: the rendered view (depth and mask include the clutter).
        object_scene: ray-casting scene of the object (ground truth for the oracle).
        notes: what was drawn (object, yaw, hidden depth, ...), for the records.
        film_view: where the filmstrip's camera looks from: distance (m), azimuth and elevation (degrees,
            MuJoCo's free camera), chosen to see the hand and the object past the clutter.
        yaw_range_deg: the range the scenario draws a mug's yaw from (its prior over where the handle points), or
            None (boxes).
        pool: ray-casting scenes of the objects the scenario draws from (its prior over the object), boxes only.
    """

    scenario: str
    index: int
    physics: PhysicsScene
    view: RenderedView
    object_scene: ObjectScene
    notes: dict[str, float | str]
    film_view: tuple[float, float, float] = (0.6, 215.0, -30.0)
    yaw_range_deg: tuple[float, float] | None = None
    pool: tuple[ObjectScene, ...] = ()

    def ground_truth(self, grid: GridPose) -> np.ndarray:
        """(N, N, N) true occupancy of the object in an observation grid (the project's one definition)."""
        return self.object_scene.ground_truth(self.physics.object_pose, grid, self.view.camera_pose)

    def table_height(self, grid: GridPose) -> float:
        """Height of the table (world z = 0) in a gravity-aligned grid's coordinates (voxels)."""
        camera = self.view.camera_pose
        origin_z = float(camera[2, :3] @ grid.origin + camera[2, 3])
        return -origin_z / grid.voxel_size


def _held_out(family: str, objects: str) -> Iterator[Shape]:
    """Held-out ``family`` ("mug" or "box") objects of the source ``objects``, in seed order."""
    if objects == "procedural":
        return (make_shape(family, seed) for seed in split_seeds("test", 5000))
    # The out-of-family generator makes test objects only; its seeds follow the test split's numbering.
    return (make_independent_shape(f"i{family}", seed) for seed in range(2_000_000, 2_005_000))


def body_radii(shape: Shape) -> tuple[float, float]:
    """(largest, smallest) horizontal half-width of a mug's body about its axis (x = y = 0), in metres.

    Procedural mugs record both; for other mugs they are measured on the mesh's vertices within the recorded
    body radius (the handle reaches beyond it): the smallest half-width of their convex outline, which is what
    a gripper closing across the body meets.
    """
    a = shape.attributes
    if "radius" in a and "radius_min" in a:
        return float(a["radius"]), float(a["radius_min"])
    radius = float(a["body_radius_m"])
    xy = np.asarray(shape.mesh.vertices)[:, :2]
    xy = xy[np.linalg.norm(xy, axis=1) <= radius + 1e-4]
    hull = xy[ConvexHull(xy).vertices]
    edges = np.roll(hull, -1, axis=0) - hull
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / np.linalg.norm(edges, axis=1, keepdims=True)
    widths = (hull @ normals.T).max(axis=0) - (hull @ normals.T).min(axis=0)
    return radius, float(widths.min() / 2)


def held_out_mugs(gripper: GripperConfig, objects: str = "procedural") -> Iterator[Shape]:
    """Held-out mugs, in seed order, with a handle and a body wider than the gripper opens (+2 mm)."""
    for shape in _held_out("mug", objects):
        a = shape.attributes
        if a["has_handle"] and not a["square_body"] and 2 * body_radii(shape)[1] >= gripper.max_opening + 0.002:
            yield shape


def held_out_boxes(gripper: GripperConfig, objects: str = "procedural") -> Iterator[Shape]:
    """Standing held-out boxes, in seed order, whose short horizontal side fits the gripper (1 cm spare)."""
    for shape in _held_out("box", objects):
        extents = shape.mesh.extents
        standing = not shape.attributes["lying"] if "lying" in shape.attributes else extents[2] >= min(extents[:2])
        if standing and min(extents[:2]) <= gripper.max_opening - 0.01:
            yield shape


def clutter_depth(boxes: tuple[ClutterBox, ...], camera_pose: np.ndarray, intrinsics: CameraIntrinsics
                  ) -> np.ndarray:
    """(H, W) depth along the optical axis of the nearest clutter box (inf where none): also what a robot that
    knows its surroundings expects in front of the object from a camera it could move to."""
    h, w = intrinsics.height, intrinsics.width
    if not boxes:
        return np.full((h, w), np.inf)
    scene = o3d.t.geometry.RaycastingScene()
    for box in boxes:
        mesh = o3d.geometry.TriangleMesh.create_box(*(2.0 * np.asarray(box.half)))
        mesh.translate(np.asarray(box.centre) - np.asarray(box.half))
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    dirs = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones((h, w))], -1)
    rays = np.concatenate([np.broadcast_to(camera_pose[:3, 3], (h, w, 3)), dirs @ camera_pose[:3, :3].T], axis=-1)
    t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)), nthreads=1)["t_hit"].numpy()
    return t.astype(np.float64)  # directions have unit z in the camera frame: t is depth


def composite(view: RenderedView, boxes: tuple[ClutterBox, ...]) -> tuple[RenderedView, float]:
    """The view with the clutter in front of whatever it hides, and the fraction of object pixels hidden."""
    clutter = clutter_depth(boxes, view.camera_pose, view.intrinsics)
    seen = np.where(view.depth > 0, view.depth, np.inf)
    nearer = clutter < seen
    depth = np.where(nearer, np.round(clutter * 1000.0) / 1000.0, view.depth).astype(np.float32)
    depth[~np.isfinite(depth)] = 0.0
    object_pixels = int(view.mask.sum())
    hidden = float((nearer & (view.mask != 0)).sum()) / max(object_pixels, 1)
    mask = np.where(nearer, 0, view.mask).astype(np.uint8)
    return replace(view, depth=depth, mask=mask), hidden


def _rng(seed: int, scenario: str, index: int, attempt: int = 0) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(scenario.encode()), int(index), int(attempt)])


class SceneFactory:
    """Builds the scenes of every scenario from held-out object pools (decompositions cached)."""

    def __init__(self, config: ScenarioConfig | None = None, gripper: GripperConfig | None = None) -> None:
        self.config = config or ScenarioConfig()
        self.gripper = gripper or GripperConfig()
        self._mugs: list[Shape] | None = None
        self._boxes: list[Shape] | None = None
        self._scenes: dict[str, ObjectScene] = {}
        self.faithfulness: dict[str, Faithfulness] = {}  # every decomposition measured, by object
        self.rejected: list[str] = []  # objects left out because their collision shape was not faithful

    @property
    def mugs(self) -> list[Shape]:
        if self._mugs is None:
            self._mugs = self._pool(held_out_mugs(self.gripper, self.config.objects), self.config.mugs, "mugs")
        return self._mugs

    @property
    def boxes(self) -> list[Shape]:
        if self._boxes is None:
            self._boxes = self._pool(held_out_boxes(self.gripper, self.config.objects), self.config.boxes, "boxes")
        return self._boxes

    def _pool(self, candidates: Iterator[Shape], count: int, what: str) -> list[Shape]:
        """The first ``count`` candidates whose collision shape is faithful (volume within
        ``max_volume_error``, a mug's handle hole kept)."""
        pool: list[Shape] = []
        for shape in candidates:
            faithful = measure_faithfulness(shape, self.parts(shape))
            self.faithfulness[str(shape.identity)] = faithful
            if abs(faithful.volume_error) <= self.config.max_volume_error and faithful.hole_kept is not False:
                pool.append(shape)
                if len(pool) == count:
                    return pool
            else:
                self.rejected.append(str(shape.identity))
        raise ScenarioError(f"only {len(pool)} held-out {what} qualify, {count} asked for")

    def parts(self, shape: Shape) -> list[ConvexPart]:
        """The shape's collision parts (decomposed once, then from the disk cache)."""
        return decompose(shape.mesh, self.config.decomposition, self.config.cache_dir)

    def _object_scene(self, shape: Shape) -> ObjectScene:
        key = str(shape.identity)
        if key not in self._scenes:
            self._scenes[key] = ObjectScene(shape, threads=1)
        return self._scenes[key]

    def scene(self, scenario: str, index: int, seed: int = 0) -> TrialScene:
        """Scene ``index`` of ``scenario``; the same arguments always give the same scene.

        Raises:
            ScenarioError: unknown scenario, or no valid scene within :data:`MAX_ATTEMPTS` draws.
        """
        builders = {"mug_hidden_handle": self._mug_hidden_handle, "box_slit": self._box_slit,
                    "mug_slit": self._mug_slit, "control": lambda rng: self._control(rng, mug=index % 2 == 1)}
        if scenario not in builders:
            raise ScenarioError(f"unknown scenario {scenario!r}; expected one of {ALL_SCENARIOS}")
        for attempt in range(MAX_ATTEMPTS):
            shape, pose, camera, clutter, exit_path, notes, yaw_range = builders[scenario](
                _rng(seed, scenario, index, attempt))
            object_scene = self._object_scene(shape)
            view, hidden = composite(object_scene.render(pose, camera, self.config.intrinsics), clutter)
            if scenario == "mug_hidden_handle" and (view.handle_visible or hidden > self.config.max_occlusion):
                continue
            if scenario == "control" and shape.handle is not None and not view.handle_visible:
                continue
            notes = {**notes, "object": str(shape.identity), "occluded": round(hidden, 4), "attempt": attempt}
            physics = PhysicsScene(shape, self.parts(shape), pose, clutter, exit_path)
            # From behind and above (the robot's side); the box's wall stands behind it, so look from nearer.
            film_view = (0.45, 240.0, -30.0) if scenario in ("box_slit", "mug_slit") else (0.6, 215.0, -30.0)
            pool = tuple(self._object_scene(b) for b in self.boxes) if shape.handle is None else ()
            return TrialScene(scenario, index, physics, view, object_scene, notes, film_view, yaw_range, pool)
        raise ScenarioError(f"no valid {scenario} scene {index} in {MAX_ATTEMPTS} draws")

    # ---------------------------------------------------------------------------------------- builders

    def _mug_hidden_handle(self, rng: np.random.Generator):
        shape = self.mugs[int(rng.integers(len(self.mugs)))]
        yaw_range = (-80.0, 80.0)
        yaw = float(rng.uniform(*yaw_range))
        pose = object_pose(shape.mesh, yaw)
        radius, radius_min = body_radii(shape)
        height = float(shape.bounds[1, 2])
        reach = float(shape.bounds[1, 0])  # body axis to the handle's outer side
        shelf_z = height + self.config.shelf_gap
        shelf_x = (-radius - 0.015, radius + 0.005)  # from just in front of the body to just behind it
        side_y = reach + 0.01  # the blocks stand clear of the handle at any yaw
        shelf = ClutterBox(centre=(0.5 * sum(shelf_x), 0.0, shelf_z + 0.01),
                           half=(0.5 * (shelf_x[1] - shelf_x[0]), side_y + 0.05, 0.01), name="shelf")
        blocks = tuple(ClutterBox(centre=(0.5 * sum(shelf_x), sign * (side_y + 0.025), shelf_z / 2),
                                  half=(0.5 * (shelf_x[1] - shelf_x[0]), 0.025, shelf_z / 2), name="block")
                       for sign in (-1.0, 1.0))
        target = np.array([0.0, 0.0, height / 2]) + rng.uniform(-0.01, 0.01, size=3)
        camera = orbit_camera(target, float(rng.uniform(0.5, 0.8)), float(rng.uniform(5.0, 20.0)))
        notes = {"yaw_deg": round(yaw, 2), "body_diameter": round(2 * radius_min, 4)}
        return shape, pose, camera, (shelf, *blocks), ((0.0, 0.0, 0.02), (0.15, 0.0, 0.0)), notes, yaw_range

    def _box_slit(self, rng: np.random.Generator):
        shape = self.boxes[int(rng.integers(len(self.boxes)))]
        yaw = float(rng.choice([0.0, 90.0]) + rng.uniform(-10.0, 10.0))
        return self._behind_slit(rng, shape, yaw, None)

    def _mug_slit(self, rng: np.random.Generator):
        shape = self.mugs[int(rng.integers(len(self.mugs)))]
        yaw_range = (-180.0, 180.0)
        return self._behind_slit(rng, shape, float(rng.uniform(*yaw_range)), yaw_range)

    def _behind_slit(self, rng: np.random.Generator, shape: Shape, yaw: float,
                     yaw_range: tuple[float, float] | None):
        pose = object_pose(shape.mesh, yaw)
        corners = posed_box_corners(shape, pose)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        height = float(hi[2])
        centre = 0.5 * (lo + hi)
        # Level with the object's top (at most 3 mm below it): the top is edge-on, and the rays over the object
        # reach the wall, so the space above it is seen free all the way back. Lower down, the object hides
        # a wedge above its own top in which completions are free to make it taller behind its front face.
        target = np.array([centre[0], centre[1], height - rng.uniform(0.0, 0.003)])
        distance = float(rng.uniform(0.5, 0.8))
        camera = orbit_camera(target, distance, 0.0)
        gap = float(rng.uniform(0.03, 0.05))  # between the blocks' back faces and the box's front
        depth = 0.06
        front = float(lo[0]) - gap  # blocks' back face (x)
        # The slit's edges are the blocks' front inner edges: scale the slit at the box to their distance.
        camera_x = float(camera[0, 3])
        slit = self.config.slit_width * (front - depth - camera_x) / (float(centre[0]) - camera_x)
        offset = float(rng.uniform(-0.01, 0.01))
        tall = height + float(rng.uniform(0.02, 0.05))
        blocks = tuple(ClutterBox(centre=(front - depth / 2, offset + sign * (slit / 2 + 0.05), tall / 2),
                                  half=(depth / 2, 0.05, tall / 2), name="block") for sign in (-1.0, 1.0))
        # A wall well behind (beyond the grid and the hand's reach round the deepest box): rays over the box
        # read it, so the space above the box is seen free, as over a table in the training views.
        wall = ClutterBox(centre=(float(lo[0]) + 0.37, 0.0, 0.2), half=(0.01, 0.3, 0.2), name="wall")
        notes = {"yaw_deg": round(yaw, 2), "hidden_depth": round(float(hi[0] - lo[0]), 4),
                 "width": round(float(hi[1] - lo[1]), 4), "slit_offset": round(offset, 4)}
        return shape, pose, camera, (*blocks, wall), ((0.0, 0.0, 0.15),), notes, yaw_range

    def _control(self, rng: np.random.Generator, mug: bool):
        pool = self.mugs if mug else self.boxes
        shape = pool[int(rng.integers(len(pool)))]
        # A mug's handle turned towards the camera's side; a box at any yaw.
        yaw_range = (100.0, 260.0) if mug else (0.0, 360.0)
        yaw = float(rng.uniform(*yaw_range))
        pose = object_pose(shape.mesh, yaw)
        height = float(posed_box_corners(shape, pose)[:, 2].max())
        target = np.array([0.0, 0.0, height / 2]) + rng.uniform(-0.01, 0.01, size=3)
        camera = orbit_camera(target, float(rng.uniform(0.5, 0.8)), float(rng.uniform(25.0, 45.0)))
        return shape, pose, camera, (), ((0.0, 0.0, 0.15),), {"yaw_deg": round(yaw, 2)}, yaw_range if mug else None


@dataclass(frozen=True)
class LookCamera:
    """A place to look from: ``pose`` world <- camera, at ``azimuth_deg`` and ``elevation_deg`` about the object."""

    azimuth_deg: float
    elevation_deg: float
    pose: np.ndarray = field(repr=False)


def look_cameras(scene: TrialScene) -> list[LookCamera]:
    """Where a robot could take a second look from: a ring about the centre of what the first camera saw of the
    object, at that camera's distance, at every place of :data:`pssnet_core.next_view.RING_PLACES` (the
    first camera's own place left out). Some look through clutter; the choice of where to look
    (:mod:`pssnet_core.next_view`) knows the clutter and sees that."""
    view = scene.view
    seen = view.mask != 0
    v, u = np.nonzero(seen)
    points = view.intrinsics.backproject(u, v, view.depth[seen])
    target = points.mean(axis=0) @ view.camera_pose[:3, :3].T + view.camera_pose[:3, 3]
    distance = float(np.linalg.norm(view.camera_pose[:3, 3] - target))
    first = view.camera_pose[:3, 3]
    cameras = []
    for azimuth, elevation in RING_PLACES:
        pose = orbit_camera(target, distance, elevation, azimuth)
        if np.linalg.norm(pose[:3, 3] - first) > 0.05:
            cameras.append(LookCamera(azimuth, elevation, pose))
    return cameras


def render_look(scene: TrialScene, camera_pose: np.ndarray) -> RenderedView | None:
    """What a camera at ``camera_pose`` sees of the scene (the clutter in front of what it hides), or None when
    the object is not in its image."""
    try:
        view = scene.object_scene.render(scene.physics.object_pose, camera_pose, scene.view.intrinsics)
    except SceneError:
        return None
    return composite(view, scene.physics.clutter)[0]


def clear_of_clutter(poses: np.ndarray, widths: np.ndarray, clutter: tuple[ClutterBox, ...],
                     exit_path: tuple[tuple[float, float, float], ...], gripper: GripperConfig,
                     physics: PhysicsConfig, margin: float, step: float = 0.005) -> np.ndarray:
    """(K,) bool: the hand (palm and fingers at the grasp's width) stays ``margin`` clear of every clutter box
    at every pose along its motion: pre-grasp to grasp along the approach, then the exit path.

    Poses along the motion are taken every ``step`` metres; each (gripper box, clutter box) pair is tested
    exactly with the separating-axis theorem.

    Args:
        poses: (K, 4, 4) world <- gripper at the grasp.
        widths: (K,) planned openings (m).
        clutter: the static boxes.
        exit_path: the scenario's exit segments (world displacements).
        gripper: the gripper's dimensions.
        physics: for the pre-grasp distance.
        margin: clearance (m).
        step: spacing of the checked poses (m).
    """
    k = len(poses)
    ok = np.ones(k, dtype=bool)
    if not clutter or k == 0:
        return ok
    g = gripper
    fl, fw, ft, wmax = g.finger_length, g.finger_width, g.finger_thickness, g.max_opening
    # Gripper boxes in the gripper frame: (K, 3 parts, 3) centres and half extents.
    w = np.asarray(widths, dtype=np.float64)
    zeros = np.zeros(k)
    centres = np.stack([
        np.stack([zeros, w / 2 + ft / 2, np.full(k, -fl / 2)], axis=1),
        np.stack([zeros, -w / 2 - ft / 2, np.full(k, -fl / 2)], axis=1),
        np.broadcast_to([0.0, 0.0, -fl - g.palm_depth / 2], (k, 3)),
    ], axis=1)
    halves = np.stack([np.broadcast_to([fw / 2, ft / 2, fl / 2], (k, 3)),
                       np.broadcast_to([fw / 2, ft / 2, fl / 2], (k, 3)),
                       np.broadcast_to([fw / 2, wmax / 2 + ft, g.palm_depth / 2], (k, 3))], axis=1)
    rot = np.asarray(poses)[:, :3, :3]
    origin = np.asarray(poses)[:, :3, 3]
    world_centres = np.einsum("kij,kpj->kpi", rot, centres) + origin[:, None, :]  # (K, 3, 3)
    # Offsets of the hand along its motion, relative to the grasp pose (world).
    n_back = int(np.ceil(physics.pre_grasp / step)) + 1
    back = -np.linspace(0.0, physics.pre_grasp, n_back)[:, None] * rot[:, None, :, 2]  # (K, n_back, 3)
    path = [np.zeros(3)]
    for segment in exit_path:
        start, delta = path[-1], np.asarray(segment, dtype=np.float64)
        n = max(1, int(np.ceil(np.linalg.norm(delta) / step)))
        path.extend(start + delta * (i / n) for i in range(1, n + 1))
    offsets = np.concatenate([back, np.broadcast_to(np.asarray(path)[None], (k, len(path), 3))], axis=1)
    axes_a = rot  # (K, 3, 3): columns are the gripper axes (shared by all its boxes)
    for box in clutter:
        b_centre, b_half = np.asarray(box.centre), np.asarray(box.half) + margin
        # t: (K, P, parts, 3) from each gripper box's centre to the clutter box's centre.
        t = b_centre - (world_centres[:, None, :, :] + offsets[:, :, None, :])
        separated = np.zeros(t.shape[:3], dtype=bool)
        candidate_axes = [np.broadcast_to(np.eye(3)[i], (k, 3)) for i in range(3)]
        candidate_axes += [axes_a[:, :, j] for j in range(3)]
        candidate_axes += [np.cross(np.eye(3)[i], axes_a[:, :, j]) for i in range(3) for j in range(3)]
        for axis in candidate_axes:  # (K, 3)
            proj_a = np.einsum("kpj,kj->kp", halves, np.abs(np.einsum("kij,ki->kj", axes_a, axis)))  # (K, parts)
            proj_b = np.abs(axis) @ b_half  # (K,)
            distance = np.abs(np.einsum("kopi,ki->kop", t, axis))
            separated |= distance > (proj_a[:, None, :] + proj_b[:, None, None] + 1e-12)
        ok &= separated.all(axis=(1, 2))
    return ok


def allowed_by_clutter(scene: TrialScene, grid: GridPose, gripper: GripperConfig, physics: PhysicsConfig,
                       margin: float):
    """The ``allowed`` filter for ``plan_grasps``: grid-coordinate candidates -> clear of the scene's clutter."""
    camera_pose = scene.view.camera_pose

    def allowed(candidates: GraspCandidates) -> np.ndarray:
        k = len(candidates)
        poses = np.tile(np.eye(4), (k, 1, 1))
        poses[:, :3, :3] = camera_pose[:3, :3] @ np.einsum("ij,kjl->kil", grid.rotation, candidates.rotations)
        poses[:, :3, 3] = grid.grid_to_camera(candidates.origins) @ camera_pose[:3, :3].T + camera_pose[:3, 3]
        return clear_of_clutter(poses, candidates.widths * grid.voxel_size, scene.physics.clutter,
                                scene.physics.exit, gripper, physics, margin)

    return allowed
