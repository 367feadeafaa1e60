"""The reference strategies' shapes: the true object changed only where the view cannot see, as an ideal sampler.

The question they answer: how many objects would the planner lift if a sampler drew exactly what the view allows?
That lies between the oracle (which knows the hidden side) and PSSNet (whose samples are also wrong where the view
*is* clear). These strategies see the true object: they are yardsticks for evaluation, not something a robot runs.

Proposals are variants of the scene's true object, voxelised with the project's one occupancy definition:

- a mug turned about its own vertical axis (object frame z, through x = y = 0) to every ``azimuth_step_deg``, so
  its handle goes round (:func:`pssnet_core.evaluation.handles.turned`); the body is a surface of revolution;
- any other object with each of its four vertical faces moved in or out along its own horizontal axes, in
  ``face_step`` steps (an affine stretch per axis, so the other faces stay where they are; the height stays).
  Faces are first moved one at a time; the offsets the view accepts for each are then combined (all
  combinations, or ``box_combinations`` of them drawn at random).

Each proposal is judged by the checked sampler's own check (:class:`pssnet_core.sampling.GridCheck` with the
node's :class:`~pssnet_core.sampling.CheckedSamplerConfig`), and ``num_samples`` of the accepted ones are chosen
and weighted the way the checked sampler chooses its samples (farthest point on Jaccard distance, weight = the
share of accepted proposals each stands for; when none is accepted, the least-violating ones, as the sampler
does). So this strategy is the node's default sampler with perfect proposals: the difference between it and
``pssnet`` is what the network's proposals cost. One difference since stop 58: when fewer variants than
``num_samples`` are accepted it returns only those, where the node's sampler makes the number up with its nearest misses
(``CheckedSamplerConfig.fill_with_nearest_misses``); the committed reference runs were made before that default.

The ``scene_posterior`` strategy proposes only what the scenario itself could have drawn (:func:`posterior_shapes`):
a mug's turns within the scenario's yaw range, the exact posterior of the hidden handle given the view (no sampler
that learned the mugs' distribution can expect more); or the scenario's own boxes at every sideways place the view
allows, a posterior under that stated prior (the scenario's own prior places the box where the camera aims, which
would give its hidden depth away).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import trimesh

from pssnet_core.data.scenes import ObjectScene, object_pose, posed_box_corners
from pssnet_core.evaluation.handles import turned
from pssnet_core.geometry import GridPose
from pssnet_core.sampling import CheckedSamplerConfig, GridCheck, spread_selection
from pssnet_core.shapes import Shape
from pssnet_core.spread import BitRows


@dataclass(frozen=True)
class PlausibleVariantsConfig:
    """How the true object's variants are proposed.

    Attributes:
        azimuth_step_deg: step of a mug's turns (degrees).
        face_step: step of a face's moves (metres).
        face_reach: farthest a face moves outwards (metres).
        min_extent: least extent a face's inward move leaves along its axis (metres).
        box_combinations: at most this many combinations of the faces' accepted offsets are judged.
    """

    azimuth_step_deg: float = 5.0
    face_step: float = 0.01
    face_reach: float = 0.12
    min_extent: float = 0.02
    box_combinations: int = 200

    def __post_init__(self) -> None:
        if not 0.5 <= self.azimuth_step_deg <= 90.0:
            raise ValueError(f"azimuth_step_deg must lie in [0.5, 90], got {self.azimuth_step_deg}")
        if not (0.001 <= self.face_step <= self.face_reach <= 0.5 and 0.0 < self.min_extent <= 0.2):
            raise ValueError(f"need 0.001 <= face_step <= face_reach <= 0.5 and 0 < min_extent <= 0.2 (m), got "
                             f"{self.face_step}, {self.face_reach}, {self.min_extent}")
        if self.box_combinations < 1:
            raise ValueError(f"box_combinations must be >= 1, got {self.box_combinations}")


@dataclass(frozen=True)
class PlausibleShapes:
    """The chosen variants.

    Attributes:
        occupancy: (n, N, N, N) bool, the samples.
        weights: (n,) share of the accepted variants each stands for (sums to 1).
        proposed: variants judged.
        accepted: variants the check accepted (0: none, then ``occupancy`` holds the least-violating ones).
    """

    occupancy: np.ndarray
    weights: np.ndarray
    proposed: int
    accepted: int


def _stretched(shape: Shape, bounds: np.ndarray) -> Shape:
    """``shape`` mapped affinely along x and y so that its horizontal bounds become ``bounds`` ((2, 2): min, max of
    x and y; the other faces stay where they are)."""
    old = shape.bounds[:, :2]
    vertices = np.array(shape.mesh.vertices, dtype=np.float64)
    vertices[:, :2] = bounds[0] + (vertices[:, :2] - old[0]) * (bounds[1] - bounds[0]) / (old[1] - old[0])
    return Shape(identity=shape.identity, mesh=trimesh.Trimesh(vertices=vertices, faces=np.asarray(shape.mesh.faces),
                                                               process=False))


@dataclass(frozen=True)
class Variants:
    """Proposed variants and the check's verdict.

    Attributes:
        grids: (P, N, N, N) bool.
        packed: the same, bit-packed (:class:`~pssnet_core.spread.BitRows`).
        ok: (P,) the check accepts it.
        badness: (P,) how badly it violates the view (:meth:`pssnet_core.sampling.GridCheck.badness`).
        judged: variants judged in all (also those screened out before ``grids``).
    """

    grids: np.ndarray
    packed: BitRows
    ok: np.ndarray
    badness: np.ndarray
    judged: int


class VariantJudge:
    """Voxelises variants of one scene's object in the observation grid and judges them with the checked sampler's
    check."""

    def __init__(self, shape: Shape, object_pose: np.ndarray, camera_pose: np.ndarray, known_occupied: np.ndarray,
                 known_free: np.ndarray, grid: GridPose, sampler: CheckedSamplerConfig) -> None:
        self.shape = shape
        self.object_pose = np.asarray(object_pose, dtype=np.float64)
        self.camera_pose = np.asarray(camera_pose, dtype=np.float64)
        self.grid = grid
        self.sampler = sampler
        self.check = GridCheck.prepare(known_occupied, known_free, grid, sampler.delta)
        self._scene = ObjectScene(shape, threads=1)

    def turned(self, azimuths_deg: np.ndarray) -> np.ndarray:
        """(A, N, N, N) bool: the object turned about its vertical axis by each azimuth."""
        return np.stack([self._scene.ground_truth(turned(self.object_pose, a), self.grid, self.camera_pose)
                         for a in azimuths_deg])

    def stretched(self, bounds: list[np.ndarray]) -> np.ndarray:
        """(B, N, N, N) bool: the object with each of the horizontal ``bounds`` (see :func:`_stretched`)."""
        return np.stack([ObjectScene(_stretched(self.shape, b), threads=1).ground_truth(
            self.object_pose, self.grid, self.camera_pose) for b in bounds])

    def placed(self, scene: ObjectScene, poses: list[np.ndarray]) -> np.ndarray:
        """(P, N, N, N) bool: another object (its ray-casting scene) at each world pose."""
        return np.stack([scene.ground_truth(pose, self.grid, self.camera_pose) for pose in poses])

    def judge(self, occupancy: np.ndarray) -> tuple[BitRows, np.ndarray, np.ndarray]:
        """For (P, N, N, N) grids: the grids bit-packed, which of them the checked sampler's check keeps, and how
        badly each violates the view (as the sampler orders them when it keeps none)."""
        flat = occupancy.reshape(len(occupancy), -1)
        packed = BitRows.pack(flat)
        missed, free = self.check.violations(flat, packed)
        ok = self.sampler.accepts(missed, free, np.ones(len(flat), dtype=bool))
        return packed, ok, self.check.badness(missed, free)

    def accepts(self, occupancy: np.ndarray) -> np.ndarray:
        """(P,) bool: which of the (P, N, N, N) grids the checked sampler's check keeps."""
        return self.judge(occupancy)[1]


