"""Every grasp checked against every completion at once (see the package docstring for the rules)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pssnet_core.geometry import GridPose
from pssnet_core.grasps.config import GraspConfig, VoxelDims
from pssnet_core.grasps.inputs import check_occupancy
from pssnet_core.grasps.lattice import PackedGrids, box_or, lattice_count, lowest_point
from pssnet_core.grasps.results import GraspCandidates


def _extents(bits: PackedGrids, slices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(W, n, K) occupied-slice words -> first, last occupied slice and whether any, each (K, S).

    First and last are meaningless where there is none.
    """
    n = slices.shape[1]
    # Bit s of the running AND of the complements stays set while completion s has no object yet.
    before = bits.count(np.bitwise_and.accumulate(~slices, axis=1))
    after = bits.count(np.bitwise_and.accumulate(~slices[:, ::-1], axis=1))
    return before, n - 1 - after, before < n


@dataclass
class GraspChecks:
    """Why each grasp holds or not, per completion (see the package docstring for the rules).

    Attributes:
        fits: (K,) the opening fits the gripper.
        above: (K,) no gripper part reaches below the support plane.
        contains: (K, S) the closing region holds at least ``min_object_width`` of object.
        finger_hit: (K, S) a finger overlaps the completion.
        palm_hit: (K, S) the palm overlaps the completion.
        coverage: (K, S) fraction of the finger pads touching the object when the fingers close (0 if none).
        squeezed_out: (K, S) the object widens towards the fingertips where they hold it (its extent across the
            closing axis grows by a slice or more over the last row of pad cells): the pads meet a surface
            inclined towards the palm by more than ~27 degrees, outside a friction cone of coefficient 0.5, and
            closing pushes the object out of the hand (a fingertip pinch of a round body's near side).
        lever: (K, S) the arm (voxels) of completion s's weight about the grasp, the part of its moment that lies
            across the closing axis: the pads can resist that part only by pressing unevenly, which a small
            contact (a pinch of a handle from above and below) cannot. A moment about the closing axis itself is
            taken by friction over both pads (see ``resistance``).
        resistance: (K, S) the share of completion s's weight (at ``object_density``, acting at its centroid) that
            the two pads can hold by friction, capped at 1 (:func:`_weight_resistance`): a pad pressed with
            ``grip_force`` resists a tangential force and a twist about its normal (the closing axis) together up
            to the soft-finger limit ``(f / mu F)^2 + (tau / (mu F r))^2 <= 1``, r = the mean distance of its
            contact patch from the patch's centre. A pinch of a thin handle touches a narrow strip (small r) while
            the mug's weight hangs 6-7 cm away about the closing axis: the twist, not the weight, makes it slip.
    """

    fits: np.ndarray
    above: np.ndarray
    contains: np.ndarray
    finger_hit: np.ndarray
    palm_hit: np.ndarray
    coverage: np.ndarray
    squeezed_out: np.ndarray
    lever: np.ndarray
    resistance: np.ndarray

    @property
    def holds(self) -> np.ndarray:
        """(K, S) the grasp holds for the completion."""
        return ((self.fits & self.above)[:, None] & self.contains & ~self.finger_hit & ~self.palm_hit
                & ~self.squeezed_out)


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
    return checks_from_packed(candidates, PackedGrids(check_occupancy(occupancy, pose)), pose, support_z, config)


