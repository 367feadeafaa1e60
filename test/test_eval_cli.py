"""`pssnet evaluate` / `pssnet plausible` end to end on tiny test sets built by the data module."""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from pssnet_core.cli import main
from pssnet_core.data.build import build
from pssnet_core.data.store import DatasetReader
from pssnet_core.evaluation.cli import resolve_checkpoints
from pssnet_core.evaluation.evaluate import EvaluateConfig, TestSetsConfig, run_evaluation
from pssnet_core.evaluation.experiment import write_report
from pssnet_core.evaluation.report import evaluation_report
from pssnet_core.evaluation.testsets import find_test_set, load_test_set


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("evaldata")
    build("mugs", "test", root, grid_size=16, num_objects=1, views=6, progress=False)
    build("ycb", "test", root, grid_size=16, num_objects=1, views=3, progress=False)
    return root


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    from pssnet_core.models.checkpoint import save_checkpoint
    from pssnet_core.models.registry import build_model, default_config

    folder = tmp_path_factory.mktemp("ckpt")
    save_checkpoint(folder / "vae.pt", build_model(default_config("vae", grid_size=16, channels=[4, 8, 8, 8])))
    return folder


class Oracle:
    """A fake completer that returns the dataset's ground truth for each input (plus one empty sample)."""

    def __init__(self, roots: list[Path]) -> None:
        self.grid_size = 16
        self.table = {}
        for root in roots:
            reader = DatasetReader(root)
            for k in range(len(reader)):
                s = reader.get(k, images=False)
                self.table[s["known_occupied"].tobytes() + s["known_free"].tobytes()] = s["occupancy"]

    def complete(self, observation, num_samples=20, seed=0):
        x = observation.network_input() > 0.5  # the evaluation hands over its views
        truth = self.table[x[0].tobytes() + x[1].tobytes()]
        return argparse.Namespace(occupancy=np.stack([truth] * (num_samples - 1) + [np.zeros_like(truth)]))


def test_loader_reads_the_data_module_layout(tiny_data):
    root = find_test_set(tiny_data, "mugs")
    views, meta = load_test_set(root)
    assert len(views) == 6 and meta["name"] == "mugs"
    v = views[0]
    assert v.identity.startswith("mug-") and "rotation_deg" in v.meta
    assert v.depth_view.depth.dtype == np.float32
    assert 0.3 < v.depth_view.depth[v.depth_view.mask].max() < 1.5  # metres, not millimetres
    assert np.isclose(np.linalg.det(v.object_pose[:3, :3]), 1.0)


def test_evaluate_with_oracle_completer(tiny_data, tmp_path):
    config = EvaluateConfig(TestSetsConfig(data=str(tiny_data), sets=("mugs", "ycb_narrow", "ycb_wide"),
                                           cache_dir=str(tmp_path / "cache"), progress=False),
                            out=str(tmp_path / "out"), samples=3, delta=0.04, scaled_delta=0.01, plot_mugs=1)
    roots = [find_test_set(tiny_data, n) for n in ("mugs", "ycb_narrow", "ycb_wide")]
    files = write_report(evaluation_report(run_evaluation(config, {"oracle": Oracle(roots)})), config.out)
    rows = list(csv.DictReader(open(files["per_observation"])))
    assert len(rows) == (6 + 3 + 3) * 2
    # The stored ground truth and the evaluation's rebuilt one (same definition) agree: best accuracy 0.
    assert max(float(r["best_accuracy_mm"]) for r in rows) == pytest.approx(0.0, abs=1e-9)
    # One sample of three is empty (penalised by the grid diagonal, 0.2 m * sqrt(3)), so plausibility is
    # at least that / 3 where the set is the ground truth alone.
    diagonal_mm = 16 * DatasetReader(roots[0]).voxel_size * np.sqrt(3) * 1000
    singles = [r for r in rows if int(r["num_plausible"]) == 1]
    assert singles and all(float(r["plausibility_mm"]) == pytest.approx(diagonal_mm / 3, rel=1e-6) for r in singles)
    summary = list(csv.DictReader(open(files["csv"])))
    assert {r["subset"] for r in summary} == {"all mugs", "occluded-handle mugs", "ycb wide slit", "ycb narrow slit"}
    assert Path(files["coverage_plot"]).stat().st_size > 0
    assert "delta = 4 cm" in Path(files["markdown"]).read_text()


