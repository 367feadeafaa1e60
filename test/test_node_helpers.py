"""Shared helpers of the node tests: a rendered mug scene, checkpoints, messages and node arguments.

(Named test_node_* so it belongs to the node area; it holds no tests itself. The rclpy client in this process
is :class:`pssnet_testing.client.RosClient`, the one the demo and the benchmark use.)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from pssnet_core.data.scenes import RenderedView, render_view
from pssnet_core.inference import DEFAULT_CHECKPOINT
from pssnet_core.models import build_model, default_config
from pssnet_core.models.checkpoint import save_checkpoint
from pssnet_core.models.integrity import canonical_input
from pssnet_core.shapes import make_shape

TINY = {"channels": [4, 8, 8, 16], "latent_dim": 32, "flow_hidden": 32, "flow_couplings": 4}


def domain_for(module_index: int) -> int:
    """A ROS_DOMAIN_ID for one test module (10..99), claimed for this test session: one that no DDS participant
    on this machine uses and no other process has claimed, searched from a start that differs between modules
    and runs. (Imported here: the ROS-free tests of pssnet_core use this module's scenes and checkpoints
    without the harness package.)"""
    from pssnet_testing.processes import claim_domain_id

    return claim_domain_id(10 + (os.getpid() * 5 + module_index) % 90)


def render_mug_scene(seed: int = 0, distance: float = 0.6, tilt_deg: float = 30.0) -> RenderedView:
    """A test-split mug on the support plane, its handle pointing away from the camera (hidden), 640x480."""
    return render_view(make_shape("mug", 2_000_000 + seed), yaw_deg=0.0, distance=distance, tilt_deg=tilt_deg)


def tiny_checkpoint(path: Path, grid_size: int = 32, seed: int = 0) -> Path:
    """A small random PSSNet checkpoint: exercises the plumbing, completes nothing sensible.

    Untrained, so its output logits hardly depend on the input; its output bias is set so that about 15 % of
    the canonical observation's grid is occupied: every output carries points, and the serving checks, which
    refuse a model that empties or fills the grid (as a randomly initialised full-size PSSNet does), accept it.
    """
    torch.manual_seed(seed)
    model = build_model(default_config("pssnet", grid_size=grid_size, **TINY)).eval()
    canonical = torch.from_numpy(canonical_input(grid_size).astype(np.float32))[None]
    with torch.no_grad():
        model.decoder.deconv[-1].bias.fill_(0.0)
        logits = model.reconstruct(canonical).flatten()
        model.decoder.deconv[-1].bias.fill_(-float(torch.quantile(logits, 0.85)))
    return save_checkpoint(path, model, inference_only=True)


def node_checkpoint(tmp_dir: Path) -> tuple[Path, bool]:
    """The checkpoint node tests run: the shipped default when present (trained = True), else a tiny one."""
    if DEFAULT_CHECKPOINT.is_file():
        return DEFAULT_CHECKPOINT, True
    return tiny_checkpoint(tmp_dir / "tiny32.pt"), False


def stamped_header(sec: int, nanosec: int = 0, frame_id: str = "camera_depth_optical_frame"):
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def scene_messages(scene: RenderedView, header, depth_encoding: str = "32FC1"):
    """(depth, mask, camera_info) messages of a scene, all with ``header``."""
    from pssnet_ros.conversions import intrinsics_to_camera_info, numpy_to_image

    depth = scene.depth
    if depth_encoding == "16UC1":
        depth = np.rint(depth * 1000.0).astype(np.uint16)
    return (numpy_to_image(depth, depth_encoding, header), numpy_to_image(scene.mask, "mono8", header),
            intrinsics_to_camera_info(scene.intrinsics, header))


def make_request(scene: RenderedView, header, num_samples: int = 0, compute_grasps: bool = False,
                 depth_encoding: str = "32FC1"):
    from pssnet_interfaces.srv import SampleCompletions

    depth, mask, info = scene_messages(scene, header, depth_encoding)
    return SampleCompletions.Request(depth=depth, mask=mask, camera_info=info, num_samples=num_samples,
                                     compute_grasps=compute_grasps)
