"""Grasp scoring on hand-built grids: gripper config, widths, collisions, support plane, ranking, poses."""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pssnet_core.geometry import GridPose
from pssnet_core.grasps import (
    GraspCandidates,
    GraspConfig,
    GraspError,
    GripperConfig,
    check_grasps,
    estimate_support_height,
    generate_candidates,
    matrix_to_position_quaternion,
    plan_grasps,
    plot_grasps,
    score_grasps,
    single_completion_choice,
)
from pssnet_core.grasps.config import VoxelDims
from pssnet_core.grasps.lattice import PackedGrids
from pssnet_core.grasps.scoring import observed_point_hits

N = 32
VOXEL = 0.00625  # 0.2 m grid: the default gripper opens 12.8 voxels
CONFIG = GraspConfig()
CLEAR = CONFIG.clearance / VOXEL
GAP = CLEAR - 0.5  # left between a pad and the outermost voxels' faces: the clearance is from their centres
FL = CONFIG.gripper.finger_length / VOXEL
FT = CONFIG.gripper.finger_thickness / VOXEL


def identity_pose(size: int = N, voxel: float = VOXEL) -> GridPose:
    # A camera whose optical frame coincides with the grid frame keeps grid <-> camera checks readable.
    return GridPose(rotation=np.eye(3), origin=np.array([0.1, -0.05, 0.4]), voxel_size=voxel, size=size)


def bar(copies: int = 3, x: tuple[int, int] = (10, 15)) -> np.ndarray:
    """A bar ``x[1] - x[0]`` voxels thick along grid x, 16 long along y, standing on z = 2 up to z = 20."""
    occ = np.zeros((copies, N, N, N), dtype=bool)
    occ[:, x[0]:x[1], 8:24, 2:20] = True
    return occ


def top_grasp(x: float, y: float, tip_z: float, width: float) -> GraspCandidates:
    """One top grasp (approach straight down) closing along grid x; grid units."""
    down = np.array([0.0, 0.0, -1.0])
    closing = np.array([1.0, 0.0, 0.0])
    rot = np.stack([np.cross(closing, down), closing, down], axis=1)
    return GraspCandidates(np.array([[x, y, tip_z]]), rot[None], np.array([width]), np.zeros(1, np.int8))


# ----------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize("kwargs, message", [
    ({"max_opening": -0.01}, "max_opening must be in"),
    ({"max_opening": 3.0}, "max_opening must be in"),
    ({"finger_length": 0.0}, "finger_length must be in"),
    ({"finger_width": float("nan")}, "finite"),
    ({"palm_depth": "2cm"}, "finite number"),
    ({"min_object_width": 0.09}, "min_object_width"),
    ({"grip_force": 0.0}, "grip_force"),
    ({"holds_axial_load": 1}, "holds_axial_load"),
])
def test_gripper_config_rejects_absurd_values(kwargs, message):
    with pytest.raises(GraspError, match=message):
        GripperConfig(**kwargs)


@pytest.mark.parametrize("kwargs, message", [
    ({"max_candidates": 0}, "max_candidates"),
    ({"top_yaws": 0, "side_yaws": 0}, "no approach direction"),
    ({"clearance": 0.05}, "clearance"),
    ({"seed": -1}, "seed"),
    ({"friction": 0.0}, "friction"),
    ({"object_density": -1.0}, "object_density"),
    ({"gripper": {"max_opening": 0.08}}, "GripperConfig"),
    ({"dense_below": 1.5}, "dense_below"),
    ({"dense_below": True}, "dense_below"),
    ({"dense_tilted_pitches": (95.0,)}, "tilted_pitches"),
    ({"dense_below": 0.9, "dense_max_candidates": 0}, "max_candidates"),
])
def test_grasp_config_rejects_bad_values(kwargs, message):
    with pytest.raises(GraspError, match=message):
        GraspConfig(**kwargs)


def test_grasp_error_is_a_value_error():
    assert issubclass(GraspError, ValueError)


# ------------------------------------------------------------------------------------ input checks


@pytest.mark.parametrize("occ, message", [
    (np.zeros((N, N, N), bool), r"\(S, N, N, N\)"),
    (np.zeros((0, N, N, N), bool), "S >= 1"),
    (np.zeros((2, 16, 16, 16), bool), "grid pose says 32"),
])
def test_bad_completions_are_rejected(occ, message):
    with pytest.raises(GraspError, match=message):
        plan_grasps(occ, identity_pose())


def test_bad_points_are_rejected():
    with pytest.raises(GraspError, match="NaN"):
        plan_grasps(bar(), identity_pose(), np.array([[0.0, np.nan, 0.4]]))
    with pytest.raises(GraspError, match=r"\(M, 3\)"):
        plan_grasps(bar(), identity_pose(), np.zeros((4, 2)))


def test_empty_completions_without_observation_cannot_place_the_plane():
    with pytest.raises(GraspError, match="support plane"):
        plan_grasps(np.zeros((2, N, N, N), bool), identity_pose())


def test_empty_completions_give_no_grasps():
    grasps = plan_grasps(np.zeros((2, N, N, N), bool), identity_pose(), support_z=1.0)
    assert len(grasps) == 0 and grasps.holds.shape == (0, 2) and grasps.poses.shape == (0, 4, 4)


# -------------------------------------------------------------------------------------- width


