"""One grasp trial in MuJoCo: the true object on a table among clutter, a parallel-jaw hand, a fixed sequence.

Scene (world frame: z up, table top at z = 0):

- the object: a free body at its resting pose; collision shape = its CoACD convex parts
  (:mod:`pssnet_core.trials.collision`), drawn with the true mesh; mass = true volume x density (mug
  ceramic 2000 kg/m^3, packed boxes and everything else 400 kg/m^3: a YCB sugar box weighs 514 g for
  0.59 l, a cracker box 411 g for 2 l), inertia of the true solid at that density;
- clutter: static boxes (shelves, neighbouring objects);
- the hand, built from the project's :class:`~pssnet_core.grasps.GripperConfig` with exactly the boxes the
  planner checks (palm, two fingers): free-floating, its orientation fixed to the grasp's, its position
  on three world-axis slide joints and each finger on a slide joint along the closing axis, all driven by
  position actuators (the hand under gravity compensation, as a robot arm would hold it).

Friction (MuJoCo uses the larger coefficient of the two geoms in contact): finger pads 1.0 sliding (rubber
pads, as on a Franka hand's fingertips) with torsional friction 5 mm (a pad's contact patch resists
twisting: a mug held by its handle hangs from it), object 0.6, table and clutter 0.6; elliptic friction
cones. The fingers close by a position target beyond the object with their force capped at
``grip_force`` (20 N per finger; a Franka hand grips with up to 70 N continuous): ten times the weight of
the heaviest mug at the pads' friction, while 40 N squeezed 60 g boxes out of fingertip grasps).

The sequence (:func:`run_trial`): the hand appears 10 cm back along the approach with the fingers open to
the planned width, waits while the object settles, approaches, closes, leaves along the scenario's exit
path (default: straight up 15 cm), then holds 2 s while shaking +-1 cm at 2 Hz. Outcome:

- ``collision``: a hand part touches the object, the clutter or the table before the fingers close;
- ``missed``: after closing, the two fingers do not both touch the object;
- ``slipped``: both touched, but at the end the object is no longer held (see below);
- ``success``: at the end both fingers touch the object, it followed the hand along the exit (its
  displacement along the hand's is at least ``followed_fraction`` of the hand's) and its centre of mass is
  at least ``followed_fraction`` of the hand's rise above where it rested.

MuJoCo is deterministic: the same scene and grasp give the same outcome, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from pssnet_core.grasps import GripperConfig
from pssnet_core.shapes import Shape
from pssnet_core.trials.collision import ConvexPart

OUTCOMES = ("success", "collision", "missed", "slipped")
DENSITIES: dict[str, float] = {"mug": 2000.0}
DEFAULT_DENSITY = 400.0


@dataclass(frozen=True)
class ClutterBox:
    """A static axis-aligned box in the world frame (metres).

    Attributes:
        centre: (x, y, z) centre.
        half: (x, y, z) half extents.
        name: what it stands for (shown in reports).
    """

    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    name: str = "clutter"

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(..., 3) points -> (...) bool: inside the box grown by ``margin``."""
        offset = np.abs(np.asarray(points) - np.asarray(self.centre))
        return np.all(offset <= np.asarray(self.half) + margin, axis=-1)


@dataclass
class PhysicsScene:
    """The true object (and its collision parts), where it rests, the clutter and the way out.

    Attributes:
        shape: the true object.
        parts: its convex collision parts (object frame).
        object_pose: (4, 4) world <- object, resting on the table (z = 0).
        clutter: static boxes.
        exit: hand displacements (world, metres) after closing, one segment each; default: up 15 cm.
    """

    shape: Shape
    parts: list[ConvexPart]
    object_pose: np.ndarray
    clutter: tuple[ClutterBox, ...] = ()
    exit: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.15),)


