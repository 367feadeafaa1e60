"""Model integrity: every corruption of the weights is refused at load, a model that empties or
fills the grid at start or at a call, never served. The corruptions are the benchmark's own
(benchmarks/integrity_bench.py), applied to a small checkpoint here and to the shipped one where size matters."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_node_helpers import render_mug_scene, tiny_checkpoint

from pssnet_core.inference import DEFAULT_CHECKPOINT
from pssnet_core.models.checkpoint import CheckpointError, export_checkpoint, load_verified, read_checkpoint
from pssnet_core.models.integrity import IntegrityError, check_samples, weights_digest
from pssnet_core.pipeline import CompletionPipeline, ModelOutputError, PipelineConfig

_spec = importlib.util.spec_from_file_location("integrity_bench", Path(__file__).parents[1] / "benchmarks" /
                                               "integrity_bench.py")
bench = importlib.util.module_from_spec(_spec)
sys.modules["integrity_bench"] = bench  # dataclasses look their module up there
_spec.loader.exec_module(bench)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("integrity") / "tiny.pt")


def copy_of(source: Path, tmp_path: Path) -> Path:
    return Path(shutil.copyfile(source, tmp_path / "copy.pt"))


def refused(path: Path, pattern: str) -> str:
    with pytest.raises(CheckpointError, match=pattern) as error:
        load_verified(path, for_serving=True)
    message = str(error.value)
    assert "\n" not in message
    return message


def test_every_save_records_digest_ranges_and_self_test_and_every_load_checks_them(tiny):
    payload = read_checkpoint(tiny)
    record = payload["integrity"]
    assert record["digest"] == weights_digest(payload["state_dict"])
    assert set(record["ranges"]) == {n for n, t in payload["state_dict"].items() if t.is_floating_point()}
    loaded = load_verified(tiny, for_serving=True)
    assert loaded.self_test.iou == 1.0
    assert loaded.self_test.occupied_fraction == pytest.approx(record["self_test"]["occupied_fraction"])


@pytest.mark.parametrize("kind", ["flip", "zero", "random"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("archive", ["stored", "deflated"])
def test_corrupt_bytes_in_the_weight_storage_are_refused(tiny, tmp_path, kind, seed, archive):
    """In a training checkpoint (weights stored raw) and in an export (deflated), where a corrupt byte may also
    leave the archive unreadable."""
    if archive == "stored":
        path = copy_of(tiny, tmp_path)
    else:
        path = export_checkpoint(tiny, tmp_path / "exported.pt")
    bench.edit_bytes(path, np.random.default_rng(seed), kind)
    unreadable = r"|is not a readable checkpoint \(corrupt or truncated\?\)" if archive == "deflated" else ""
    refused(path, r"is corrupt: (weights differ from those saved: SHA-256|weight \S+ (has \d+ NaN/inf|spans))"
            + unreadable)


@pytest.mark.parametrize("name", ["one NaN weight", "NaN in the last layer", "output bias +inf"])
@pytest.mark.parametrize("resave", [False, True])
def test_non_finite_weights_are_refused_even_with_a_matching_record(tiny, tmp_path, name, resave):
    edit = {"one NaN weight": bench.one_nan, "NaN in the last layer": bench.nan_last_layer,
            "output bias +inf": bench.set_bias(float("inf"))}[name]
    path = copy_of(tiny, tmp_path)
    bench.edit_state(path, edit, np.random.default_rng(0), resave)
    refused(path, r"is corrupt: weight \S+ has [1-9]\d* NaN/inf value")


def test_an_output_bias_of_minus_60000_is_refused_by_range_or_by_the_self_test(tiny, tmp_path):
    path = copy_of(tiny, tmp_path)
    bench.edit_state(path, bench.set_bias(-60000.0), np.random.default_rng(0), False)
    refused(path, r"weight decoder\.deconv\.\d+\.bias spans \[-6e\+04, -6e\+04\], outside the")
    bench.edit_state(path, bench.set_bias(-60000.0), np.random.default_rng(0), True)  # a record that matches
    refused(path, r"self-test failed: the model empties the grid: its completion of the canonical view occupies "
                  r"0\.0% of the grid")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_randomly_initialised_full_size_model_is_refused(tmp_path, seed):
    path = copy_of(DEFAULT_CHECKPOINT, tmp_path)
    bench.edit_state(path, bench.random_init(DEFAULT_CHECKPOINT), np.random.default_rng(seed), True)
    refused(path, r"self-test failed: the model (empties|fills) the grid")


def test_random_weights_in_place_of_the_shipped_ones_are_refused_by_their_ranges(tmp_path):
    path = copy_of(DEFAULT_CHECKPOINT, tmp_path)
    bench.edit_state(path, bench.random_init(DEFAULT_CHECKPOINT), np.random.default_rng(0), False)
    refused(path, r"is corrupt: weight \S+ spans .* outside the .* recorded when it was saved")


def test_a_fingerprint_that_no_longer_matches_is_refused(tiny, tmp_path):
    """What the digest cannot see: the same weights completing differently (e.g. changed network code)."""
    path = copy_of(tiny, tmp_path)
    payload = torch.load(path, weights_only=True)
    test = payload["integrity"]["self_test"]
    test["fingerprint"] = torch.bitwise_not(test["fingerprint"])
    torch.save(payload, path)
    refused(path, r"self-test failed: .* overlaps the recorded completion by IoU 0\.000 \(need 0\.9\)")


def test_a_checkpoint_without_a_record_loads_for_research_is_refused_for_serving_and_export_adds_one(tiny, tmp_path):
    path = copy_of(tiny, tmp_path)
    payload = torch.load(path, weights_only=True)
    del payload["integrity"]
    torch.save(payload, path)
    assert load_verified(path).self_test is None
    refused(path, r"has no integrity record .* re-export it with `pssnet export-model")
    exported = export_checkpoint(path, tmp_path / "exported.pt")
    assert load_verified(exported, for_serving=True).self_test.iou == 1.0


def test_the_shipped_checkpoint_passes_with_its_weights_digest_and_a_fast_self_test():
    loaded = load_verified(DEFAULT_CHECKPOINT, for_serving=True)
    assert loaded.self_test.iou >= 0.99
    assert 0.03 < loaded.self_test.occupied_fraction < 0.07  # the canonical cylinder is 6.3 % of the grid
    assert loaded.self_test.seconds < 2.0  # 30 ms on one idle thread; a few hundred ms on the shared 2 cores


def test_samples_that_are_empty_or_fill_the_grid_are_refused():
    grids = np.zeros((3, 8, 8, 8), bool)
    grids[:, 2:4, 2:4, 2:4] = True
    check_samples(grids)
    grids[1] = False
    with pytest.raises(IntegrityError, match=r"sample 1 of 3 is empty"):
        check_samples(grids)
    grids[1] = True
    with pytest.raises(IntegrityError, match=r"sample 1 of 3 fills the grid \(100% of its voxels occupied\)"):
        check_samples(grids)


def test_a_call_whose_samples_are_empty_fails_instead_of_succeeding_with_nothing(tiny):
    """A model broken after its start-up check (here: its output bias changed in memory) is caught at the call."""
    pipeline = CompletionPipeline.from_checkpoint(tiny, PipelineConfig(num_samples=4, sampler="posterior"))
    scene = render_mug_scene()
    assert pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False).num_samples == 4
    with torch.no_grad():
        pipeline.completer.model.decoder.deconv[-1].bias.fill_(-60000.0)
    with pytest.raises(ModelOutputError, match=r"sample 0 of 4 is empty; the model or its weights are broken"):
        pipeline.run(scene.depth, scene.mask, scene.intrinsics, compute_grasps=False)