def test_width_of_a_five_voxel_bar_is_its_voxel_centres_plus_clearance():
    grasps = plan_grasps(bar(), identity_pose(), support_z=2.0)
    grid = grasps.grid
    along_x = np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9  # closing axis = grid x
    assert along_x.sum() >= 5
    # 4 voxels between the outermost voxels' centres, the clearance beyond each
    np.testing.assert_allclose(grid.widths[along_x], 4.0 + 2 * CLEAR, atol=1e-6)
    np.testing.assert_allclose(grid.origins[along_x, 0], 12.5, atol=1e-6)  # centred on the bar
    np.testing.assert_allclose(grasps.widths[along_x], (5.0 + 2 * GAP) * VOXEL, atol=1e-9)
    best = grasps.subset(slice(0, 1))
    assert best.scores[0] == 1.0
    assert grasps.widths[0] <= 8.0 * VOXEL + 2 * CONFIG.clearance + 1e-9  # the narrow side is preferred
    # Measured from the voxels' outer faces (the rule before stop 45), the whole clearance beyond them.
    faces = dataclasses.replace(CONFIG, surface_at_voxel_centres=False)
    grid = generate_candidates(bar(), identity_pose(), config=faces, support_z=2.0)
    along_x = np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9
    np.testing.assert_allclose(grid.widths[along_x], 5.0 + 2 * CLEAR, atol=1e-6)


def test_a_box_whose_voxels_read_a_voxel_wider_is_still_closed_across():
    """12 voxels (7.5 cm) of a box whose faces lie inside its outermost voxels (6.5-7 cm): the 8 cm hand closes
    across it with the clearance from those voxels' centres, and no finger enters an occupied voxel."""
    box = bar(2, x=(10, 22))
    grid = generate_candidates(box, identity_pose(), config=CONFIG, support_z=2.0)
    along_x = np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9
    assert along_x.any()
    np.testing.assert_allclose(grid.widths[along_x], 12.0 + 2 * GAP, atol=1e-6)
    assert 12.0 + 2 * GAP <= CONFIG.gripper.max_opening / VOXEL
    checks = check_grasps(grid.subset(np.flatnonzero(along_x)), box, identity_pose(), 2.0, CONFIG)
    assert not checks.finger_hit.any() and not checks.palm_hit.any()
    assert checks.holds[grid.kinds[along_x] == 0].all()  # every top grasp across it (some side ones reach the table)
    faces = dataclasses.replace(CONFIG, surface_at_voxel_centres=False)
    grid = generate_candidates(box, identity_pose(), config=faces, support_z=2.0)
    assert not np.any(np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9)  # 12 + 2 x 0.8 > 12.8 voxels


def test_width_is_the_widest_completion_plus_clearance():
    occ = bar(3)
    occ[1, 15:17] = occ[1, 14]  # completion 1 is 7 voxels thick
    grid = generate_candidates(occ, identity_pose(), config=CONFIG, support_z=2.0)
    along_x = np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9
    np.testing.assert_allclose(grid.widths[along_x], 7.0 + 2 * GAP, atol=1e-6)
    holds, _ = score_grasps(grid.subset(np.flatnonzero(along_x)), occ, identity_pose(), 2.0, CONFIG)
    assert holds.any(axis=0).all()


def test_too_wide_object_is_rejected():
    wide = bar(2, x=(8, 22))  # 14 voxels = 8.75 cm > 8 cm opening
    grid = generate_candidates(wide, identity_pose(), config=CONFIG, support_z=2.0)
    assert len(grid) > 0
    assert not np.any(np.abs(np.abs(grid.rotations[:, 0, 1]) - 1.0) < 1e-9)  # nothing closes across x
    too_wide = top_grasp(15.0, 16.0, 12.5, 14.0 + 2 * CLEAR)
    holds, _ = score_grasps(too_wide, wide, identity_pose(), 2.0, CONFIG)
    assert not holds.any()
    # the same hand-built grasp on the thin bar at a legal width holds
    holds, _ = score_grasps(top_grasp(12.5, 16.0, 12.5, 5.0 + 2 * CLEAR), bar(2), identity_pose(), 2.0, CONFIG)
    assert holds.all()


# --------------------------------------------------------------------------------- collisions


def test_finger_overlapping_one_voxel_is_not_held_for_that_completion_only():
    occ = bar(3)
    grasp = top_grasp(12.5, 16.0, 12.5, 5.0 + 2 * CLEAR)
    holds, _ = score_grasps(grasp, occ, identity_pose(), 2.0, CONFIG)
    assert holds.tolist() == [[True, True, True]]
    finger_x = int(np.floor(12.5 + (5.0 + 2 * CLEAR) / 2 + FT / 2))
    occ[1, finger_x, 16, 12] = True  # one voxel where the +y finger (grid +x side) goes
    holds, _ = score_grasps(grasp, occ, identity_pose(), 2.0, CONFIG)
    assert holds.tolist() == [[True, False, True]]


def test_palm_collision_and_empty_closing_region_are_not_held():
    occ = bar(2)
    occ[0, 12, 16, int(12.5 + FL + 1)] = True  # a voxel just above the fingers' root: under the palm
    holds, _ = score_grasps(top_grasp(12.5, 16.0, 12.5, 5.0 + 2 * CLEAR), occ, identity_pose(), 2.0, CONFIG)
    assert holds.tolist() == [[False, True]]
    holds, _ = score_grasps(top_grasp(12.5, 28.0, 12.5, 5.0 + 2 * CLEAR), occ, identity_pose(), 2.0, CONFIG)
    assert not holds.any()  # nothing between the fingers