def face_offsets(extent: float, config: PlausibleVariantsConfig) -> np.ndarray:
    """Outward moves (metres) of one face of an object ``extent`` long along the face's axis: 0, then inwards as
    far as ``min_extent`` leaves and outwards to ``face_reach``."""
    inward = max(0, math.floor((extent - config.min_extent) / config.face_step + 1e-9))
    outward = math.floor(config.face_reach / config.face_step + 1e-9)
    return np.arange(-inward, outward + 1) * config.face_step


def box_variants(judge: VariantJudge, config: PlausibleVariantsConfig, rng: np.random.Generator) -> Variants:
    """Horizontal stretches of the object (the true shape first): every face alone, then combinations of the
    offsets each face allows alone (only the combinations are returned)."""
    base = judge.shape.bounds[:, :2].copy()
    judged = 0
    accepted_offsets: list[np.ndarray] = []
    for face in range(4):  # x min, x max, y min, y max
        axis, side = divmod(face, 2)
        offsets = face_offsets(float(base[1, axis] - base[0, axis]), config)
        offsets = offsets[offsets != 0.0]
        bounds = []
        for d in offsets:
            b = base.copy()
            b[side, axis] += d if side == 1 else -d
            bounds.append(b)
        ok = judge.accepts(judge.stretched(bounds)) if bounds else np.zeros(0, dtype=bool)
        judged += len(bounds)
        accepted_offsets.append(np.concatenate([[0.0], offsets[ok]]))
    extents = base[1] - base[0]
    combos = [c for c in itertools.product(*accepted_offsets)  # both faces of an axis moved in: keep min_extent
              if min(extents[0] + c[0] + c[1], extents[1] + c[2] + c[3]) >= config.min_extent - 1e-9]
    if len(combos) > config.box_combinations:  # the truth (all zero) is the first combination
        keep = np.concatenate([[0], 1 + rng.choice(len(combos) - 1, config.box_combinations - 1, replace=False)])
        combos = [combos[i] for i in np.sort(keep)]
    bounds = []
    for combo in combos:
        b = base.copy()
        b[0, 0] -= combo[0]
        b[1, 0] += combo[1]
        b[0, 1] -= combo[2]
        b[1, 1] += combo[3]
        bounds.append(b)
    grids = judge.stretched(bounds)
    return Variants(grids, *judge.judge(grids), judged + len(grids))


