"""A synthetic depth camera: publishes a rendered mug (handle hidden) on the completion node's input topics.

    python -m pssnet_testing.synthetic_camera --rate 5 [--qos best_effort|reliable] [--depth-encoding 16UC1]

Publishes ``depth`` (32FC1 metres or 16UC1 millimetres), ``mask`` (mono8) and ``camera_info`` with one
shared stamp per frame, in the frame ``camera_depth_optical_frame``. The scene is rendered once by
:func:`pssnet_core.data.scenes.render_view` (a mug of the test split, standing on a table, seen from the side
opposite its handle); the up vector the node needs is printed at start-up and given by :func:`render_scene`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from pssnet_ros.conversions import intrinsics_to_camera_info, numpy_to_image
from pssnet_ros.spinning import shutdown_once, spin_until_shutdown

if TYPE_CHECKING:  # the scenes (and their shapes: manifold3d) load only where a scene is rendered
    from pssnet_core.data.scenes import RenderedView

FRAME_ID = "camera_depth_optical_frame"
#: a test-split mug (round body, ring handle) that the shipped model never saw in training
DEFAULT_MUG_SEED = 2_000_002


@dataclass(frozen=True)
class SceneOptions:
    """What the synthetic camera shows.

    Attributes:
        mug_seed: identity of the procedural mug.
        yaw_deg: mug yaw; 0 turns the handle away from the camera (hidden), 180 towards it.
        distance: camera distance from the mug's centre (metres).
        tilt_deg: camera looks down by this angle.
    """

    mug_seed: int = DEFAULT_MUG_SEED
    yaw_deg: float = 0.0
    distance: float = 0.6
    tilt_deg: float = 30.0


def render_scene(options: SceneOptions, azimuth_deg: float = 180.0) -> RenderedView:
    """Renders the scene (640x480, Kinect-like intrinsics, depth in whole millimetres), from the camera's place or
    from ``azimuth_deg`` round the mug (the same distance and tilt)."""
    from pssnet_core.data.scenes import render_view
    from pssnet_core.shapes import make_shape

    return render_view(make_shape("mug", options.mug_seed), yaw_deg=options.yaw_deg, distance=options.distance,
                       tilt_deg=options.tilt_deg, azimuth_deg=azimuth_deg)


def view_messages(view: RenderedView, depth_encoding: str = "32FC1", header: Header | None = None
                  ) -> tuple[Image, Image, CameraInfo]:
    """The (depth, mask, camera_info) messages the camera publishes for ``view`` (32FC1 metres or 16UC1 mm)."""
    depth = view.depth if depth_encoding == "32FC1" else np.rint(view.depth * 1000.0).astype(np.uint16)
    return (numpy_to_image(depth, depth_encoding, header), numpy_to_image(view.mask, "mono8", header),
            intrinsics_to_camera_info(view.intrinsics, header))


class SyntheticCamera(Node):
    """Publishes one rendered view at a fixed rate with fresh stamps."""

    def __init__(self, view: RenderedView, rate_hz: float, reliable: bool, depth_encoding: str = "32FC1",
                 count: int = 0, **kwargs) -> None:
        super().__init__("synthetic_camera", **kwargs)
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE) if reliable else qos_profile_sensor_data
        self._pubs = [self.create_publisher(Image, "depth", qos), self.create_publisher(Image, "mask", qos),
                      self.create_publisher(CameraInfo, "camera_info", qos)]
        self._messages = view_messages(view, depth_encoding)
        self._count, self._sent = count, 0
        self.create_timer(1.0 / rate_hz, self._tick)

    def _tick(self) -> None:
        stamp = self.get_clock().now().to_msg()
        for pub, msg in zip(self._pubs, self._messages, strict=True):
            msg.header.stamp = stamp
            msg.header.frame_id = FRAME_ID
            pub.publish(msg)
        self._sent += 1
        if self._count and self._sent >= self._count:
            raise SystemExit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="synthetic_camera", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=5.0, help="frames per second (default 5)")
    parser.add_argument("--qos", choices=("best_effort", "reliable"), default="best_effort",
                        help="publisher reliability (default best_effort, as camera drivers do)")
    parser.add_argument("--depth-encoding", choices=("32FC1", "16UC1"), default="32FC1")
    parser.add_argument("--mug-seed", type=int, default=DEFAULT_MUG_SEED)
    parser.add_argument("--yaw", type=float, default=0.0, help="mug yaw in degrees (0 = handle hidden)")
    parser.add_argument("--distance", type=float, default=0.6, help="camera distance in metres")
    parser.add_argument("--tilt", type=float, default=30.0, help="camera tilt down in degrees")
    parser.add_argument("--count", type=int, default=0, help="stop after this many frames (0 = run until SIGINT)")
    return parser


def main(args: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    options = build_parser().parse_args(remove_ros_args(argv)[1:])
    if not 0 < options.rate <= 100:
        print(f"[synthetic_camera] error: --rate must be in (0, 100], got {options.rate}", file=sys.stderr)
        return 2
    view = render_scene(SceneOptions(options.mug_seed, options.yaw, options.distance, options.tilt))
    rclpy.init(args=argv)
    node = None
    try:
        node = SyntheticCamera(view, options.rate, options.qos == "reliable", options.depth_encoding, options.count)
        up = ", ".join(f"{v:.6f}" for v in view.up)
        node.get_logger().info(f"publishing mug {options.mug_seed} at {options.rate:g} Hz ({options.qos}, "
                               f"{options.depth_encoding}); up_vector [{up}]; handle visible: {view.handle_visible}")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spin_until_shutdown(executor)
    except (KeyboardInterrupt, ExternalShutdownException, SystemExit):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        shutdown_once()
    return 0


if __name__ == "__main__":
    sys.exit(main())