def test_min_object_width_rejects_slivers():
    occ = np.zeros((1, N, N, N), bool)
    occ[0, 12, 8:24, 2:20] = True  # one voxel = 6.25 mm thick
    grasp = top_grasp(12.5, 16.0, 12.5, 1.0 + 2 * CLEAR)
    assert score_grasps(grasp, occ, identity_pose(), 2.0, CONFIG)[0].all()
    strict = GraspConfig(gripper=GripperConfig(min_object_width=0.012))
    assert not score_grasps(grasp, occ, identity_pose(), 2.0, strict)[0].any()


def test_below_the_support_plane_is_rejected():
    occ = bar(2)
    occ[:, :, :, 8:] = False  # a short bar: fingers reaching down to the plane do not put the palm into it
    low = top_grasp(12.5, 16.0, 1.5, 5.0 + 2 * CLEAR)  # fingertips half a voxel below a plane at z = 2
    assert not score_grasps(low, occ, identity_pose(), 2.0, CONFIG)[0].any()
    assert score_grasps(low, occ, identity_pose(), 1.0, CONFIG)[0].all()
    grasps = plan_grasps(occ, identity_pose(), support_z=6.0)  # a plane through the bar's lower part
    assert len(grasps) > 0
    corners = lowest_gripper_z(grasps)
    assert np.all(corners[grasps.scores > 0] >= 6.0 - 1e-6)


def lowest_gripper_z(grasps) -> np.ndarray:
    """Brute force: lowest grid z of the eight corners of every gripper box (fingers at width, palm)."""
    g = CONFIG.gripper
    fl, fw, ft, pd, wmax = (v / VOXEL for v in (g.finger_length, g.finger_width, g.finger_thickness,
                                                g.palm_depth, g.max_opening))
    lows = []
    for origin, rot, w in zip(grasps.grid.origins, grasps.grid.rotations, grasps.grid.widths, strict=True):
        boxes = [((-fw / 2, fw / 2), (w / 2, w / 2 + ft), (-fl, 0)),
                 ((-fw / 2, fw / 2), (-w / 2 - ft, -w / 2), (-fl, 0)),
                 ((-fw / 2, fw / 2), (-wmax / 2 - ft, wmax / 2 + ft), (-fl - pd, -fl))]
        z = min((origin + rot @ np.array([x, y, zz]))[2] for b in boxes for x in b[0] for y in b[1] for zz in b[2])
        lows.append(z)
    return np.array(lows)


# --------------------------------------------------------------------------- ranking and poses


def test_a_denser_search_is_added_only_where_no_grasp_holds_the_weight_firmly():
    # Solid water-dense bar: the best grasp holds all its weight, so the denser search (by default below 0.9)
    # changes nothing. At 25 times that density no grasp holds a quarter of it: the denser search's candidates join
    # the default's, and the best of both comes first.
    assert GraspConfig().dense_below == 0.9
    off = GraspConfig(dense_below=0.0)
    plain = plan_grasps(bar(), identity_pose(), config=off)
    assert plain.weight_shares[0] == 1.0
    firm = plan_grasps(bar(), identity_pose(), config=GraspConfig())
    np.testing.assert_array_equal(firm.poses, plain.poses)

    heavy = GraspConfig(object_density=25_000.0)
    default = plan_grasps(bar(), identity_pose(), config=dataclasses.replace(heavy, dense_below=0.0))
    assert default.weight_shares[0] < 0.9
    denser = plan_grasps(bar(), identity_pose(), config=heavy.denser())
    assert len(denser) > len(default)
    both = plan_grasps(bar(), identity_pose(), config=heavy)
    assert len(both) == len(default) + len(denser)
    assert both.grip[0] == max(default.grip[0], denser.grip[0])
    assert np.all(np.diff(both.grip) <= 0)  # ranked together, not one list after the other
    assert heavy.denser().dense_below == 0.0 and heavy.denser().max_candidates == heavy.dense_max_candidates


def test_ranking_scores_and_determinism():
    occ = bar(4)
    occ[2:, 15:18, 8:24, 2:20] = True  # two of four completions are thicker (8 voxels)
    by_fraction = GraspConfig(max_candidates=60, seed=3, rank_by="fraction")
    first = plan_grasps(occ, identity_pose(), support_z=2.0, config=by_fraction)
    again = plan_grasps(occ, identity_pose(), support_z=2.0, config=by_fraction)
    assert first.grip is None
    assert 0 < len(first) <= 60
    np.testing.assert_array_equal(first.poses, again.poses)
    np.testing.assert_array_equal(first.holds, again.holds)
    np.testing.assert_allclose(first.scores, first.holds.mean(axis=1))
    assert np.all((first.scores >= 0) & (first.scores <= 1)) and np.all((first.secondary >= 0) & (first.secondary <= 1))
    key = np.stack([first.scores, first.secondary], axis=1)
    for a, b in zip(key[:-1], key[1:], strict=True):
        assert a[0] > b[0] or (a[0] == b[0] and a[1] >= b[1])
    other = plan_grasps(occ, identity_pose(), support_z=2.0,
                        config=dataclasses.replace(by_fraction, seed=4))
    assert other.scores[0] == first.scores[0] == 1.0
    # The default: the expected grip first, then the secondary term.
    grip = plan_grasps(occ, identity_pose(), support_z=2.0, config=GraspConfig(max_candidates=60, seed=3))
    key = np.stack([grip.grip, grip.scores, grip.secondary], axis=1)
    for a, b in zip(key[:-1], key[1:], strict=True):
        assert a[0] > b[0] or (a[0] == b[0] and (a[1] > b[1] or (a[1] == b[1] and a[2] >= b[2])))
    checks = check_grasps(grip.grid, occ, identity_pose(), 2.0, CONFIG)
    np.testing.assert_allclose(grip.grip, (checks.holds * checks.coverage * checks.resistance).mean(axis=1))


