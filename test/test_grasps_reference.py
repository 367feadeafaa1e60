"""Grasps are exactly those recorded before the grasp kernel was optimised (test/data/grasps_reference.npz).

The fixture holds its own inputs (mug completions from ``benchmarks/grasp_bench.py``, a subset of the observed
points, the grid pose and the support height), so nothing here renders and the expected values depend only on
the grasp code. Compared exactly: candidates (grid frame), widths, scores, holds, secondary terms and every
per-completion check of 500 scored candidates (benchmark-style ones plus some at random rotations, partly
outside the grid). Re-record only when the grasp rules change on purpose::

    .venv/bin/python test/test_grasps_reference.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pssnet_core.geometry import GridPose
from pssnet_core.grasps import GraspCandidates, GraspConfig, GraspSet, approach_orientations, check_grasps, plan_grasps
from pssnet_core.grasps.lattice import PackedGrids, box_or, voxel_box_rows

FIXTURE = Path(__file__).parent / "data" / "grasps_reference.npz"
# The kernel's rules as recorded; the observed-points check and the clearance from the voxels' centres came later
# (their own tests in test_grasps.py): on the shifted completions of plan70 the recorded points fall inside fingers
# that the voxels leave free, and the recorded widths are from the voxels' faces.
CONFIG = GraspConfig(observed_points_check=False, surface_at_voxel_centres=False)
CHECKS = ("fits", "above", "contains", "finger_hit", "palm_hit")


def _many(occ: np.ndarray, count: int) -> np.ndarray:
    """``count`` completions (> 64: several bit words) from the recorded ones, each shifted by a voxel or none."""
    return np.stack([np.roll(occ[i % len(occ)], i // len(occ) - 1, axis=i % 3) for i in range(count)])


def _inputs(data: dict) -> tuple[np.ndarray, GridPose, np.ndarray, float]:
    size = int(data["size"])
    count = int(data["completions"])
    occ = np.unpackbits(data["occupancy"], count=count * size**3).reshape(count, size, size, size).astype(bool)
    pose = GridPose(data["rotation"], data["origin"], float(data["voxel_size"]), size)
    return occ, pose, data["points"], float(data["support_z"])


def _plan_arrays(grasps: GraspSet) -> dict[str, np.ndarray]:
    return {"origins": grasps.grid.origins, "rotations": grasps.grid.rotations, "widths": grasps.grid.widths,
            "kinds": grasps.grid.kinds, "scores": grasps.scores, "secondary": grasps.secondary,
            "holds": grasps.holds}


def _candidates(data: dict) -> GraspCandidates:
    return GraspCandidates(data["cand_origins"], data["cand_rotations"], data["cand_widths"], data["cand_kinds"])


def _plans(occ: np.ndarray, pose: GridPose, points: np.ndarray, support_z: float) -> dict[str, GraspSet]:
    return {"plan": plan_grasps(occ, pose, points, CONFIG, support_z=support_z),
            "plan70": plan_grasps(_many(occ, 70), pose, points, CONFIG, support_z=support_z)}


@pytest.fixture(scope="module")
def reference() -> dict:
    with np.load(FIXTURE) as data:
        return dict(data)


def test_planned_grasps_are_the_recorded_ones(reference):
    occ, pose, points, support_z = _inputs(reference)
    for name, grasps in _plans(occ, pose, points, support_z).items():
        assert len(grasps) == len(reference[f"{name}_scores"]) > 0, name
        for key, value in _plan_arrays(grasps).items():
            np.testing.assert_array_equal(value, reference[f"{name}_{key}"], err_msg=f"{name} {key}")


def test_checks_of_every_candidate_against_every_completion_are_the_recorded_ones(reference):
    occ, pose, _, support_z = _inputs(reference)
    checks = check_grasps(_candidates(reference), occ, pose, support_z, CONFIG)
    for key in CHECKS:
        np.testing.assert_array_equal(getattr(checks, key), reference[f"check_{key}"], err_msg=key)
    np.testing.assert_array_equal(checks.coverage, reference["check_coverage"])
    assert reference["check_finger_hit"].any() and reference["check_coverage"].any() and checks.holds.any()


# The palm column of the default gripper at 6.25 mm voxels (some side orientations put lattice points exactly on
# voxel faces), and a one-point box 2^-25 voxel short of a face, where the float32 sums round onto the face.
@pytest.mark.parametrize("centre, half, counts", [
    (np.array([0.0, 0.0, -5.6]), np.array([1.6, 8.0, 5.6]), (5, 17, 13)),
    (np.array([0.5 - 2.0**-25, 0.0, 0.0]), np.zeros(3), (1, 1, 1)),
])
def test_voxel_centred_boxes_read_what_the_general_lattice_reads(centre, half, counts):
    rng = np.random.default_rng(0)
    n = 24
    grid = rng.random((n, n, n)) < 0.3
    rotations = np.concatenate([approach_orientations(CONFIG)[0], Rotation.random(8, random_state=1).as_matrix()])
    voxels = rng.integers(0, n, (3000, 3))
    orientation = rng.integers(0, len(rotations), len(voxels))
    expected = box_or(np.pad(grid, 1).reshape(1, -1), n + 2, voxels + 0.5, rotations[orientation], centre, half,
                      counts, keep=(2,))[0]
    np.testing.assert_array_equal(voxel_box_rows(grid, voxels, rotations, orientation, centre, half, counts),
                                  expected)
    assert 0.05 < expected.mean() < 0.95


@pytest.mark.parametrize("count", [1, 20, 70, 130])
def test_bit_words_pack_unpack_and_count(count):
    rng = np.random.default_rng(count)
    bits = PackedGrids(rng.random((count, 4, 4, 4)) < 0.3)
    flags = rng.random((6, 7, count)) < 0.4
    words = bits.pack(flags)
    assert words.shape == (len(bits.data), 6, 7) and words.dtype == bits.data.dtype
    np.testing.assert_array_equal(bits.unpack(words), flags)
    np.testing.assert_array_equal(bits.count(words), flags.sum(axis=0))


def record(path: Path = FIXTURE) -> None:
    """Write the fixture from the benchmark's 32^3 mugs with the grasp code importable now."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    from grasp_bench import completions, random_candidates

    occ, pose, points = completions(32, 20)
    points = points[::8]  # a subset keeps the file small; they only add anchors here
    support_z = float(np.floor(pose.camera_to_grid(points)[:, 2].min() * 4) / 4)  # a round height: no BLAS in it
    data = {"size": occ.shape[1], "completions": len(occ), "occupancy": np.packbits(occ),
            "rotation": pose.rotation, "origin": pose.origin, "voxel_size": pose.voxel_size, "points": points,
            "support_z": support_z}
    rng = np.random.default_rng(1)
    near = random_candidates(occ, 450, CONFIG, pose.voxel_size, seed=1)
    k = 50  # anywhere in and around the grid, at any rotation and width
    odd = GraspCandidates(rng.uniform(-8.0, 40.0, (k, 3)), Rotation.random(k, random_state=2).as_matrix(),
                          rng.uniform(0.0, 14.0, k), np.ones(k, np.int8))
    cands = GraspCandidates(*(np.concatenate([getattr(near, f), getattr(odd, f)])
                              for f in ("origins", "rotations", "widths", "kinds")))
    data.update({f"cand_{f}": getattr(cands, f) for f in ("origins", "rotations", "widths", "kinds")})
    checks = check_grasps(cands, occ, pose, support_z, CONFIG)
    data.update({f"check_{key}": getattr(checks, key) for key in (*CHECKS, "coverage")})
    for name, grasps in _plans(occ, pose, points, support_z).items():
        data.update({f"{name}_{key}": value for key, value in _plan_arrays(grasps).items()})
    path.parent.mkdir(exist_ok=True)
    np.savez_compressed(path, **data)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    record()
