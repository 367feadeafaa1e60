"""What a trained model's posterior does on each split: the memorisation gap and the width of the box posterior.

Two questions from the ambiguity work, answered with the posterior *mean* (no true box, no sampling):

- Does the model recognise training objects? BCE per voxel and IoU of the posterior mean (``reconstruct``) on
  views of training objects against views of objects it has never seen (validation, test). A model that
  generalises has about the same numbers on both; one that memorised its few hundred objects is clearly better
  on the training ones.
- Does the posterior widen where the view is ambiguous? The posterior standard deviation of the latent, in
  the units of the prior (1 = as wide as the prior), averaged over the box dims (PSSNet's first ``box_dim``;
  with a mixture box posterior the whole mixture's standard deviation) and over the others, separately for mug
  views whose handle is hidden and visible.

Datasets are whatever `pssnet dataset build` wrote; the comparison is fair when they are built alike (e.g.
``--family mugs --num-objects 12 --views 12`` for each split: the first training objects are training objects
of every training set, since object seeds are the first ``count`` of each split).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from pssnet_core.data.store import GRID_KEYS, DatasetReader
from pssnet_core.models.base import CompletionModel, StepContext
from pssnet_core.spread import evenly_spaced
from pssnet_core.training.trainer import batch_to_tensors, reconstruction_scores


@dataclass(frozen=True)
class PosteriorStats:
    """Posterior-mean reconstruction and posterior width on one dataset.

    Attributes:
        label: the dataset's name in the report (e.g. "train", "val", "test").
        views: views measured.
        bce: mean binary cross-entropy per voxel of decode(mu) against the ground truth.
        iou: mean IoU of decode(mu) > 0.5 against the ground truth.
        box_sigma_hidden: mean posterior sigma of the box dims on mug views with a hidden handle (nan: none).
        box_sigma_visible: the same on mug views with a visible handle (nan: none).
        box_sigma_all: the same on every view (nan: the model has no box part).
        rest_sigma_all: mean posterior sigma of the non-box dims on every view.
    """

    label: str
    views: int
    bce: float
    iou: float
    box_sigma_hidden: float
    box_sigma_visible: float
    box_sigma_all: float
    rest_sigma_all: float


def posterior_stats(model: CompletionModel, reader: DatasetReader, label: str, ctx: StepContext,
                    max_views: int | None = None, batch_size: int = 16) -> PosteriorStats:
    """Measures :class:`PosteriorStats` of ``model`` (a VAE-family model with ``encode``) on ``reader``.

    Views are spread evenly over the dataset when ``max_views`` is smaller than it (so every object counts).
    """
    if not hasattr(model, "encode"):
        raise ValueError(f"{type(model).__name__} has no latent posterior to measure")
    total = len(reader)
    indices = np.asarray(evenly_spaced(total, max_views), dtype=np.int64)
    box_dim = model.box_dim
    bces, ious, box_sigmas, rest_sigmas, index_order = [], [], [], [], []
    model.eval()
    with torch.inference_mode():
        for batch in reader.iter_batches(batch_size, shuffle=False, keys=GRID_KEYS, indices=indices):
            t = batch_to_tensors(batch)
            with ctx.autocast():
                mu, logvar = model.encode(model.check_input(t["input"]))
                # The model's own posterior mean (a mixture box posterior decodes its heaviest component).
                logits = model.reconstruct(t["input"]).float()
            bce, iou = reconstruction_scores(logits, t["target"].to(logits.device))
            bces.append(bce.cpu().numpy())
            ious.append(iou.cpu().numpy())
            sigma = torch.exp(0.5 * logvar.float())
            box_sigmas.append(model.box_spread(mu.float(), logvar.float()).mean(1).cpu().numpy() if box_dim
                              else np.full(len(mu), np.nan))
            rest_sigmas.append(sigma[:, box_dim:].mean(1).cpu().numpy())
            index_order.append(np.asarray(batch["index"]))
    order = np.concatenate(index_order)
    box = np.concatenate(box_sigmas)
    handle = [(bool(reader.records[i].get("has_handle")), reader.records[i].get("handle_visible")) for i in order]
    hidden = np.array([has and seen is False for has, seen in handle], dtype=bool)
    shown = np.array([has and seen is True for has, seen in handle], dtype=bool)

    def mean_where(mask: np.ndarray) -> float:
        return float(box[mask].mean()) if mask.any() else float("nan")

    return PosteriorStats(
        label=label, views=len(order), bce=float(np.concatenate(bces).mean()), iou=float(np.concatenate(ious).mean()),
        box_sigma_hidden=mean_where(hidden), box_sigma_visible=mean_where(shown),
        box_sigma_all=float(box.mean()), rest_sigma_all=float(np.concatenate(rest_sigmas).mean()))


def format_table(rows: Sequence[tuple[str, PosteriorStats]]) -> str:
    """A text table of (model label, stats) rows, with each model's BCE relative to its "train" row."""
    header = (f"{'model':<22} {'data':<10} {'views':>6} {'bce':>8} {'vs train':>9} {'iou':>6} "
              f"{'box sd hid':>10} {'box sd vis':>10} {'box sd':>7} {'rest sd':>7}")
    lines = [header, "-" * len(header)]
    train_bce = {model: s.bce for model, s in rows if s.label == "train"}
    for model, s in rows:
        ratio = f"{s.bce / train_bce[model]:.3f}" if model in train_bce else "-"
        lines.append(f"{model:<22} {s.label:<10} {s.views:>6} {s.bce:>8.4f} {ratio:>9} {s.iou:>6.3f} "
                     f"{s.box_sigma_hidden:>10.3f} {s.box_sigma_visible:>10.3f} {s.box_sigma_all:>7.3f} "
                     f"{s.rest_sigma_all:>7.3f}")
    return "\n".join(lines)


def stats_dict(rows: Sequence[tuple[str, PosteriorStats]]) -> list[dict]:
    """JSON form of the rows."""
    return [{"model": model, **asdict(s)} for model, s in rows]


__all__ = ["PosteriorStats", "format_table", "posterior_stats", "stats_dict"]
