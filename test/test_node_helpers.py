"""Shared helpers of the node tests: a rendered mug scene, checkpoints, and an rclpy client in this process.

(Named test_node_* so it belongs to the node area; it holds no tests itself.)
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import torch

from pssnet_core.data.scenes import RenderedView, render_view
from pssnet_core.inference import DEFAULT_CHECKPOINT
from pssnet_core.models import build_model, default_config
from pssnet_core.shapes import make_shape
from pssnet_core.training import save_checkpoint
from pssnet_ros.processes import configure_this_process

TINY = {"channels": [4, 8, 8, 16], "latent_dim": 32, "flow_hidden": 32, "flow_couplings": 4}


def domain_for(module_index: int) -> int:
    """A ROS_DOMAIN_ID for one test module, unlikely to clash with another run (domains 10..99)."""
    return 10 + (os.getpid() * 5 + module_index) % 90


def render_mug_scene(seed: int = 0, distance: float = 0.6, tilt_deg: float = 30.0) -> RenderedView:
    """A test-split mug on the support plane, its handle pointing away from the camera (hidden), 640x480."""
    return render_view(make_shape("mug", 2_000_000 + seed), yaw_deg=0.0, distance=distance, tilt_deg=tilt_deg)


def tiny_checkpoint(path: Path, grid_size: int = 32, seed: int = 0) -> Path:
    """A small random PSSNet checkpoint: exercises the plumbing, completes nothing sensible."""
    torch.manual_seed(seed)
    model = build_model(default_config("pssnet", grid_size=grid_size, **TINY))
    with torch.no_grad():  # about half the voxels occupied, so that every output carries points
        model.decoder.deconv[-1].bias.fill_(0.0)
    return save_checkpoint(path, model, inference_only=True)


def node_checkpoint(tmp_dir: Path) -> tuple[Path, bool]:
    """The checkpoint node tests run: the shipped default when present (trained = True), else a tiny one."""
    if DEFAULT_CHECKPOINT.is_file():
        return DEFAULT_CHECKPOINT, True
    return tiny_checkpoint(tmp_dir / "tiny32.pt"), False


class RosClient:
    """An rclpy context + node in this (pytest) process, spun by a background executor."""

    def __init__(self, domain_id: int, name: str = "test_client") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        configure_this_process(domain_id)
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.1)
        except (ExternalShutdownException, RuntimeError):
            pass

    def client(self, srv_type, name: str, timeout: float = 30.0):
        """A service client whose server has been discovered (waits up to ``timeout`` s)."""
        client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"service {name} not discovered within {timeout} s")
        return client

    @staticmethod
    def call(client, request, timeout: float = 60.0):
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise TimeoutError(f"no response from {client.srv_name} within {timeout} s")
            time.sleep(0.005)
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(timeout=5)


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


def node_args(checkpoint: Path, **params) -> list[str]:
    """``--ros-args`` for the completion node: the checkpoint plus ``name:=value`` parameters."""
    args = ["--ros-args", "-p", f"model_path:={checkpoint}"]
    for name, value in params.items():
        if isinstance(value, bool):
            text = str(value).lower()
        elif isinstance(value, list | tuple | np.ndarray):
            text = "[" + ",".join(repr(float(v)) for v in value) + "]"
        else:
            text = repr(value) if isinstance(value, float) else str(value)
        args += ["-p", f"{name}:={text}"]
    return args
