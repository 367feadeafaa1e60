"""Plausible-diversity metrics (paper, Sec. 5): best accuracy, coverage, plausibility, plausible diversity.

Distance: the chamfer distance between the voxel-centre point clouds of two occupancy grids,
``d(A, B) = mean_a min_b |a - b| + mean_b min_a |a - b|`` (unsquared, summed both ways, as in the authors'
``chamfer_distance_pointcloud``), reported in millimetres.

How it is computed: every cloud here is a set of voxel centres of the *same* grid (the reference
observation's), so the nearest-neighbour distance from any voxel to cloud B is B's Euclidean distance
transform (``scipy.ndimage.distance_transform_edt``, exact). One transform per grid (over the box that holds it
and the other side's voxels, see :func:`chamfer_matrix`) then turns every pair into two masked sums: for 100
samples against a plausible set of 100 shapes at 32^3 that is ~0.3 s instead of ~90 s of KD-tree queries. It
needs only numpy/scipy (no open3d), so it also runs on the training machine. The tests check it against a
KD-tree over the voxel centres.

Empty clouds: the distance between an empty and a non-empty cloud is undefined; we use ``empty_distance``
(default: the grid's diagonal, the largest distance two of its points can have) so that a model that outputs
empty grids is penalised rather than silently skipped; two empty clouds are at distance 0.

Metrics for one observation, samples S (n of them), plausible set P (its first member the ground truth):

- best accuracy    M_A  = min_s d(s, ground truth)
- coverage         M_C  = mean_{p in P} min_s d(s, p)   (every plausible shape should be near some sample)
- plausibility     M_P  = mean_s min_{p in P} d(s, p)   (every sample should be near some plausible shape)
- plausible div.   M_PD = M_C + M_P
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage


class MetricsError(ValueError):
    """Bad input to a metric (shapes, empty sets)."""


def _as_grids(grids: np.ndarray, name: str) -> np.ndarray:
    grids = np.asarray(grids)
    if grids.ndim == 3:
        grids = grids[None]
    if grids.ndim != 4:
        raise MetricsError(f"{name} must be (K, N, N, N) or (N, N, N) occupancy, got shape {grids.shape}")
    return grids.astype(bool, copy=False)


def distance_fields(grids: np.ndarray) -> np.ndarray:
    """Distance (voxel units) from every voxel centre to the nearest occupied voxel centre, per grid.

    Empty grids get +inf everywhere.
    """
    grids = _as_grids(grids, "grids")
    out = np.empty(grids.shape, dtype=np.float32)
    for k, grid in enumerate(grids):
        out[k] = ndimage.distance_transform_edt(~grid) if grid.any() else np.inf
    return out


def _bounding_box(grid: np.ndarray) -> tuple[slice, ...]:
    """Slices of the smallest box holding every occupied voxel of a non-empty (N, N, N) grid."""
    box = []
    for axis in range(3):
        occupied = np.flatnonzero(grid.any(axis=tuple(a for a in range(3) if a != axis)))
        box.append(slice(int(occupied[0]), int(occupied[-1]) + 1))
    return tuple(box)


def _field_sums(owners: np.ndarray, fields: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """(O, P) sums, over the occupied voxels of ``points[p]``, of the distance to the nearest voxel of ``owners[o]``
    (voxel units; 0 where an owner is empty).

    With ``fields`` (the owners' :func:`distance_fields`) one matrix product. Without, each owner's distance
    transform is taken only over the box around its own voxels and every voxel of ``points``: every voxel it can
    be nearest to lies inside, so the distances there are the whole grid's, exactly; the box of a completion and
    its plausible shapes is about a quarter of the 32^3 grid, which makes this ~3x faster than whole fields.
    Owners that are the same grid are transformed once.
    """
    if fields is not None:
        # float64 accumulation: sums of up to N^3 distances.
        flat = np.where(np.isfinite(fields), fields, 0).reshape(len(owners), -1)
        return flat.astype(np.float64) @ points.reshape(len(points), -1).T.astype(np.float64)
    union = points.any(axis=0)
    # Identical owners share one transform (a deterministic model's samples are all one grid).
    # (By bytes in a dict: np.unique(axis=0) takes ~40 ms for 100 grids of 32^3, this ~0.3.)
    ids: dict[bytes, int] = {}
    inverse = np.array([ids.setdefault(row.tobytes(), len(ids))
                        for row in np.packbits(owners.reshape(len(owners), -1), axis=1)], dtype=np.intp)
    distinct = np.unique(inverse, return_index=True)[1]  # the first owner of each distinct grid
    sums = np.zeros((len(distinct), len(points)))
    for o, owner in enumerate(owners[distinct]):
        if not owner.any():
            continue
        box = _bounding_box(owner | union)
        # float32 as distance_fields stores them, so both ways give the same distances.
        field = ndimage.distance_transform_edt(~owner[box]).astype(np.float32)
        sums[o] = points[(slice(None), *box)].reshape(len(points), -1).astype(np.float64) @ field.ravel()
    return sums[inverse]


def chamfer_matrix(a: np.ndarray, b: np.ndarray, voxel_size: float, empty_distance: float | None = None,
                   fields_a: np.ndarray | None = None, fields_b: np.ndarray | None = None) -> np.ndarray:
    """Chamfer distances between every grid of ``a`` and every grid of ``b`` (voxel-centre clouds), metres.

    Args:
        a: (A, N, N, N) bool occupancy grids.
        b: (B, N, N, N) bool occupancy grids of the same grid.
        voxel_size: voxel edge in metres.
        empty_distance: distance (metres) when exactly one cloud is empty; default the grid diagonal.
        fields_a, fields_b: precomputed :func:`distance_fields` (worth it for grids compared against many calls'
            grids); without them each grid's distances are computed only where the other side's voxels lie.

    Returns:
        (A, B) float64 metres.
    """
    a = _as_grids(a, "a")
    b = _as_grids(b, "b")
    if a.shape[1:] != b.shape[1:]:
        raise MetricsError(f"grids differ in shape: {a.shape[1:]} vs {b.shape[1:]}")
    if not voxel_size > 0:
        raise MetricsError(f"voxel_size must be positive, got {voxel_size}")
    if empty_distance is None:
        empty_distance = math.sqrt(3.0) * a.shape[1] * voxel_size
    na = a.reshape(len(a), -1).sum(1).astype(np.float64)
    nb = b.reshape(len(b), -1).sum(1).astype(np.float64)
    sum_ab = _field_sums(b, fields_b, a).T  # over a's points of the distance to b
    sum_ba = _field_sums(a, fields_a, b)  # over b's points of the distance to a
    with np.errstate(invalid="ignore", divide="ignore"):
        d = (sum_ab / na[:, None] + sum_ba / nb[None, :]) * voxel_size
    empty_a = na == 0
    empty_b = nb == 0
    d[empty_a[:, None] ^ empty_b[None, :]] = empty_distance
    d[empty_a[:, None] & empty_b[None, :]] = 0.0
    return d


@dataclass(frozen=True)
class ObservationMetrics:
    """Metrics of one observation, millimetres.

    Attributes:
        best_accuracy_mm: M_A.
        coverage_mm: M_C.
        plausibility_mm: M_P.
        plausible_diversity_mm: M_PD = M_C + M_P.
        num_samples: samples evaluated.
        num_plausible: size of the plausible set.
    """

    best_accuracy_mm: float
    coverage_mm: float
    plausibility_mm: float
    plausible_diversity_mm: float
    num_samples: int
    num_plausible: int

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def metrics_from_distances(sample_to_plausible: np.ndarray, sample_to_truth: np.ndarray) -> ObservationMetrics:
    """Metrics from precomputed distances (metres).

    Args:
        sample_to_plausible: (S, P) d(sample s, plausible shape p).
        sample_to_truth: (S,) d(sample s, ground truth).
    """
    dsp = np.asarray(sample_to_plausible, dtype=np.float64)
    dst = np.asarray(sample_to_truth, dtype=np.float64).reshape(-1)
    if dsp.ndim != 2 or dsp.shape[0] == 0 or dsp.shape[1] == 0:
        raise MetricsError(f"need at least one sample and one plausible shape, got distances of shape {dsp.shape}")
    if dst.shape[0] != dsp.shape[0]:
        raise MetricsError(f"{dst.shape[0]} ground-truth distances for {dsp.shape[0]} samples")
    best = dst.min() * 1000.0
    coverage = dsp.min(axis=0).mean() * 1000.0
    plausibility = dsp.min(axis=1).mean() * 1000.0
    return ObservationMetrics(best_accuracy_mm=float(best), coverage_mm=float(coverage),
                              plausibility_mm=float(plausibility),
                              plausible_diversity_mm=float(coverage + plausibility),
                              num_samples=int(dsp.shape[0]), num_plausible=int(dsp.shape[1]))


METRIC_NAMES: tuple[str, ...] = ("best_accuracy_mm", "coverage_mm", "plausibility_mm", "plausible_diversity_mm")