def test_evaluate_command_end_to_end(tiny_data, tiny_checkpoint, tmp_path, capsys):
    out = tmp_path / "results"
    code = main(["evaluate", "--models", "vae", "--checkpoints", str(tiny_checkpoint), "--data", str(tiny_data),
                 "--samples", "2", "--out", str(out), "--workers", "1", "--max-observations", "3", "--no-progress",
                 "--cache-dir", str(tmp_path / "cache"), "--threads", "1"])
    assert code == 0
    for name in ("results.md", "results.csv", "per_observation.csv", "evaluation_info.json"):
        assert (out / name).stat().st_size > 0
    text = (out / "results.md").read_text()
    assert "| vae |" in text and "delta = 1 cm" in text
    rows = list(csv.DictReader(open(out / "per_observation.csv")))
    assert len(rows) == 3 * 3 * 2  # 3 observations per set x 3 sets x 2 deltas
    # A second run finds the cached plausible sets.
    capsys.readouterr()
    assert main(["plausible", "--data", str(tiny_data), "--sets", "mugs", "--max-observations", "3",
                 "--cache-dir", str(tmp_path / "cache"), "--no-progress", "--deltas", "0.04,0.01"]) == 0
    assert "cached" in capsys.readouterr().out


def test_bad_inputs(tiny_data, tiny_checkpoint, tmp_path, capsys):
    assert main(["evaluate", "--models", "vae,pssnet", "--checkpoints", str(tiny_checkpoint),
                 "--data", str(tiny_data), "--out", str(tmp_path)]) == 2
    assert "no checkpoint for pssnet" in capsys.readouterr().err
    assert main(["plausible", "--data", str(tmp_path / "nothing"), "--no-progress"]) == 2
    assert "no test sets" in capsys.readouterr().err
    assert main(["plausible", "--data", str(tiny_data), "--sets", "cats"]) == 2
    with pytest.raises(ValueError, match="checkpoints for"):
        resolve_checkpoints(["vae", "recgan"], str(tiny_checkpoint / "vae.pt"))
    vae = str(tiny_checkpoint / "vae.pt")
    common = ["--data", str(tiny_data), "--out", str(tmp_path), "--no-progress"]
    assert main(["evaluate", "--models", "vae,vae", "--checkpoints", f"{vae},{vae}", *common]) == 2
    assert "must differ" in capsys.readouterr().err
    assert main(["evaluate", "--models", "vae", "--checkpoints", vae, "--model-box-temperatures", "1,2",
                 *common]) == 2
    assert "2 box temperatures for 1 models" in capsys.readouterr().err
    assert main(["evaluate", "--models", "vae", "--checkpoints", vae, "--model-box-temperatures", "2",
                 *common]) == 2
    assert "no box latent" in capsys.readouterr().err


def test_evaluate_applies_each_models_box_temperature(tiny_data, tmp_path, monkeypatch):
    from pssnet_core.evaluation import cli as eval_cli
    from pssnet_core.evaluation.evaluate import EvaluationResult
    from pssnet_core.models.checkpoint import save_checkpoint
    from pssnet_core.models.registry import build_model, default_config

    ckpt = save_checkpoint(tmp_path / "p.pt", build_model(default_config("pssnet", grid_size=16, channels=[4, 8, 8, 8],
                                                                        flow_hidden=16, flow_couplings=2)))
    seen = {}

    def record(config, completers):  # stands in for the evaluation: what temperature does each completer carry?
        seen.update({m: c.box_temperature for m, c in completers.items()})
        return EvaluationResult(config=config, methods=list(completers), test_sets={}, rows=[], examples=[],
                                timings={})

    monkeypatch.setattr(eval_cli, "run_evaluation", record)
    assert main(["evaluate", "--models", "plain,warm", "--checkpoints", f"{ckpt},{ckpt}", "--data", str(tiny_data),
                 "--model-box-temperatures", "1,1.5", "--out", str(tmp_path), "--no-progress"]) == 0
    assert seen == {"plain": 1.0, "warm": 1.5}