def checks_from_packed(candidates: GraspCandidates, bits: PackedGrids, pose: GridPose, support_z: float,
                       config: GraspConfig) -> GraspChecks:
    """:func:`check_grasps` on completions packed once (the planner generated the candidates on them)."""
    k, s = len(candidates), bits.num
    if k == 0:
        none = np.zeros((0, s), dtype=bool)
        return GraspChecks(np.zeros(0, bool), np.zeros(0, bool), none, none, none, np.zeros((0, s)), none,
                           np.zeros((0, s)), np.zeros((0, s)))
    dims = VoxelDims.of(config, pose.voxel_size)
    fl, fw, ft, wmax = dims.finger_length, dims.finger_width, dims.finger_thickness, dims.max_opening
    origins = np.asarray(candidates.origins, dtype=np.float64)
    rot = np.asarray(candidates.rotations, dtype=np.float64)
    widths = np.asarray(candidates.widths, dtype=np.float64)
    nx, nz = lattice_count(fw, 1.0), lattice_count(fl, 1.0)

    fits = widths <= wmax + 1e-9
    above = lowest_point(origins, rot, widths, dims) >= support_z + dims.plane_clearance - 1e-6

    # Closing region: the object's extent along the closing axis, and which pad cells face object.
    n_y = lattice_count(wmax, 1.0)
    closing = box_or(bits.data, bits.padded, origins, rot, np.array([0.0, 0.0, -fl / 2]),
                     np.stack([np.full(k, fw / 2), widths / 2, np.full(k, fl / 2)], axis=1), (nx, n_y, nz),
                     keep=(1, 0, 2)).reshape(len(bits.data), n_y, nx * nz, k)  # (W, n_y, pad cells, K)
    lo, hi, has = _extents(bits, np.bitwise_or.reduce(closing, axis=2))
    step = (widths / (n_y - 1))[:, None]  # slice spacing, voxels
    extent = (hi - lo + 1) * step
    contains = has & (extent >= dims.min_object_width - 1e-9)
    # Squeeze-out: the object's extent in the fingertip row of pad cells against the row behind it (rows are the
    # lattice's z, last = fingertips; cells are x-major).
    rows = np.bitwise_or.reduce(closing.reshape(len(bits.data), n_y, nx, nz, k)[:, :, :, nz - 2:], axis=2)
    row_extents = []  # (K, S) each: the fingertip row's, then the one behind it
    for row in (1, 0):
        row_lo, row_hi, row_has = _extents(bits, rows[:, :, row])
        row_extents.append(np.where(row_has, (row_hi - row_lo + 1) * step, 0.0))
    squeezed_out = row_extents[0] > row_extents[1] + 0.5 * step
    # Pad contact: closing each finger until it touches completion s (slice lo / hi), the pad cells whose
    # column meets object within one voxel of that first touch, i.e. at or before slice reach[k, s]. For all
    # completions at once: OR over slices i of the words masked to the completions with reach >= i, then bit s
    # of a cell's OR says whether it touches in completion s.
    tol = np.ceil(1.0 / (widths / (n_y - 1)) - 1e-9).astype(np.int64)[:, None]  # slices in one voxel
    slice_index = np.arange(n_y)[:, None, None]
    coverage = np.zeros((k, s))
    patches = []  # per pad: (pad cells, K, S) the cells touching
    for words, touch in ((closing, lo), (closing[:, ::-1], n_y - 1 - hi)):
        reach = bits.pack(np.clip(touch + tol, 0, n_y - 1)[None] >= slice_index)  # (W, n_y, K)
        touching = np.bitwise_or.reduce(words & reach[:, :, None, :], axis=1)  # (W, pad cells, K)
        coverage += bits.count(touching) / (nx * nz)
        patches.append(bits.unpack(touching) & has[None])
    coverage = np.where(has, coverage / 2.0, 0.0)

    # Fingers and palm.
    finger_hit = np.zeros((k, s), dtype=bool)
    for sign in (-1.0, 1.0):
        centre = np.stack([np.zeros(k), sign * (widths / 2 + ft / 2), np.full(k, -fl / 2)], axis=1)
        finger_hit |= bits.unpack(box_or(bits.data, bits.padded, origins, rot, centre,
                                         np.array([fw / 2, ft / 2, fl / 2]), (nx, lattice_count(ft, 1.0), nz),
                                         keep=()))
    palm_hit = bits.unpack(box_or(bits.data, bits.padded, origins, rot, np.array([0.0, 0.0, -fl - dims.palm_depth / 2]),
                                  np.array([fw / 2, wmax / 2 + ft, dims.palm_depth / 2]),
                                  (nx, lattice_count(wmax + 2 * ft, 1.0), lattice_count(dims.palm_depth, 1.0)),
                                  keep=()))
    return GraspChecks(fits, above, contains, finger_hit, palm_hit, coverage, squeezed_out,
                       _levers(bits, origins, rot, fl),
                       _weight_resistance(bits, origins, rot, patches, (fw, fl), (nx, nz), pose.voxel_size, config))