def test_expected_grip_prefers_a_flat_grip_of_most_completions_to_clipping_every_ones_edge():
    # Four completions disagree about where a bar lies along y: three span y = 4..16, one 15..27. Only the 1-voxel
    # overlap lies in all four: a grasp over it (y = 15.5) holds for every completion but touches each with half its
    # pads, as it would touch the real bar. One over y = 10.5 grips three of them with the whole pads.
    occ = np.zeros((4, N, N, N), dtype=bool)
    occ[:3, 10:15, 4:16, 2:20] = True
    occ[3, 10:15, 15:27, 2:20] = True

    def allowed(c: GraspCandidates) -> np.ndarray:  # closing along x, over y = 10.5 or 15.5
        return np.isin(c.origins[:, 1], (10.5, 15.5)) & (np.abs(c.rotations[:, 0, 1]) > 0.99)

    config = GraspConfig(top_yaws=2, side_yaws=0, tilted_pitches=(), max_candidates=400, seed=1)
    expected = plan_grasps(occ, identity_pose(), support_z=2.0, config=config, allowed=allowed)
    fraction = plan_grasps(occ, identity_pose(), support_z=2.0, config=dataclasses.replace(config, rank_by="fraction"),
                           allowed=allowed)
    assert fraction.grid.origins[0, 1] == 15.5 and fraction.scores[0] == 1.0 and fraction.grip is None
    assert expected.grid.origins[0, 1] == 10.5 and expected.scores[0] == 0.75
    flat = check_grasps(expected.grid.subset(np.array([0])), occ, identity_pose(), 2.0, config)
    clipped = check_grasps(fraction.grid.subset(np.array([0])), occ, identity_pose(), 2.0, config)
    assert flat.coverage[0, :3].min() > 0.8 and clipped.coverage[0].max() < 0.6
    assert expected.grip[0] == np.max(expected.grip) == pytest.approx(flat.coverage[0, :3].sum() / 4)
    with pytest.raises(GraspError, match="rank_by"):
        GraspConfig(rank_by="score")


def test_many_completions_use_several_bit_words():
    occ = bar(70)
    grasp = top_grasp(12.5, 16.0, 12.5, 5.0 + 2 * CLEAR)
    finger_x = int(np.floor(12.5 + (5.0 + 2 * CLEAR) / 2 + FT / 2))
    occ[1::3, finger_x, 16, 12] = True
    holds, _ = score_grasps(grasp, occ, identity_pose(), 2.0, CONFIG)
    expected = np.ones(70, bool)
    expected[1::3] = False
    np.testing.assert_array_equal(holds[0], expected)


def test_camera_frame_pose_convention():
    pose = GridPose(rotation=Rotation.from_euler("xyz", [100, 10, -20], degrees=True).as_matrix(),
                    origin=np.array([0.05, 0.02, 0.6]), voxel_size=VOXEL, size=N)
    grasps = plan_grasps(bar(), pose, support_z=2.0, config=GraspConfig(max_candidates=40))
    assert len(grasps) > 0
    for m, origin, rot in zip(grasps.poses, grasps.grid.origins, grasps.grid.rotations, strict=True):
        r = m[:3, :3]
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(np.cross(r[:, 1], r[:, 2]), r[:, 0], atol=1e-9)  # x = y cross z
        np.testing.assert_allclose(m[:3, 3], pose.grid_to_camera(origin[None])[0], atol=1e-12)
        np.testing.assert_allclose(r[:, 2], pose.rotation @ rot[:, 2], atol=1e-12)  # approach
    p, q = matrix_to_position_quaternion(grasps.poses[0])
    np.testing.assert_allclose(p, grasps.poses[0, :3, 3])
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), grasps.poses[0, :3, :3], atol=1e-9)
    with pytest.raises(GraspError, match="4x4"):
        matrix_to_position_quaternion(np.eye(3))
    top = [k for k, kind in enumerate(grasps.kinds) if kind == "top"]
    assert top and np.allclose(grasps.grid.rotations[top][:, :, 2], [0, 0, -1])  # top = straight down in the grid


def test_top_side_and_tilted_approaches_are_generated():
    grid = generate_candidates(bar(), identity_pose(), config=GraspConfig(max_candidates=400), support_z=2.0)
    assert set(grid.kinds.tolist()) == {0, 1, 2}
    np.testing.assert_allclose(grid.rotations[grid.kinds == 0][:, 2, 2], -1.0, atol=1e-12)  # top: straight down
    np.testing.assert_allclose(grid.rotations[grid.kinds == 1][:, 2, 2], 0.0, atol=1e-12)  # side: horizontal
    tilted = grid.rotations[grid.kinds == 2]
    np.testing.assert_allclose(tilted[:, 2, 2], -np.sin(np.radians(45.0)), atol=1e-12)  # 45 degrees down
    np.testing.assert_allclose(np.einsum("kij,kil->kjl", tilted, tilted), np.tile(np.eye(3), (len(tilted), 1, 1)),
                               atol=1e-12)