def within_yaw_range(yaw_deg: float, turns_deg: np.ndarray, yaw_range_deg: tuple[float, float]) -> np.ndarray:
    """Which turns put an object at ``yaw_deg`` at a yaw inside ``yaw_range_deg`` (degrees, low to high; wraps)."""
    low, high = yaw_range_deg
    return np.mod(yaw_deg + np.asarray(turns_deg, dtype=np.float64) - low, 360.0) <= (high - low) + 1e-9


def mug_variants(judge: VariantJudge, config: PlausibleVariantsConfig, yaw_deg: float = 0.0,
                 yaw_range_deg: tuple[float, float] | None = None) -> Variants:
    """Turns of the mug (the true pose first); with ``yaw_range_deg`` only the turns that leave the mug (now at
    ``yaw_deg``) inside that range."""
    azimuths = np.arange(0.0, 360.0, config.azimuth_step_deg)
    if yaw_range_deg is not None:
        azimuths = azimuths[within_yaw_range(yaw_deg, azimuths, yaw_range_deg)]
    grids = judge.turned(azimuths)
    return Variants(grids, *judge.judge(grids), len(grids))


def pool_variants(judge: VariantJudge, pool: tuple[ObjectScene, ...], yaw_deg: float, observed: np.ndarray,
                  config: PlausibleVariantsConfig) -> Variants:
    """The scenario's own boxes placed as the view allows.

    Each box of ``pool`` stands at the seen box's yaw or a quarter turn from it (the seen face shows the yaw only up
    to a quarter turn: through a slit narrower than the face, wide and narrow faces look alike), with its face
    nearest the camera where the seen box's is
    (the camera sees that face through the slit) and its height within ``face_step`` of the seen box's (the camera
    sees its top edge). It is moved sideways in ``face_step`` steps to every place where it covers the observed
    points (``observed``: (M, 3) world). Nothing here reads where the scene put the box, which the camera's aim
    would give away (the scenario aims the camera at the box's centre).
    """
    forward = judge.camera_pose[:3, 2].copy()
    forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    side = np.array([-forward[1], forward[0], 0.0])
    seen = posed_box_corners(judge.shape, judge.object_pose)
    front, height = float((seen @ forward).min()), float(seen[:, 2].max())
    lo, hi = float((observed @ side).min()), float((observed @ side).max())
    placed = []
    for scene in pool:
        for yaw in (yaw_deg, yaw_deg + 90.0):
            base = object_pose(scene.shape.mesh, yaw)
            corners = posed_box_corners(scene.shape, base)
            if abs(float(corners[:, 2].max()) - height) > config.face_step:
                continue
            along, across = corners @ forward, corners @ side
            # Lateral shifts that keep the box over every observed point, face_step apart.
            shifts = np.arange(math.ceil((hi - across.max()) / config.face_step - 1e-9),
                               math.floor((lo - across.min()) / config.face_step + 1e-9) + 1) * config.face_step
            poses = []
            for shift in shifts:
                pose = base.copy()
                pose[:3, 3] += (front - along.min()) * forward + shift * side
                poses.append(pose)
            if poses:
                placed.append(judge.placed(scene, poses))
    if not placed:  # no box of the pool is as tall as the seen one: the truth alone, as least violating
        placed.append(judge.turned(np.zeros(1)))
    grids = np.concatenate(placed)
    return Variants(grids, *judge.judge(grids), len(grids))


