"""The out-of-family test sets (``--family oof``): specs, a tiny build, and the ambiguity measure and the paper's
evaluation on it with a stand-in completer that returns each view's stored truth.

Tiny sets keep the first objects of each list, which are the independent generator's, so nothing is downloaded.
"""

from __future__ import annotations

import argparse
import csv
import json

import numpy as np
import pytest

from pssnet_core.data.build import build
from pssnet_core.data.datasets import DatasetSpec, DatasetSpecError, dataset_specs
from pssnet_core.data.store import DatasetReader
from pssnet_core.evaluation.ambiguity import AmbiguityConfig, AmbiguityError, run_ambiguity
from pssnet_core.evaluation.ambiguity_report import ambiguity_report
from pssnet_core.evaluation.evaluate import EvaluateConfig, TestSetsConfig, run_evaluation
from pssnet_core.evaluation.experiment import write_report
from pssnet_core.evaluation.report import evaluation_report
from pssnet_core.evaluation.testsets import OOF_TEST_SETS, find_test_set
from pssnet_core.shapes import BOX_FAMILIES, MUG_FAMILIES, ShapeId
from pssnet_core.shapes.registry_objects import registry_identities


def test_oof_specs_list_independent_objects_first_then_the_real_ones():
    specs = {s.name: s for s in dataset_specs("oof", "test")}
    assert tuple(specs) == OOF_TEST_SETS
    mugs = [ShapeId.parse(i) for i in specs["oof_mugs"].identities]
    assert all(i.family in MUG_FAMILIES for i in mugs) and specs["oof_mugs"].is_mugs
    real = [str(i) for i in registry_identities()]
    assert [str(i) for i in mugs if i.family == "rmug"] == [r for r in real if r.startswith("rmug")]
    assert mugs[0] == ShapeId("imug", 2_000_000)
    narrow, wide = specs["oof_narrow"], specs["oof_wide"]
    assert narrow.identities == wide.identities and narrow.stream == wide.stream  # same objects, poses, cameras
    assert (narrow.slit_width_m, wide.slit_width_m) == (0.036, 0.18) and narrow.views == 24
    assert {ShapeId.parse(i).family for i in narrow.identities} >= {"ibox", "rbox", "rcan", "rbottle"}
    assert specs["oof_mugs"].tilt_range_deg == DatasetSpec.tilt_range_deg  # cameras as in training
    again = DatasetSpec.from_dict(json.loads(json.dumps(narrow.to_dict())))
    assert again == narrow
    small = {s.name: s for s in dataset_specs("oof", "test", num_objects=2)}
    assert small["oof_mugs"].identities == specs["oof_mugs"].identities[:2]
    with pytest.raises(DatasetSpecError, match="test sets only"):
        dataset_specs("oof", "train")
    with pytest.raises(DatasetSpecError, match="identities"):
        DatasetSpec(name="x", split="test", families=("imug",), num_objects=2, views=1, identities=("imug-00001",))


@pytest.fixture(scope="module")
def oof_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("oof")
    build("oof", "test", root, grid_size=16, num_objects=2, views=4, progress=False)
    return root / "test"


class TruthCompleter:
    """Stand-in completer: every sample is the view's stored ground truth."""

    has_box_latent = False

    def __init__(self, root) -> None:
        self.truth = {}
        for name in OOF_TEST_SETS:
            reader = DatasetReader(root / name)
            self.grid_size = reader.meta["grid_size"]
            for k in range(len(reader)):
                s = reader.get(k, images=False)
                self.truth[s["known_occupied"].tobytes() + s["known_free"].tobytes()] = s["occupancy"]

    def complete(self, observation, num_samples=20, seed=0):
        x = (observation.network_input() if hasattr(observation, "network_input") else np.asarray(observation)) > 0.5
        return argparse.Namespace(occupancy=np.stack([self.truth[x[0].tobytes() + x[1].tobytes()]] * num_samples))


def test_tiny_oof_build_records_the_new_families(oof_sets):
    mugs = DatasetReader(oof_sets / "oof_mugs")
    assert len(mugs) == 8 and {r["family"] for r in mugs.records} == {"imug"}
    assert all(r["has_handle"] is True for r in mugs.records)  # declared by the generator, recorded as such
    assert any(r["handle_visible"] is False for r in mugs.records) and any(r["handle_visible"] for r in mugs.records)
    narrow = DatasetReader(oof_sets / "oof_narrow")
    assert {r["family"] for r in narrow.records} == {"ibox"} and narrow.records[0]["slit_width_m"] == 0.036
    assert narrow.meta["spec"]["identities"] == ["ibox-2000000", "ibox-2000001"]


def test_ambiguity_runs_on_the_oof_sets(oof_sets, tmp_path):
    config = AmbiguityConfig(data=str(oof_sets), out=str(tmp_path / "amb"), sets=("oof_mugs", "oof_narrow"),
                             samples=3, progress=False)
    files = write_report(ambiguity_report(run_ambiguity(config, {"truth": TruthCompleter(oof_sets)})), config.out)
    result = json.loads(files["json"].read_text())
    summary = {e["delta_m"]: e for e in result["summary"]}
    for delta in (0.01, 0.04):
        e = summary[delta]
        assert e["hidden_views"] > 0 and e["visible_views"] > 0 and e["slit_views"] == 8
        # The truth is always plausible: samples equal to it are all inside the plausible sets.
        assert e["arc_precision"] == 1.0 and e["truth_in_arc"] == 1.0 and e["handle_rate_hidden"] == 1.0
        assert e["slit_precision"] == 1.0
    assert summary[0.01]["handle_error_visible_deg"] < 10.0
    assert "`oof_mugs`, `oof_narrow`" in files["markdown"].read_text()
    with pytest.raises(AmbiguityError, match="at most one mug set"):
        AmbiguityConfig(data=str(oof_sets), out=str(tmp_path / "x"), sets=("mugs", "oof_mugs"))


def test_the_paper_evaluation_runs_on_the_oof_sets(oof_sets, tmp_path):
    config = EvaluateConfig(TestSetsConfig(data=str(oof_sets), sets=OOF_TEST_SETS, cache_dir=str(tmp_path / "cache"),
                                           progress=False),
                            out=str(tmp_path / "out"), samples=2, delta=0.04, scaled_delta=0.01, plot_mugs=1)
    files = write_report(evaluation_report(run_evaluation(config, {"truth": TruthCompleter(oof_sets)})), config.out)
    rows = list(csv.DictReader(open(files["per_observation"])))
    assert {r["set"] for r in rows} == set(OOF_TEST_SETS) and len(rows) == (8 + 8 + 8 + 8) * 2
    assert max(float(r["best_accuracy_mm"]) for r in rows) == pytest.approx(0.0, abs=1e-9)
    summary = list(csv.DictReader(open(files["csv"])))
    assert {r["subset"] for r in summary} == {"oof all mugs", "oof occluded-handle mugs", "oof wide slit",
                                              "oof narrow slit", "oof mugs narrow slit"}
    assert "oof narrow slit (n=8)" in open(files["markdown"]).read()
    assert find_test_set(oof_sets, "oof_wide") is not None and all(f in BOX_FAMILIES for f in ("ibox", "rbox"))
