"""Ambiguity measured directly (pssnet_core.evaluation.ambiguity): plausible handle arcs and slit box depths.

The scores are checked on numbers worked out by hand; the plausible sets on tiny test sets built by the data
module, where what the view allows is known (the true shape always passes, a handle facing the camera never
does); the whole command on fake completers whose samples are the true mug turned by chosen angles.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from pssnet_core.data.build import build
from pssnet_core.data.scenes import ObjectScene, ground_truth_occupancy
from pssnet_core.data.store import DatasetReader
from pssnet_core.evaluation.ambiguity import (
    AmbiguityConfig,
    arc_composition,
    arc_scores,
    extent_scores,
    run_ambiguity,
)
from pssnet_core.evaluation.ambiguity_report import ambiguity_report
from pssnet_core.evaluation.ambiguity_sets import (
    REJECTED,
    AmbiguityError,
    AmbiguityMeasure,
    HandleArc,
    grid_x_extent,
    hidden_axis,
    mug_parts,
    plausible_handle_arc,
    plausible_slit_range,
    stretched,
)
from pssnet_core.evaluation.experiment import write_report
from pssnet_core.evaluation.handles import (
    HandleGeometry,
    circular_difference_deg,
    circular_spread_deg,
    handle_azimuths,
    turned,
)
from pssnet_core.evaluation.testsets import load_test_set
from pssnet_core.geometry import GridPose
from pssnet_core.shapes import ShapeId, make_shape

ROUND_MUG = "mug-2000002"  # third test mug: round body, ring handle


# ------------------------------------------------------------------------------------ scores by hand


def test_arc_scores_by_hand():
    arc = np.arange(-20.0, 21.0, 5.0)  # 9 azimuths
    s = arc_scores(arc, np.array([0.0, 0.0, np.nan, 90.0]), tolerance_deg=15.0, margin_deg=10.0)
    assert s.rate == pytest.approx(0.75)
    assert s.coverage == pytest.approx(7 / 9)  # -15..15 lie within 15 deg of the handles at 0
    assert s.precision == pytest.approx(2 / 3)  # 90 deg is 70 deg from the arc's end
    assert s.spread_ratio == pytest.approx(circular_spread_deg(np.array([0.0, 0.0, 90.0])) / circular_spread_deg(arc))


def test_arc_scores_wrap_around_and_degenerate_cases():
    arc = np.array([170.0, 175.0, -180.0, -175.0])
    s = arc_scores(arc, np.array([179.0, -178.0]))
    assert s.coverage == 1.0 and s.precision == 1.0
    none = arc_scores(arc, np.array([np.nan, np.nan]))
    assert none.coverage == 0.0 and math.isnan(none.precision) and none.rate == 0.0
    assert math.isnan(arc_scores(np.array([0.0]), np.array([0.0, 10.0])).spread_ratio)  # one azimuth: no spread
    with pytest.raises(AmbiguityError, match="empty"):
        arc_scores(np.array([]), np.array([0.0]))


def test_arc_composition_counts_handles_facing_the_camera_and_bounds_a_strict_sampler():
    azimuths = np.arange(-180.0, 180.0, 5.0)
    strict = np.abs(azimuths) <= 30  # behind the mug: -30..30 (13 azimuths)
    wide = strict | (np.abs(azimuths) >= 170)  # and the handle facing the camera (at 180): 5 azimuths more
    violations = np.stack([np.where(strict, 0, 5), np.where(wide, 0, REJECTED)], axis=1)
    arc = HandleArc(index=0, identity="mug", deltas=(0.01, 0.04), azimuths_deg=azimuths, violations=violations,
                    camera_azimuth_deg=180.0)
    mix = arc_composition([arc, arc], 0.04, 0.01)
    assert mix.views == 2 and mix.facing_deg == 45.0
    assert mix.facing_share == pytest.approx(5 / 18)  # 170..-170 lie within 45 deg of facing the camera
    assert mix.strict_cover == pytest.approx(13 / 18)  # 15 deg of tolerance reach none of the facing azimuths
    itself = arc_composition([arc], 0.01, 0.01)
    assert itself.strict_cover == 1.0 and itself.facing_share == 0.0


def test_extent_scores_by_hand():
    allowed = np.array([5.0, 6.0, 7.0, 8.0, 9.0, 9.0])  # repeats count once
    samples = np.array([5.0, 5.0, 9.0, np.nan, 12.0])
    s = extent_scores(allowed, samples, tolerance=1.0, margin=1.0)
    assert s.rate == pytest.approx(0.8)
    assert s.coverage == pytest.approx(4 / 5)  # 7 is 2 voxels from every sample
    assert s.precision == pytest.approx(3 / 4)  # 12 is 3 voxels beyond the range
    assert s.spread_ratio == pytest.approx(np.std([5, 5, 9, 12]) / np.std([5, 6, 7, 8, 9]))


def test_grid_x_extent_ignores_stray_voxels():
    grid = np.zeros((2, 16, 16, 16), dtype=bool)
    grid[0, 3:8, 4:9, 2:6] = True
    grid[0, 14, 14, 14] = True  # a stray voxel far behind
    np.testing.assert_array_equal(grid_x_extent(grid)[:1], [5.0])
    assert math.isnan(grid_x_extent(grid)[1])


def test_hidden_axis_and_stretching_keep_the_near_face():
    bounds = np.array([[-0.05, -0.02, 0.0], [0.05, 0.02, 0.1]])
    pose = np.eye(4)
    pose[:3, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]  # object y -> camera x, object x -> camera y
    grid_rotation = np.array([[0, 0, 1], [1, 0, 0], [0, -1, 0]], dtype=float)  # grid x = camera y (toy)
    axis, front = hidden_axis(pose, grid_rotation, bounds)
    assert axis == 0 and front == -0.05  # object +x points along grid x (away): its -x face is in front
    corners = np.array([[-0.05, 0, 0], [0.05, 0, 0]])
    np.testing.assert_allclose(stretched(corners, axis, front, 2.0)[:, 0], [-0.05, 0.15])


# ------------------------------------------------------------------------------- plausible sets


@pytest.fixture(scope="module")
def tiny_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("ambiguity_data")
    build("mugs", "test", root, grid_size=32, num_objects=3, views=4, progress=False)
    build("ycb", "test", root, grid_size=32, num_objects=1, views=3, progress=False)
    return root


@pytest.fixture(scope="module")
def hidden_view(tiny_sets):
    views, _ = load_test_set(tiny_sets / "test" / "mugs")
    view = next(v for v in views if v.identity == ROUND_MUG and v.meta["rotation_deg"] == 0.0)
    assert view.meta["handle_visible"] is False
    return view


def test_plausible_arc_holds_the_truth_and_not_a_handle_facing_the_camera(hidden_view):
    parts = mug_parts(make_shape("mug", ShapeId.parse(ROUND_MUG).seed))
    arc = plausible_handle_arc(hidden_view, hidden_view.depth_view, parts, AmbiguityMeasure())
    for delta in (0.01, 0.04):
        assert arc.truth_accepted(delta)
    allowed = arc.arc(0.01)
    assert len(allowed) >= 3  # a hidden handle can lie elsewhere behind the body
    # Contiguous around the truth (the body does not move when the handle turns: no one-pixel facet misses).
    assert np.all(np.isin(np.arange(-10.0, 11.0, 5.0), allowed))
    # Turned towards the camera (its azimuth in the mug's frame) or sideways, the handle would be seen.
    assert abs(abs(arc.camera_azimuth_deg) - 180.0) < 10.0
    for az in (arc.camera_azimuth_deg, 90.0, -90.0):
        assert circular_difference_deg(allowed, az).min() > 20.0
    # The handle turned to its own azimuth renders the true mug exactly.
    vertices, faces = parts.turned(0.0)
    assert len(faces) == len(parts.body_faces) + len(parts.handle_faces)


def test_slit_range_holds_the_true_box(tiny_sets):
    root = tiny_sets / "test" / "ycb_narrow"
    views, _ = load_test_set(root)
    reader = DatasetReader(root)
    view = views[0]
    assert view.identity.startswith("box-")
    mesh = make_shape("box", ShapeId.parse(view.identity).seed).mesh
    plausible = plausible_slit_range(view, view.depth_view, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    truth_extent = grid_x_extent(reader.get(view.index, images=False)["occupancy"])[0]
    assert plausible.true_extent_voxels == truth_extent  # the one occupancy definition, same grid
    for delta in (0.01, 0.04):
        assert plausible.truth_accepted(delta)
        assert truth_extent in plausible.extents(delta)
    # Candidates run from almost nothing to the grid's far face, in half-voxel steps through the true length.
    step = np.diff(plausible.lengths_m)
    np.testing.assert_allclose(step, 0.5 * view.grid_pose.voxel_size, rtol=1e-9)
    assert plausible.lengths_m[0] <= step[0] and np.isclose(plausible.lengths_m, plausible.true_length_m).any()


# ----------------------------------------------------------------------------------- the command


class TurningCompleter:
    """Fake completer: the view's true mug turned by given angles (or its stored truth for other objects)."""

    grid_size = 32
    has_box_latent = False

    def __init__(self, root, turns_for):
        self.views = {}
        for name in ("mugs", "ycb_narrow"):
            reader = DatasetReader(root / "test" / name)
            for k in range(len(reader)):
                sample = reader.get(k, images=False)
                key = sample["known_occupied"].tobytes() + sample["known_free"].tobytes()
                self.views[key] = sample
        self.turns_for = turns_for
        self.calls: list[float] = []
        self.scenes: dict[int, ObjectScene] = {}

    def complete(self, observation, num_samples=20, seed=0):
        x = observation.network_input() > 0.5
        sample = self.views[x[0].tobytes() + x[1].tobytes()]
        turns = self.turns_for(sample)
        if turns is None:  # not a mug: the truth every time
            return argparse.Namespace(occupancy=np.stack([sample["occupancy"]] * num_samples))
        seed = int(sample["seed"])
        if seed not in self.scenes:  # one scene per mug: its surface samples are made once
            self.scenes[seed] = ObjectScene(make_shape("mug", seed))
        pose = np.linalg.inv(np.asarray(sample["camera_pose"])) @ np.asarray(sample["object_pose"])
        grid = GridPose.from_dict(sample["grid_pose"])
        grids = [self.scenes[seed].ground_truth(turned(pose, turns[k % len(turns)]), grid, np.eye(4))
                 for k in range(num_samples)]
        return argparse.Namespace(occupancy=np.stack(grids))


