"""``pssnet bag``: the completion node over a recorded rosbag2 (the work is in :mod:`pssnet_ros.bag`).

The ROS package adds this command to the ``pssnet`` command line through the ``pssnet.commands`` entry point
(setup.py): pssnet_core knows nothing of ROS. Only the arguments live here, so that ``pssnet --help`` does not
import rclpy; the ROS side is imported when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "bag", help="complete every synchronised depth/mask/camera_info set of a recorded rosbag2 (MCAP or sqlite3)",
        description="Reads a rosbag2, synchronises depth, mask and camera_info by stamp as the completion node does "
                    "(its sync_tolerance), completes every synchronised set (or every k-th) with the node's pipeline "
                    "and parameters, and writes a new bag with every input message plus /pssnet/completions, "
                    "/pssnet/known_occupied, /pssnet/grasps and /pssnet/grasp_candidates, each with its input's "
                    "stamp and frame, as the node publishes them. Parameters the node applies to live input only "
                    "(continuous, max_rate_hz, max_input_age) do not apply. Exit code: 0 when at least one set was "
                    "completed, 1 when none was, 2 on an error (unreadable bag, missing topic, bad parameter).")
    p.add_argument("input", type=Path, metavar="IN", help="rosbag2 directory, or one .mcap or .db3 file")
    p.add_argument("--out", type=Path, required=True,
                   help="output bag: a rosbag2 directory (storage from --storage), or one file if it ends in .mcap")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="storage of a directory output")
    p.add_argument("--depth-topic", default="/depth", help="sensor_msgs/Image 32FC1 or 16UC1 (default /depth)")
    p.add_argument("--mask-topic", default="/mask", help="sensor_msgs/Image mono8 or 8UC1 (default /mask)")
    p.add_argument("--camera-info-topic", default="/camera_info",
                   help="sensor_msgs/CameraInfo (default /camera_info)")
    p.add_argument("--every", type=_positive, default=1, metavar="K",
                   help="complete every K-th synchronised set (default 1: all)")
    p.add_argument("--params-file", type=Path, default=None,
                   help="the node's ROS parameter file, e.g. config/completion_node.yaml (default: its defaults)")
    p.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                   help="one node parameter, as after --ros-args -p (after --params-file; repeatable), "
                        "e.g. -p model_path:=runs/pssnet32/best.pt -p sync_tolerance:=0.02")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_command)


def run_command(args: argparse.Namespace) -> int:
    from pssnet_ros.bag import run_command as run_bag  # rclpy and rosbags: only when the command runs

    return run_bag(args)
