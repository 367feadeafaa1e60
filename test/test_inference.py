"""The inference facade: checkpoint in, seeded completions out (tiny 16^3 models)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_models_helpers import cuboid_sample, tiny_model

import pssnet_core.inference as inference
from pssnet_core.inference import CheckpointError, Completer, CompletionInputError, CompletionResult
from pssnet_core.models.checkpoint import save_checkpoint

GRID = 16


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def checkpoint(tmp_path, name="pssnet"):
    model = tiny_model(name, GRID)
    if hasattr(model, "encoder"):
        with torch.no_grad():  # spread the posterior so that samples visibly differ
            model.encoder.dense.bias[model.latent_dim:] = 1.0
    return save_checkpoint(tmp_path / f"{name}.pt", model)


class FakeObservation:
    """Duck-typed stand-in for pssnet_core.geometry.Observation."""

    def __init__(self, seed=0):
        s = cuboid_sample(np.random.default_rng(seed), GRID)
        self.known_occupied, self.known_free = s["known_occupied"], s["known_free"]

    def network_input(self):
        return np.stack([self.known_occupied, self.known_free]).astype(np.float32)


def test_complete_shapes_dtypes_and_threshold(tmp_path):
    completer = Completer.from_checkpoint(checkpoint(tmp_path), threads=1)
    result = completer.complete(FakeObservation(), num_samples=5, seed=1)
    assert isinstance(result, CompletionResult)
    assert result.probabilities.shape == (5, GRID, GRID, GRID) and result.probabilities.dtype == np.float32
    assert result.occupancy.dtype == bool and np.array_equal(result.occupancy, result.probabilities > 0.5)
    assert result.grid_size == GRID and result.model == "pssnet" and result.num_samples == 5
    same = completer.complete(FakeObservation().network_input(), num_samples=5, seed=1)
    np.testing.assert_array_equal(same.probabilities, result.probabilities)


def test_seeds(tmp_path):
    completer = Completer.from_checkpoint(checkpoint(tmp_path))
    obs = FakeObservation()
    a = completer.complete(obs, 4, seed=0).probabilities
    b = completer.complete(obs, 4, seed=0).probabilities
    c = completer.complete(obs, 4, seed=1).probabilities
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3
    assert np.abs(a[0] - a[1]).max() > 1e-3, "samples of one call must differ"


def test_fast_path_close_to_fp32(tmp_path):
    path = checkpoint(tmp_path)
    fast = Completer.from_checkpoint(path, fast=True)
    ref = Completer.from_checkpoint(path, fast=False)
    assert ref.precision == "fp32"
    obs = FakeObservation(2)
    diff = np.abs(fast.complete(obs, 3, seed=5).probabilities - ref.complete(obs, 3, seed=5).probabilities)
    assert diff.max() < 0.05


def test_recgan_repeats_its_single_completion(tmp_path):
    completer = Completer.from_checkpoint(checkpoint(tmp_path, "recgan"))
    probs = completer.complete(FakeObservation(), 3, seed=0).probabilities
    assert np.array_equal(probs[0], probs[1]) and np.array_equal(probs[0], probs[2])


def test_bad_inputs(tmp_path):
    completer = Completer.from_checkpoint(checkpoint(tmp_path))
    with pytest.raises(CompletionInputError, match=r"\(2, 16, 16, 16\)"):
        completer.complete(np.zeros((2, 32, 32, 32), np.float32), 2)
    with pytest.raises(CompletionInputError, match="num_samples"):
        completer.complete(FakeObservation(), 0)
    with pytest.raises(CompletionInputError, match="NaN"):
        completer.complete(np.full((2, GRID, GRID, GRID), np.nan, np.float32), 2)
    with pytest.raises(CompletionInputError, match="Observation"):
        completer.complete([1, 2, 3], 2)


def test_box_temperature_is_a_completer_default_that_a_call_overrides(tmp_path):
    path = checkpoint(tmp_path)
    obs = FakeObservation()
    plain = Completer.from_checkpoint(path).complete(obs, 4, seed=2).probabilities
    warm = Completer.from_checkpoint(path, box_temperature=2.0)
    assert warm.box_temperature == 2.0
    np.testing.assert_array_equal(warm.complete(obs, 4, seed=2, box_temperature=1.0).probabilities, plain)
    assert np.abs(warm.complete(obs, 4, seed=2).probabilities - plain).max() > 1e-4
    with pytest.raises(CompletionInputError, match="box_temperature"):
        warm.complete(obs, 2, box_temperature=-1.0)
    with pytest.raises(ValueError, match="box_temperature"):
        Completer.from_checkpoint(checkpoint(tmp_path, "vae"), box_temperature=2.0)


def test_an_export_carries_its_calibrated_box_temperature(tmp_path):
    from pssnet_core.models.checkpoint import export_checkpoint

    shipped = export_checkpoint(checkpoint(tmp_path), tmp_path / "ship.pt", box_temperature=1.5)
    assert Completer.from_checkpoint(shipped).box_temperature == 1.5
    assert Completer.from_checkpoint(shipped, box_temperature=1.0).box_temperature == 1.0
    assert Completer.from_checkpoint(export_checkpoint(shipped, tmp_path / "plain.pt")).box_temperature == 1.5
    assert Completer.from_checkpoint(checkpoint(tmp_path)).box_temperature == 1.0
    with pytest.raises(CheckpointError, match="no box latent"):
        export_checkpoint(checkpoint(tmp_path, "vae"), tmp_path / "v.pt", box_temperature=2.0)


def test_missing_default_checkpoint_says_how_to_train(tmp_path, monkeypatch):
    monkeypatch.setattr(inference, "DEFAULT_CHECKPOINT", tmp_path / "absent.pt")
    with pytest.raises(CheckpointError, match="pssnet train"):
        Completer.from_checkpoint(None)
    with pytest.raises(CheckpointError, match="no checkpoint file"):
        Completer.from_checkpoint(tmp_path / "other.pt")



@pytest.mark.skipif(not inference.DEFAULT_CHECKPOINT.is_file(), reason="no shipped default model")
def test_shipped_model_fused_sampling_equals_the_autograd_path():
    """The fused inference path (oneDNN matmuls, gather) against the training path (addmm, ReLU, permuted
    copy) on the shipped 32^3 model: same occupancy, probabilities within fp32 rounding, several inputs."""
    completer = Completer.from_checkpoint(None, threads=1)
    n = completer.grid_size
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x = np.zeros((2, n, n, n), np.float32)
        lo = n // 4 + int(rng.integers(0, 4))
        x[0, lo, lo:3 * n // 4, lo:3 * n // 4] = 1  # a face and the free space in front of it
        x[1, :lo, lo:3 * n // 4, lo:3 * n // 4] = 1
        result = completer.complete(x, 20, seed=seed)
        with torch.enable_grad():  # autograd on: the plain path
            reference = completer.model.sample(torch.from_numpy(x)[None], 20,
                                               generator=torch.Generator().manual_seed(seed),
                                               box_temperature=completer.box_temperature)
        reference = reference[:, 0].detach().numpy()
        np.testing.assert_allclose(result.probabilities, reference, rtol=0, atol=1e-5)
        assert np.array_equal(result.occupancy, reference > 0.5)
        assert 0 < result.occupancy.mean() < 0.5
