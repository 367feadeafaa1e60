"""Every grasp checked against every completion at once (see the package docstring for the rules)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pssnet_core.geometry import GridPose
from pssnet_core.grasps.config import GraspConfig, VoxelDims
from pssnet_core.grasps.inputs import check_occupancy
from pssnet_core.grasps.lattice import PackedGrids, box_or, gripper_part_boxes, lattice_count, lowest_point
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


#: Object extent along the closing axis (voxels) from which the pads' contact normals are tested
#: (:func:`_outside_friction_cone`): 6 voxels (3.75 cm at 32^3) and more is a body or a box held across, whose faces a
#: pad meets over its width. Thinner parts (handles, rims, wires: a 6-12 mm tube is 1-2 voxels) have no resolved
#: section at this resolution: on the true shapes of the grasp trials' mugs the handle pinches that lifted read 30-47
#: degrees from their voxel normals, and a check from 3 voxels on left 17 % more of those mugs with no grasp.
MIN_NORMAL_EXTENT = 6.0

#: Between :data:`MIN_SOLID_NORMAL_EXTENT` and :data:`MIN_NORMAL_EXTENT` voxels across, the contact normals are also
#: tested where the pads hold a solid part: at least :data:`MIN_SOLID_SHARE` of the object between them lies in its
#: solid core (:attr:`PackedGrids.solid_cores`, inside a part 3 voxels thick every way). A box's edge or corner pinched
#: at the fingertips is such a part, and its faces span enough voxels for their normals to read true; a handle, however
#: it is pinched, is one or two voxels thick somewhere across and has little or no core.
MIN_SOLID_NORMAL_EXTENT = 3.0
MIN_SOLID_SHARE = 0.1


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
        squeezed_out: (K, S) where a pad touches the object, the surface is inclined to the closing axis by more
            than the friction angle ``atan(friction)`` (:func:`_outside_friction_cone`): the pad's push lies outside
            the friction cone, and closing pushes the object out of the hand or turns it (a pinch of a round
            body's chord: in the grasp trials the oracle's chords of mug bodies too wide for the hand missed or
            slipped). Judged only where every other check passes and the pads hold at least
            :data:`MIN_NORMAL_EXTENT` voxels of object across, or a solid part (:func:`_solid_pinch`) from
            :data:`MIN_SOLID_NORMAL_EXTENT` (False elsewhere).
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
    closing_box = (np.array([0.0, 0.0, -fl / 2]),  # centre, (K, 3) half extents, lattice counts
                   np.stack([np.full(k, fw / 2), widths / 2, np.full(k, fl / 2)], axis=1), (nx, n_y, nz))
    closing = box_or(bits.data, bits.padded, origins, rot, *closing_box,
                     keep=(1, 0, 2)).reshape(len(bits.data), n_y, nx * nz, k)  # (W, n_y, pad cells, K)
    lo, hi, has = _extents(bits, np.bitwise_or.reduce(closing, axis=2))
    step = (widths / (n_y - 1))[:, None]  # slice spacing, voxels
    extent = (hi - lo + 1) * step
    contains = has & (extent >= dims.min_object_width - 1e-9)
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
    centres, halves = gripper_part_boxes(widths, dims)
    finger_hit = np.zeros((k, s), dtype=bool)
    for part in (0, 1):
        finger_hit |= bits.unpack(box_or(bits.data, bits.padded, origins, rot, centres[:, part], halves[:, part],
                                         (nx, lattice_count(ft, 1.0), nz), keep=()))
    palm_hit = bits.unpack(box_or(bits.data, bits.padded, origins, rot, centres[:, 2], halves[:, 2],
                                  (nx, lattice_count(wmax + 2 * ft, 1.0), lattice_count(dims.palm_depth, 1.0)),
                                  keep=()))
    # The contact normals only where the rest holds and the pads hold a body across (MIN_NORMAL_EXTENT) or a solid
    # part (MIN_SOLID_NORMAL_EXTENT): on a handle, rim or wire the voxels do not resolve the part's section, and its
    # voxel normals read as tilted whichever way it lies.
    rest = (fits & above)[:, None] & contains & ~finger_hit & ~palm_hit
    judged = rest & ((extent >= MIN_NORMAL_EXTENT)
                     | _solid_pinch(bits, closing, closing_box, rest & (extent >= MIN_SOLID_NORMAL_EXTENT), origins,
                                    rot))
    squeezed_out = _outside_friction_cone(bits, origins, rot, widths, (lo, hi), n_y, patches, (fw, fl), (nx, nz),
                                          config.friction, judged)
    return GraspChecks(fits, above, contains, finger_hit, palm_hit, coverage, squeezed_out,
                       _levers(bits, origins, rot, fl),
                       _weight_resistance(bits, origins, rot, patches, (fw, fl), (nx, nz), pose.voxel_size, config))


def _solid_pinch(bits: PackedGrids, closing: np.ndarray, closing_box: tuple[np.ndarray, np.ndarray, tuple[int, ...]],
                 asked: np.ndarray, origins: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(K, S) where ``asked``: at least :data:`MIN_SOLID_SHARE` of the closing region's occupied lattice points
    (``closing``, (W, n_y, nx * nz, K) words of the box ``closing_box``: centre, (K, 3) half extents, lattice counts)
    lie in the completion's solid core (False elsewhere)."""
    solid = np.zeros(asked.shape, dtype=bool)
    grasps = np.flatnonzero(asked.any(axis=1))
    if not len(grasps):
        return solid
    centre, halves, counts = closing_box
    cores = bits.solid_cores
    in_core = box_or(cores.data, cores.padded, origins[grasps], rot[grasps], centre, halves[grasps], counts,
                     keep=(1, 0, 2))
    words = len(bits.data)
    core_points = cores.count(in_core.reshape(words, -1, len(grasps)))  # (K', S)
    object_points = bits.count(closing[..., grasps].reshape(words, -1, len(grasps)))
    solid[grasps] = asked[grasps] & (core_points >= MIN_SOLID_SHARE * np.maximum(object_points, 1))
    return solid