def handle_behind_body() -> np.ndarray:
    """A block (x 0-14) and, 3 voxels behind it, a 1-voxel thin bar (x 17, y 14-18, z 8-14): a mug's handle."""
    occ = np.zeros((1, N, N, N), dtype=bool)
    occ[:, 0:14, 6:26, 2:20] = True
    occ[:, 17, 14:18, 8:14] = True
    return occ


def test_shallow_grasps_pinch_a_handle_whose_body_deep_fingers_would_hit():
    occ, pose = handle_behind_body(), identity_pose()
    # Level approaches only, and only from +x (onto the bar, towards the block), closing axis horizontal.
    options = dict(max_candidates=2000, top_yaws=0, tilted_pitches=(), side_rolls=(0.0,), oversample=20.0)

    def from_behind(config: GraspConfig) -> tuple[GraspCandidates, np.ndarray]:
        candidates = generate_candidates(occ, pose, config=config, support_z=2.0)
        candidates = candidates.subset(np.flatnonzero(candidates.rotations[:, 0, 2] < -0.99))
        return candidates, score_grasps(candidates, occ, pose, 2.0, config)[0][:, 0]

    def from_behind_holding(config: GraspConfig) -> GraspCandidates:
        candidates, holds = from_behind(config)
        return candidates.subset(np.flatnonzero(holds))

    # The deepest grasps from behind take the block between the fingers too, which is wider than the opening.
    assert len(from_behind_holding(GraspConfig(shallow_depths=(), **options))) == 0
    shallow = from_behind_holding(GraspConfig(**options))
    assert len(shallow) > 0
    assert np.all(shallow.origins[:, 0] > 14.0)  # fingertips stop in the gap, short of the block


def test_thin_parts_get_more_candidates_with_the_thin_anchor_bias():
    occ, pose = handle_behind_body(), identity_pose()

    def share_on_bar(bias: float) -> float:
        config = GraspConfig(max_candidates=150, oversample=2.0, thin_anchor_bias=bias)
        candidates = generate_candidates(occ, pose, config=config, support_z=2.0)
        return float(np.mean(candidates.origins[:, 0] > 15.0))

    assert share_on_bar(1.0) > 1.5 * share_on_bar(0.0)


def test_a_filter_that_rejects_most_draws_gets_more_rounds_of_draws():
    # Like a mug in a cupboard: only approaches from the +x side pass the filter, a small share of the draws.
    occ, pose = handle_behind_body(), identity_pose()

    def from_plus_x(c: GraspCandidates) -> np.ndarray:
        return c.rotations[:, 0, 2] < -0.5

    def candidates(rounds: int, allowed=from_plus_x) -> GraspCandidates:
        config = GraspConfig(max_candidates=150, oversample=2.0, draw_rounds=rounds)
        return generate_candidates(occ, pose, config=config, support_z=2.0, allowed=allowed)

    one, many = candidates(1), candidates(8)
    assert np.all(many.rotations[:, 0, 2] < -0.5)
    assert len(many) >= 4 * len(one) > 0
    # Without a filter, or one that takes nothing, one round is drawn whatever draw_rounds says.
    np.testing.assert_array_equal(candidates(1, None).origins, candidates(8, None).origins)
    np.testing.assert_array_equal(candidates(1, None).origins, candidates(8, lambda c: np.ones(len(c), bool)).origins)
    with pytest.raises(GraspError, match="draw_rounds"):
        GraspConfig(draw_rounds=0)


def test_max_candidates_bounds_the_count():
    grid = generate_candidates(bar(), identity_pose(), config=GraspConfig(max_candidates=7), support_z=2.0)
    assert 1 <= len(grid) <= 7


def test_support_height_estimate():
    occ = bar(3)
    pose = identity_pose()
    assert estimate_support_height(occ, pose) == 2.0  # lowest occupied layer of the completions
    points = pose.grid_to_camera(np.array([[12.0, 10.0, 4.3], [12.0, 12.0, 9.0]]))
    assert estimate_support_height(occ, pose, points) == 2.0  # completions reach lower than the points
    occ[:, :, :, 2:5] = False
    assert estimate_support_height(occ, pose, points) == pytest.approx(4.3)
    known = np.zeros((N, N, N), bool)
    known[12, 10, 3] = True
    assert estimate_support_height(occ, pose, known_occupied=known) == 3.0
    occ[0, 12, 12, 0] = True  # one stray low voxel in one sample does not move the median
    assert estimate_support_height(occ, pose, known_occupied=known) == 3.0


def test_single_completion_choice_and_plot(tmp_path):
    occ = bar(4)
    occ[1:, 15:20] = occ[1:, 14:15]  # three of four completions are 10 voxels thick
    choice = single_completion_choice(occ, identity_pose(), 0, support_z=2.0)
    assert choice.score_alone == 1.0
    assert len(choice.grasp) == 1 and choice.grasp.holds.shape == (1, 4)
    assert choice.score_all == pytest.approx(choice.grasp.holds.mean())
    with pytest.raises(GraspError, match="out of range"):
        single_completion_choice(occ, identity_pose(), 4, support_z=2.0)
    grasps = plan_grasps(occ, identity_pose(), support_z=2.0)
    assert grasps.scores[0] == 1.0
    path = tmp_path / "grasps.png"
    fig = plot_grasps(grasps, occ, identity_pose(), top_k=3, path=path, title="bar")
    assert path.stat().st_size > 10_000 and len(fig.axes) == 2
    matplotlib.pyplot.close(fig)


