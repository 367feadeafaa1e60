"""Plausible-set throughput: pairs per second of Alg. 2 (ICP + observation model), and a full-set estimate.

    .venv/bin/python benchmarks/plausible_bench.py --data data/test/mugs --references 16 --workers 2
    .venv/bin/python benchmarks/plausible_bench.py --data /shared/data/test/mugs --references 864 --ray-address auto
    .venv/bin/python benchmarks/plausible_bench.py --synthetic-mugs 4 --views 72 --references 16
    .venv/bin/python benchmarks/plausible_bench.py --data data/test/mugs --references 24 --workers 2 --acceptance

With --data it loads a test set built by `pssnet dataset build`; with --synthetic-mugs it renders test mugs
itself (test-split seeds, 5 degree steps, 30 degree camera tilt at 0.7 m, 32^3 grid). Only --references
observations are computed (evenly spaced), each against every other observation of the set, and the time
for the full quadratic set is extrapolated from the measured rate (the script says so when it does).

--acceptance also reports what any test run before ICP would have to reject (see :func:`acceptance_report`);
--icp-scaling N times N ICPs in one process and in two processes at once (how open3d's ICP uses the cores).
--prefilter-study measures how well the cheap tests one could run before the full ICP separate the accepted pairs
from the rest (see :func:`prefilter_study`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pssnet_core"))  # pssnet_core, also without a venv

from pssnet_core.evaluation.observation_model import MultiDeltaView  # noqa: E402
from pssnet_core.evaluation.plausible import (  # noqa: E402
    EvalView,
    MeshSource,
    MeshTable,
    PlausibleConfig,
    PlausibleSets,
    ShapeMeshes,
    _PairJudge,
    compute_plausible_sets,
    icp_cloud,
)
from pssnet_core.ray_tasks import TaskRunner, add_ray_options, ray_config  # noqa: E402


def synthetic_mugs(num_mugs: int, views: int, grid: int):
    from pssnet_core.data.scenes import ObjectScene, render_view
    from pssnet_core.evaluation.testsets import eval_view_from_render
    from pssnet_core.geometry import GridConfig
    from pssnet_core.shapes import make_shape, split_seeds

    config = GridConfig.for_size(grid)
    out, meshes = [], {}
    for seed in split_seeds("test", num_mugs):
        shape = make_shape("mug", seed)
        meshes[str(shape.identity)] = (np.asarray(shape.mesh.vertices), np.asarray(shape.mesh.faces))
        scene = ObjectScene(shape)
        for k in range(views):
            yaw = k * 360.0 / views
            view = render_view(shape, yaw_deg=yaw, distance=0.7, tilt_deg=30.0, scene=scene)
            out.append(eval_view_from_render(len(out), str(shape.identity), view, config,
                                             meta={"rotation_deg": yaw}))
    return out, MeshTable(meshes)


def acceptance_report(sets: PlausibleSets, views: Sequence[EvalView]) -> list[str]:
    """Lines on the accepted candidates: how much a pre-ICP rejection test could save at most.

    A candidate is "accepted" when it is stored (plausible at some delta within the recording allowance). Every
    accepted pair needs its ICP whatever the prefilter, so the accepted fraction bounds the speed-up of any
    pre-ICP test. A test that provably holds for every rigid placement (what ICP may return) can only depend on the
    reference and the candidate's mesh, never on the candidate's view; so it can at most prune the pairs whose
    (reference, mesh) has no accepted candidate at all. The tilt and base shift of the accepted placements (against
    the reference's own pose) show how far from upright and grounded ICP's accepted answers are.
    """
    pairs = int(sets.stats["pairs"])
    rest = sets.other != sets.ref
    identities = sorted({v.identity for v in views})
    per_identity = {name: sum(v.identity == name for v in views) for name in identities}
    accepted_groups = {(int(i), views[int(j)].identity) for i, j in zip(sets.ref[rest], sets.other[rest], strict=True)}
    prunable = sum(per_identity[name] - (views[int(i)].identity == name)
                   for i in sets.references for name in identities if (int(i), name) not in accepted_groups)
    tilts, shifts = [], []
    for i, j, transform in zip(sets.ref[rest], sets.other[rest], sets.transforms[rest], strict=True):
        placed, truth = transform @ views[int(j)].object_pose, views[int(i)].object_pose
        tilts.append(np.degrees(np.arccos(np.clip(placed[:3, 2] @ truth[:3, 2], -1.0, 1.0))))
        shifts.append((placed[:3, 3] - truth[:3, 3]) @ truth[:3, 2])
    lines = [f"accepted candidates: {int(rest.sum())} of {pairs} pairs ({rest.sum() / max(pairs, 1):.1%}): "
             f"each needs its ICP whatever a pre-ICP test does",
             f"most any rigid-invariant (reference, mesh) test could prune: {prunable} pairs "
             f"({prunable / max(pairs, 1):.1%}) from {len(sets.references) * len(identities) - len(accepted_groups)} "
             f"of {len(sets.references) * len(identities)} (reference, mesh) groups with nothing accepted"]
    if tilts:
        lines.append(f"accepted placements: tilt {np.percentile(tilts, 50):.1f} deg median, {max(tilts):.1f} max; "
                     f"base shift along up {min(shifts) * 100:+.1f} .. {max(shifts) * 100:+.1f} cm")
    return lines


def prefilter_study(sets: PlausibleSets, views: Sequence[EvalView], meshes: MeshSource, config: PlausibleConfig,
                    coarse_points: int = 64, coarse_iterations: int = 10, sparse_pixels: int = 128) -> list[str]:
    """Lines on cheap pre-ICP tests: how many pairs each could reject without rejecting one accepted pair.

    Every pair (reference i, candidate j) of the computed references gets these scores, the larger the less
    plausible, and each is reported with the fraction of all pairs scoring above the largest score of an accepted
    pair (what the test could reject at the threshold the data allows, with no safety margin):

    - view descriptors: |height_i - height_j| and |width_i - width_j| of the observed points in the gravity-aligned
      grid frames (vertical and sideways extent);
    - cloud residual at the grid alignment ICP starts from: the larger of the mean nearest-neighbour distances
      j -> i and i -> j of the two ICP clouds;
    - the same residual after the full ICP (an upper bound on any residual-based test, which would need the ICP);
    - a coarse copy of Alg. 2: ICP of ``coarse_points`` of j's points for ``coarse_iterations`` iterations, then
      the fraction of ``sparse_pixels`` reliable pixels of i whose depth differs by more than the largest delta.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    reg = o3d.pipelines.registration
    clouds = [icp_cloud(v, config) for v in views]
    judge = _PairJudge(views, meshes, clouds, config)
    in_grid = [v.grid_pose.camera_to_grid(c) * v.grid_pose.voxel_size for c, v in zip(clouds, views, strict=True)]
    grid_trees = [cKDTree(c) for c in in_grid]
    observed = [v.grid_pose.camera_to_grid(v.depth_view.object_points()) * v.grid_pose.voxel_size for v in views]
    height = np.array([np.ptp(p[:, 2]) for p in observed])
    width = np.array([np.ptp(p[:, 1]) for p in observed])
    coarse = []
    for c in clouds:
        pick = np.linspace(0, len(c) - 1, min(coarse_points, len(c))).round().astype(np.int64)
        coarse.append(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c[pick])))
    largest = max(config.deltas)
    names = ["height difference (m)", "width difference (m)", "cloud residual at the ICP start (m)",
             "cloud residual after the full ICP (m)", "coarse ICP + sparse pixels: violating fraction"]
    scores, accepted = [], []
    for i in (int(r) for r in sets.references):
        kept = {int(j) for j in sets.other[sets.ref == i]}
        multi = MultiDeltaView(views[i].depth_view, config.recording_observation, config.deltas,
                               sparse_pixels=sparse_pixels)
        if multi.sparse is None:
            continue
        rows, cols = multi.sparse
        observed_depth = multi.any.observed[rows, cols]
        u0, v0 = views[i].depth_view.offset
        tree_i = cKDTree(clouds[i])
        for j in range(len(views)):
            if j == i:
                continue
            start = max(grid_trees[i].query(in_grid[j])[0].mean(), grid_trees[j].query(in_grid[i])[0].mean())
            transform = judge.icp(i, j)
            moved = clouds[j] @ transform[:3, :3].T + transform[:3, 3]
            after = max(tree_i.query(moved)[0].mean(), cKDTree(moved).query(clouds[i])[0].mean())
            rough = np.asarray(reg.registration_icp(
                coarse[j], judge.cloud(i), config.icp_max_distance, judge.initial_transform(i, j),
                reg.TransformationEstimationPointToPoint(),
                reg.ICPConvergenceCriteria(max_iteration=coarse_iterations)).transformation)
            expected = judge.raycaster(views[j].identity).depth_at(
                rough @ views[j].object_pose, views[i].depth_view.intrinsics, cols + u0, rows + v0,
                config.observation.pixel_offset)
            violating = float((np.abs(expected - observed_depth) > largest).mean())
            scores.append((abs(height[i] - height[j]), abs(width[i] - width[j]), start, after, violating))
            accepted.append(j in kept)
    table, ok = np.array(scores), np.array(accepted)
    lines = [f"pre-ICP tests on {len(ok)} pairs ({int(ok.sum())} accepted); 'rejectable' = pairs scoring above every "
             "accepted pair (no safety margin)"]
    for k, name in enumerate(names):
        worst = table[ok, k].max() if ok.any() else float("nan")
        lines.append(f"{name}: accepted up to {worst:.4f}, all pairs median {np.median(table[:, k]):.4f}; "
                     f"rejectable {(table[:, k] > worst).mean():.1%}")
    for threshold in (0.1, 0.15, 0.2, 0.3):
        above = table[:, 4] > threshold
        lines.append(f"coarse check rejecting above {threshold:.0%} violating: rejects {above.mean():.1%} of pairs, "
                     f"{int((above & ok).sum())} of them accepted")
    return lines


