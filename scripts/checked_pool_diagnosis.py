"""Where the checked sampler loses hidden-handle arc coverage: its proposals, its check, or its selection?

On hidden-handle views of a mug test set, runs the checked sampler's three steps by hand (the node's defaults)
and scores, against the plausible arc at ``--delta``, the handles of (1) all its proposals, (2) the proposals
the check accepts, (3) the ones the farthest-point selection returns; then per proposal source, the share the
check accepts and the share of those that draw a handle at all. If (1) already falls short, no check or
selection can reach the target: the model must propose more. Plausible arcs come from (or go into) the same
cache as ``pssnet ambiguity``'s.

Usage (results/reach/README.md):
    .venv/bin/python scripts/checked_pool_diagnosis.py --data data/oof/test --set oof_mugs \\
        --cache-dir data/oof/ambiguity_cache --views 40
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from pssnet_core.evaluation.ambiguity import arc_scores
from pssnet_core.evaluation.ambiguity_cache import AmbiguityTestSet, cached_plausible
from pssnet_core.evaluation.ambiguity_sets import AmbiguityMeasure
from pssnet_core.evaluation.handles import handle_azimuths, handle_geometries
from pssnet_core.evaluation.testsets import find_test_set
from pssnet_core.inference import Completer
from pssnet_core.sampling import SOURCES, CheckedSampler, CheckedSamplerConfig, GridCheck
from pssnet_core.spread import BitRows, farthest_point_selection


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="PSSNet checkpoint (default: the shipped model)")
    parser.add_argument("--data", default="data/oof/test")
    parser.add_argument("--set", default="oof_mugs")
    parser.add_argument("--cache-dir", type=Path, default=Path("runs/plausible_cache"),
                        help="plausible-set cache (as pssnet ambiguity's --cache-dir)")
    parser.add_argument("--views", type=int, default=40, help="hidden-handle views, evenly spaced")
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--delta", type=float, default=0.04, help="the arc's observation-model tolerance (m)")
    parser.add_argument("--check-delta", type=float, default=None, help="the check's tolerance (m; default the node's)")
    parser.add_argument("--turned-rest-low", type=float, default=None,
                        help="the turned boxes' rest-of-latent scale's low end (default the node's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    completer = Completer.from_checkpoint(args.checkpoint, threads=1)
    config = CheckedSamplerConfig()
    config = replace(config, delta=args.check_delta or config.delta,
                     turned_rest_low=config.turned_rest_low if args.turned_rest_low is None else args.turned_rest_low)
    sampler = CheckedSampler(completer, config)
    mugs = AmbiguityTestSet(find_test_set(args.data, args.set), False)
    geometries = handle_geometries(v.identity for v in mugs.views)
    hidden = [v for v in mugs.views if v.identity in geometries and v.meta.get("handle_visible") is False]
    hidden = [hidden[i] for i in np.unique(np.linspace(0, len(hidden) - 1, min(args.views, len(hidden))).round()
                                           .astype(int))]
    arcs, _ = cached_plausible(mugs, hidden, "handle_arcs", AmbiguityMeasure(), args.cache_dir, False)
    stages: dict[str, list[tuple[float, float, float]]] = {"all proposals": [], "accepted": [], "selected": []}
    sources: dict[str, list[tuple[float, float]]] = {name: [] for name in SOURCES}
    none_accepted = 0
    n = completer.grid_size
    for view in hidden:
        counts = config.proposal_counts(args.samples, sampler.has_box_latent, sampler.has_flow)
        generator = torch.Generator().manual_seed(view.index)
        _, probabilities = sampler.propose(completer.network_input(view), counts, generator,
                                           completer.box_temperature)
        occupancy = probabilities[:, completer.model.decoder.block_order()].numpy() > 0.5  # in spatial order
        packed = BitRows.pack(occupancy)
        check = GridCheck.prepare(view.known_occupied, view.known_free, view.grid_pose, config.delta)
        missed, free = check.violations(occupancy, packed)
        source = np.repeat(np.arange(len(SOURCES)), [counts[s] for s in SOURCES])
        ok = config.accepts(missed, free, source == 0)
        accepted = np.flatnonzero(ok)
        if not len(accepted):
            none_accepted += 1
            continue
        picked, _ = farthest_point_selection(packed.subset(accepted), args.samples)
        azimuths = handle_azimuths(occupancy.reshape(-1, n, n, n), view.grid_pose, view.object_pose,
                                   geometries[view.identity])
        arc = arcs[view.index].arc(args.delta)
        for stage, index in (("all proposals", np.arange(len(ok))), ("accepted", accepted),
                             ("selected", accepted[picked])):
            scores = arc_scores(arc, azimuths[index])
            stages[stage].append((scores.coverage, scores.precision, scores.rate))
        for i, name in enumerate(SOURCES):
            kept = ok & (source == i)
            if (source == i).any():
                sources[name].append((kept.sum() / (source == i).sum(),
                                      np.isfinite(azimuths[kept]).mean() if kept.any() else np.nan))
    print(f"{len(hidden)} hidden-handle views of {args.set}, arcs at delta {args.delta:g} m, check delta "
          f"{config.delta:g} m, {args.samples} samples from {sum(counts.values())} proposals; "
          f"{none_accepted} views with no proposal accepted (left out)")
    for stage, rows in stages.items():
        coverage, precision, rate = np.nanmean(np.array(rows, dtype=float), axis=0)
        print(f"  {stage:>13}: arc coverage {coverage:.2f}, precision {precision:.2f}, handle rate {rate:.2f}")
    for name, rows in sources.items():
        if rows:
            share, rate = np.nanmean(np.array(rows, dtype=float), axis=0)
            print(f"  source {name:>9}: {100 * share:.0f} % accepted, {100 * rate:.0f} % of those draw a handle")


if __name__ == "__main__":
    main()