def test_confident_choice_grips_firmest_among_the_sure_grasps_or_abstains():
    grasps = plan_grasps(bar(), identity_pose(), None, GraspConfig(max_candidates=50), support_z=2.0)
    grasps = grasps.subset(np.arange(3))
    grasps = dataclasses.replace(grasps, scores=np.array([1.0, 0.95, 0.5]), secondary=np.array([0.2, 0.9, 1.0]))
    assert grasps.confident_choice(0.9) == 1  # sure enough and grips best; the surest grips worse
    assert grasps.confident_choice(1.0) == 0
    assert dataclasses.replace(grasps, scores=np.array([0.8, 0.7, 0.5])).confident_choice(0.9) is None
    with pytest.raises(GraspError):
        grasps.confident_choice(0.0)


def test_lever_is_the_weights_moment_across_the_closing_axis():
    occ = bar(1)  # centroid (12.5, 16, 11) in grid coordinates
    approach = np.array([-1.0, 0.0, 0.0])  # a side grasp from +x, its closing region centred 6 voxels off in x

    def lever(closing: np.ndarray) -> float:
        rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)
        fl = CONFIG.gripper.finger_length / VOXEL
        origin = np.array([18.5, 16.0, 11.0]) + 0.5 * fl * approach  # closing region's middle at x = 18.5
        candidates = GraspCandidates(origin[None], rot[None], np.array([4.0]), np.ones(1, np.int8))
        return float(check_grasps(candidates, occ, identity_pose(), 2.0, CONFIG).lever[0, 0])

    assert lever(np.array([0.0, 1.0, 0.0])) == pytest.approx(0.0, abs=1e-9)  # the moment is about the closing axis
    assert lever(np.array([0.0, 0.0, 1.0])) == pytest.approx(6.0)  # pinched from above and below: all across


def test_a_fingertip_pinch_of_a_round_bodys_near_side_is_squeezed_out_a_flat_one_is_not():
    # A vertical cylinder of radius 7 voxels (too wide for the opening) and a 6-voxel-thick slab, both pinched
    # by a side grasp from -x whose fingertips reach 2 voxels past the near face, closing along y.
    i, j = np.meshgrid(np.arange(N) + 0.5, np.arange(N) + 0.5, indexing="ij")
    cylinder = np.zeros((1, N, N, N), dtype=bool)
    cylinder[0, (i - 16.0) ** 2 + (j - 16.0) ** 2 <= 7.0**2, 2:20] = True
    slab = np.zeros((1, N, N, N), dtype=bool)
    slab[0, 9:23, 13:19, 2:20] = True
    approach, closing = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)

    def checks(occ: np.ndarray, width: float):
        candidates = GraspCandidates(np.array([[11.0, 16.0, 11.0]]), rot[None], np.array([width]), np.ones(1, np.int8))
        return check_grasps(candidates, occ, identity_pose(), 2.0, CONFIG)

    round_pinch = checks(cylinder, 12.0)
    assert round_pinch.contains[0, 0] and round_pinch.squeezed_out[0, 0] and not round_pinch.holds[0, 0]
    flat_pinch = checks(slab, 8.0)
    assert flat_pinch.contains[0, 0] and not flat_pinch.squeezed_out[0, 0] and flat_pinch.holds[0, 0]


@pytest.mark.parametrize(("yaw_deg", "outside"), [(0.0, False), (20.0, False), (30.0, True), (35.0, True)])
def test_pads_outside_the_friction_cone_squeeze_a_body_out(yaw_deg: float, outside: bool):
    # A wall 8 voxels thick along y, pinched from above with the closing axis turned `yaw_deg` from its normal: the
    # pads meet its faces that far from square. Friction 0.5 holds up to 26.6 degrees, read from the voxels'
    # smoothed normals. Nothing else fails (fingers and palm clear), so the cone alone decides.
    occ = np.zeros((1, N, N, N), dtype=bool)
    occ[0, 4:28, 12:20, 2:10] = True
    turn = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    approach, closing = np.array([0.0, 0.0, -1.0]), turn @ np.array([0.0, 1.0, 0.0])
    rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)
    candidates = GraspCandidates(np.array([[16.0, 16.0, 4.0]]), rot[None], np.array([12.5]), np.ones(1, np.int8))
    checks = check_grasps(candidates, occ, identity_pose(), 2.0, CONFIG)
    assert checks.squeezed_out[0, 0] == outside
    assert checks.holds[0, 0] != outside