@dataclass(frozen=True)
class PhysicsConfig:
    """Simulation and trial-sequence settings (SI units).

    Attributes:
        timestep: integration step (s).
        object_friction: sliding friction of the object.
        finger_friction: sliding friction of the finger pads.
        finger_torsional: torsional friction of the finger pads (m).
        table_friction: sliding friction of the table and the clutter.
        grip_force: force limit of each finger's actuator (N).
        pre_grasp: distance back along the approach where the hand starts (m).
        approach_speed: hand speed along the approach (m/s).
        exit_speed: hand speed along the exit path (m/s).
        settle_s: time for the object to settle before the approach (s).
        close_s: time over which the finger targets move from open to closed (s).
        squeeze_s: time the closed fingers squeeze before the exit (s).
        hold_s: holding time at the end of the exit (s).
        shake_amplitude: amplitude of the shake in each world axis (m).
        shake_hz: shake frequency (Hz).
        followed_fraction: success needs the object to follow this fraction of the hand's exit.
        hand_kp: position gain of the hand's slide actuators (N/m).
        finger_kp: position gain of the finger actuators (N/m).
        finger_overshoot: the finger target when closing lies this far past the centre (m).
    """

    timestep: float = 0.002
    object_friction: float = 0.6
    finger_friction: float = 1.0
    finger_torsional: float = 0.005
    table_friction: float = 0.6
    grip_force: float = 20.0
    pre_grasp: float = 0.10
    approach_speed: float = 0.10
    exit_speed: float = 0.10
    settle_s: float = 0.3
    close_s: float = 0.4
    squeeze_s: float = 0.3
    hold_s: float = 2.0
    shake_amplitude: float = 0.01
    shake_hz: float = 2.0
    followed_fraction: float = 0.5
    hand_kp: float = 5000.0
    finger_kp: float = 2000.0
    finger_overshoot: float = 0.02


@dataclass
class TrialOutcome:
    """What happened in one trial.

    Attributes:
        outcome: one of :data:`OUTCOMES`.
        lift: rise of the object's centre of mass at the end (m).
        followed: object displacement along the hand's exit direction, over the hand's displacement.
        contact: description of the first forbidden contact (collision failures), else "".
        frames: rendered RGB frames (start, grasp, end) when asked for, else empty.
    """

    outcome: str
    lift: float
    followed: float
    contact: str = ""
    frames: list[np.ndarray] = field(default_factory=list)

    @property
    def success(self) -> bool:
        return self.outcome == "success"


def density_of(shape: Shape) -> float:
    """Density (kg/m^3) used for a shape's family."""
    return DENSITIES.get(shape.identity.family, DEFAULT_DENSITY)