def _timed_icps(clouds: Sequence[np.ndarray], starts: Sequence[np.ndarray], max_distance: float,
                iterations: int) -> tuple[float, float]:
    """Wall and CPU seconds (every thread of this process) of ICP from each of clouds[1:] onto clouds[0]."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(clouds[0])))
    sources = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(c))) for c in clouds[1:]]
    wall, cpu = time.perf_counter(), time.process_time()
    for source, start in zip(sources, starts, strict=True):
        reg.registration_icp(source, target, max_distance, start, reg.TransformationEstimationPointToPoint(),
                             reg.ICPConvergenceCriteria(max_iteration=iterations))
    return time.perf_counter() - wall, time.process_time() - cpu


def _started(_: int) -> None:
    import open3d  # noqa: F401  (imported before the timed calls, as in a warm Ray worker)

    time.sleep(1.0)  # long enough that the pool hands the two calls to two processes


def icp_scaling(views: Sequence[EvalView], meshes: MeshSource, config: PlausibleConfig, count: int) -> list[str]:
    """Lines on how ICP uses the cores: ``count`` ICPs of this set's pairs (reference 0 against the next views)
    in this process, then the same in two processes at once.

    open3d parallelises one ICP over threads of its own (``OMP_NUM_THREADS`` does not limit them), so one process
    already keeps more than one core busy; a second process then adds only what those threads left idle.
    """
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    count = min(count, len(views) - 1)
    clouds = [icp_cloud(v, config) for v in views[:count + 1]]
    judge = _PairJudge(views, meshes, clouds, config)
    starts = [judge.initial_transform(0, j) for j in range(1, count + 1)]
    task = (clouds, starts, config.icp_max_distance, config.icp_iterations)
    wall1, cpu1 = _timed_icps(*task)
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        list(pool.map(_started, range(2)))
        both = [f.result() for f in [pool.submit(_timed_icps, *task) for _ in range(2)]]
    wall2 = max(w for w, _ in both)
    return [f"ICP of {count} pairs (reference 0 vs views 1..{count}): one process {wall1:.2f} s wall, "
            f"{cpu1:.2f} s CPU ({cpu1 / wall1:.2f} cores busy, {1e3 * wall1 / count:.2f} ms a pair)",
            "  two processes at once: " + "; ".join(f"{w:.2f} s wall, {c:.2f} s CPU" for w, c in both)
            + f"; throughput {2 * wall1 / wall2:.2f}x one process's"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=None, help="a test dataset directory")
    parser.add_argument("--synthetic-mugs", type=int, default=4, help="mugs to render when --data is not given")
    parser.add_argument("--views", type=int, default=72, help="views per synthetic mug")
    parser.add_argument("--grid", type=int, default=32)
    parser.add_argument("--references", type=int, default=16, help="reference observations computed")
    add_ray_options(parser, default_workers=1, what="reference observations")
    parser.add_argument("--deltas", default="0.04,0.01")
    parser.add_argument("--no-prefilter", action="store_true")
    parser.add_argument("--acceptance", action="store_true",
                        help="also report the accepted pairs: what any pre-ICP rejection test could save at most")
    parser.add_argument("--prefilter-study", action="store_true",
                        help="also score cheap pre-ICP tests on every pair (runs every pair's ICP again)")
    parser.add_argument("--icp-scaling", type=int, default=0, metavar="N",
                        help="also time N ICPs in one process and in two at once (how ICP uses the cores)")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    parser.add_argument("--record-fraction", type=float, default=0.01,
                        help="as `pssnet plausible` (default 0.01); 0 = strict sets, where the diameter bound prunes")
    args = parser.parse_args()

    t0 = time.perf_counter()
    if args.data:
        from pssnet_core.evaluation.testsets import load_test_set

        views, _ = load_test_set(args.data)
        meshes = ShapeMeshes()
        source = args.data
    else:
        views, meshes = synthetic_mugs(args.synthetic_mugs, args.views, args.grid)
        source = f"{args.synthetic_mugs} synthetic mugs x {args.views} views"
    t_load = time.perf_counter() - t0
    m = len(views)
    refs = np.linspace(0, m - 1, min(args.references, m)).round().astype(int).tolist()
    config = PlausibleConfig(deltas=tuple(float(d) for d in args.deltas.split(",")), prefilter=not args.no_prefilter,
                             record_fraction=args.record_fraction)
    with TaskRunner(ray_config(args)) as runner:
        print(f"running {runner.describe()}")  # starts Ray before the clock does
        sets = compute_plausible_sets(views, meshes, config, references=refs, runner=runner, progress=True)
    s = sets.stats
    full_pairs = m * (m - 1)
    print(f"test set: {source}: {m} observations ({t_load:.1f} s to load/render)")
    print(f"computed {len(refs)} references x {m - 1} candidates = {s['pairs']} pairs in {s['seconds']:.1f} s "
          f"({s['executor']}): {s['pairs_per_second']:.0f} pairs/s")
    print(f"  pruned before ICP (diameter bound): {s['pruned_by_prefilter']}; rejected on sparse pixels: "
          f"{s['rejected_on_sparse_pixels']}; ICP {s['icp_seconds']:.1f} s, judge "
          f"{s['judge_seconds']:.1f} s (wall time, summed over references)")
    print(f"  own ground truth plausible: {s['own_ground_truth_plausible_rate']}; mean set size: {s['mean_set_size']}")
    if args.acceptance:
        for line in acceptance_report(sets, views):
            print(f"  {line}")
    if args.prefilter_study:
        for line in prefilter_study(sets, views, meshes, config):
            print(f"  {line}")
    if args.icp_scaling:
        for line in icp_scaling(views, meshes, config, args.icp_scaling):
            print(f"  {line}")
    if args.json:
        args.json.write_text(json.dumps({"source": source, "observations": m, "references": len(refs),
                                         "pairs": int(s["pairs"]), "seconds": float(s["seconds"]),
                                         "pairs_per_second": float(s["pairs_per_second"])}, indent=2))
    if len(refs) < m:
        print(f"ESTIMATE (extrapolated, not measured): full set {full_pairs} pairs -> "
              f"{full_pairs / s['pairs_per_second'] / 60:.1f} min at this rate")
    return 0


if __name__ == "__main__":
    sys.exit(main())
