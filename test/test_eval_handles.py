"""Handle azimuth and spread of sampled mugs (pssnet_core.evaluation.handles), on hand-built grids."""

from __future__ import annotations

import argparse
import csv
import math

import numpy as np
import pytest

from pssnet_core.data.build import build
from pssnet_core.data.scenes import ground_truth_occupancy
from pssnet_core.evaluation.experiment import write_report
from pssnet_core.evaluation.handles import (
    HandleGeometry,
    HandleMeasureError,
    HandlesConfig,
    circular_spread_deg,
    handle_azimuths,
    run_handles,
)
from pssnet_core.evaluation.handles_report import handles_report
from pssnet_core.geometry import GridPose
from pssnet_core.shapes import make_shape

ROUND_MUG = 2000002  # test-split seed: straight body, ring handle
VOXEL = 0.2 / 32


def yaw(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    return pose


@pytest.fixture(scope="module")
def mug():
    shape = make_shape("mug", ROUND_MUG)
    # The mug frame is the "camera" frame here; the grid is centred on the mug's axis.
    grid = GridPose(rotation=np.eye(3), origin=np.array([-0.1, -0.1, -0.02]), voxel_size=VOXEL, size=32)
    grids = {angle: ground_truth_occupancy(shape, yaw(angle), grid, np.eye(4)) for angle in (0, 90, -120)}
    return shape, grid, grids


def test_true_and_turned_handles_are_found_where_they_are(mug):
    shape, grid, grids = mug
    geometry = HandleGeometry.of(shape)
    assert geometry.body_radius < geometry.reach
    az = handle_azimuths(np.stack([grids[0], grids[90], grids[-120]]), grid, np.eye(4), geometry)
    # Voxel quantisation moves the mean azimuth by a few degrees at most.
    np.testing.assert_allclose(az, [0, 90, -120], atol=6)


def test_a_mug_without_its_handle_has_none(mug):
    shape, grid, grids = mug
    body = grids[0].copy()
    centres = grid.occupied_centres(np.ones((grid.size,) * 3, bool)).reshape(32, 32, 32, 3)
    body[np.hypot(centres[..., 0], centres[..., 1]) > HandleGeometry.of(shape).body_radius + 0.5 * VOXEL] = False
    az = handle_azimuths(np.stack([body, np.zeros_like(body)]), grid, np.eye(4), HandleGeometry.of(shape))
    assert np.isnan(az).all()


def test_circular_spread():
    assert circular_spread_deg(np.array([10.0, 10.0, 10.0])) == pytest.approx(0.0, abs=1e-3)
    assert circular_spread_deg(np.array([179.0, -179.0])) == pytest.approx(1.0, abs=0.05)  # wraps around
    assert circular_spread_deg(np.array([-90.0, 90.0, np.nan])) > 300  # opposite: no agreement at all
    assert math.isnan(circular_spread_deg(np.array([5.0, np.nan])))


def test_unmeasurable_mugs_are_refused():
    with pytest.raises(HandleMeasureError, match="round mugs"):
        HandleGeometry.of(make_shape("mug", 2000000))  # square body, no handle


class TurningCompleter:
    """Fake completer: the view's true mug, turned about its axis by a different angle per sample."""

    grid_size = 32

    def __init__(self, truth_by_input, turns):
        self.truth_by_input, self.turns = truth_by_input, turns

    def complete(self, observation, num_samples=20, seed=0):
        return argparse.Namespace(occupancy=np.stack([self.truth_by_input(observation, t)
                                                      for t in self.turns[:num_samples]]))


def test_handles_command_separates_agreeing_from_spread_out_samples(tmp_path):
    from pssnet_core.data.store import DatasetReader
    from pssnet_core.evaluation.testsets import load_test_set

    root = tmp_path / "data"
    build("mugs", "test", root, grid_size=32, num_objects=3, views=4, progress=False)
    views, _ = load_test_set(root / "test" / "mugs")
    reader = DatasetReader(root / "test" / "mugs")
    shapes = {v.identity: make_shape("mug", int(v.identity.split("-")[1])) for v in views}

    def turned(observation, turn):
        observation = observation.network_input()  # what the real Completer reads of an observation
        view = next(v for v in views if np.array_equal(v.known_occupied, observation[0] > 0.5)
                    and np.array_equal(v.known_free, observation[1] > 0.5))
        if turn == 0:
            return reader.get(view.index, images=False)["occupancy"]
        pose = view.object_pose @ yaw(turn)
        return ground_truth_occupancy(shapes[view.identity], pose, view.grid_pose, np.eye(4))

    config = HandlesConfig(data=str(root), samples=4, out=str(tmp_path / "out"), progress=False)
    result = run_handles(config, {"agree": TurningCompleter(turned, [0, 0, 0, 0]),
                                  "spread": TurningCompleter(turned, [0, 90, 180, -90])})
    files = write_report(handles_report(result), config.out)
    rows = list(csv.DictReader(open(files["summary_csv"])))
    got = {r["method"]: r for r in rows}
    assert float(got["agree"]["handle_rate"]) == 1.0 and float(got["agree"]["spread_deg"]) < 5
    assert float(got["agree"]["error_deg"]) < 6 and float(got["agree"]["pairwise_mm"]) == 0.0
    assert float(got["spread"]["spread_deg"]) > 100 and float(got["spread"]["pairwise_mm"]) > 1.0
    assert "| spread |" in files["markdown"].read_text()
    figures = [files[k] for k in ("figure_hidden", "figure_visible") if k in files]
    assert figures and all(f.stat().st_size > 0 for f in figures)