def spread_choice(variants: Variants, num_samples: int) -> PlausibleShapes:
    """``num_samples`` of the variants, chosen and weighted as the checked sampler chooses
    (:func:`pssnet_core.sampling.spread_selection`, without its fill: see the module's docstring)."""
    chosen, weights = spread_selection(variants.packed, variants.ok, variants.badness, num_samples)
    return PlausibleShapes(variants.grids[chosen], weights.astype(np.float32), variants.judged, int(variants.ok.sum()))


def plausible_shapes(judge: VariantJudge, num_samples: int, config: PlausibleVariantsConfig | None = None,
                     seed: int = 0) -> PlausibleShapes:
    """``num_samples`` variants of the judge's object that its view allows (a mug's turns, another object's face
    stretches), chosen and weighted as the checked sampler chooses."""
    config = config or PlausibleVariantsConfig()
    if judge.shape.handle is not None:
        return spread_choice(mug_variants(judge, config), num_samples)
    return spread_choice(box_variants(judge, config, np.random.default_rng(seed)), num_samples)


def posterior_shapes(judge: VariantJudge, num_samples: int, yaw_deg: float,
                     yaw_range_deg: tuple[float, float] | None, pool: tuple[ObjectScene, ...], observed: np.ndarray,
                     config: PlausibleVariantsConfig | None = None) -> PlausibleShapes:
    """``num_samples`` of what the view allows under the scenario's own prior: a mug's turns that keep it (now at
    ``yaw_deg``) inside ``yaw_range_deg``, the exact posterior of its hidden handle; or the scenario's own boxes
    (``pool``) placed as :func:`pool_variants` places them. Chosen and weighted as the checked sampler chooses."""
    config = config or PlausibleVariantsConfig()
    if judge.shape.handle is not None:
        return spread_choice(mug_variants(judge, config, yaw_deg, yaw_range_deg), num_samples)
    return spread_choice(pool_variants(judge, pool, yaw_deg, observed, config), num_samples)