def test_dense_mug_views_pick_a_full_turn_of_the_first_handled_mugs():
    from pssnet_core.evaluation.evaluate import EvaluationError, dense_mug_views

    views = [argparse.Namespace(identity=f"mug-{m}", meta={"has_handle": m != 0}) for m in range(3) for _ in range(6)]
    assert dense_mug_views(views, 1, 2) == [6, 8, 10]  # mug-0 has no handle: mug-1's views 0, 2, 4
    assert dense_mug_views(views, 5, 3) == [6, 9, 12, 15]
    assert dense_mug_views(views, 0, 2) == []
    with pytest.raises(EvaluationError, match="dense_step"):
        dense_mug_views(views, 1, 0)


def test_evaluate_scores_each_model_with_both_samplers(tiny_data, tiny_checkpoint, tmp_path, capsys):
    """--samplers posterior,checked adds <model>_checked (the checked sampler on the evaluation's own views);
    a model without a latent keeps its one method and says why."""
    from pssnet_core.evaluation.cli import load_completers
    from pssnet_core.models.checkpoint import save_checkpoint
    from pssnet_core.models.registry import build_model, default_config
    from pssnet_core.sampling import CheckedSampler, CheckedSamplerConfig

    out = tmp_path / "results"
    assert main(["evaluate", "--models", "vae", "--checkpoints", str(tiny_checkpoint), "--data", str(tiny_data),
                 "--samples", "2", "--out", str(out), "--workers", "1", "--max-observations", "2", "--no-progress",
                 "--cache-dir", str(tmp_path / "cache"), "--threads", "1", "--samplers", "posterior,checked",
                 "--check-delta", "0.02"]) == 0
    rows = list(csv.DictReader(open(out / "per_observation.csv")))
    assert {r["method"] for r in rows} == {"vae", "vae_checked"}
    # methods.json: what made each method's samples, the checked sampler's every parameter included.
    methods = json.loads((out / "methods.json").read_text())
    assert methods["code"] and methods["cpu"]
    assert methods["methods"]["vae"]["sampler"] == "posterior" and "checked_sampler" not in methods["methods"]["vae"]
    checked = methods["methods"]["vae_checked"]
    assert checked["sampler"] == "checked" and checked["checkpoint"].endswith("vae.pt")
    assert checked["checked_sampler"] == json.loads(json.dumps(asdict(CheckedSamplerConfig(delta=0.02))))
    recgan = save_checkpoint(tmp_path / "r.pt", build_model(default_config("recgan", grid_size=16,
                                                                          channels=[4, 8, 8, 8], bottleneck_dim=8,
                                                                          disc_channels=[4, 8])))
    capsys.readouterr()
    completers = load_completers(["vae", "recgan"], f"{tiny_checkpoint / 'vae.pt'},{recgan}", "cpu", 1,
                                 ("checked",), 0.02)
    assert set(completers) == {"vae_checked", "recgan"} and isinstance(completers["vae_checked"], CheckedSampler)
    assert completers["vae_checked"].sampler_config.delta == 0.02
    assert "recgan" in capsys.readouterr().err
    # --sampler-option sets the checked sampler's other parameters; a bad one is refused before anything runs.
    tuned = load_completers(["vae"], str(tiny_checkpoint / "vae.pt"), "cpu", 1, ("checked",), 0.02,
                            sampler_options=("max_free_voxels=5", "max_missed_fraction=0.1"))
    assert tuned["vae_checked"].sampler_config == CheckedSamplerConfig(delta=0.02, max_free_voxels=5,
                                                                       max_missed_fraction=0.1)
    assert main(["evaluate", "--models", "vae", "--checkpoints", str(tiny_checkpoint), "--data", str(tiny_data),
                 "--out", str(out), "--samplers", "checked", "--sampler-option", "max_free_voxels=many"]) == 2
    assert "--sampler-option: sampler option 'max_free_voxels=many': 'many' is not an integer" in \
        capsys.readouterr().err
    assert main(["evaluate", "--models", "vae", "--checkpoints", str(tiny_checkpoint), "--data", str(tiny_data),
                 "--out", str(out), "--samplers", "best"]) == 2
    assert "samplers must be" in capsys.readouterr().err
