"""Parallel-jaw grasps chosen against many sampled completions: grasps that hold whatever the hidden side is.

One call from completions to ranked grasps::

    grasps = plan_grasps(occupancy, observation.pose, observation.points, GraspConfig())
    grasps.poses[0]        # (4, 4) best grasp in the camera frame
    grasps.scores[0]       # fraction of the completions it holds for

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

How a grasp is judged against one completion (:func:`score_grasps`, module ``scoring``). A grasp *holds*
for completion s when
  1. its opening fits the gripper (``width <= max_opening``),
  2. no part of the gripper reaches below the support plane (analytic, from the boxes' corners),
  3. the closing region contains at least ``min_object_width`` of object along the closing axis,
  4. neither finger nor the palm overlaps an occupied voxel of s, and
  5. where the pads hold ``MIN_NORMAL_EXTENT`` (6) voxels or more of object across, each pad meets a surface within
     its friction cone: the push along the closing axis lies within ``atan(friction)`` of the surface's inward
     normal, the sum over the pad's touching cells of the gradient of the completion smoothed by one voxel. A pinch
     of a body's chord or of a box across its edges fails it (the pads push the object out of the hand, or turn
     it); handles, rims and wires, too thin for their voxel normals to mean anything, are not judged by it. From
     ``MIN_SOLID_NORMAL_EXTENT`` (3) voxels across it is also judged where at least ``MIN_SOLID_SHARE`` (10 %) of
     the object between the pads lies in the completion's solid core (the voxels left by a one-voxel erosion): the
     fingertips pinching a solid box's edge or corner, whose faces the voxels do resolve.
  6. in :func:`plan_grasps`, with ``GraspConfig.observed_points_check`` (on by default): no observed point (at the
     camera's resolution) lies inside a finger or the palm. Surface the camera saw is part of every completion,
     and the voxels alone can leave a finger room in the few millimetres where it was seen.
Volumes are tested on lattices of sample points (spacing at most one voxel along every axis, faces
included) transformed into the grid; a part "overlaps" s when any of its sample points falls in an
occupied voxel of s, i.e. the part overlaps the occupied voxel cubes to within the lattice resolution.
All completions are tested at once: the S occupancy grids are packed into one bit word per voxel (bit s =
completion s), so each sample point costs one gather and a bitwise OR, whatever S.

Score = (weighted) fraction of completions the grasp holds for. Grasps are ranked (``GraspConfig.rank_by``, default
``"expected_grip"``) by the *expected grip* :func:`~pssnet_core.grasps.scoring.expected_grip`, the (weighted) mean over
the completions of ``holds x pad contact x weight held`` (0 where it does not hold), or else by the score. Where the
completions disagree about hidden extents (a box behind a slit), the grasps that hold for all of them often clip
each one's edge or corner, and touch the real object with a corner of the pads: the fraction alone ranks them
first, and in the grasp trials they missed or slipped (issue 26). Ties are broken by the *secondary* term in [0, 1]:
``0.5 * weight held + 0.5 * (0.6 * pad contact + 0.2 * opening margin + 0.2 * balance)``. Weight held
(``GraspChecks.resistance``) is the mean over the completions the grasp holds for of the share of the completion's
weight (voxel volume x ``object_density``, at its centroid) that the pads can hold, capped at 1: each pad, pressed
with ``grip_force``, holds the weight's part across the closing axis and its moment about that axis by friction
(coefficient ``friction``) over its contact patch, up to the soft-finger limit ``(f / mu F)^2 + (tau / (mu F r))^2
<= 1`` (r = the patch's mean radius), and the moment across the axis by the spread of its pressure over the patch,
both at once while their shares of those limits sum to <= 1; a load along the closing axis is not held by
force-controlled fingers (``holds_axial_load``). ``GraspSet.weight_shares`` reports it per grasp, the mean over the
completions the grasp holds for (the service's ``grasp_weight_shares``). A pinch of a thin handle touches a narrow
strip while the mug's weight hangs 6-7 cm away about the closing axis: in the grasp trials such pinches slipped by
turning about the closing axis, and those with the larger twist per patch radius slipped more (records of
``grasp_trials/planner2``).
Grasps that hold the whole weight (body grasps on flat faces) keep the order of the other half. Pad contact is the
mean, over the completions the grasp holds for, of the fraction of the two finger pads (finger-width x finger-length
faces, sampled on the lattice) that touch the object when the fingers close on it: a pad cell touches when the
object along its line across the closing region lies within one voxel of the pad's first contact. Deep grasps on
faces square to the closing axis touch with the whole pad; fingertip grasps, and grasps across a box's corner or on
a slanted face, touch with a small part. Opening margin is ``(max_opening - width) / max_opening``: spare opening
tolerates pose error. Balance is the mean over the same completions of ``1 - lever / max_opening`` (clipped to [0,
1]), lever = the arm of the completion's weight (at its centroid) about the grasp, the part of the moment that lies
across the closing axis: two pads resist a moment about the closing axis by friction over both pads, but one across
it only by pressing unevenly, which a small contact cannot (in the grasp trials every grasp pinching a mug's handle
from above and below slipped, 9 of 9, where pinches across the handle held).

Candidates (:func:`generate_candidates`, module ``candidates``). Anchors are the surface voxels of the union
of the completions plus the observed points, drawn with a bias towards thin parts (``thin_anchor_bias``: a
handle offers few surface voxels, so uniform draws rarely propose a grasp on it). Orientations are a top approach
(straight down, ``top_yaws`` closing axes about the vertical), side approaches (``side_yaws`` horizontal
approach directions around the vertical, each with the closing axis horizontal and/or vertical: ``side_rolls``)
and the same approaches tilted downwards (``tilted_pitches``, e.g. 45 degrees), which reach a handle under a
shelf. For each (anchor, orientation) pair the hand slides along the approach until the palm would touch the
union of the completions (one voxel short) or, approaching downwards, until the fingertips would reach the
support plane: the deepest grasp. Shallow variants stop with the fingertips ``shallow_depths`` past the first
contact, so that a thin part in front of a body (a handle) can be pinched without the fingertips reaching the
body. Then the closing axis is swept at full opening (half-voxel resolution): in each completion, the run of
object along the closing axis through the anchor is measured; the completions whose run fits the gripper (with
``clearance`` on both sides) define the needed opening, ``width = their combined extent + 2 clearance`` (the
widest completion's extent when the runs share a side), and the grasp is re-centred on it. With
``surface_at_voxel_centres`` (default) the extent runs between the outermost voxels' centres, where the surface
passes on average (a voxel is occupied wherever the surface crosses it); a finger still never enters an occupied
voxel. A completion whose run does not fit is not held by this grasp; a run stops at the first empty slice, so a
mug's rim is pinched wall by wall rather than across the whole cup. Near-duplicates are dropped; at most
``max_candidates`` are kept (a seeded random subset). A caller's ``allowed`` filter (approaches clear of known
clutter) is applied before that subset, and pairs are drawn again, up to ``draw_rounds`` rounds, until
``max_candidates`` pass it.
Where the best grasp so found holds less than ``dense_below`` (0.9) of the weight, or none holds, :func:`plan_grasps`
searches again with more candidates, yaws, pitches and depths (``dense_*``) and ranks both searches' grasps together:
a handle in a cupboard leaves few candidates that hold, and the denser search finds firmer ones there, while an open
view's best grasp nearly always holds the whole weight and pays nothing (``results/grasp_trials/dense_below/``).
Deterministic given the seed.

Support plane: the grid is gravity aligned, so the plane is the horizontal plane ``z = support_z`` (grid
voxel units). Unless given, :func:`estimate_support_height` takes the lower of (a) the lowest observed point
(or, without points, the bottom face of the lowest known-occupied layer) and (b) the median over completions
of the bottom face of each completion's lowest occupied layer: the object rests on the plane, so the plane
is at or below everything seen, and lower still where the completions say the hidden bottom reaches lower
(the median ignores a single stray sample).

Modules: ``config`` (options), ``results`` (returned types), ``lattice`` (the bit kernel), ``inputs`` (checks,
support plane), ``candidates``, ``scoring``, ``planning`` (:func:`plan_grasps`, the single-completion
baseline), ``plotting``.
"""

from pssnet_core.grasps.candidates import approach_orientations, generate_candidates
from pssnet_core.grasps.config import GraspConfig, GraspError, GripperConfig
from pssnet_core.grasps.inputs import estimate_support_height
from pssnet_core.grasps.planning import plan_grasps, single_completion_choice
from pssnet_core.grasps.plotting import gripper_lines, gripper_segments, plot_grasps
from pssnet_core.grasps.results import (
    KIND_NAMES,
    GraspCandidates,
    GraspSet,
    SingleCompletionChoice,
    matrix_to_position_quaternion,
)
from pssnet_core.grasps.scoring import GraspChecks, check_grasps, expected_grip, score_grasps

__all__ = [
    "KIND_NAMES",
    "GraspCandidates",
    "GraspChecks",
    "GraspConfig",
    "GraspError",
    "GraspSet",
    "GripperConfig",
    "SingleCompletionChoice",
    "approach_orientations",
    "check_grasps",
    "expected_grip",
    "estimate_support_height",
    "generate_candidates",
    "gripper_lines",
    "gripper_segments",
    "matrix_to_position_quaternion",
    "plan_grasps",
    "plot_grasps",
    "score_grasps",
    "single_completion_choice",
]