class BoxCompleter(TurningCompleter):
    """Accepts a box temperature (as PSSNet does) and records it."""

    has_box_latent = True

    def complete(self, observation, num_samples=20, seed=0, box_temperature=1.0):
        self.calls.append(box_temperature)
        return super().complete(observation, num_samples, seed)


def test_command_scores_spread_and_agreeing_samples(tiny_sets, hidden_view, tmp_path):
    parts = mug_parts(make_shape("mug", ShapeId.parse(ROUND_MUG).seed))
    arc = plausible_handle_arc(hidden_view, hidden_view.depth_view, parts).arc(0.01)
    picks = [float(a) for a in arc[::3]] + [float(arc[-1])]  # every arc azimuth within 10 deg of a pick

    def spread(sample):
        if sample["family"] != "mug":
            return None
        return picks if sample["identity"] == ROUND_MUG and not sample["handle_visible"] else [0.0]

    completers = {"agree": TurningCompleter(tiny_sets, lambda s: None if s["family"] != "mug" else [0.0]),
                  "spread": BoxCompleter(tiny_sets, spread)}
    config = AmbiguityConfig(data=str(tiny_sets), out=str(tmp_path / "out"), samples=len(picks),
                             box_temperatures=(1.0, 2.0), max_views=2, progress=False)
    files = write_report(ambiguity_report(run_ambiguity(config, completers)), config.out)
    result = json.loads(files["json"].read_text())
    summary = {(e["method"], e["box_temperature"], e["delta_m"]): e for e in result["summary"]}
    assert set(summary) == {("agree", 1.0, 0.01), ("agree", 1.0, 0.04), ("spread", 1.0, 0.01),
                            ("spread", 1.0, 0.04), ("spread", 2.0, 0.01), ("spread", 2.0, 0.04)}
    assert sorted(set(completers["spread"].calls)) == [1.0, 2.0]  # temperatures reach models with a box part
    rows = [r for r in result["rows"] if r["kind"] == "hidden_handle" and r["identity"] == ROUND_MUG
            and r["delta"] == 0.01]
    by_method = {r["method"]: r for r in rows if r["box_temperature"] == 1.0}
    # All samples at the truth: full precision, no spread, coverage = arc azimuths within 15 deg of 0.
    agree = by_method["agree"]
    assert agree["precision"] == 1.0 and agree["spread_ratio"] < 0.1 and agree["handle_rate"] == 1.0
    assert agree["coverage"] == pytest.approx(np.mean(np.abs(arc) <= 15.0), abs=1.5 / len(arc))
    # Samples spread over the arc: everything covered, everything inside, spread like the arc.
    s = by_method["spread"]
    assert s["coverage"] == 1.0 and s["precision"] == 1.0 and 0.75 < s["spread_ratio"] < 1.25
    # Visible handles reproduced: small error.
    visible = summary[("agree", 1.0, 0.01)]
    assert visible["visible_views"] > 0 and visible["handle_error_visible_deg"] < 8.0
    # Slit boxes completed with the truth: all inside the plausible range.
    assert summary[("agree", 1.0, 0.01)]["slit_views"] > 0 and summary[("agree", 1.0, 0.01)]["slit_precision"] == 1.0
    text = files["markdown"].read_text()
    assert "| spread | 2 |" in text and "delta = 4 cm" in text
    assert "fall-back" not in text  # no checked sampler here
    for key in ("handle_figure", "slit_figure", "summary_figure"):
        assert files[key].stat().st_size > 0
    # The plausible sets are cached: a second run with other models computes none.
    costs = run_ambiguity(config, {"agree": completers["agree"]}).costs
    assert costs["handle_arcs"]["computed_now"] == 0 and costs["slit_ranges"]["computed_now"] == 0
    assert costs["handle_arcs"]["cached"] == costs["handle_arcs"]["views"] > 0