def _levers(bits: PackedGrids, origins: np.ndarray, rot: np.ndarray, finger_length: float) -> np.ndarray:
    """(K, S) :attr:`GraspChecks.lever`: each completion's centroid stands for its centre of mass (uniform density)."""
    centroids, counts = bits.mass_centres
    centre = origins - 0.5 * finger_length * rot[:, :, 2]  # middle of the closing region
    arm = centroids[None, :, :] - centre[:, None, :]  # (K, S, 3)
    moment = np.stack([-arm[..., 1], arm[..., 0], np.zeros(arm.shape[:2])], axis=2)  # arm x (0, 0, -1)
    closing = rot[:, None, :, 1]
    across = moment - np.sum(moment * closing, axis=2, keepdims=True) * closing
    return np.where(counts[None, :] > 0, np.linalg.norm(across, axis=2), 0.0)


def _weight_resistance(bits: PackedGrids, origins: np.ndarray, rot: np.ndarray, patches: list[np.ndarray],
                       pad: tuple[float, float], cells: tuple[int, int], voxel_size: float,
                       config: GraspConfig) -> np.ndarray:
    """(K, S) :attr:`GraspChecks.resistance` from each pad's touching cells ``patches`` ((nx * nz, K, S) each).

    The weight W (voxel count x voxel volume x density) acts at the completion's centroid; its moment is taken
    about the closing axis through the middle of the two contact patches. Each pad presses with F =
    ``grip_force`` and holds by its own contact patch (a pair of pads that touch a curved part at a point may
    roll on it, so no couple between the two pads is counted):

    - friction (coefficient mu): the weight's part across the closing axis, f = W sqrt(1 - y_z^2), and its
      moment about the closing axis, W d, shared in proportion to the patch radii r (the mean distance of a
      patch's cells from its centre), load both pads alike: ``W sqrt((f/2W)^2 + (d / (r_1 + r_2))^2) <= mu F``
      (the soft-finger limit surface);
    - pressure: the moment across the closing axis, W d', shifts each pad's centre of pressure towards the
      edge of its patch; the pads hold it while ``W d' <= F (e_1 + e_2)``, e = the patch's reach from its centre
      in the direction the pressure must shift;

    both together (the same pressure serves both) while the two loads' shares of their limits sum to <= 1.
    The weight's part along the closing axis, W y_z, is borne by the normal forces only if the hand holds an
    axial load (``GripperConfig.holds_axial_load``); otherwise any such part is not held (share 0).
    """
    (fw, fl), (nx, nz) = pad, cells
    # Pad cell (ix, iz), x-major, sits at gripper x = -fw/2 + ix fw/(nx-1), z = -fl + iz fl/(nz-1) (voxels).
    xs = np.linspace(-fw / 2, fw / 2, nx) if nx > 1 else np.zeros(1)
    zs = np.linspace(-fl, 0.0, nz) if nz > 1 else np.full(1, -fl / 2)
    cell_x, cell_z = (a.ravel()[:, None, None] for a in np.meshgrid(xs, zs, indexing="ij"))
    n = [touching.sum(axis=0) for touching in patches]
    centres = [((t * cell_x).sum(axis=0) / np.maximum(c, 1), (t * cell_z).sum(axis=0) / np.maximum(c, 1))
               for t, c in zip(patches, n, strict=True)]
    cx = 0.5 * (centres[0][0] + centres[1][0])
    cz = 0.5 * (centres[0][1] + centres[1][1])
    axis_point = origins[:, None, :] + cx[..., None] * rot[:, None, :, 0] + cz[..., None] * rot[:, None, :, 2]
    centroids, voxels = bits.mass_centres
    arm = centroids[None, :, :] - axis_point  # (K, S, 3) voxels
    # Moment of a unit weight (0, 0, -1) at the centroid: arm x (0, 0, -1) = (-arm_y, arm_x, 0).
    moment = np.stack([-arm[..., 1], arm[..., 0], np.zeros(arm.shape[:2])], axis=2)
    closing = rot[:, None, :, 1]
    twist = np.sum(moment * closing, axis=2)
    across = moment - twist[..., None] * closing
    bend = np.linalg.norm(across, axis=2)
    # The pressure shifts along closing x moment-direction, in the pad plane (gripper x, z components).
    shift = np.cross(closing, across / np.maximum(bend, 1e-12)[..., None])
    shift_x = np.sum(shift * rot[:, None, :, 0], axis=2)
    shift_z = np.sum(shift * rot[:, None, :, 2], axis=2)
    radius, reach = np.zeros(twist.shape), np.zeros(twist.shape)
    for touching, count, (px, pz) in zip(patches, n, centres, strict=True):
        dx, dz = cell_x - px, cell_z - pz
        radius += (touching * np.hypot(dx, dz)).sum(axis=0) / np.maximum(count, 1)
        reach += np.where(touching, np.abs(dx * shift_x + dz * shift_z), 0.0).max(axis=0)
    tangential = np.sqrt(np.clip(1.0 - closing[..., 2] ** 2, 0.0, 1.0))
    # Per newton of weight: the friction each pad needs, and the pressing force the pads need.
    friction_need = np.hypot(0.5 * tangential, np.abs(twist) / np.maximum(radius, 1e-9))
    pressure_need = bend / np.maximum(reach, 1e-9)
    weight = voxels * voxel_size**3 * config.object_density * 9.81  # (S,) newtons
    force = config.gripper.grip_force
    # The same pressure serves both: pressure shifted to a patch's edge shortens the lever of its torsional
    # friction. The linear interaction of the two loads is the conservative bound of their convex limit.
    holdable = 1.0 / np.maximum(friction_need / (config.friction * force) + pressure_need / force, 1e-12)
    if not config.gripper.holds_axial_load:  # force-controlled fingers: an axial load slides the pinch
        holdable = np.where(np.abs(closing[..., 2]) > 1e-6, 0.0, holdable)
    touched = (n[0] > 0) & (n[1] > 0) & (voxels[None, :] > 0)
    return np.where(touched, np.minimum(1.0, holdable / np.maximum(weight[None, :], 1e-12)), 0.0)


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
        holds (K, S) bool, and the secondary tie-break term (K,) in [0, 1] (see the package docstring).
    """
    config = config or GraspConfig()
    return holds_and_secondary(check_grasps(candidates, occupancy, pose, support_z, config), candidates, config,
                               pose.voxel_size)


def holds_and_secondary(checks: GraspChecks, candidates: GraspCandidates, config: GraspConfig,
                        voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """The (K, S) holds of ``checks`` and the secondary tie-break term (K,) of :func:`score_grasps`."""
    holds = checks.holds
    n_held = holds.sum(axis=1)

    def mean_over_held(values: np.ndarray) -> np.ndarray:
        return np.where(n_held > 0, (values * holds).sum(axis=1) / np.maximum(n_held, 1), 0.0)

    wmax = config.gripper.max_opening / voxel_size
    margin = np.clip((wmax - np.asarray(candidates.widths, dtype=np.float64)) / wmax, 0.0, 1.0)
    balance = mean_over_held(np.clip(1.0 - checks.lever / wmax, 0.0, 1.0))
    # Half the term: the share of the weight the pads hold (1 for every grasp that holds all of it, so those keep
    # the order of the other half among themselves).
    contact_term = 0.6 * mean_over_held(checks.coverage) + 0.2 * margin + 0.2 * balance
    return holds, 0.5 * mean_over_held(checks.resistance) + 0.5 * contact_term


def expected_grip(checks: GraspChecks, weights: np.ndarray | None = None) -> np.ndarray:
    """(K,) the expected grip of each grasp over the completions (``GraspConfig.rank_by = "expected_grip"``).

    Per completion: 0 where the grasp does not hold, else its pad contact times the share of the weight the pads
    hold; averaged with ``weights`` ((S,) summing to 1; None: alike). Where the completions disagree about the
    object's hidden extents, the grasp that holds for every one of them often does so by clipping an edge or a
    corner of each (the only place they all share): it touches little of the pads in each, and the real object
    likewise. The fraction held alone cannot tell it from a grasp that grips most completions flat.
    """
    per = checks.holds * checks.coverage * checks.resistance
    if per.shape[1] == 0:
        return np.zeros(per.shape[0])
    return per.mean(axis=1) if weights is None else per @ weights
