"""Gripper and planning options (metres, validated on construction) and the gripper's sizes in voxels."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


class GraspError(ValueError):
    """Grasp planning input or configuration is invalid; the message says exactly what is wrong."""


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
        grip_force: force each finger presses on the object when closed (newtons); a Franka Hand holds up to 70 N
            continuously, a Robotiq 2F-85 20-235 N.
        holds_axial_load: whether the hand holds a load along the closing axis. False: each finger presses with
            ``grip_force`` on its own (force control), so the pads push on the object with equal and opposite
            forces and a load along the axis carries the object and both fingers along it until a finger
            stops (in the grasp trials a mug pinched from above and below sinks with the fingers and falls).
            True for fingers coupled by a stiff, non-backdrivable drive.
    """

    max_opening: float = 0.08
    finger_length: float = 0.05
    finger_width: float = 0.02
    finger_thickness: float = 0.01
    palm_depth: float = 0.02
    min_object_width: float = 0.005
    grip_force: float = 20.0
    holds_axial_load: bool = False

    def __post_init__(self) -> None:
        values = {"max_opening": self.max_opening, "finger_length": self.finger_length,
                  "finger_width": self.finger_width, "finger_thickness": self.finger_thickness,
                  "palm_depth": self.palm_depth, "min_object_width": self.min_object_width}
        if isinstance(self.grip_force, bool) or not isinstance(self.grip_force, int | float) \
                or not 0.1 <= self.grip_force <= 1000.0:
            raise GraspError(f"gripper grip_force must be in [0.1, 1000] N, got {self.grip_force!r}")
        if not isinstance(self.holds_axial_load, bool):
            raise GraspError(f"gripper holds_axial_load must be a bool, got {self.holds_axial_load!r}")
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


