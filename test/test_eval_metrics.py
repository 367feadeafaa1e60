"""Chamfer distance and the plausible-diversity metrics on sets whose answers are known by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pssnet_core.evaluation.metrics import (
    MetricsError,
    ObservationMetrics,
    chamfer_matrix,
    distance_fields,
    metrics_from_distances,
)

N = 8
VOXEL = 0.01  # 1 cm voxels: one voxel step = 10 mm


def grid(*cells) -> np.ndarray:
    g = np.zeros((N, N, N), dtype=bool)
    for c in cells:
        g[c] = True
    return g


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The reference: chamfer distance of two point clouds by KD-tree, mean NN a->b + mean NN b->a."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) == 0 or len(b) == 0:
        raise ValueError("chamfer distance of an empty point cloud is undefined")
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def observation_metrics(samples: np.ndarray, ground_truth: np.ndarray, plausible: np.ndarray) -> ObservationMetrics:
    """M_A, M_C, M_P, M_PD of one observation as the evaluation computes them: the ground truth is a member of
    the plausible set (added when no member equals it) and the last column of the distance matrix."""
    if not any(np.array_equal(p, ground_truth) for p in plausible):
        plausible = np.concatenate([ground_truth[None], plausible])
    d = chamfer_matrix(samples, np.concatenate([plausible, ground_truth[None]]), VOXEL)
    return metrics_from_distances(d[:, :-1], d[:, -1])


def test_chamfer_point_clouds_by_hand():
    a = np.array([[0.0, 0.0, 0.0]])
    b = np.array([[3.0, 4.0, 0.0]])
    assert chamfer_distance(a, b) == pytest.approx(10.0)  # 5 each way
    # a = {0, 1}, b = {0}: a->b mean (0 + 1) / 2, b->a 0.
    assert chamfer_distance(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[0.0, 0, 0]])) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        chamfer_distance(np.zeros((0, 3)), b)


def test_grid_chamfer_single_voxels():
    a = grid((0, 0, 0))
    b = grid((3, 4, 0))
    d = chamfer_matrix(a, b, VOXEL)
    assert d.shape == (1, 1)
    assert d[0, 0] == pytest.approx(2 * 5 * VOXEL)  # 5 voxels each way


def test_grid_chamfer_matches_kdtree_reference():
    rng = np.random.default_rng(0)
    a = rng.random((3, N, N, N)) < 0.05
    b = rng.random((4, N, N, N)) < 0.1
    d = chamfer_matrix(a, b, VOXEL)
    for s in range(3):
        for p in range(4):
            pa = (np.argwhere(a[s]) + 0.5) * VOXEL
            pb = (np.argwhere(b[p]) + 0.5) * VOXEL
            assert d[s, p] == pytest.approx(chamfer_distance(pa, pb), rel=1e-6)


def test_empty_clouds():
    full = grid((1, 1, 1))
    empty = grid()
    d = chamfer_matrix(np.stack([full, empty]), np.stack([full, empty]), VOXEL)
    diagonal = math.sqrt(3) * N * VOXEL
    assert d[0, 0] == 0 and d[1, 1] == 0
    assert d[0, 1] == pytest.approx(diagonal) and d[1, 0] == pytest.approx(diagonal)
    assert chamfer_matrix(full, empty, VOXEL, empty_distance=1.0)[0, 0] == 1.0


def test_metrics_by_hand():
    # Ground truth g at x=0; another plausible shape p at x=4 (4 cm away); samples at x=1 and x=2.
    g = grid((0, 0, 0))
    p = grid((4, 0, 0))
    s1 = grid((1, 0, 0))
    s2 = grid((2, 0, 0))
    m = observation_metrics(np.stack([s1, s2]), g, np.stack([g, p]))
    # d = 2 * |dx| voxels * 10 mm: d(s1,g)=20, d(s2,g)=40, d(s1,p)=60, d(s2,p)=40.
    assert m.best_accuracy_mm == pytest.approx(20.0)
    assert m.coverage_mm == pytest.approx((20.0 + 40.0) / 2)  # g: min(20, 40); p: min(60, 40)
    assert m.plausibility_mm == pytest.approx((20.0 + 40.0) / 2)  # s1: min(20, 60); s2: min(40, 40)
    assert m.plausible_diversity_mm == pytest.approx(60.0)
    assert (m.num_samples, m.num_plausible) == (2, 2)


def test_samples_collapsed_on_truth_miss_coverage():
    g = grid((0, 0, 0))
    p = grid((5, 0, 0))
    m = observation_metrics(np.stack([g, g, g]), g, np.stack([g, p]))
    assert m.best_accuracy_mm == 0.0
    assert m.plausibility_mm == 0.0
    assert m.coverage_mm == pytest.approx((0.0 + 100.0) / 2)


def test_ground_truth_added_when_missing_from_plausible():
    g = grid((0, 0, 0))
    p = grid((2, 0, 0))
    m = observation_metrics(np.stack([p]), g, np.stack([p]))
    assert m.num_plausible == 2
    assert m.coverage_mm == pytest.approx((40.0 + 0.0) / 2)


def test_metrics_from_distances():
    m1 = metrics_from_distances(np.array([[0.001, 0.003], [0.002, 0.001]]), np.array([0.001, 0.002]))
    assert m1.best_accuracy_mm == pytest.approx(1.0)
    assert m1.coverage_mm == pytest.approx(1.0)
    assert m1.plausibility_mm == pytest.approx(1.0)
    m2 = metrics_from_distances(np.array([[0.003]]), np.array([0.003]))
    assert (m1.plausible_diversity_mm, m2.plausible_diversity_mm) == pytest.approx((2.0, 6.0))
    with pytest.raises(MetricsError):
        metrics_from_distances(np.zeros((0, 1)), np.zeros(0))
    with pytest.raises(MetricsError):
        chamfer_matrix(np.zeros((2, 4, 4)), np.zeros((N, N, N)), VOXEL)


def test_grid_chamfer_over_boxes_equals_whole_fields_and_kdtree():
    """Compact shapes at different places (their boxes leave most of the grid out): the per-box distance transforms
    give the whole-grid fields' distances, and both the KD-tree reference."""
    rng = np.random.default_rng(1)
    n = 20
    a = np.zeros((4, n, n, n), bool)
    b = np.zeros((3, n, n, n), bool)
    for k, grids in enumerate((a, b)):
        for g in grids:
            lo = rng.integers(0, n - 6, 3)
            size = rng.integers(2, 6, 3)
            box = tuple(slice(int(start), int(start + extent)) for start, extent in zip(lo, size, strict=True))
            g[box] = rng.random(tuple(size)) < 0.6 + 0.2 * k
    a[0] = False  # an empty grid among the rest
    boxes = chamfer_matrix(a, b, VOXEL)
    whole = chamfer_matrix(a, b, VOXEL, fields_a=distance_fields(a), fields_b=distance_fields(b))
    np.testing.assert_allclose(boxes, whole, rtol=1e-12)
    for s in range(1, 4):
        for p in range(3):
            pa = (np.argwhere(a[s]) + 0.5) * VOXEL
            pb = (np.argwhere(b[p]) + 0.5) * VOXEL
            assert boxes[s, p] == pytest.approx(chamfer_distance(pa, pb), rel=1e-6)
    assert np.all(boxes[0] == math.sqrt(3) * n * VOXEL)


def test_identical_grids_share_one_distance_transform(monkeypatch):
    """Repeated grids (a deterministic model's samples) are transformed once, and each row is still its own."""
    from pssnet_core.evaluation import metrics

    rng = np.random.default_rng(2)
    n = 16
    distinct = np.zeros((3, n, n, n), bool)
    for k, g in enumerate(distinct):
        g[2 + k:9 + k, 3:10, 4:8 + k] = rng.random((7, 7, 4 + k)) < 0.7
    b = np.roll(distinct, 3, axis=1)
    order = [2, 0, 2, 1, 0, 2]
    calls = []
    real = metrics.ndimage.distance_transform_edt
    monkeypatch.setattr(metrics.ndimage, "distance_transform_edt", lambda x: calls.append(1) or real(x))
    repeated = chamfer_matrix(distinct[order], b, VOXEL)
    assert len(calls) == 3 + 3  # the three distinct grids of a, then the three of b
    np.testing.assert_array_equal(repeated, chamfer_matrix(distinct, b, VOXEL)[order])
