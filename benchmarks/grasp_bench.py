"""Grasp benchmark: candidate generation and scoring of 500 candidates x 20 completions at 32^3 and 64^3.

    .venv/bin/python benchmarks/grasp_bench.py [--candidates 500] [--completions 20]
        [--repeats 21] [--sizes 32 64] [--baseline REV]

Scoring cost does not depend on how good the candidates are, so the scored candidates are grasps of the
generator's orientation set placed at random occupied voxels with random widths (seeded); the completions
are mugs of the project's procedural family rendered into the grid with their handle turned to different
angles. Timed: ``generate_candidates`` and ``score_grasps`` (each packs the completions itself, as a caller
of the public functions pays) and the whole ``plan_grasps`` (packs once). The target is generation + scoring
<= 30 ms at 32^3. Each is reported as median and min over the repeats, wall clock and CPU time of this thread
(on a shared machine the CPU time is the steadier of the two). Single thread (gathers and bitwise
reductions, no BLAS).

``--baseline REV`` also times the grasp package as it was at git revision REV, interleaved call by call
with the current one in this process (on a noisy machine only such ratios compare), and checks that both
rank the same grasps.
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np

import pssnet_core.grasps as current
from pssnet_core.bench import cpu_kind
from pssnet_core.geometry import GridConfig
from pssnet_core.grasps import GraspCandidates, GraspConfig, approach_orientations

TARGET_MS = 30.0


def completions(size: int, count: int) -> tuple[np.ndarray, object, np.ndarray]:
    from pssnet_core.data.scenes import ObjectScene, object_pose, render_view
    from pssnet_core.shapes import make_shape

    shape = make_shape("mug", 2000003)
    scene = ObjectScene(shape)
    view = render_view(shape, yaw_deg=0.0, distance=0.6, tilt_deg=30.0, scene=scene)
    observation = view.observe(GridConfig.for_size(size))
    yaws = np.linspace(-40.0, 40.0, count)
    occ = np.stack([scene.ground_truth(object_pose(shape.mesh, yaw), observation.pose, view.camera_pose)
                    for yaw in yaws])
    return occ, observation.pose, observation.points


def random_candidates(occ: np.ndarray, count: int, config: GraspConfig, voxel: float,
                      seed: int = 0) -> GraspCandidates:
    rng = np.random.default_rng(seed)
    voxels = np.argwhere(occ.any(axis=0)) + 0.5
    rotations, kinds = approach_orientations(config)
    pick = rng.integers(0, len(rotations), count)
    wmax = config.gripper.max_opening / voxel
    return GraspCandidates(voxels[rng.integers(0, len(voxels), count)] + rng.uniform(-0.5, 0.5, (count, 3)),
                           rotations[pick], rng.uniform(0.1 * wmax, wmax, count), kinds[pick])


def baseline_package(rev: str, into: Path) -> ModuleType:
    """The grasp package at git revision ``rev``, importable as ``grasps_baseline`` (its own modules): in
    pssnet_core/pssnet_core/grasps, or pssnet_core/grasps at revisions before the repository held packages."""
    root = Path(__file__).resolve().parents[1]
    for folder in ("pssnet_core/pssnet_core/grasps", "pssnet_core/grasps"):
        archive = subprocess.run(["git", "-C", str(root), "archive", rev, folder], capture_output=True)
        if archive.returncode == 0:
            break
    else:
        raise SystemExit(f"no grasp package at {rev}: {archive.stderr.decode().strip()}")
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(into, filter="data")
    package = into / "grasps_baseline"
    (into / folder).rename(package)
    for path in package.glob("*.py"):  # its modules import each other by absolute name
        path.write_text(path.read_text().replace("pssnet_core.grasps", "grasps_baseline"))
    sys.path.insert(0, str(into))
    return importlib.import_module("grasps_baseline")


def calls(grasps: ModuleType, occ: np.ndarray, pose: object, points: np.ndarray, cands: GraspCandidates,
          candidates: int) -> dict[str, Callable[[], object]]:
    config = grasps.GraspConfig(max_candidates=candidates)
    scored = grasps.GraspCandidates(cands.origins, cands.rotations, cands.widths, cands.kinds)
    support = 1.0
    return {"generate": lambda: grasps.generate_candidates(occ, pose, points, config, support),
            "score": lambda: grasps.score_grasps(scored, occ, pose, support, config),
            "plan_grasps": lambda: grasps.plan_grasps(occ, pose, points, config)}


def run(versions: dict[str, dict[str, Callable[[], object]]], repeats: int) -> dict[tuple[str, str], np.ndarray]:
    """(version, call) -> (repeats, 2) wall and thread-CPU ms, every call of every version in each round."""
    for fns in versions.values():
        for fn in fns.values():
            fn()  # warm-up
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for _ in range(repeats):
        for name in next(iter(versions.values())):
            for version, fns in versions.items():
                wall, cpu = time.perf_counter(), time.thread_time()
                fns[name]()
                times.setdefault((version, name), []).append(((time.perf_counter() - wall) * 1e3,
                                                              (time.thread_time() - cpu) * 1e3))
    return {key: np.array(value) for key, value in times.items()}


def same_grasps(a: object, b: object) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, f), getattr(b, f))
                                    for f in ("poses", "widths", "scores", "holds", "secondary"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidates", type=int, default=500)
    parser.add_argument("--completions", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--baseline", metavar="REV", help="also time the grasp package at this git revision")
    parser.add_argument("--json", type=Path, default=None, help="also write the current code's numbers here")
    args = parser.parse_args()
    numbers: dict[str, dict[str, float]] = {}
    print(f"CPU: {cpu_kind()}; single thread")
    with tempfile.TemporaryDirectory() as tmp:
        versions = {"current": current}
        if args.baseline:
            versions[f"baseline {args.baseline}"] = baseline_package(args.baseline, Path(tmp))
        print(f"{'grid':>5} {'version':>18} {'call':>12}   {'wall ms median/min':>18}   {'CPU ms median/min':>17}")
        for size in args.sizes:
            occ, pose, points = completions(size, args.completions)
            cands = random_candidates(occ, args.candidates, GraspConfig(max_candidates=args.candidates),
                                      pose.voxel_size)
            fns = {name: calls(grasps, occ, pose, points, cands, args.candidates) for name, grasps in versions.items()}
            times = run(fns, args.repeats if size <= 32 else max(3, args.repeats // 3))
            for version in fns:
                for call in fns[version]:
                    t = times[(version, call)]
                    print(f"{size:>4}^3 {version:>18} {call:>12}   {np.median(t[:, 0]):8.1f} {t[:, 0].min():8.1f}   "
                          f"{np.median(t[:, 1]):8.1f} {t[:, 1].min():8.1f}")
                both = times[(version, "generate")] + times[(version, "score")]
                generated = len(fns[version]["generate"]())
                verdict = "met" if statistics.median(both[:, 1]) <= TARGET_MS else "NOT met"
                print(f"{size:>4}^3 {version:>18} {'gen + score':>12}   {np.median(both[:, 0]):8.1f} "
                      f"{both[:, 0].min():8.1f}   {np.median(both[:, 1]):8.1f} {both[:, 1].min():8.1f}   "
                      f"({args.candidates} x {args.completions} scored, {generated} generated"
                      + (f"; target <= {TARGET_MS:.0f} ms (CPU median) {verdict})" if size == 32 else ")"))
            numbers[str(size)] = {f"{call}_ms": float(np.median(times[("current", call)][:, 1]))
                                  for call in fns["current"]}
            if args.baseline:
                ranked = [fns[version]["plan_grasps"]() for version in fns]
                print(f"{size:>4}^3 same ranked grasps as the baseline: {same_grasps(*ranked)}")
    if args.json:  # CPU-time medians, as the target is judged
        args.json.write_text(json.dumps({"candidates": args.candidates, "completions": args.completions,
                                         "sizes": numbers}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
