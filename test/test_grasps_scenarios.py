"""Scenarios after the paper's robot trials, on rendered scenes through ``observe()``.

Completions are hand-built variants of the true object (not a trained model), rendered into the
observation's grid with the project's ground-truth occupancy: (a) a box seen through a narrow slit, with
completions of different depths; (b) a mug whose handle is hidden, with completions that put the handle at
different hidden angles; (c) a box in full view whose completions are all the true box.

``python test/test_grasps_scenarios.py OUT.png`` draws scenario (b)'s best grasps.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
import trimesh

from pssnet_core.data.scenes import ObjectScene, Slit, object_pose, orbit_camera
from pssnet_core.geometry import CameraIntrinsics, GridConfig, Observation
from pssnet_core.grasps import (
    GraspConfig,
    GraspSet,
    check_grasps,
    plan_grasps,
    plot_grasps,
    single_completion_choice,
)
from pssnet_core.shapes.procedural import Shape, ShapeId

GRID = GridConfig.for_size(32)  # 6.25 mm voxels over 0.2 m
CONFIG = GraspConfig()
CAMERA = CameraIntrinsics.kinect_like()


@dataclass
class Scenario:
    observation: Observation
    completions: np.ndarray  # (S, N, N, N)
    camera_pose: np.ndarray  # world <- camera
    extra: dict


def _box(size: tuple[float, float, float], front_at_zero: bool = False) -> Shape:
    mesh = trimesh.creation.box(size)
    mesh.apply_translation((size[0] / 2 if front_at_zero else 0.0, 0.0, size[2] / 2))
    return Shape(ShapeId("box", 0), mesh)


def _mug(radius: float = 0.035, height: float = 0.10, wall: float = 0.008, bottom: float = 0.012):
    """A cup (cylinder with a cavity) with a rectangular loop handle pointing along +x; and the cup alone."""
    body = trimesh.creation.cylinder(radius=radius, height=height, sections=64)
    body.apply_translation((0.0, 0.0, height / 2))
    cavity = trimesh.creation.cylinder(radius=radius - wall, height=height, sections=64)
    cavity.apply_translation((0.0, 0.0, bottom + height / 2))
    cup = trimesh.boolean.difference([body, cavity], engine="manifold")
    centre_x = radius + 0.0125
    outer = trimesh.creation.box((0.035, 0.014, 0.065))
    outer.apply_translation((centre_x, 0.0, 0.05))
    inner = trimesh.creation.box((0.021, 0.03, 0.041))
    inner.apply_translation((centre_x - 0.002, 0.0, 0.05))
    loop = trimesh.boolean.difference([outer, inner], engine="manifold")
    handle = trimesh.boolean.difference([loop, body], engine="manifold")
    mug = trimesh.boolean.union([cup, loop], engine="manifold")
    return Shape(ShapeId("mug", 0), mug, handle), Shape(ShapeId("mug", 1), cup)


def slit_box_scenario() -> Scenario:
    """A 5 cm wide, 10 cm deep, 8 cm tall box seen front-on (camera level with it) through a 3.6 cm slit;
    completions keep the seen front face and vary the depth from 2 to 14 cm."""
    true = _box((0.10, 0.05, 0.08), front_at_zero=True)
    pose = object_pose(true.mesh)
    camera = orbit_camera(np.array([0.05, 0.0, 0.04]), 0.6, 0.0)
    view = ObjectScene(true).render(pose, camera, CAMERA, slit=Slit(0.036))
    observation = view.observe(GRID)
    depths = (0.02, 0.04, 0.06, 0.08, 0.10, 0.12, 0.14)
    completions = np.stack([ObjectScene(_box((d, 0.05, 0.08), front_at_zero=True)).ground_truth(
        pose, observation.pose, camera) for d in depths])
    return Scenario(observation, completions, camera, {"depths": depths, "view": view})


def mug_scenario() -> Scenario:
    """A mug seen from 30 degrees above with its handle pointing away; completions turn the handle to
    -30..30 degrees (all hidden from this camera)."""
    mug, cup = _mug()
    pose = object_pose(mug.mesh, 0.0)
    camera = orbit_camera(np.array([0.0, 0.0, 0.05]), 0.6, 30.0)
    scene = ObjectScene(mug)
    view = scene.render(pose, camera, CAMERA)
    observation = view.observe(GRID)
    yaws = (-30.0, -18.0, -6.0, 6.0, 18.0, 30.0)
    completions = np.stack([scene.ground_truth(object_pose(mug.mesh, yaw), observation.pose, camera) for yaw in yaws])
    cup_only = ObjectScene(cup).ground_truth(pose, observation.pose, camera)
    return Scenario(observation, completions, camera,
                    {"yaws": yaws, "view": view, "cup": cup_only, "radius": 0.035, "scene": scene, "mug": mug})


def full_box_scenario() -> Scenario:
    """A 5 x 6.5 x 9 cm box seen in full from 30 degrees above; four completions, all the true box."""
    true = _box((0.05, 0.065, 0.09))
    pose = object_pose(true.mesh)
    camera = orbit_camera(np.array([0.0, 0.0, 0.045]), 0.6, 30.0)
    view = ObjectScene(true).render(pose, camera, CAMERA)
    observation = view.observe(GRID)
    occupancy = ObjectScene(true).ground_truth(pose, observation.pose, camera)
    return Scenario(observation, np.stack([occupancy] * 4), camera, {"size": (0.05, 0.065, 0.09), "shape": true,
                                                                      "pose": pose})


def _plan(s: Scenario) -> GraspSet:
    return plan_grasps(s.completions, s.observation.pose, s.observation.points, CONFIG)


def _world_to_grid(s: Scenario, points: np.ndarray) -> np.ndarray:
    camera = (np.asarray(points, float) - s.camera_pose[:3, 3]) @ s.camera_pose[:3, :3]
    return s.observation.pose.camera_to_grid(camera)


# ------------------------------------------------------------------------------------------ (a)


@pytest.fixture(scope="module")
def slit_box() -> Scenario:
    return slit_box_scenario()


def test_slit_box_best_grasp_holds_for_most_depths(slit_box):
    s = slit_box
    volumes = s.completions.sum(axis=(1, 2, 3))
    assert np.all(np.diff(volumes) > 0)  # the completions really differ in depth
    assert s.extra["view"].slit_columns is not None
    grasps = _plan(s)
    assert len(grasps) > 20
    best = grasps.subset(slice(0, 1))
    assert best.scores[0] >= 6 / 7
    assert best.holds[0, -1] and best.holds[0, 0]  # holds for the deepest and the shallowest alike
    # Grasps sized for the shallow completions (closing along the viewing direction, across the depth)
    # exist but rank below: they fail for the deep ones.
    along_view = np.abs(grasps.grid.rotations[:, 0, 1]) > 0.95
    shallow_only = along_view & grasps.holds[:, 0] & ~grasps.holds[:, -1]
    assert shallow_only.any()
    assert grasps.scores[shallow_only].max() < best.scores[0]
    # What the shallowest completion alone would choose fails for most of the others.
    choice = single_completion_choice(s.completions, s.observation.pose, 0, s.observation.points, CONFIG)
    assert choice.score_alone == 1.0
    assert choice.score_all <= 0.5 < best.scores[0]
    assert not choice.grasp.holds[0, -1]


# ------------------------------------------------------------------------------------------ (b)


@pytest.fixture(scope="module")
def mug() -> Scenario:
    return mug_scenario()


def test_mug_handle_is_hidden_in_every_completion(mug):
    scene, mesh = mug.extra["scene"], mug.extra["mug"]
    for yaw in mug.extra["yaws"]:
        view = scene.render(object_pose(mesh.mesh, yaw), mug.camera_pose, CAMERA)
        assert view.handle_visible is False
    handle = mug.completions & ~mug.extra["cup"][None]
    assert np.all(handle.sum(axis=(1, 2, 3)) > 30)
    assert len({h.tobytes() for h in handle}) == len(mug.extra["yaws"])  # handles at different places


def test_mug_grasps_through_the_hidden_handle_region_score_below_body_grasps(mug):
    grasps = _plan(mug)
    pose = mug.observation.pose
    handles = mug.completions & ~mug.extra["cup"][None]  # each completion's handle alone
    on_handles = check_grasps(grasps.grid, handles, pose, grasps.support_z, CONFIG)
    on_cup = check_grasps(grasps.grid, mug.extra["cup"][None], pose, grasps.support_z, CONFIG)
    # "through the hidden-handle region": a finger or the palm passes where some completion has its handle
    hit = on_handles.finger_hit | on_handles.palm_hit
    through = hit.any(axis=1)
    body = ~through & on_cup.contains[:, 0]  # grasps on the cup that stay clear of every possible handle
    handle_only = on_handles.contains.any(axis=1) & ~on_cup.contains[:, 0]  # grasps relying on a handle
    assert through.sum() >= 10 and body.sum() >= 10 and handle_only.sum() >= 5
    assert grasps.scores[0] == 1.0 and body[0]
    assert not np.any(grasps.holds & hit)  # a grasp never holds for a completion whose handle it runs into
    assert grasps.scores[through].max() < grasps.scores[0]
    # Against the body grasps that hold at all: chords of the cup, which the pads would push out of the hand
    # (outside the friction cone), hold for no completion and say nothing about the handle.
    held_body = body & (grasps.scores > 0)
    assert held_body.sum() >= 10
    assert grasps.scores[through].mean() < grasps.scores[held_body].mean() - 0.2
    assert grasps.scores[handle_only].mean() < grasps.scores[held_body].mean() - 0.2


# ------------------------------------------------------------------------------------------ (c)


def test_full_view_box_best_grasp_holds_and_matches_the_true_width():
    s = full_box_scenario()
    grasps = _plan(s)
    assert len(grasps) > 20
    assert grasps.scores[0] == 1.0 and grasps.holds[0].all()
    # The box's extent along the best grasp's closing axis inside its closing region, exactly: intersect the
    # closing region (as a box mesh at the grasp pose, opened wide) with the true box mesh.
    g = CONFIG.gripper
    region = trimesh.creation.box((g.finger_width, 0.3, g.finger_length))
    region.apply_translation((0.0, 0.0, -g.finger_length / 2))
    world_from_grasp = s.camera_pose @ grasps.poses[0]
    region.apply_transform(world_from_grasp)
    box = s.extra["shape"].mesh.copy()
    box.apply_transform(s.extra["pose"])
    inside = trimesh.boolean.intersection([region, box], engine="manifold")
    along = inside.vertices @ world_from_grasp[:3, 1]
    true_width = along.max() - along.min()
    needed = grasps.widths[0] - 2 * CONFIG.clearance
    assert abs(needed - true_width) <= s.observation.pose.voxel_size
    # for a box the best grasp closes square to a face, across its 5 cm side
    axes = _world_to_grid(s, np.eye(3)) - _world_to_grid(s, np.zeros((1, 3)))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.max(np.abs(axes @ grasps.grid.rotations[0][:, 1])) > 0.999
    assert abs(true_width - 0.05) < 1e-6


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "/tmp/grasps_mug.png"
    scenario = mug_scenario()
    result = _plan(scenario)
    plot_grasps(result, scenario.completions, scenario.observation.pose, top_k=5, path=out,
                observed=scenario.observation.points,
                title=f"mug, handle hidden; {len(scenario.completions)} completions (handle at "
                      f"{', '.join(f'{y:.0f}' for y in scenario.extra['yaws'])} deg)")
    print(f"wrote {out}: {len(result)} grasps, top grasp's score {result.scores[0]:.2f}")