@pytest.mark.parametrize("tip_depth", [2.0, 2.5, 3.0])
def test_a_fingertip_pinch_of_a_solid_boxs_corner_is_judged_by_its_faces_a_thin_plates_is_not(tip_depth: float):
    # A side grasp pushed diagonally onto a vertical edge of a 16-voxel block, the fingertips `tip_depth` voxels past
    # the edge: the pads hold less of the corner across than MIN_NORMAL_EXTENT (the planner before judged none of
    # these), and meet its two faces at 45 degrees, outside the friction cone (26.6). The block's solid core puts the
    # pinch under the friction-cone test; a plate 2 voxels thick cut to the same corner has no core (its voxels do not
    # resolve its faces' slope, as on a handle) and is not judged.
    approach = np.array([-1.0, -1.0, 0.0]) / np.sqrt(2.0)
    closing = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)
    tip = np.array([24.0, 24.0, 11.0]) + tip_depth * approach
    candidates = GraspCandidates(tip[None], rot[None], np.array([9.0]), np.ones(1, np.int8))
    block = np.zeros((1, N, N, N), dtype=bool)
    block[0, 8:24, 8:24, 2:20] = True
    plate = np.zeros_like(block)
    plate[0, 8:24, 8:24, 10:12] = True
    on_block = check_grasps(candidates, block, identity_pose(), 2.0, CONFIG)
    on_plate = check_grasps(candidates, plate, identity_pose(), 2.0, CONFIG)
    assert on_block.contains[0, 0] and on_plate.contains[0, 0]
    assert on_block.squeezed_out[0, 0] and not on_block.holds[0, 0]
    assert not on_plate.squeezed_out[0, 0] and on_plate.holds[0, 0]


def test_solid_cores_erode_each_completion_alone():
    # A block in the first completion and nothing in the second: the first's core is the block less one voxel on
    # every side, whatever the (empty) neighbour; a wall 2 voxels thick has none.
    occ = np.zeros((3, N, N, N), dtype=bool)
    occ[0, 8:16, 8:16, 2:10] = True
    occ[2, 8:16, 8:10, 2:10] = True
    cores = PackedGrids(occ).solid_cores
    expected = np.zeros_like(occ)
    expected[0, 9:15, 9:15, 3:9] = True
    np.testing.assert_array_equal(cores.unpack(cores.data.reshape(len(cores.data), N + 2, N + 2, N + 2))
                                  [1:-1, 1:-1, 1:-1].transpose(3, 0, 1, 2), expected)


def _mug_like(body: bool = True) -> np.ndarray:
    """A vertical rod 2 x 2 voxels thick, 14 tall (a handle), and, 10 voxels away along -x, a heavy block."""
    occ = np.zeros((1, N, N, N), dtype=bool)
    occ[0, 22:24, 15:17, 4:18] = True
    if body:
        occ[0, 4:16, 10:22, 2:20] = True
    return occ


def _rod_pinch(closing: np.ndarray) -> GraspCandidates:
    """A side grasp from +x pinching the rod of :func:`_mug_like` (its closing region centred on the rod)."""
    approach = np.array([-1.0, 0.0, 0.0])
    rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)
    origin = np.array([23.0, 16.0, 11.0]) + 0.5 * FL * approach
    return GraspCandidates(origin[None], rot[None], np.array([2.0 + 2 * CLEAR]), np.ones(1, np.int8))


def test_a_pinch_twisted_by_the_weight_on_a_narrow_patch_resists_only_part_of_it():
    horizontal = _rod_pinch(np.array([0.0, 1.0, 0.0]))  # the weight's moment is about the closing axis
    twisted = check_grasps(horizontal, _mug_like(), identity_pose(), 2.0, CONFIG)
    assert twisted.holds[0, 0] and twisted.lever[0, 0] == pytest.approx(0.0, abs=0.5)
    share = twisted.resistance[0, 0]
    assert 0.0 < share < 0.5  # the strip of contact on the rod cannot twist-hold the block 10 voxels away
    # Alone, the rod hangs straight below the pads: nothing twists and its small weight is held in full.
    assert check_grasps(horizontal, _mug_like(body=False), identity_pose(), 2.0, CONFIG).resistance[0, 0] == 1.0
    # The share scales with the friction and the grip force over the weight (density), and saturates at 1.
    def share_with(**changes) -> float:
        gripper = dataclasses.replace(CONFIG.gripper, **changes.pop("gripper", {}))
        config = dataclasses.replace(CONFIG, gripper=gripper, **changes)
        return float(check_grasps(horizontal, _mug_like(), identity_pose(), 2.0, config).resistance[0, 0])

    assert share_with(friction=1.0) == pytest.approx(min(1.0, 2 * share), rel=1e-6)
    assert share_with(object_density=2 * CONFIG.object_density) == pytest.approx(share / 2, rel=1e-6)
    assert share_with(gripper={"grip_force": 50 * CONFIG.gripper.grip_force}) == 1.0


def test_a_flat_wide_contact_holds_the_whole_weight():
    occ = bar(1)  # 5 voxels thick: a top grasp over its middle touches with the whole pads
    checks = check_grasps(top_grasp(12.5, 16.0, 13.0, 5.0 + 2 * CLEAR), occ, identity_pose(), 2.0, CONFIG)
    assert checks.holds[0, 0] and checks.resistance[0, 0] == 1.0


def test_a_load_along_the_closing_axis_is_not_held_by_force_controlled_fingers():
    vertical = _rod_pinch(np.array([0.0, 0.0, 1.0]))  # from above and below: the weight pushes along the axis
    rod = _mug_like(body=False)
    rod[0, 22:24, 15:17, 4:18] = False
    rod[0, 22:24, 12:20, 10:12] = True  # a horizontal bar instead, pinched from above and below
    assert check_grasps(vertical, rod, identity_pose(), 2.0, CONFIG).resistance[0, 0] == 0.0
    stiff = dataclasses.replace(CONFIG, gripper=dataclasses.replace(CONFIG.gripper, holds_axial_load=True))
    assert check_grasps(vertical, rod, identity_pose(), 2.0, stiff).resistance[0, 0] == 1.0


