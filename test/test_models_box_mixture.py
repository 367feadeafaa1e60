"""The mixture box posterior (pssnet_core/models/box_mixture.py), PSSNet with it, and `pssnet fit-box-head`."""

from __future__ import annotations

import math

import pytest
import torch
from test_models_helpers import export_as_before_stop_38, make_dataset, tiny_model

from pssnet_core.models import StepContext, config_from_dict
from pssnet_core.models.box_mixture import BoxMixtureHead
from pssnet_core.models.checkpoint import CheckpointError, export_checkpoint, load_checkpoint, save_checkpoint
from pssnet_core.training.box_head import BoxHeadFitConfig, fit_box_head

pytestmark = pytest.mark.usefixtures("one_torch_thread")
GRID = 16


def head_with(weights: list[float], means: torch.Tensor, sigmas: torch.Tensor) -> BoxMixtureHead:
    """A head whose output ignores its input: fixed weights, means (K, D) and sigmas (K, D)."""
    k, d = means.shape
    head = BoxMixtureHead(3, d, k, 4).eval()
    last = head.net[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.cat([torch.log(torch.tensor(weights)), means.reshape(-1),
                                   (2 * torch.log(sigmas)).reshape(-1)]))
    return head


def test_nll_is_the_mixture_density():
    means = torch.tensor([[0.0, 1.0], [3.0, -1.0]])
    sigmas = torch.tensor([[1.0, 0.5], [2.0, 1.0]])
    head = head_with([0.25, 0.75], means, sigmas)
    code = torch.tensor([[0.5, 0.0]])
    dens = sum(w * torch.distributions.Normal(m, s).log_prob(code[0]).sum().exp()
               for w, m, s in zip([0.25, 0.75], means, sigmas, strict=True))
    torch.testing.assert_close(head.nll(torch.zeros(1, 3), code), -torch.log(dens).reshape(1))


def test_sampling_picks_components_by_weight_and_scales_sigma_by_temperature():
    means = torch.tensor([[-5.0, 0.0], [5.0, 0.0]])
    head = head_with([0.2, 0.8], means, torch.full((2, 2), 0.5))
    draws = head.sample(torch.zeros(2, 3), 4000, torch.Generator().manual_seed(0))
    assert draws.shape == (8000, 2)
    right = (draws[:, 0] > 0).float()
    assert abs(float(right.mean()) - 0.8) < 0.03
    assert abs(float(draws[right.bool(), 1].std()) - 0.5) < 0.03
    hot = head.sample(torch.zeros(1, 3), 4000, torch.Generator().manual_seed(0), temperature=2.0)
    assert abs(float(hot[hot[:, 0] > 0, 1].std()) - 1.0) < 0.06
    again = head.sample(torch.zeros(2, 3), 4000, torch.Generator().manual_seed(0))
    assert torch.equal(draws, again)


def test_mode_is_the_heaviest_components_centre_and_spread_the_total_sd():
    means = torch.tensor([[-2.0, 0.0], [2.0, 1.0]])
    head = head_with([0.3, 0.7], means, torch.tensor([[1.0, 1.0], [1.0, 3.0]]))
    torch.testing.assert_close(head.mode(torch.zeros(1, 3)), means[1:])
    draws = head.sample(torch.zeros(1, 3), 200_000, torch.Generator().manual_seed(1))
    torch.testing.assert_close(head.spread(torch.zeros(1, 3))[0], draws.std(0), rtol=0.02, atol=0.0)