def _outside_friction_cone(bits: PackedGrids, origins: np.ndarray, rot: np.ndarray, widths: np.ndarray,
                           touch: tuple[np.ndarray, np.ndarray], slices: int, patches: list[np.ndarray],
                           pad: tuple[float, float], cells: tuple[int, int], friction: float,
                           judged: np.ndarray) -> np.ndarray:
    """(K, S) :attr:`GraspChecks.squeezed_out`: either pad meets a surface outside its friction cone (False where
    not ``judged``).

    A pad pushes along the closing axis; friction holds the contact only while that push lies within
    ``atan(friction)`` of the surface's inward normal (the antipodal condition). A pad's contact normal is the sum,
    over its touching cells (``patches``, (nx * nz, K, S) each), of the completion's inward surface normal
    (:attr:`PackedGrids.inward_normals`) one voxel before the cell's line across the closing region first meets
    the object (``touch``: (K, S) slice lo for the pad at -y, hi for the one at +y, of ``slices`` across
    ``widths``). Summed over the patch, a flat face's voxel staircase reads as its slope, and a pinch across a
    round part's middle as square to the axis.
    """
    outside = np.zeros(judged.shape, dtype=bool)
    grasp, completion = np.nonzero(judged)  # the pairs judged, P of them
    if not len(grasp):
        return outside
    (fw, fl), (nx, nz) = pad, cells
    xs = np.linspace(-fw / 2, fw / 2, nx) if nx > 1 else np.zeros(1)
    zs = np.linspace(-fl, 0.0, nz) if nz > 1 else np.full(1, -fl / 2)
    cell_x, cell_z = (a.ravel()[:, None, None] for a in np.meshgrid(xs, zs, indexing="ij"))
    axes = rot[grasp]  # (P, 3, 3)
    in_pad = origins[grasp][None] + cell_x * axes[None, :, :, 0] + cell_z * axes[None, :, :, 2]  # (C, P, 3)
    step = widths[grasp] / max(slices - 1, 1)
    normals, last = bits.inward_normals, bits.size - 1
    cos_limit = 1.0 / np.sqrt(1.0 + friction**2)
    for sign, first, touching in zip((1.0, -1.0), touch, patches, strict=True):
        # One voxel on the pad's side of the first contact: just outside the surface, where the gradient points
        # into the object even across a one-voxel-thick wall (at the wall's own voxel it cancels).
        across = (first[grasp, completion] * step - widths[grasp] / 2 - sign)[:, None] * axes[:, :, 1]  # (P, 3)
        voxel = np.clip(np.floor(in_pad + across[None]).astype(np.intp), 0, last)
        normal = np.einsum("cp,cpd->pd", touching[:, grasp, completion].astype(np.float32),
                           normals[completion[None], voxel[..., 0], voxel[..., 1], voxel[..., 2]])
        length = np.linalg.norm(normal, axis=1)
        cos = sign * np.einsum("pd,pd->p", normal, axes[:, :, 1]) / np.maximum(length, 1e-12)
        outside[grasp, completion] |= (length > 1e-9) & (cos < cos_limit)
    return outside


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


def observed_point_hits(candidates: GraspCandidates, points_grid: np.ndarray, dims: VoxelDims,
                        which: np.ndarray | None = None, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(K,) whether an observed point lies inside a finger, and (K,) inside the palm, of each candidate.

    The points are the camera's (grid coordinates), one kept per half-voxel cell (the test is then exact to a
    quarter voxel, and a fused view's tens of thousands of points cost what a few thousand do). Written with
    numpy rather than a collision library: every candidate's three boxes against the same few thousand points is
    one batched matrix product. ``which``: (K,) test only these candidates (the rest come out False).
    """
    k = len(candidates)
    finger, palm = np.zeros(k, dtype=bool), np.zeros(k, dtype=bool)
    if k == 0 or len(points_grid) == 0:
        return finger, palm
    _, first = np.unique(np.floor(points_grid * 2.0).astype(np.int64), axis=0, return_index=True)
    points = points_grid[np.sort(first)]
    index = np.flatnonzero(which) if which is not None else np.arange(k)
    centres, halves = gripper_part_boxes(candidates.widths, dims)
    for start in range(0, len(index), chunk):
        part = index[start:start + chunk]
        # each point in each candidate's gripper frame (x, y closing, z approach; origin between the fingertips)
        local = (points[None] - candidates.origins[part][:, None]) @ candidates.rotations[part]  # (k, M, 3)
        inside = [(np.abs(local - centres[part, p, None]) <= halves[part, p, None]).all(axis=-1).any(axis=1)
                  for p in range(3)]
        finger[part], palm[part] = inside[0] | inside[1], inside[2]
    return finger, palm


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
    return holds, 0.5 * weight_shares(checks) + 0.5 * contact_term


def weight_shares(checks: GraspChecks, weights: np.ndarray | None = None) -> np.ndarray:
    """(K,) the mean share of the weight each grasp's pads hold, over the completions it holds for (``weights``:
    (S,) summing to 1; None: alike); 0 where it holds for none (``GraspSet.weight_shares``)."""
    held = checks.holds.astype(np.float64)
    if weights is not None:
        held = held * weights
    total = held.sum(axis=1)
    return np.where(total > 0, (held * checks.resistance).sum(axis=1) / np.where(total > 0, total, 1.0), 0.0)


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
