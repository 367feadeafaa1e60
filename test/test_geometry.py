"""Observation geometry: intrinsics, masked points, grid placement, known-occupied/free grids."""

from __future__ import annotations

import numpy as np
import pytest

from pssnet_core.geometry import (
    CameraIntrinsics,
    GridConfig,
    GridPose,
    ObservationError,
    gravity_aligned_rotation,
    masked_points,
    observe,
    place_grid,
)

K = CameraIntrinsics(width=160, height=120, fx=140.0, fy=140.0, cx=79.5, cy=59.5)


def wall_scene(distance: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """A camera facing a vertical wall at ``distance`` with a 'raised' square object 5 cm in front of it."""
    depth = np.full((K.height, K.width), distance, dtype=np.float32)
    mask = np.zeros_like(depth, dtype=np.uint8)
    mask[50:70, 70:90] = 1
    depth[mask == 1] = distance - 0.05
    return depth, mask


UP = np.array([0.0, -1.0, 0.0])  # camera looking horizontally: up is -y in the optical frame


def test_intrinsics_from_k_and_projection_round_trip():
    k = [140.0, 0.0, 79.5, 0.0, 140.0, 59.5, 0.0, 0.0, 1.0]
    intr = CameraIntrinsics.from_k(k, 160, 120)
    assert intr == K
    u, v = np.array([0.0, 10.5, 159.0]), np.array([0.0, 100.0, 60.0])
    points = intr.backproject(u, v, np.array([0.5, 1.0, 2.0]))
    pu, pv, pz = intr.project(points)
    np.testing.assert_allclose(pu, u)
    np.testing.assert_allclose(pv, v)
    np.testing.assert_allclose(pz, [0.5, 1.0, 2.0])


@pytest.mark.parametrize("kwargs, message", [
    ({"fx": 0.0}, "focal lengths must be positive"),
    ({"fy": float("nan")}, "finite"),
    ({"width": 0}, "image size"),
])
def test_bad_intrinsics_are_rejected(kwargs, message):
    params = dict(width=160, height=120, fx=140.0, fy=140.0, cx=79.5, cy=59.5) | kwargs
    with pytest.raises(ObservationError, match=message):
        CameraIntrinsics(**params)


def test_masked_points_skip_invalid_readings():
    depth, mask = wall_scene()
    depth[50, 70] = np.nan
    depth[51, 70] = 0.0
    depth[52, 70] = np.inf
    depth[53, 70] = 9.0  # beyond max_depth
    points = masked_points(depth, mask, K)
    assert len(points) == 20 * 20 - 4
    assert np.all(np.isfinite(points))
    np.testing.assert_allclose(points[:, 2], 0.55, atol=1e-6)


@pytest.mark.parametrize("change, message", [
    (lambda d, m: (d, np.zeros_like(m)), "mask is empty"),
    (lambda d, m: (np.zeros_like(d), m), "only 0 of 400 masked pixels"),
    (lambda d, m: (d, m[:-1]), "mask shape"),
    (lambda d, m: (d.astype(np.uint16), m), "float metres"),
    (lambda d, m: (d[:, :-2], m[:, :-2]), "camera_info says"),
])
def test_masked_points_errors_say_what_is_wrong(change, message):
    depth, mask = change(*wall_scene())
    with pytest.raises(ObservationError, match=message):
        masked_points(depth, mask, K)


def test_gravity_aligned_rotation_is_proper_and_level():
    tilt = np.radians(30.0)
    up = np.array([0.0, -np.cos(tilt), -np.sin(tilt)])  # camera pitched down by 30 degrees
    r = gravity_aligned_rotation(up)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r[:, 2], up / np.linalg.norm(up))
    assert r[:, 0] @ np.array([0.0, 0.0, 1.0]) > 0  # x points away from the camera
    assert abs(r[:, 0] @ up) < 1e-12  # and is horizontal


def test_looking_straight_down_is_an_error():
    with pytest.raises(ObservationError, match="straight along the up vector"):
        gravity_aligned_rotation(np.array([0.0, 0.0, -1.0]))


def test_grid_placement_is_deterministic_and_holds_the_points():
    depth, mask = wall_scene()
    config = GridConfig(size=32, voxel_size=0.005)
    points = masked_points(depth, mask, K)
    pose = place_grid(points, UP, config)
    again = place_grid(points.copy(), UP, config)
    np.testing.assert_array_equal(again.to_matrix(), pose.to_matrix())
    grid = pose.camera_to_grid(points)
    # Front margin of one voxel along the viewing direction, bottom margin one voxel, centred sideways.
    assert grid[:, 0].min() == pytest.approx(config.front_margin)
    assert grid[:, 2].min() == pytest.approx(config.bottom_margin)
    assert 0.5 * (grid[:, 1].min() + grid[:, 1].max()) == pytest.approx(config.size / 2)
    np.testing.assert_allclose(pose.grid_to_camera(grid), points, atol=1e-9)