def test_pssnet_with_a_mixture_trains_samples_reconstructs_and_round_trips(tmp_path):
    model = tiny_model("pssnet", box_components=3, box_head_hidden=8).train()
    assert model.box_head is not None
    ctx = StepContext(torch.device("cpu"))
    opts = model.make_optimizers(1e-3)
    x = torch.zeros(4, 2, GRID, GRID, GRID)
    x[:, 0, 4, 4:9, 4:9] = 1
    batch = {"input": x, "target": torch.zeros(4, 1, GRID, GRID, GRID),
             "box": torch.rand(4, 24) * GRID}
    before = [p.clone() for p in model.box_head.parameters()]
    out = model.training_step(batch, opts, ctx)
    assert math.isfinite(out["flow"])
    assert any(not torch.equal(a, b) for a, b in zip(before, model.box_head.parameters(), strict=True))
    model.eval()
    with torch.inference_mode():
        probs = model.sample(x[:1], 5, generator=torch.Generator().manual_seed(0))
        again = model.sample(x[:1], 5, generator=torch.Generator().manual_seed(0))
        assert probs.shape == (5, 1, GRID, GRID, GRID) and torch.equal(probs, again)
        assert model.reconstruct(x[:1]).shape == (1, 1, GRID, GRID, GRID)
    # The export keeps the head (it samples).
    save_checkpoint(tmp_path / "m.pt", model)
    export_checkpoint(tmp_path / "m.pt", tmp_path / "e.pt")
    loaded, config, _ = load_checkpoint(tmp_path / "e.pt")
    assert config.box_components == 3
    with torch.inference_mode():
        torch.testing.assert_close(loaded.sample(x[:1], 5, generator=torch.Generator().manual_seed(0)), probs,
                                   atol=2e-2, rtol=0)


def test_configs_written_before_the_mixture_load_as_the_papers_gaussian():
    config = tiny_model("pssnet").config.to_dict()
    for key in ("box_components", "box_head_hidden"):
        config.pop(key)
    assert config_from_dict(config).box_components == 1
    assert tiny_model("pssnet").box_head is None


def test_fit_box_head_writes_a_mixture_checkpoint_that_fits_the_training_boxes(tmp_path, monkeypatch):
    data = make_dataset(tmp_path / "data", num=40, grid=GRID)
    base = tiny_model("pssnet")
    save_checkpoint(tmp_path / "base.pt", base)
    logs: list[str] = []
    summary = fit_box_head(BoxHeadFitConfig(checkpoint=str(tmp_path / "base.pt"), data=str(data),
                                            out=str(tmp_path / "mix.pt"), components=4, hidden=16, steps=150,
                                            batch=32, val_fraction=0.2, threads=1), log=logs.append)
    assert summary["views"] == 40 and summary["val_views"] == 8
    assert math.isfinite(summary["val_nll_mixture"])
    model, config, extra = load_checkpoint(tmp_path / "mix.pt")
    assert config.box_components == 4 and extra["box_head_fit"]["components"] == 4
    # Everything but the head is the base model's.
    base_state = base.state_dict()
    for name, tensor in model.state_dict().items():
        if not name.startswith("box_head."):
            torch.testing.assert_close(tensor, base_state[name])
    # An export written before exports kept the flow has none to embed the true boxes: refused with the reason.
    export_as_before_stop_38(tmp_path / "base.pt", tmp_path / "export.pt", monkeypatch)
    with pytest.raises(CheckpointError, match="without the flow"):
        fit_box_head(BoxHeadFitConfig(checkpoint=str(tmp_path / "export.pt"), data=str(data),
                                      out=str(tmp_path / "x.pt"), components=2, steps=1, threads=1))
    # Today's export keeps it: the head fits from the export as from the training checkpoint.
    export_checkpoint(tmp_path / "base.pt", tmp_path / "export_with_flow.pt")
    fitted = fit_box_head(BoxHeadFitConfig(checkpoint=str(tmp_path / "export_with_flow.pt"), data=str(data),
                                           out=str(tmp_path / "y.pt"), components=2, steps=1, threads=1))
    assert math.isfinite(fitted["val_nll_mixture"])
    with pytest.raises(ValueError, match="components"):
        BoxHeadFitConfig(checkpoint="a", data="b", out="c", components=1)