def test_sampled_handle_azimuths_are_those_of_the_turned_mug(hidden_view):
    shape = make_shape("mug", ShapeId.parse(ROUND_MUG).seed)
    grids = np.stack([ground_truth_occupancy(shape, turned(hidden_view.object_pose, a), hidden_view.grid_pose,
                                             np.eye(4)) for a in (-40.0, 0.0, 35.0)])
    az = handle_azimuths(grids, hidden_view.grid_pose, hidden_view.object_pose, HandleGeometry.of(shape))
    np.testing.assert_allclose(az, [-40.0, 0.0, 35.0], atol=6.0)


def test_config_is_checked():
    with pytest.raises(AmbiguityError):
        AmbiguityMeasure(azimuth_step_deg=7.0)  # does not divide 360
    with pytest.raises(AmbiguityError):
        AmbiguityMeasure(deltas=(0.01, 0.01))
    assert len(AmbiguityMeasure().azimuths()) == 72 and 0.0 in AmbiguityMeasure().azimuths()


def test_cli_runs_a_real_checkpoint_at_each_box_temperature(tiny_sets, tmp_path, one_torch_thread):
    from test_models_helpers import tiny_model

    from pssnet_core.cli import main
    from pssnet_core.models.checkpoint import save_checkpoint

    checkpoint = save_checkpoint(tmp_path / "pssnet.pt", tiny_model("pssnet", grid=32))
    out = tmp_path / "out"
    code = main(["ambiguity", "--models", "pssnet", "--checkpoints", str(checkpoint), "--data", str(tiny_sets),
                 "--samples", "2", "--box-temperatures", "1,2", "--max-views", "1", "--samplers", "posterior,checked",
                 "--out", str(out), "--no-progress"])
    assert code == 0
    result = json.loads((out / "ambiguity.json").read_text())
    summary = result["summary"]
    assert {(e["method"], e["box_temperature"], e["delta_m"]) for e in summary} == {
        (m, t, d) for m in ("pssnet", "pssnet_checked") for t in (1.0, 2.0) for d in (0.01, 0.04)}
    # The checked sampler's accepted proposals are kept per view, and the share of views it fell back on.
    for entry in summary:
        rows = [r for r in result["rows"] if r["method"] == entry["method"] and r["kind"] == "visible_handle"
                and r["box_temperature"] == entry["box_temperature"]]
        assert rows
        if entry["method"] == "pssnet":
            assert all(r["accepted"] is None for r in rows) and entry["nothing_accepted_visible"] is None  # NaN
        else:
            assert all(isinstance(r["accepted"], int) and r["accepted"] >= 0 for r in rows)
            assert entry["nothing_accepted_visible"] == pytest.approx(np.mean([r["accepted"] == 0 for r in rows]))
    text = (out / "ambiguity.md").read_text()
    fallback = text[text.index("## The checked sampler's fall-back"):text.index("## Cost")]
    assert "- pssnet_checked (box T 1): hidden" in fallback and "- pssnet (" not in fallback
    assert main(["ambiguity", "--models", "pssnet", "--checkpoints", str(checkpoint), "--data", str(tmp_path),
                 "--out", str(out), "--no-progress"]) == 2  # no test sets there: an error message, not a crash