def _quat_wxyz(rotation: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def _box_geom(body: mujoco.MjsBody, name: str, centre: Sequence[float], half: Sequence[float],
              friction: float, rgba: Sequence[float], condim: int = 3, torsional: float = 0.005) -> None:
    geom = body.add_geom()
    geom.name = name
    geom.type = mujoco.mjtGeom.mjGEOM_BOX
    geom.pos = list(centre)
    geom.size = list(half)
    geom.friction = [friction, torsional, 0.0001]
    geom.condim = condim
    geom.rgba = list(rgba)


def build_model(scene: PhysicsScene, grasp_pose: np.ndarray, gripper: GripperConfig,
                config: PhysicsConfig) -> mujoco.MjModel:
    """The MuJoCo model of one trial: table, clutter, object at rest, hand at the pre-grasp pose.

    Args:
        scene: object, clutter and exit path.
        grasp_pose: (4, 4) world <- gripper at the grasp (origin between the fingertips, z approach, y closing).
        gripper: finger and palm dimensions.
        config: friction, gains and limits.

    Returns:
        The model; its finger joints read 0 with the pads touching at the centre: set them to half the
        opening in the data (``finger_left``/``finger_right`` joints) before stepping.
    """
    spec = mujoco.MjSpec()
    spec.option.timestep = config.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0  # stiffer friction than normal forces: less creep in a held grasp
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    world = spec.worldbody
    light = world.add_light()
    light.pos = [0.0, 0.0, 1.5]
    light.dir = [0.0, 0.0, -1.0]
    table = world.add_geom()
    table.name = "table"
    table.type = mujoco.mjtGeom.mjGEOM_PLANE
    table.size = [1.0, 1.0, 0.01]
    table.friction = [config.table_friction, 0.005, 0.0001]
    table.rgba = [0.75, 0.72, 0.68, 1.0]
    for i, box in enumerate(scene.clutter):
        _box_geom(world, f"clutter{i}_{box.name}", box.centre, box.half, config.table_friction,
                  (0.35, 0.45, 0.75, 0.35))

    # The object: collision parts (hidden group 3) and the true mesh for the eye only.
    body = world.add_body()
    body.name = "object"
    body.pos = list(scene.object_pose[:3, 3])
    body.quat = list(_quat_wxyz(scene.object_pose[:3, :3]))
    body.add_freejoint()
    density = density_of(scene.shape)
    props = scene.shape.mesh.mass_properties  # trimesh: density 1, so mass = volume
    body.explicitinertial = True
    body.mass = float(props["volume"] * density)
    body.ipos = list(props["center_mass"])
    inertia = np.asarray(props["inertia"]) * density
    body.fullinertia = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    for i, part in enumerate(scene.parts):
        mesh = spec.add_mesh()
        mesh.name = f"part{i}"
        mesh.uservert = np.asarray(part.vertices, dtype=np.float64).ravel().tolist()
        mesh.userface = np.asarray(part.faces, dtype=np.int64).ravel().tolist()
        geom = body.add_geom()
        geom.type = mujoco.mjtGeom.mjGEOM_MESH
        geom.meshname = mesh.name
        geom.friction = [config.object_friction, 0.005, 0.0001]
        geom.group = 3
        geom.mass = 0.0
    visual = spec.add_mesh()
    visual.name = "object_visual"
    visual.uservert = np.asarray(scene.shape.mesh.vertices, dtype=np.float64).ravel().tolist()
    visual.userface = np.asarray(scene.shape.mesh.faces, dtype=np.int64).ravel().tolist()
    geom = body.add_geom()
    geom.type = mujoco.mjtGeom.mjGEOM_MESH
    geom.meshname = visual.name
    geom.contype = geom.conaffinity = 0
    geom.group = 1
    geom.mass = 0.0
    geom.rgba = [0.85, 0.35, 0.2, 1.0]

    # The hand at the pre-grasp pose; its slide joints move it along the world axes.
    rotation = grasp_pose[:3, :3]
    start = grasp_pose[:3, 3] - config.pre_grasp * rotation[:, 2]
    hand = world.add_body()
    hand.name = "hand"
    hand.pos = list(start)
    hand.quat = list(_quat_wxyz(rotation))
    hand.gravcomp = 1.0
    hand.explicitinertial = True
    hand.mass = 0.6
    hand.inertia = [1e-3, 1e-3, 1e-3]
    g = gripper
    fl, fw, ft, wmax = g.finger_length, g.finger_width, g.finger_thickness, g.max_opening
    _box_geom(hand, "palm", (0.0, 0.0, -fl - g.palm_depth / 2), (fw / 2, wmax / 2 + ft, g.palm_depth / 2),
              config.finger_friction, (0.25, 0.25, 0.25, 1.0))
    for axis in range(3):
        joint = hand.add_joint()
        joint.name = "hand_" + "xyz"[axis]
        joint.type = mujoco.mjtJoint.mjJNT_SLIDE
        joint.axis = list(rotation[axis])  # world axis `axis` in the hand frame (row of R = column of R^T)
        joint.armature = 0.1
    for side, sign in (("left", 1.0), ("right", -1.0)):
        finger = hand.add_body()
        finger.name = f"finger_{side}"
        finger.gravcomp = 1.0
        finger.explicitinertial = True
        finger.mass = 0.05
        finger.inertia = [1e-5, 1e-5, 1e-5]
        joint = finger.add_joint()
        joint.name = f"finger_{side}"
        joint.type = mujoco.mjtJoint.mjJNT_SLIDE
        joint.axis = [0.0, sign, 0.0]
        joint.range = [-config.finger_overshoot, wmax / 2]
        joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.damping = [20.0, 0.0, 0.0]  # linear damping (MuJoCo 4 also takes higher-order terms)
        joint.armature = 0.01
        _box_geom(finger, f"finger_{side}", (0.0, sign * ft / 2, -fl / 2), (fw / 2, ft / 2, fl / 2),
                  config.finger_friction, (0.15, 0.15, 0.15, 1.0), condim=4, torsional=config.finger_torsional)
    exclude = spec.add_exclude()
    exclude.bodyname1, exclude.bodyname2 = "finger_left", "finger_right"

    kv_hand = 2.0 * math.sqrt(config.hand_kp * 1.0)  # about critically damped for hand plus object
    for axis in range(3):
        act = spec.add_actuator()
        act.name = "hand_" + "xyz"[axis]
        act.target = "hand_" + "xyz"[axis]
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_position(kp=config.hand_kp, kv=kv_hand)
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-200.0, 200.0]
    for side in ("left", "right"):
        act = spec.add_actuator()
        act.name = f"finger_{side}"
        act.target = f"finger_{side}"
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_position(kp=config.finger_kp)
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-config.grip_force, config.grip_force]
    return spec.compile()


