"""Plausible sets (Alg. 2) on a tiny test set rendered here, where the membership is known by construction.

Objects (object frame: z up, base at z = 0):
- "cyl": a cylinder, radius 3 cm, height 8 cm: rotationally symmetric, so any two views show the same thing.
- "box": a 12 x 12 x 10 cm box.
- "bump": the same box with a 6 cm bump on its +y side: hidden when +y faces away from the camera (yaw 0),
  in plain sight at yaw 180.
Views: cyl@0, cyl@90, box@0, bump@0, bump@180. Expected sets at delta 1 cm (and 4 cm):
cyl@0 <-> cyl@90; box@0 <-> bump@0 (the bump is hidden); bump@180 alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pssnet_core.evaluation.observation_model import DepthView, MeshRaycaster
from pssnet_core.evaluation.plausible import (
    EvalView,
    MeshTable,
    PlausibleConfig,
    PlausibleSetError,
    PlausibleSets,
    cached_plausible_sets,
    compute_plausible_sets,
    diameter,
    plausible_shape_occupancy,
)
from pssnet_core.geometry import CameraIntrinsics, GridConfig, observe

K = CameraIntrinsics(width=64, height=64, fx=90.0, fy=90.0, cx=31.5, cy=31.5)
UP = np.array([0.0, -1.0, 0.0])
GRID = GridConfig(size=16, voxel_size=0.0125)


def tiny_meshes() -> dict[str, trimesh.Trimesh]:
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=48)
    cyl.apply_translation((0, 0, 0.04))
    box = trimesh.creation.box(extents=(0.12, 0.12, 0.10))
    box.apply_translation((0, 0, 0.05))
    bump = trimesh.creation.box(extents=(0.05, 0.07, 0.05))
    bump.apply_translation((0, 0.06 + 0.03, 0.03))  # overlaps the box by 1 cm, reaches y = 0.125
    bumped = trimesh.boolean.union([box, bump], engine="manifold")
    return {"cyl": cyl, "box": box, "bump": bumped}


def camera_from_object(yaw_deg: float, distance: float = 0.45) -> np.ndarray:
    """Horizontal camera; object z (up) -> camera -y, object y -> camera +z (away) at yaw 0."""
    base = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    a = np.radians(yaw_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = base @ rz
    pose[:3, 3] = (0.0, 0.05, distance)
    return pose


def scene_casters() -> tuple[MeshRaycaster, MeshRaycaster]:
    floor = trimesh.creation.box(extents=(2.0, 0.02, 2.0))
    floor.apply_translation((0, 0.05 + 0.01, 0.5))  # top surface at camera y = 0.05 (the object's base)
    wall = trimesh.creation.box(extents=(2.0, 2.0, 0.02))
    wall.apply_translation((0, 0, 0.9))
    return MeshRaycaster.from_trimesh(floor), MeshRaycaster.from_trimesh(wall)


def render_view(index: int, identity: str, mesh: trimesh.Trimesh, yaw: float, k: CameraIntrinsics = K,
                grid: GridConfig = GRID) -> EvalView:
    """Depth + mask of one object on a floor in front of a wall, its observation, as an EvalView."""
    pose = camera_from_object(yaw)
    us, vs = np.arange(k.width), np.arange(k.height)
    d_obj = MeshRaycaster.from_trimesh(mesh).depth(pose, k, us, vs)
    floor, wall = scene_casters()
    d_scene = np.minimum(floor.depth(np.eye(4), k, us, vs), wall.depth(np.eye(4), k, us, vs))
    mask = d_obj < d_scene
    depth = np.where(mask, d_obj, d_scene)
    obs = observe(depth, mask.astype(np.uint8), k, UP, grid)
    return EvalView(index=index, identity=identity, depth_view=DepthView(depth, mask, k), object_pose=pose,
                    grid_pose=obs.pose, known_occupied=obs.known_occupied,
                    known_free=obs.known_free, meta={"yaw": yaw})


SPECS = [("cyl", 0.0), ("cyl", 90.0), ("box", 0.0), ("bump", 0.0), ("bump", 180.0)]
EXPECTED = {0: {0, 1}, 1: {0, 1}, 2: {2, 3}, 3: {2, 3}, 4: {4}}


@pytest.fixture(scope="module")
def tiny_set():
    meshes = tiny_meshes()
    views = [render_view(k, name, meshes[name], yaw) for k, (name, yaw) in enumerate(SPECS)]
    table = MeshTable({k: (np.asarray(m.vertices), np.asarray(m.faces)) for k, m in meshes.items()})
    return views, table


def members(sets: PlausibleSets, i: int, delta: float) -> set[int]:
    return {j for j, _ in sets.members(i, delta)}


def test_plausible_sets_membership(tiny_set):
    views, table = tiny_set
    sets = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.04, 0.01)), progress=False)
    for i, expected in EXPECTED.items():
        assert members(sets, i, 0.01) == expected, f"view {i} at 1 cm"
        assert members(sets, i, 0.04) == expected, f"view {i} at 4 cm"
        assert sets.members(i, 0.01)[0][0] == i  # own ground truth first
    assert sets.stats["own_ground_truth_plausible_rate"] == {"0.04": 1.0, "0.01": 1.0}
    assert sets.stats["pairs"] == len(views) * (len(views) - 1)


def test_prefilter_changes_nothing_and_is_used(tiny_set):
    views, table = tiny_set
    # record_fraction 0: strict sets, where the diameter bound is safe and used.
    on = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.01,), prefilter=True, record_fraction=0.0),
                                progress=False)
    off = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.01,), prefilter=False, record_fraction=0.0),
                                 progress=False)
    for i in range(len(views)):
        assert members(on, i, 0.01) == members(off, i, 0.01)
    assert off.stats["pruned_by_prefilter"] == 0 and off.stats["rejected_on_sparse_pixels"] == 0
    assert on.stats["rejected_on_sparse_pixels"] > 0
    # Box views (reliable front ~11 x 9 cm, diagonal > 13 cm) against the cylinder mesh (diameter 10 cm,
    # + 2 x 1 cm x ray scale): the 3 box views x 2 cylinder views are pruned.
    assert on.stats["pruned_by_prefilter"] == 6


def test_outlier_allowance_applied_after_recording(tiny_set):
    views, table = tiny_set
    sets = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.01,), record_fraction=0.05),
                                  progress=False)
    strict = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.01,), record_fraction=0.0),
                                    progress=False)
    for i in range(len(views)):
        assert members(sets, i, 0.01) == members(strict, i, 0.01)  # default allowance 0: the paper's rule
        wider = {j for j, _ in sets.members(i, 0.01, outlier_fraction=0.05)}
        assert members(sets, i, 0.01) <= wider
    with pytest.raises(PlausibleSetError, match="record_fraction"):
        strict.members(0, 0.01, outlier_fraction=0.01)
    with pytest.raises(PlausibleSetError, match="delta"):
        sets.members(0, 0.02)


def test_transformed_truth_lands_on_reference(tiny_set):
    views, table = tiny_set
    sets = compute_plausible_sets(views, table, PlausibleConfig(deltas=(0.01,)), references=[3], progress=False)
    assert list(sets.references) == [3]
    mem = sets.members(3, 0.01)
    occ = plausible_shape_occupancy(views, table, 3, mem)
    # The box placed from view 2 by ICP must cover the front part of view 3's bumped box: the observed voxels.
    observed = views[3].known_occupied
    for grid in occ:
        assert (grid & observed).sum() >= 0.8 * observed.sum()
    # Own ground truth rebuilt: every voxel whose centre is inside the bumped box at its pose, plus the
    # surface voxels, which hold every observed voxel.
    own = occ[0]
    pose, placed = views[3].grid_pose, views[3].object_pose
    local = (pose.occupied_centres(np.ones((pose.size,) * 3, bool)) - placed[:3, 3]) @ placed[:3, :3]
    centre_inside = MeshRaycaster(*table("bump")).inside(local).reshape(own.shape)
    assert centre_inside.sum() > 50 and not (centre_inside & ~own).any()
    assert not (observed & ~own).any()
    assert own.sum() > centre_inside.sum()


def test_cache(tiny_set, tmp_path):
    # The same sets on a 2-worker Ray, and resuming a killed run: test_ray_tasks.py.
    views, table = tiny_set
    cfg = PlausibleConfig(deltas=(0.01,))
    sets, path, hit = cached_plausible_sets(views, table, "fingerprint-a", tmp_path, cfg, progress=False)
    assert not hit and path.exists() and not path.with_suffix(".parts").exists()  # parts go once the file is there
    for i, expected in EXPECTED.items():
        assert members(sets, i, 0.01) == expected
    again, path2, hit2 = cached_plausible_sets(views, table, "fingerprint-a", tmp_path, cfg, progress=False)
    assert hit2 and path2 == path
    assert np.array_equal(again.other, sets.other) and np.allclose(again.transforms, sets.transforms)
    _, path3, hit3 = cached_plausible_sets(views, table, "fingerprint-b", tmp_path, cfg, references=[0],
                                           progress=False)
    assert not hit3 and path3 != path


def test_diameter():
    pts = np.array([[0, 0, 0], [3, 4, 0], [1, 1, 0]], dtype=float)
    assert diameter(pts) == pytest.approx(5.0)
    cube = trimesh.creation.box(extents=(1, 2, 2))
    assert diameter(cube.vertices) == pytest.approx(3.0)
