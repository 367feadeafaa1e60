"""Surfaces for figures: voxel centres back on their lattice, marching cubes, agreement between samples."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest

from pssnet_core.surfaces import lattice_occupancy, most_different, sample_agreement, surface_of

VOXEL = 0.01


def block(lo: tuple[int, int, int], hi: tuple[int, int, int], offset: float = 0.003) -> np.ndarray:
    """Centres of the voxels lo..hi-1 (inclusive ranges per axis) on a lattice shifted by ``offset``."""
    axes = [np.arange(a, b) for a, b in zip(lo, hi, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) * VOXEL + offset


def test_lattice_round_trip_and_padding():
    points = block((0, 0, 0), (2, 3, 4))
    grid = lattice_occupancy(points, VOXEL, points.min(axis=0))
    assert grid.shape == (4, 5, 6) and grid.sum() == 24
    assert not grid[0].any() and not grid[-1].any()  # one empty layer on every side
    with pytest.raises(ValueError, match="voxel_size"):
        lattice_occupancy(points, 0.0, points.min(axis=0))
    with pytest.raises(ValueError, match="below the lattice origin"):
        lattice_occupancy(points, VOXEL, points.min(axis=0) + VOXEL)


def test_surface_of_a_box_encloses_its_voxels():
    points = block((0, 0, 0), (3, 3, 3))
    mesh = surface_of(points, VOXEL, points.min(axis=0))
    assert not mesh.empty
    # Marching cubes at 0.5 puts the surface halfway between occupied and empty centres: the voxel faces.
    assert mesh.vertices.min(axis=0) == pytest.approx(points.min(axis=0) - VOXEL / 2)
    assert mesh.vertices.max(axis=0) == pytest.approx(points.max(axis=0) + VOXEL / 2)
    assert surface_of(np.zeros((0, 3)), VOXEL, np.zeros(3)).empty


def test_agreement_is_one_on_the_shared_body_and_a_half_on_one_samples_handle():
    body = block((0, 0, 0), (4, 4, 4))
    handle = block((4, 1, 1), (6, 3, 3))
    union, agreement = sample_agreement([body, np.concatenate([body, handle])], VOXEL, body.min(axis=0))
    centroids = union.vertices[union.faces].mean(axis=1)
    on_handle = centroids[:, 0] > body[:, 0].max() + VOXEL  # faces beyond the body's +x face
    assert on_handle.any() and (~on_handle).any()
    assert np.all(agreement[on_handle] == 0.5)
    assert np.mean(agreement[~on_handle] == 1.0) > 0.9  # the body (only faces at the handle's root differ)


def test_most_different_picks_the_odd_sample_first():
    body = block((0, 0, 0), (4, 4, 4))
    odd = np.concatenate([body, block((4, 0, 0), (8, 4, 4))])
    samples = [body, body.copy(), odd, body.copy()]
    assert most_different(samples, 2, VOXEL, body.min(axis=0)) == [0, 2]
    assert sorted(most_different(samples, 9, VOXEL, body.min(axis=0))) == [0, 1, 2, 3]


def test_draw_surface_with_per_face_colours():
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.surfaces import draw_surface, equal_box

    points = block((0, 0, 0), (2, 2, 2))
    mesh = surface_of(points, VOXEL, points.min(axis=0))
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    draw_surface(ax, mesh, np.tile([0.2, 0.4, 0.6], (len(mesh.faces), 1)))
    draw_surface(ax, mesh, "darkred", alpha=0.5)
    equal_box(ax, mesh.vertices)
    assert len(ax.collections) == 2
    plt.close(fig)
