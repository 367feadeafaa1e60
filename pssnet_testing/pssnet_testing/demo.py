"""The README's first command: the completion node, a synthetic camera and a client, end to end over ROS 2.

    python -m pssnet_testing.demo --out demo_output

1. starts ``completion_node`` (the shipped model unless ``--model``) in its own process;
2. starts ``synthetic_camera`` in another process: a mug on a table, its handle hidden, at a few Hz;
3. calls ``/pssnet/sample_completions`` from this process with an empty depth image, so the node completes
   the latest synchronised depth/mask/camera_info it received on its topics;
4. takes a second look: asks the node which of 16 places round the mug would best tell its samples apart
   (``candidate_views``), renders the mug from there and calls again with both views (``more_*``);
5. writes ``completions.png`` (the observation, several sampled completions, the best grasps) and ``demo.mcap``
   (the depth/mask/camera_info set the node completed and its answer as the node's four topics) to ``--out``,
   prints a summary (samples, points, latency, the second look), stops both processes with SIGINT and exits 0.

Everything runs on its own ROS domain with discovery limited to this machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pssnet_core.grasps import GripperConfig
from pssnet_core.next_view import RING_PLACES
from pssnet_ros.bag import SENSOR_QOS, BagWriter
from pssnet_ros.completion_io import STREAMS, outputs_from_response, stamp_ns
from pssnet_testing.client import SAMPLE_SERVICE, RosClient
from pssnet_testing.node_under_test import NodeUnderTest
from pssnet_testing.processes import RosProcess, claim_domain_id, ros_env, stale_shm_files
from pssnet_testing.synthetic_camera import FRAME_ID, SceneOptions, render_scene, view_messages

if TYPE_CHECKING:
    from pssnet_interfaces.srv import SampleCompletions

    from pssnet_core.data.scenes import RenderedView


def write_demo_bag(path: Path, view: RenderedView, response: SampleCompletions.Response) -> Path:
    """Records one demo exchange: the camera's depth/mask/camera_info of the set the node completed (as the
    synthetic camera sent them: same images, stamp and frame) and the node's answer as its topics (the demo's node
    runs with the default gripper)."""
    header = response.header
    log_ns = stamp_ns(header)
    with BagWriter(path, overwrite=True) as writer:
        for stream, message in zip(STREAMS, view_messages(view, "32FC1", header), strict=True):
            writer.write(f"/{stream}", message, log_ns, SENSOR_QOS)
        for topic, message in outputs_from_response(response, GripperConfig()).by_topic().items():
            writer.write(topic, message, log_ns)
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pssnet_testing.demo", description=__doc__.split("\n\n")[0])
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
        if response.status != response.STATUS_NO_INPUT or time.monotonic() > deadline:
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


#: Of the ring of places the demo's second look may come from, the one beside the camera (its azimuth, a little lower
#: than its 30 degrees).
CAMERA_SIDE = RING_PLACES.index((180.0, 15.0))


@dataclass
class DemoLook:
    """The demo's second look: the places' scores, the place chosen, and the answers before and after."""

    scores: list[float]
    place: tuple[float, float]
    before: SampleCompletions.Response
    after: SampleCompletions.Response


def take_second_look(domain_id: int, options: SceneOptions, view: RenderedView, samples: int,
                     timeout: float) -> DemoLook:
    """Asks where to look from (the first view in the request, every place of :data:`RING_PLACES` as a candidate),
    renders the mug from the best place and completes both views."""
    from pssnet_interfaces.srv import SampleCompletions
    from std_msgs.msg import Header

    from pssnet_ros.conversions import matrix_to_pose

    first_from_world = np.linalg.inv(view.camera_pose)
    looks = [render_scene(replace(options, tilt_deg=elevation), azimuth_deg=azimuth)
             for azimuth, elevation in RING_PLACES]
    header = Header(frame_id=FRAME_ID)
    depth, mask, info = view_messages(view, "32FC1", header)
    request = SampleCompletions.Request(depth=depth, mask=mask, camera_info=info, num_samples=samples,
                                        compute_grasps=True,
                                        candidate_views=[matrix_to_pose(first_from_world @ look.camera_pose)
                                                         for look in looks])
    with RosClient(domain_id, "pssnet_demo_look") as ros:
        client = ros.service(SampleCompletions, SAMPLE_SERVICE, timeout)
        before = ros.call(client, request, timeout)
        if not before.success or len(before.candidate_view_scores) != len(looks):
            raise DemoError(f"asking where to look failed: {before.message}")
        best = int(np.argmax(before.candidate_view_scores))
        more_depth, more_mask, more_info = view_messages(looks[best], "32FC1", header)
        request.more_depths, request.more_masks, request.more_camera_infos = [more_depth], [more_mask], [more_info]
        request.more_camera_poses = [matrix_to_pose(first_from_world @ looks[best].camera_pose)]
        request.candidate_views = []
        after = ros.call(client, request, timeout)
        if not after.success:
            raise DemoError(f"completing both views failed: {after.message}")
    return DemoLook([float(x) for x in before.candidate_view_scores], RING_PLACES[best], before, after)


def write_figure(path: Path, view, response, max_samples: int = 4) -> None:
    """What the node made of the view, as surfaces one colour per sample, so that the hidden side's spread shows.

    Top row, seen from the camera: the depth image with the object's mask, then each sample (the observed part
    dark red): they agree where the camera saw. The samples shown: the heaviest (the checked sampler's weights), or
    the most different when all weigh the same. Bottom row, seen from above with the camera at the bottom, so
    that the hidden side is at the top: every sample's surface coloured by the share of samples that have it,
    then each sample alone. Last column: the best grasps (gripper outlines, best in green,
    labelled with rank and score) over the observed surface and the samples, from both sides.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pssnet_core.geometry import gravity_aligned_rotation
    from pssnet_core.grasps import gripper_segments
    from pssnet_core.surfaces import draw_surface, equal_box, most_different, sample_agreement, surface_of
    from pssnet_ros.conversions import pointcloud2_to_numpy, pose_to_matrix

    axes_cam = gravity_aligned_rotation(view.up)  # columns: horizontal view direction, left, up

    def level(points: np.ndarray) -> np.ndarray:
        return np.asarray(points, np.float64) @ axes_cam

    voxel = float(response.voxel_size)
    known = level(pointcloud2_to_numpy(response.known_occupied)[0])
    every_sample = [level(pointcloud2_to_numpy(c)[0]) for c in response.completions]
    clouds = [c for c in [known, *every_sample] if len(c)]
    origin = np.min([c.min(axis=0) for c in clouds], axis=0)  # one lattice for every cloud
    weights = np.asarray(response.sample_weights, np.float64)
    if len(weights) == len(every_sample) and np.ptp(weights) > 1e-6:
        # The checked sampler's samples are already spread over what the view allows: show the ones that stand
        # for most of the plausible shapes.
        chosen = [int(i) for i in np.argsort(-weights, kind="stable")[:max_samples]]
        which = "the heaviest"
    else:
        chosen = most_different(every_sample, max_samples, voxel, origin)
        weights = np.full(len(every_sample), 1.0 / max(len(every_sample), 1))
        which = "the most different"
    samples = [every_sample[i] for i in chosen]
    known_mesh = surface_of(known, voxel, origin)
    meshes = [surface_of(c, voxel, origin) for c in samples]
    union_mesh, agreement = sample_agreement(every_sample, voxel, origin)
    colours = [plt.get_cmap("tab10")(i) for i in (0, 1, 2, 4, 6, 8, 9)]  # no red: red is what was observed
    poses = np.array([pose_to_matrix(p) for p in response.grasps.poses[:5]]).reshape(-1, 4, 4)
    grasp_lines = gripper_segments(poses, np.asarray(response.grasp_widths[:len(poses)]), GripperConfig())
    grasp_lines = level(grasp_lines.reshape(-1, 3)).reshape(grasp_lines.shape)
    objects = np.concatenate(clouds)
    everything = np.concatenate([objects, grasp_lines.reshape(-1, 3)])

    columns = len(samples) + 1
    fig = plt.figure(figsize=(3.6 * (columns + 1), 7.6))
    # (elevation, azimuth) in the level axes: the camera looks along +x, so it sees the -x side.
    # From above with the camera at the bottom of the panel: a hidden handle shows as a protrusion whose
    # direction reads directly (from straight behind, a handle pointing at the viewer hides in front of the body).
    from_camera, from_above = (20.0, -160.0), (88.0, 180.0)

    def panel(position: int, title: str, viewpoint: tuple[float, float], frame: np.ndarray) -> Any:
        ax3d = fig.add_subplot(2, columns + 1, position, projection="3d")
        ax3d.view_init(*viewpoint)
        equal_box(ax3d, frame)
        ax3d.set_title(title, fontsize=9)
        ax3d.set_axis_off()
        return ax3d

    ax = fig.add_subplot(2, columns + 1, 1)
    rows, cols = np.nonzero(view.mask)
    pad = max(rows.max() - rows.min(), cols.max() - cols.min()) // 2 + 10
    v0, v1 = max(0, rows.min() - pad), min(view.mask.shape[0], rows.max() + pad)
    u0, u1 = max(0, cols.min() - pad), min(view.mask.shape[1], cols.max() + pad)
    ax.imshow(np.where(view.depth > 0, view.depth, np.nan)[v0:v1, u0:u1], cmap="viridis")
    ax.contour(view.mask[v0:v1, u0:u1] > 0, levels=[0.5], colors="red", linewidths=1.0)
    hidden = {False: "hidden", True: "visible"}.get(view.handle_visible, "absent")
    ax.set_title(f"depth + mask (handle {hidden})\nbelow: {len(samples)} of {len(every_sample)} samples, {which};"
                 f"\ndark red = observed; yellow = in every sample", fontsize=9)
    ax.set_axis_off()
    for k, (i, mesh) in enumerate(zip(chosen, meshes, strict=True)):
        ax3d = panel(2 + k, f"sample {i} (weight {weights[i]:.2f}), from the camera", from_camera, objects)
        draw_surface(ax3d, mesh, colours[k % len(colours)])
        draw_surface(ax3d, known_mesh, "darkred")
    ax3d = panel(columns + 2, f"all {len(every_sample)} samples from above:\nshare of samples with each part",
                 from_above, objects)
    draw_surface(ax3d, union_mesh, plt.get_cmap("viridis")(agreement)[:, :3])
    for k, (i, mesh) in enumerate(zip(chosen, meshes, strict=True)):
        ax3d = panel(columns + 3 + k, f"sample {i}, from above (camera below)", from_above, objects)
        draw_surface(ax3d, mesh, colours[k % len(colours)])
        draw_surface(ax3d, known_mesh, "darkred")
    for position, viewpoint, side in ((columns + 1, from_camera, "from the camera"),
                                      (2 * (columns + 1), from_above, "from above")):
        ax3d = panel(position, f"best grasps (green = best), {side}", viewpoint, everything)
        for mesh in meshes:
            draw_surface(ax3d, mesh, "lightgray", alpha=0.15)
        draw_surface(ax3d, known_mesh, "darkred")
        for rank in range(len(grasp_lines) - 1, -1, -1):  # best drawn last, on top
            colour = "tab:green" if rank == 0 else "tab:orange"
            for segment in grasp_lines[rank]:
                ax3d.plot(*segment.T, color=colour, linewidth=3.0 if rank == 0 else 1.5)
            ax3d.text(*grasp_lines[rank, 3, 1], f"#{rank + 1} {response.grasp_scores[rank]:.2f}", color=colour,
                      fontsize=8)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.93, wspace=0.02, hspace=0.12)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 1 <= args.samples <= 100:
        print(f"[demo] error: --samples must be in [1, 100], got {args.samples}", file=sys.stderr)
        return 2
    domain = args.domain_id if args.domain_id is not None else claim_domain_id()
    env = ros_env(domain)
    options = SceneOptions(mug_seed=args.mug_seed)
    view = render_scene(options)
    # rcl cannot parse an empty value (model_path:=); leaving it out means the shipped model
    model = {"model_path": args.model} if args.model else {}
    print(f"[demo] ROS_DOMAIN_ID={domain}; starting completion_node and synthetic_camera ...", flush=True)
    t_start = time.perf_counter()
    node = NodeUnderTest(domain, timeout=args.timeout, echo=args.verbose, client_name="pssnet_demo_ready",
                         up_vector=view.up, num_samples=args.samples, **model)
    camera = None
    code = 1
    try:
        node.start()
        node.close_client()  # only the readiness check used it; run_client has its own
        camera = RosProcess.python_module(
            "pssnet_testing.synthetic_camera", ["--rate", str(args.rate), "--mug-seed", str(args.mug_seed)], env,
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
        best = (f", top grasp's score {response.grasp_scores[0]:.2f}, weight share "
                f"{response.grasp_weight_shares[0]:.2f}" if len(response.grasp_scores) else "")
        print(f"[demo]   grasps: {len(response.grasps.poses)}{best}")
        print(f"[demo]   service latency (request -> response, {len(latencies)} calls): median "
              f"{np.median(latencies) * 1000:.0f} ms, min {np.min(latencies) * 1000:.0f} ms")
        print(f"[demo]   node: {response.message}")
        print(f"[demo]   figure: {out}")
        print(f"[demo]   bag: {bag} (the set the node completed and its answer, as topics)")
        look = take_second_look(domain, options, view, args.samples, args.timeout)
        top = [f"{r.grasp_scores[0]:.2f}" if len(r.grasp_scores) else "none" for r in (look.before, look.after)]
        print(f"[demo] second look: of {len(look.scores)} places round the mug, the samples disagree most about the "
              f"view from azimuth {look.place[0]:.0f}, {look.place[1]:.0f} deg up (probability {max(look.scores):.2f} "
              f"that it tells two samples apart; from the camera's side {look.scores[CAMERA_SIDE]:.2f})")
        print(f"[demo]   with that view added: observed voxels {look.before.known_occupied.width} -> "
              f"{look.after.known_occupied.width}, top grasp's score {top[0]} -> {top[1]}")
        code = 0
    except (DemoError, TimeoutError, RuntimeError) as error:
        print(f"[demo] error: {error}", file=sys.stderr)
    finally:
        codes = {}
        for process in (camera, node.process):
            if process is not None:
                codes[process.name] = process.stop()
        node.close_client()
        leftovers = stale_shm_files({**(node.process.shm_files if node.process else {}),
                                     **(camera.shm_files if camera else {})})
    bad = {name: c for name, c in codes.items() if c != 0}
    if bad and code == 0:
        print(f"[demo] error: processes exited with {bad}", file=sys.stderr)
        for process in (camera, node.process):
            if process is not None and process.name in bad:  # what it said last says why
                print(f"[demo] last output of {process.name}:\n" + "\n".join(process.lines()[-30:]), file=sys.stderr)
        code = 1
    if leftovers:
        print(f"[demo] warning: stale shared memory left: {sorted(leftovers)}", file=sys.stderr)
    if code == 0:
        print(f"[demo] done in {time.perf_counter() - t_start:.1f} s; all processes stopped cleanly")
    return code


if __name__ == "__main__":
    sys.exit(main())