def _smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


def _path_point(waypoints: np.ndarray, lengths: np.ndarray, s: float) -> np.ndarray:
    """Point at arc length fraction ``s`` (smoothstepped) along a polyline starting at the origin."""
    total = float(lengths.sum())
    if total <= 0:
        return np.zeros(3)
    d = _smoothstep(s) * total
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    i = min(int(np.searchsorted(cum, d, side="right")) - 1, len(lengths) - 1)
    start = waypoints[i - 1] if i > 0 else np.zeros(3)
    frac = (d - cum[i]) / lengths[i] if lengths[i] > 0 else 1.0
    return start + frac * (waypoints[i] - start)


class _Contacts:
    """Which bodies touch, from MuJoCo's contact list."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.body_of_geom = model.geom_bodyid
        self.hand = {model.body(name).id for name in ("hand", "finger_left", "finger_right")}
        self.object = model.body("object").id
        self.fingers = (model.body("finger_left").id, model.body("finger_right").id)
        self.model = model

    def pairs(self, data: mujoco.MjData) -> list[tuple[int, int]]:
        n = data.ncon
        if n == 0:
            return []
        geoms = data.contact.geom[:n]
        touching = data.contact.dist[:n] <= 0.0
        bodies = self.body_of_geom[geoms[touching]]
        return [(int(a), int(b)) for a, b in bodies]

    def forbidden(self, data: mujoco.MjData) -> str:
        """Name of the first hand-vs-anything contact, or ""."""
        for pair in data.contact.geom[:data.ncon][data.contact.dist[:data.ncon] <= 0.0]:
            a, b = (int(g) for g in pair)
            ba, bb = self.body_of_geom[a], self.body_of_geom[b]
            if (ba in self.hand) != (bb in self.hand):
                other = b if ba in self.hand else a
                name = self.model.geom(other).name or self.model.body(self.body_of_geom[other]).name
                return name
        return ""

    def fingers_on_object(self, data: mujoco.MjData) -> tuple[bool, bool]:
        touching = set()
        for a, b in self.pairs(data):
            if self.object in (a, b):
                touching.add(b if a == self.object else a)
        return self.fingers[0] in touching, self.fingers[1] in touching


def run_trial(scene: PhysicsScene, grasp_pose: np.ndarray, width: float, gripper: GripperConfig | None = None,
              config: PhysicsConfig | None = None,
              render: Callable[[mujoco.MjModel, mujoco.MjData], np.ndarray] | None = None) -> TrialOutcome:
    """Runs the trial sequence (module docstring) for one grasp.

    Args:
        scene: object, clutter and exit path.
        grasp_pose: (4, 4) world <- gripper at the grasp.
        width: planned opening (m).
        gripper: the gripper (default :class:`GripperConfig`).
        config: simulation settings.
        render: if given, called at the start, at the grasp (or the collision) and at the end to draw a frame.
    """
    gripper = gripper or GripperConfig()
    config = config or PhysicsConfig()
    model = build_model(scene, np.asarray(grasp_pose, dtype=np.float64), gripper, config)
    data = mujoco.MjData(model)
    open_half = min(width, gripper.max_opening) / 2
    for side in ("left", "right"):
        data.qpos[model.joint(f"finger_{side}").qposadr[0]] = open_half
    mujoco.mj_forward(model, data)
    contacts = _Contacts(model)
    frames: list[np.ndarray] = []

    def snap() -> None:
        if render is not None:
            frames.append(render(model, data))

    rotation = np.asarray(grasp_pose)[:3, :3]
    approach = config.pre_grasp * rotation[:, 2]
    closed = -config.finger_overshoot
    dt = model.opt.timestep
    hand_ctrl = slice(0, 3)

    def steps(seconds: float) -> int:
        return max(1, int(round(seconds / dt)))

    def object_com() -> np.ndarray:
        return data.xipos[contacts.object].copy()

    # 1. Settle, then approach: any hand contact here is a collision.
    snap()
    data.ctrl[3:5] = open_half
    phases = ((steps(config.settle_s), lambda s: np.zeros(3)),
              (steps(config.pre_grasp / config.approach_speed), lambda s: _smoothstep(s) * approach))
    rest = None
    for count, target in phases:
        for i in range(count):
            data.ctrl[hand_ctrl] = target((i + 1) / count)
            mujoco.mj_step(model, data)
            hit = contacts.forbidden(data)
            if hit:
                snap()
                snap()
                return TrialOutcome("collision", 0.0, 0.0, contact=hit, frames=frames)
        if rest is None:
            rest = object_com()

    # 2. Close with the force limit, then squeeze.
    n_close = steps(config.close_s)
    for i in range(n_close + steps(config.squeeze_s)):
        s = min((i + 1) / n_close, 1.0)
        data.ctrl[3:5] = open_half + s * (closed - open_half)
        mujoco.mj_step(model, data)
    snap()
    if not all(contacts.fingers_on_object(data)):
        snap()
        return TrialOutcome("missed", float(object_com()[2] - rest[2]), 0.0, frames=frames)

    # 3. Exit along the scenario's path, then hold and shake.
    waypoints = np.cumsum(np.asarray(scene.exit, dtype=np.float64).reshape(-1, 3), axis=0)
    lengths = np.linalg.norm(np.diff(np.vstack([np.zeros(3), waypoints]), axis=0), axis=1)
    n_exit = steps(float(lengths.sum()) / config.exit_speed)
    for i in range(n_exit):
        data.ctrl[hand_ctrl] = approach + _path_point(waypoints, lengths, (i + 1) / n_exit)
        mujoco.mj_step(model, data)
    end = approach + waypoints[-1]
    n_hold = steps(config.hold_s)
    phase = np.array([0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0])
    for i in range(n_hold):
        t = (i + 1) * dt
        ramp = min(t / 0.25, 1.0, (config.hold_s - t) / 0.25)  # ease in and out: no jerk at either end
        data.ctrl[hand_ctrl] = end + ramp * config.shake_amplitude * np.sin(2 * math.pi * config.shake_hz * t + phase)
        mujoco.mj_step(model, data)
    snap()

    moved = object_com() - rest
    hand_move = waypoints[-1]
    distance = float(np.linalg.norm(hand_move))
    followed = float(moved @ hand_move / distance**2) if distance > 0 else 0.0
    lift = float(moved[2])
    held = all(contacts.fingers_on_object(data))
    rise_ok = lift >= config.followed_fraction * hand_move[2]
    ok = held and followed >= config.followed_fraction and rise_ok
    return TrialOutcome("success" if ok else "slipped", lift, followed, frames=frames)