RANKINGS = ("expected_grip", "fraction")


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
        tilted_pitches: approaches pitched this many degrees below the horizontal (0 < pitch < 90), at every
            side yaw and with every side roll (0 = closing axis horizontal); () = none. They reach parts that a
            level or a straight-down hand cannot, e.g. a handle under a shelf.
        shallow_depths: besides the deepest grasp (palm one voxel short of the object), grasps whose fingertips
            go only this far past the first contact (metres): a shallow pinch of a handle whose body a deep
            grasp's fingertips would hit; () = deepest only.
        thin_anchor_bias: anchors are drawn with probability proportional to ``density ** -thin_anchor_bias``,
            density = occupied voxels of the completions' union within 2 voxels of the anchor. A thin part (a
            handle) has few surface voxels, so uniform draws (0) rarely propose a grasp on it.
        clearance: free space left between each finger pad and the widest completion (metres).
        surface_at_voxel_centres: the clearance is measured from the completions' surface taken through the
            centres of their outermost voxels, not from those voxels' outer faces (a finger still never enters an
            occupied voxel, so it keeps ``max(clearance - voxel / 2, 0)`` from the faces). A voxel is occupied
            wherever the surface passes through it (:func:`pssnet_core.geometry.solid_occupancy`), so measured
            from the faces every object reads on average a voxel wider than it is: a box 6.5 cm across reads 7.5
            cm at 32^3 (6.25 mm voxels), and with 5 mm on each side the 8 cm hand cannot close across it. In the
            grasp trials the planner, on the true shape of such boxes behind the slit, then pinched their corners
            and 13 of 100 slipped; with it the true shape lifts 99 of them. The completions of a second look are
            less exact than a voxelised true shape, and there the narrower openings cost 1-4.5 points behind the
            slit (``results/grasp_trials/voxel_centres/``). Off: the rule of the planner before stop 45.
        plane_clearance: every gripper part stays at least this far above the support plane (metres).
        oversample: raw (anchor, orientation) pairs generated per kept candidate, before de-duplication.
        draw_rounds: with an ``allowed`` filter (e.g. approaches clear of known clutter), up to this many rounds of
            ``oversample x max_candidates`` raw pairs are drawn until ``max_candidates`` distinct candidates pass
            it or a round loses none to it; without one, one round.
        friction: Coulomb friction coefficient between the finger pads and the object, for the weight check (0.5:
            the usual conservative value for rubber pads on ceramic, plastic or cardboard).
        object_density: density assumed for every completion's voxels when the weight check turns volume into
            weight (kg/m^3). 1000 (water, a filled container) lies between packed cardboard boxes (~400) and
            solid ceramic (~2300); a voxel solid overstates a thin wall's volume, so a thin-walled ceramic mug
            comes out heavier than it is.
        rank_by: how grasps are ranked. ``"expected_grip"`` (default): by the expected grip over the completions'
            weights, ``sum_s w_s holds_s coverage_s resistance_s`` (pad contact x share of the weight held, 0 where
            the grasp does not hold), then the score, then the tie-break term. A grasp that holds for every
            completion by clipping each one's edge or corner (little pad contact) ranks below one that grips most of
            them flat: behind a slit, where the completions disagree about the hidden extents, the first kind
            touches the real box with part of the pads and misses or slips (issue 26). ``"fraction"``: by the
            (weighted) fraction of completions held (the score), then the tie-break term.
        observed_points_check: a grasp holds for no completion when an observed point (``plan_grasps``' points, at
            the camera's resolution) lies inside a finger or the palm at the grasp. The completions are voxels and
            the fingers are tested against them on a lattice, so a finger can be placed in the few millimetres
            where the camera saw surface; behind the slit, after a second look, 11 of the 22 grasps that hit the box
            in the grasp trials had observed points inside a finger or the palm, none of 50 that lifted it
            (``results/second_look/README.md``). On by default: with it the second look lifted more boxes behind
            the slit (+7/-0 and +3/-0 on two sets of 200 scenes) and mugs (+2/-0), and every one-view run came out
            the same; ``pssnet grasp-trials --no-observed-points-check`` turns it off.
        dense_below: when the best grasp found holds less than this share of the weight (``GraspSet.weight_shares``;
            or no grasp holds at all), the search is repeated with the ``dense_*`` options and the better grasps of
            both searches are ranked together; 0 = never. The weight check rates the grasps it calls firm well,
            and where it finds none a denser search often does: a thin handle in a cupboard leaves few candidates
            that hold, a solid box many. In the grasp trials it ran in 0-8 % of the plans in full view and behind
            the slit and in 42-90 % on the hidden-handle mug, and lifted 5 points more mugs on the true shape and 10
            more with PSSNet's samples (``results/grasp_trials/dense_below/``).
        dense_max_candidates, dense_side_yaws, dense_tilted_pitches, dense_shallow_depths: the denser search's
            ``max_candidates``, ``side_yaws``, ``tilted_pitches`` and ``shallow_depths``.
        seed: seed of the anchor/orientation sampling and of the final subset.
    """

    gripper: GripperConfig = field(default_factory=GripperConfig)
    max_candidates: int = 500
    top_yaws: int = 8
    side_yaws: int = 24
    side_rolls: tuple[float, ...] = (0.0, 90.0)
    tilted_pitches: tuple[float, ...] = (45.0,)
    shallow_depths: tuple[float, ...] = (0.015,)
    thin_anchor_bias: float = 1.0
    clearance: float = 0.005
    surface_at_voxel_centres: bool = True
    plane_clearance: float = 0.0
    oversample: float = 3.0
    draw_rounds: int = 8
    friction: float = 0.5
    object_density: float = 1000.0
    rank_by: str = "expected_grip"
    observed_points_check: bool = True
    dense_below: float = 0.9
    dense_max_candidates: int = 1500
    dense_side_yaws: int = 48
    dense_tilted_pitches: tuple[float, ...] = (20.0, 45.0, 70.0)
    dense_shallow_depths: tuple[float, ...] = (0.01, 0.02, 0.03)
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.gripper, GripperConfig):
            raise GraspError(f"gripper must be a GripperConfig, got {type(self.gripper).__name__}")
        for name in ("max_candidates", "top_yaws", "side_yaws", "draw_rounds", "dense_max_candidates",
                     "dense_side_yaws", "seed"):
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
        pitches = tuple(float(p) for p in self.tilted_pitches)
        if not all(math.isfinite(p) and 0.0 < p < 90.0 for p in pitches):
            raise GraspError(f"tilted_pitches must be degrees in (0, 90), got {self.tilted_pitches}")
        depths = tuple(float(d) for d in self.shallow_depths)
        if not all(math.isfinite(d) and 0.0 < d < self.gripper.finger_length for d in depths):
            raise GraspError(f"shallow_depths must be in (0, finger_length={self.gripper.finger_length}) m, "
                             f"got {self.shallow_depths}")
        if isinstance(self.thin_anchor_bias, bool) or not 0.0 <= float(self.thin_anchor_bias) <= 4.0:
            raise GraspError(f"thin_anchor_bias must be in [0, 4], got {self.thin_anchor_bias!r}")
        if self.top_yaws == 0 and (self.side_yaws == 0 or not rolls):
            raise GraspError("no approach direction: set top_yaws > 0, or side_yaws > 0 with side_rolls")
        if not 0.0 <= self.clearance < self.gripper.max_opening / 2:
            raise GraspError(f"clearance must be in [0, max_opening/2) m, got {self.clearance}")
        if not 0.0 <= self.plane_clearance <= 0.1:
            raise GraspError(f"plane_clearance must be in [0, 0.1] m, got {self.plane_clearance}")
        if not 1.0 <= self.oversample <= 20.0:
            raise GraspError(f"oversample must be in [1, 20], got {self.oversample}")
        if not 1 <= self.draw_rounds <= 100:
            raise GraspError(f"draw_rounds must be in [1, 100], got {self.draw_rounds}")
        if isinstance(self.friction, bool) or not 0.05 <= float(self.friction) <= 2.0:
            raise GraspError(f"friction must be in [0.05, 2], got {self.friction!r}")
        if isinstance(self.object_density, bool) or not 10.0 <= float(self.object_density) <= 25000.0:
            raise GraspError(f"object_density must be in [10, 25000] kg/m^3, got {self.object_density!r}")
        if not isinstance(self.surface_at_voxel_centres, bool | np.bool_):
            raise GraspError(f"surface_at_voxel_centres must be a bool, got {self.surface_at_voxel_centres!r}")
        if not isinstance(self.observed_points_check, bool | np.bool_):
            raise GraspError(f"observed_points_check must be a bool, got {self.observed_points_check!r}")
        if self.rank_by not in RANKINGS:
            raise GraspError(f"rank_by must be one of {RANKINGS}, got {self.rank_by!r}")
        if self.seed < 0:
            raise GraspError(f"seed must be >= 0, got {self.seed}")
        if isinstance(self.dense_below, bool) or not 0.0 <= float(self.dense_below) <= 1.0:
            raise GraspError(f"dense_below must be in [0, 1], got {self.dense_below!r}")
        searched = (self.max_candidates, self.side_yaws, tuple(self.tilted_pitches), tuple(self.shallow_depths),
                    float(self.dense_below))
        denser = (self.dense_max_candidates, self.dense_side_yaws, tuple(self.dense_tilted_pitches),
                  tuple(self.dense_shallow_depths), 0.0)
        if searched != denser:  # (the denser search's own config stops here)
            self.denser()  # the dense_* options pass the same checks as the default search's, used now or not

    def denser(self) -> GraspConfig:
        """The options of the denser search :attr:`dense_below` asks for (which itself asks for no further one)."""
        return replace(self, max_candidates=self.dense_max_candidates, side_yaws=self.dense_side_yaws,
                       tilted_pitches=self.dense_tilted_pitches, shallow_depths=self.dense_shallow_depths,
                       dense_below=0.0)


@dataclass(frozen=True)
class VoxelDims:
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
    def of(cls, config: GraspConfig, voxel_size: float) -> VoxelDims:
        g = config.gripper
        return cls(g.max_opening / voxel_size, g.finger_length / voxel_size, g.finger_width / voxel_size,
                   g.finger_thickness / voxel_size, g.palm_depth / voxel_size, g.min_object_width / voxel_size,
                   config.clearance / voxel_size, config.plane_clearance / voxel_size)