def test_grid_pose_dict_round_trip():
    depth, mask = wall_scene()
    pose = place_grid(masked_points(depth, mask, K), UP, GridConfig())
    again = GridPose.from_dict(pose.to_dict())
    np.testing.assert_allclose(again.to_matrix(), pose.to_matrix())
    assert (again.size, again.voxel_size) == (pose.size, pose.voxel_size)


@pytest.mark.parametrize("size", [16, 20])
def test_centres_of_a_stack_of_grids_equal_each_grids_own(size):
    pose = GridPose(rotation=gravity_aligned_rotation(np.array([0.1, -1.0, 0.3])), origin=np.array([0.05, -0.1, 0.6]),
                    voxel_size=0.2 / size, size=size)
    occupancy = np.random.default_rng(size).random((5, size, size, size)) < 0.1
    occupancy[2] = False  # an empty sample keeps its place in the list
    stacked = pose.occupied_centres_per_grid(occupancy)
    assert len(stacked) == 5 and stacked[2].shape == (0, 3)
    for grid, centres in zip(occupancy, stacked, strict=True):
        assert centres.dtype == np.float32
        np.testing.assert_allclose(centres, pose.occupied_centres(grid), atol=1e-6)


def test_observe_known_occupied_and_free():
    depth, mask = wall_scene()
    config = GridConfig(size=32, voxel_size=0.005)
    obs = observe(depth, mask, K, UP, config)
    assert obs.known_occupied.shape == obs.known_free.shape == (32, 32, 32)
    assert not np.any(obs.known_occupied & obs.known_free)
    # Every observed point falls in a known-occupied voxel.
    ijk, inside = obs.pose.voxel_indices(obs.points)
    assert inside.all()
    assert obs.known_occupied[tuple(ijk.T)].all()
    # The object's front face is one voxel behind the grid's front: layer 0 is seen through, so free,
    # and nothing behind the observed surface (x >= 2) is free where the object covers the view.
    assert obs.known_free[0].sum() > 0
    occupied_columns = obs.known_occupied.any(axis=0)
    assert not obs.known_free[2:][:, occupied_columns].any()
    x = obs.network_input()
    assert x.shape == (2, 32, 32, 32) and x.dtype == np.float32


def test_unknown_pixels_carve_nothing():
    depth, mask = wall_scene()
    config = GridConfig(size=32, voxel_size=0.005)
    full = observe(depth, mask, K, UP, config)
    occluded = depth.copy()
    occluded[:, :70] = 0.0  # a slit: everything left of the object has no reading
    partial = observe(occluded, mask, K, UP, config)
    assert partial.known_free.sum() < full.known_free.sum()
    # Free space can only shrink when readings are removed.
    assert not np.any(partial.known_free & ~full.known_free)


@pytest.mark.parametrize("column", [70, 140])  # 140: the object at the image's right edge, the grid beyond it
def test_free_space_is_the_windowed_minimum_over_the_whole_image(column):
    """carve_free_space erodes only the part of the image the grid projects to: the same voxels as the
    definition on the whole image (scipy's minimum filter, replicated border)."""
    from scipy import ndimage

    from pssnet_core.geometry import carve_free_space, valid_depth

    depth = np.full((K.height, K.width), 0.6, dtype=np.float32)
    mask = np.zeros(depth.shape, dtype=np.uint8)
    mask[50:70, column:column + 20] = 1
    depth[mask == 1] = 0.55
    depth[::13, ::17] = 0.0  # holes: missing readings count as distance 0
    pose = place_grid(masked_points(depth, mask, K), UP, GridConfig(size=16, voxel_size=0.01))
    usable = valid_depth(depth)
    free = carve_free_space(depth, usable, K, pose)

    centres = pose.occupied_centres(np.ones((pose.size,) * 3, bool))
    z = centres[:, 2]
    half_diagonal = 0.5 * np.sqrt(3.0) * pose.voxel_size
    radius = min(int(np.ceil(K.fx * half_diagonal / max(z.min(), 1e-3))), 8)
    nearest = ndimage.minimum_filter(np.where(usable, depth, 0.0), size=2 * radius + 1, mode="nearest")
    u = np.rint(K.fx * centres[:, 0] / z + K.cx).astype(int)
    v = np.rint(K.fy * centres[:, 1] / z + K.cy).astype(int)
    inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    assert inside.all() if column == 70 else 0 < inside.sum() < len(z)
    expected = np.zeros(len(z), dtype=bool)
    expected[inside] = z[inside] + half_diagonal < nearest[v[inside], u[inside]]
    assert expected.sum() > 100
    np.testing.assert_array_equal(free.reshape(-1), expected)


@pytest.mark.parametrize("size", [32, 64])
def test_grid_sizes(size):
    depth, mask = wall_scene()
    obs = observe(depth, mask, K, UP, GridConfig.for_size(size))
    assert obs.known_occupied.shape == (size,) * 3
    assert obs.pose.voxel_size == pytest.approx(0.20 / size)


def test_bad_grid_config():
    with pytest.raises(ObservationError, match="grid size"):
        GridConfig(size=2)
    with pytest.raises(ObservationError, match="voxel_size"):
        GridConfig(voxel_size=0.0)
