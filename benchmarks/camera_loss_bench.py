"""Are camera frames lost between processes? The synthetic camera's best-effort 640x480 stream, counted by a
subscriber in this process, under the Fast DDS profile in use (``FASTRTPS_DEFAULT_PROFILES_FILE``; default the
shipped one). Checks the profile's shared-memory segment size: with Fast DDS' default 512 kB most frames were lost.

    .venv/bin/python benchmarks/camera_loss_bench.py [--rate 30] [--frames 600]

Frames sent before the subscriber is matched are lost to discovery, not to the transport: the count includes them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from pssnet_core.bench import cpu_kind
from pssnet_testing.processes import configure_this_process, ros_env

DOMAIN_ID = 83


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=30.0, help="camera frames per second")
    parser.add_argument("--frames", type=int, default=600, help="frames the camera sends")
    args = parser.parse_args()
    configure_this_process(DOMAIN_ID)
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("camera_loss_bench")
    received = {"depth": 0, "mask": 0}

    def counter(topic: str):
        def count(_: Image) -> None:
            received[topic] += 1
        return count

    subscriptions = [node.create_subscription(Image, topic, counter(topic), qos_profile_sensor_data)
                     for topic in received]
    camera = subprocess.Popen([sys.executable, "-m", "pssnet_testing.synthetic_camera", "--rate", str(args.rate),
                               "--count", str(args.frames)], env=ros_env(DOMAIN_ID))
    started = time.monotonic()
    while camera.poll() is None or time.monotonic() - started < 3.0:
        rclpy.spin_once(node, timeout_sec=0.05)
    for _ in range(40):  # what is still in flight
        rclpy.spin_once(node, timeout_sec=0.05)
    del subscriptions
    node.destroy_node()
    rclpy.try_shutdown()
    profile = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "Fast DDS defaults")
    print(f"[camera_loss] CPU: {cpu_kind()}; profile {profile}; sent {args.frames} sets at {args.rate:g} Hz; "
          f"received depth {received['depth']}, mask {received['mask']}")
    return 0 if camera.returncode == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
