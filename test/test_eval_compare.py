"""`pssnet compare`: paired differences between methods from per_observation.csv rows."""

from __future__ import annotations

import csv
import gzip

import numpy as np
import pytest

from pssnet_core.cli import main
from pssnet_core.evaluation.compare import (
    CompareConfig,
    CompareError,
    paired_differences,
    read_per_observation,
)
from pssnet_core.evaluation.experiment import write_csv
from pssnet_core.evaluation.metrics import METRIC_NAMES
from pssnet_core.spread import evenly_spaced


def _rows(method: str, values: np.ndarray, set_name: str = "mugs", delta: float = 0.04,
          visible: list[bool] | None = None) -> list[dict]:
    rows = []
    for index, value in enumerate(values):
        row = {"set": set_name, "index": index, "method": method, "delta": delta,
               "handle_visible": "" if visible is None else str(visible[index])}
        row.update({name: float(value) for name in METRIC_NAMES})
        rows.append(row)
    return rows


def test_paired_difference_cancels_the_spread_between_observations():
    rng = np.random.default_rng(1)
    hardness = rng.uniform(1, 20, size=200)  # views differ far more than the methods do
    step = rng.normal(-0.3, 0.05, size=200)
    rows = _rows("vae", hardness) + _rows("pssnet", hardness + step)
    [d] = paired_differences(rows, ["pssnet"], "vae", CompareConfig(resamples=2000))
    assert d.subset == "all mugs" and d.count == 200
    assert d.difference == pytest.approx(step.mean())
    assert d.method_mean - d.baseline_mean == pytest.approx(d.difference)
    # paired: the interval is as narrow as the step's own noise (an unpaired one would be ~100x wider)
    assert d.low < d.difference < d.high and d.high < -0.25 and d.low > -0.35


def test_rows_pair_by_set_index_and_delta_and_subsets_follow_the_paper():
    visible = [True, False, True, False]
    rows = (_rows("vae", np.array([1.0, 2.0, 3.0, 4.0]), visible=visible)
            + _rows("pssnet", np.array([2.0, 2.0, 3.0, 6.0]), visible=visible)
            + _rows("vae", np.array([5.0, 5.0]), set_name="ycb_narrow")
            + _rows("pssnet", np.array([5.0]), set_name="ycb_narrow")  # index 1 unscored: not paired
            + _rows("vae", np.array([9.0, 9.0, 9.0, 9.0]), delta=0.01, visible=visible))  # no pssnet at 1 cm
    found = {(d.delta_m, d.subset): d for d in paired_differences(rows, ["pssnet"], "vae",
                                                                   CompareConfig(resamples=200))}
    assert set(found) == {(0.04, "all mugs"), (0.04, "occluded-handle mugs"), (0.04, "ycb narrow slit")}
    assert found[(0.04, "all mugs")].difference == pytest.approx(0.75)
    hidden = found[(0.04, "occluded-handle mugs")]
    assert (hidden.count, hidden.difference) == (2, pytest.approx(1.0))
    slit = found[(0.04, "ycb narrow slit")]
    assert (slit.count, slit.difference, slit.low, slit.high) == (1, 0.0, 0.0, 0.0)


def test_references_pick_the_observations_evaluate_would_score():
    assert evenly_spaced(864, 48) == sorted(set(np.linspace(0, 863, 48).round().astype(int).tolist()))
    assert evenly_spaced(5, 10) == list(range(5))
    values = np.arange(864, dtype=float)
    rows = _rows("vae", values) + _rows("pssnet", values + (values % 2))  # odd views differ by 1
    [d] = paired_differences(rows, ["pssnet"], "vae", CompareConfig(resamples=200, references=48))
    picked = evenly_spaced(864, 48)
    assert d.count == 48
    assert d.difference == pytest.approx(np.mean([i % 2 for i in picked]))


@pytest.mark.parametrize("kwargs", [{"metric": "iou"}, {"confidence": 1.0}, {"resamples": 10}, {"references": 0}])
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(CompareError):
        CompareConfig(**kwargs)


def test_unknown_method_and_malformed_csv_are_clear_errors(tmp_path):
    rows = _rows("vae", np.ones(3))
    with pytest.raises(CompareError, match="not in the rows"):
        paired_differences(rows, ["pssnet"], "vae")
    bad = tmp_path / "bad.csv"
    bad.write_text("set,index,method,delta\nmugs,zero,vae,0.04\n")
    with pytest.raises(CompareError, match="bad.csv:2"):
        read_per_observation([bad])
    with pytest.raises(CompareError, match="no such file"):
        read_per_observation([tmp_path / "missing.csv"])


def test_cli_joins_two_evaluations_and_writes_markdown_and_csv(tmp_path, capsys):
    rng = np.random.default_rng(2)
    hardness = rng.uniform(1, 5, size=30)
    first = write_csv(tmp_path / "a" / "per_observation.csv", _rows("vae", hardness) + _rows("recgan", hardness + 2))
    plain = write_csv(tmp_path / "b" / "per_observation.csv", _rows("shipped", hardness - 0.5))
    second = plain.with_name("per_observation.csv.gz")  # results/ keeps them gzipped
    second.write_bytes(gzip.compress(plain.read_bytes()))
    plain.unlink()
    out = tmp_path / "cmp" / "comparison.md"
    assert main(["compare", "--per-observation", f"{first},{second}", "--methods", "shipped,recgan,vae",
                 "--baseline", "vae", "--resamples", "500", "--out", str(out)]) == 0
    text = out.read_text()
    assert "| shipped | **-0.50** (-0.50 to -0.50)" in text and "| recgan | **+2.00**" in text
    with open(out.with_suffix(".csv"), newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["method"] for r in table] == ["shipped", "recgan"]
    assert [float(r["difference"]) for r in table] == pytest.approx([-0.5, 2.0])
    assert main(["compare", "--per-observation", str(tmp_path / "nothing.csv"), "--methods", "vae,recgan",
                 "--baseline", "vae", "--out", str(out)]) == 2
    assert "no such file" in capsys.readouterr().err
