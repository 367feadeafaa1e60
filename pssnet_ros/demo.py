"""The README's first command: the completion node, a synthetic camera and a client, end to end over ROS 2.

    python -m pssnet_ros.demo --out demo_output

1. starts ``completion_node`` (the shipped model unless ``--model``) in its own process;
2. starts ``synthetic_camera`` in another process: a mug on a table, its handle hidden, at a few Hz;
3. calls ``/pssnet/sample_completions`` from this process with an empty depth image, so the node completes
   the latest synchronised depth/mask/camera_info it received on its topics;
4. writes ``completions.png`` (the observation, several sampled completions, the best grasps) and ``demo.mcap``
   (the depth/mask/camera_info set the node completed and its answer as the node's four topics) to ``--out``,
   prints a summary (samples, points, latency), stops both processes with SIGINT and exits 0.

Everything runs on its own ROS domain with discovery limited to this machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pssnet_ros.bag import write_demo_bag
from pssnet_ros.client import SAMPLE_SERVICE, RosClient
from pssnet_ros.processes import RosProcess, free_domain_id, ros_env, stale_shm_files
from pssnet_ros.synthetic_camera import SceneOptions, render_scene


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pssnet_ros.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("demo_output"), help="folder for the PNG")
    parser.add_argument("--model", default="", help="checkpoint (default: the shipped model)")
    parser.add_argument("--samples", type=int, default=20, help="completions to sample (default 20)")
    parser.add_argument("--calls", type=int, default=5, help="service calls timed for the latency (default 5)")
    parser.add_argument("--rate", type=float, default=5.0, help="synthetic camera rate, Hz (default 5)")
    parser.add_argument("--mug-seed", type=int, default=SceneOptions().mug_seed)
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS_DOMAIN_ID (default: one no DDS participant on this machine uses)")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds to wait for start-up")
    parser.add_argument("--verbose", action="store_true", help="echo the node's and camera's output")
    return parser


class DemoError(RuntimeError):
    """The demo could not complete; the message says at which step."""


def call_until_ready(ros: RosClient, client, request, timeout: float):
    """Calls the service until the node has a synchronised set (its answer before the camera's first frame
    is an honest success=false); returns (response, latency in seconds)."""
    deadline = time.monotonic() + timeout
    while True:
        t0 = time.perf_counter()
        try:
            response = ros.call(client, request, max(1.0, deadline - time.monotonic()))
        except TimeoutError:
            raise DemoError(f"no answer from the service within {timeout:.0f} s") from None
        latency = time.perf_counter() - t0
        if response.success:
            return response, latency
        if "no synchronised set has arrived" not in response.message or time.monotonic() > deadline:
            raise DemoError(f"the service answered success=false: {response.message}")
        time.sleep(0.2)  # the camera's first frame is on its way


def run_client(domain_id: int, samples: int, calls: int, timeout: float):
    """Calls the service from this process; returns the last response and the latencies (s)."""
    from pssnet_interfaces.srv import SampleCompletions

    with RosClient(domain_id, "pssnet_demo_client") as ros:
        try:
            client = ros.service(SampleCompletions, SAMPLE_SERVICE, timeout)
        except TimeoutError as error:
            raise DemoError(str(error)) from None
        request = SampleCompletions.Request(num_samples=samples, compute_grasps=True)  # depth empty: use topics
        response, first = call_until_ready(ros, client, request, timeout)
        latencies = []
        for _ in range(max(0, calls - 1)):
            response, latency = call_until_ready(ros, client, request, timeout)
            latencies.append(latency)
        return response, latencies or [first]


def write_figure(path: Path, view, response) -> None:
    """observation | completions (4 samples) | best grasps, in gravity-aligned axes (z up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.geometry import gravity_aligned_rotation
    from pssnet_ros.conversions import pointcloud2_to_numpy, pose_to_matrix

    axes_cam = gravity_aligned_rotation(view.up)  # columns: horizontal view direction, side, up

    def level(points: np.ndarray) -> np.ndarray:
        return points @ axes_cam

    known = level(pointcloud2_to_numpy(response.known_occupied)[0])
    samples = [level(pointcloud2_to_numpy(c)[0]) for c in response.completions]
    shown = samples[:4]
    fig = plt.figure(figsize=(4.2 * (2 + len(shown)), 4.6))
    ax = fig.add_subplot(1, 2 + len(shown), 1)
    rows, cols = np.nonzero(view.mask)
    pad = max(rows.max() - rows.min(), cols.max() - cols.min()) // 2 + 10
    v0, v1 = max(0, rows.min() - pad), min(view.mask.shape[0], rows.max() + pad)
    u0, u1 = max(0, cols.min() - pad), min(view.mask.shape[1], cols.max() + pad)
    depth = np.where(view.depth > 0, view.depth, np.nan)[v0:v1, u0:u1]
    ax.imshow(depth, cmap="viridis")
    ax.contour(view.mask[v0:v1, u0:u1] > 0, levels=[0.5], colors="red", linewidths=1.0)
    ax.set_title("observation: depth + mask (handle hidden)")
    ax.set_axis_off()
    lo = np.min([p.min(axis=0) for p in [known, *samples] if len(p)], axis=0)
    hi = np.max([p.max(axis=0) for p in [known, *samples] if len(p)], axis=0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 + 0.01

    def frame(ax3d, title: str) -> None:
        for setter, c in zip((ax3d.set_xlim, ax3d.set_ylim, ax3d.set_zlim), centre, strict=True):
            setter(c - half, c + half)
        ax3d.view_init(elev=25, azim=40)  # from behind and above: the hidden side faces the viewer
        ax3d.set_title(title, fontsize=9)
        ax3d.set_xticklabels([])
        ax3d.set_yticklabels([])
        ax3d.set_zticklabels([])

    for i, points in enumerate(shown):
        ax3d = fig.add_subplot(1, 2 + len(shown), 2 + i, projection="3d")
        ax3d.scatter(*points.T, s=3, c="tab:blue", alpha=0.5, depthshade=False)
        ax3d.scatter(*known.T, s=2, c="tab:red", alpha=0.6, depthshade=False)
        frame(ax3d, f"sample {i}: {len(points)} voxels (red: observed)")
    ax3d = fig.add_subplot(1, 2 + len(shown), 2 + len(shown), projection="3d")
    merged = np.concatenate([s for s in samples if len(s)] or [np.zeros((0, 3))])
    ax3d.scatter(*merged[::max(1, len(merged) // 6000)].T, s=1, c="lightgray", alpha=0.2, depthshade=False)
    ax3d.scatter(*known.T, s=2, c="tab:red", depthshade=False)
    grasps = response.grasps.poses[:5]
    for rank, pose in enumerate(grasps):
        matrix = pose_to_matrix(pose)
        origin = level(matrix[:3, 3][None])[0]
        approach, closing = matrix[:3, 2] @ axes_cam, matrix[:3, 1] @ axes_cam
        width = response.grasp_widths[rank] if rank < len(response.grasp_widths) else 0.08
        tips = [origin + s * 0.5 * width * closing for s in (-1.0, 1.0)]
        colour = "tab:green" if rank == 0 else "tab:orange"
        for tip in tips:  # fingers
            ax3d.plot(*np.stack([tip, tip - 0.04 * approach]).T, c=colour, lw=2)
        ax3d.plot(*np.stack(tips).T, c=colour, lw=1)
        palm = origin - 0.04 * approach
        ax3d.plot(*np.stack([palm, palm - 0.03 * approach]).T, c=colour, lw=2)
    scores = ", ".join(f"{s:.2f}" for s in response.grasp_scores[:5])
    frame(ax3d, f"best grasps (green = best; scores {scores})" if grasps else "grasps: none returned")
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.02, top=0.9, wspace=0.05)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 1 <= args.samples <= 100:
        print(f"[demo] error: --samples must be in [1, 100], got {args.samples}", file=sys.stderr)
        return 2
    domain = args.domain_id if args.domain_id is not None else free_domain_id(10 + os.getpid() % 90)
    env = ros_env(domain)
    options = SceneOptions(mug_seed=args.mug_seed)
    view = render_scene(options)
    up = "[" + ",".join(repr(float(v)) for v in view.up) + "]"
    node_args = ["--ros-args", "-p", f"up_vector:={up}", "-p", f"num_samples:={args.samples}"]
    if args.model:  # rcl cannot parse an empty value (model_path:=); leaving it out means the shipped model
        node_args += ["-p", f"model_path:={args.model}"]
    print(f"[demo] ROS_DOMAIN_ID={domain}; starting completion_node and synthetic_camera ...", flush=True)
    t_start = time.perf_counter()
    node = RosProcess.python_module("pssnet_ros.completion_node", node_args, env, name="completion_node",
                                    echo=args.verbose)
    camera = None
    code = 1
    try:
        node.wait_for(r"ready: serving", timeout=args.timeout)
        camera = RosProcess.python_module(
            "pssnet_ros.synthetic_camera", ["--rate", str(args.rate), "--mug-seed", str(args.mug_seed)], env,
            name="synthetic_camera", echo=args.verbose)
        camera.wait_for(r"publishing mug", timeout=args.timeout)
        response, latencies = run_client(domain, args.samples, args.calls, args.timeout)
        out = args.out / "completions.png"
        write_figure(out, view, response)
        bag = write_demo_bag(args.out / "demo.mcap", view, response)
        sizes = [c.width * c.height for c in response.completions]
        hidden = "hidden" if view.handle_visible is False else "visible" if view.handle_visible else "absent"
        print(f"[demo] completions of test-split mug {args.mug_seed} (handle {hidden}), from the node's topics:")
        print(f"[demo]   samples: {len(response.completions)}; voxel {response.voxel_size * 1000:.2f} mm; "
              f"observed voxels: {response.known_occupied.width}; points per sample: min {min(sizes)}, "
              f"median {int(np.median(sizes))}, max {max(sizes)}")
        best = f", best score {response.grasp_scores[0]:.2f}" if len(response.grasp_scores) else ""
        print(f"[demo]   grasps: {len(response.grasps.poses)}{best}")
        print(f"[demo]   service latency (request -> response, {len(latencies)} calls): median "
              f"{np.median(latencies) * 1000:.0f} ms, min {np.min(latencies) * 1000:.0f} ms")
        print(f"[demo]   node: {response.message}")
        print(f"[demo]   figure: {out}")
        print(f"[demo]   bag: {bag} (the set the node completed and its answer, as topics)")
        code = 0
    except (DemoError, TimeoutError, RuntimeError) as error:
        print(f"[demo] error: {error}", file=sys.stderr)
    finally:
        codes = {}
        for process in (camera, node):
            if process is not None:
                codes[process.name] = process.stop()
        leftovers = stale_shm_files({**node.shm_files, **(camera.shm_files if camera else {})})
    bad = {name: c for name, c in codes.items() if c != 0}
    if bad and code == 0:
        print(f"[demo] error: processes exited with {bad}", file=sys.stderr)
        code = 1
    if leftovers:
        print(f"[demo] warning: stale shared memory left: {sorted(leftovers)}", file=sys.stderr)
    if code == 0:
        print(f"[demo] done in {time.perf_counter() - t_start:.1f} s; all processes stopped cleanly")
    return code


if __name__ == "__main__":
    sys.exit(main())