def test_the_share_of_the_weight_held_is_half_the_tie_break():
    from pssnet_core.grasps.scoring import holds_and_secondary

    candidates = _rod_pinch(np.array([0.0, 1.0, 0.0]))
    checks = check_grasps(candidates, _mug_like(), identity_pose(), 2.0, CONFIG)
    full = dataclasses.replace(checks, resistance=np.ones_like(checks.resistance))
    none = dataclasses.replace(checks, resistance=np.zeros_like(checks.resistance))
    _, with_full = holds_and_secondary(full, candidates, CONFIG, VOXEL)
    _, with_none = holds_and_secondary(none, candidates, CONFIG, VOXEL)
    _, actual = holds_and_secondary(checks, candidates, CONFIG, VOXEL)
    assert with_full[0] - with_none[0] == pytest.approx(0.5)
    assert actual[0] == pytest.approx(with_none[0] + 0.5 * checks.resistance[0, 0])


def test_weight_shares_are_the_weighted_mean_share_held_over_the_completions_held():
    from pssnet_core.grasps.scoring import weight_shares

    occ = np.concatenate([_mug_like(), _mug_like(body=False)])  # the handle with and without the heavy body
    candidates = _rod_pinch(np.array([0.0, 1.0, 0.0]))
    checks = check_grasps(candidates, occ, identity_pose(), 2.0, CONFIG)
    assert checks.holds[0].all()
    twisted, alone = checks.resistance[0]
    assert twisted < 0.5 and alone == 1.0
    assert weight_shares(checks)[0] == pytest.approx((twisted + alone) / 2)
    assert weight_shares(checks, np.array([0.8, 0.2]))[0] == pytest.approx(0.8 * twisted + 0.2 * alone)
    # Only the completions the grasp holds for count; a grasp that holds for none holds no share.
    first_only = dataclasses.replace(checks, contains=np.array([[True, False]]))
    assert weight_shares(first_only, np.array([0.8, 0.2]))[0] == pytest.approx(twisted)
    assert weight_shares(dataclasses.replace(checks, contains=np.zeros((1, 2), bool)))[0] == 0.0
    # The planner reports them per ranked grasp.
    grasps = plan_grasps(occ, identity_pose(), config=GraspConfig(max_candidates=100), support_z=2.0,
                         weights=np.array([0.8, 0.2]))
    recheck = check_grasps(grasps.grid, occ, identity_pose(), 2.0, CONFIG)
    np.testing.assert_allclose(grasps.weight_shares, weight_shares(recheck, np.array([0.8, 0.2])))
    assert np.all(grasps.weight_shares[grasps.scores == 0] == 0) and np.any(grasps.weight_shares > 0)
    np.testing.assert_array_equal(grasps.top(3).weight_shares, grasps.weight_shares[:3])


def test_observed_points_inside_a_finger_or_the_palm_are_found():
    width = 5.0 + 2 * CLEAR
    grasp = top_grasp(12.5, 16.0, 12.5, width)  # fingers from z = 12.5 (tips) up to 12.5 + FL, closing along x
    dims = VoxelDims.of(CONFIG, VOXEL)
    points = np.array([[12.5 + width / 2 + FT / 2, 16.0, 12.5 + FL / 2],  # in the +x finger
                       [12.5, 16.0, 13.0],  # between the fingers: what they close on
                       [12.5 + width / 2 + FT / 2, 16.0, 12.0],  # past the fingertips
                       [12.5, 16.0, 12.5 + FL + 1.0]])  # above the fingers' root: in the palm
    hits = [observed_point_hits(grasp, points[i:i + 1], dims) for i in range(4)]
    assert [(bool(f[0]), bool(p[0])) for f, p in hits] == [(True, False), (False, False), (False, False),
                                                            (False, True)]
    assert observed_point_hits(grasp, points, dims, which=np.zeros(1, bool))[0].tolist() == [False]


def test_with_the_observed_points_check_no_finger_lands_on_surface_the_camera_saw():
    # Every completion is 5 voxels thick along x, but the camera saw surface 3.5 voxels beyond its +x face (the
    # completions are too thin there): some grasps that hold for every completion put a finger or the palm on it.
    pose = identity_pose()
    y, z = np.meshgrid(np.arange(8.25, 24.0, 0.5), np.arange(2.25, 20.0, 0.5), indexing="ij")
    seen = np.stack([np.full(y.size, 18.5), y.ravel(), z.ravel()], axis=1)
    points = pose.grid_to_camera(seen)
    dims = VoxelDims.of(CONFIG, VOXEL)
    for check in (False, True):
        grasps = plan_grasps(bar(), pose, points, dataclasses.replace(CONFIG, observed_points_check=check),
                             support_z=2.0)
        held = grasps.scores > 0
        finger, palm = observed_point_hits(grasps.grid, seen, dims)
        if check:
            assert held.any() and not np.any((finger | palm) & held)
        else:
            assert np.any((finger | palm) & held)  # without it some grasps that hold sit in the seen surface
    with pytest.raises(GraspError, match="observed_points_check"):
        GraspConfig(observed_points_check="yes")
    with pytest.raises(GraspError, match="surface_at_voxel_centres"):
        GraspConfig(surface_at_voxel_centres="yes")
