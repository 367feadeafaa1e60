"""pssnet posterior: posterior-mean BCE/IoU per dataset and the box posterior's width by handle visibility."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_models_helpers import DatasetWriter, cuboid_sample, tiny_model

from pssnet_core.data.store import DatasetReader
from pssnet_core.models import StepContext
from pssnet_core.models.checkpoint import save_checkpoint
from pssnet_core.training import cli as training_cli
from pssnet_core.training.posterior import posterior_stats

GRID = 16
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def mugs_like(tmp_path_factory):
    """Nine cuboid views labelled like mug views: 3 hidden handle, 3 visible, 3 without a handle."""
    path = tmp_path_factory.mktemp("posterior") / "mugs"
    rng = np.random.default_rng(1)
    writer = DatasetWriter(path, {"grid_size": GRID, "voxel_size": 0.005, "family": "mugs"}, shard_size=4)
    for i in range(9):
        has_handle = i < 6
        writer.add({**cuboid_sample(rng, GRID), "has_handle": has_handle,
                    "handle_visible": (i % 2 == 1) if has_handle else None})
    writer.close()
    return DatasetReader(path)


def expected_numbers(model, reader):
    """The same quantities, one view at a time, the plain way."""
    bce, iou, box_sd = [], [], {}
    with torch.inference_mode():
        for i in range(len(reader)):
            s = reader.get(i, images=False)
            x = torch.from_numpy(np.stack([s["known_occupied"], s["known_free"]])[None]).float()
            y = torch.from_numpy(s["occupancy"][None, None]).float()
            mu, logvar = model.encode(x)
            logits = model.decode(mu).float()
            bce.append(float(torch.nn.functional.binary_cross_entropy_with_logits(logits, y)))
            pred, gt = logits[0, 0] > 0, y[0, 0] > 0.5
            iou.append(float((pred & gt).sum() / (pred | gt).sum()))
            box_sd[i] = float(torch.exp(0.5 * logvar[0, :model.box_dim]).mean()) if model.box_dim else math.nan
    return np.mean(bce), np.mean(iou), box_sd


def test_posterior_stats_match_a_plain_computation_and_split_by_handle_visibility(mugs_like):
    model = tiny_model("pssnet", GRID).eval()
    stats = posterior_stats(model, mugs_like, "train", StepContext(torch.device("cpu")), batch_size=4)
    bce, iou, box_sd = expected_numbers(model, mugs_like)
    assert stats.views == 9
    assert stats.bce == pytest.approx(bce, rel=1e-5) and stats.iou == pytest.approx(iou, rel=1e-5)
    assert stats.box_sigma_hidden == pytest.approx(np.mean([box_sd[i] for i in (0, 2, 4)]), rel=1e-5)
    assert stats.box_sigma_visible == pytest.approx(np.mean([box_sd[i] for i in (1, 3, 5)]), rel=1e-5)
    assert stats.box_sigma_all == pytest.approx(np.mean(list(box_sd.values())), rel=1e-5)
    # An evenly spread subset, and a model without a box part.
    assert posterior_stats(model, mugs_like, "x", StepContext(torch.device("cpu")), max_views=3).views == 3
    vae = posterior_stats(tiny_model("vae", GRID).eval(), mugs_like, "x", StepContext(torch.device("cpu")))
    assert math.isnan(vae.box_sigma_all) and math.isnan(vae.box_sigma_hidden) and vae.rest_sigma_all > 0
    with pytest.raises(ValueError, match="no latent posterior"):
        posterior_stats(tiny_model("recgan", GRID), mugs_like, "x", StepContext(torch.device("cpu")))


def test_cli_writes_the_table_with_the_gap_ratio(tmp_path, mugs_like, capsys):
    ckpt = save_checkpoint(tmp_path / "m.pt", tiny_model("pssnet", GRID))
    parser = training_cli.argparse.ArgumentParser(prog="pssnet")
    training_cli.register(parser.add_subparsers(dest="command", required=True))
    data = str(mugs_like.root)
    args = parser.parse_args(["posterior", "--checkpoints", str(ckpt), "--labels", "tiny", "--data",
                              f"train={data}", "--data", f"test={data}", "--threads", "1", "--out", str(tmp_path)])
    assert args.func(args) == 0
    rows = json.loads((tmp_path / "posterior.json").read_text())
    assert [r["label"] for r in rows] == ["train", "test"] and rows[0]["bce"] == rows[1]["bce"]
    assert "1.000" in (tmp_path / "posterior.txt").read_text()
    args = parser.parse_args(["posterior", "--checkpoints", str(ckpt), "--data", data])
    assert args.func(args) == 2 and "LABEL=DIR" in capsys.readouterr().err
